//! Epipolar geometry: fundamental matrix by the normalised 8-point algorithm, essential
//! matrix by the 8-point algorithm on calibrated points with projection onto the
//! essential manifold, both inside RANSAC with the Sampson distance, and relative pose
//! recovery by cheirality.

use nalgebra::{Matrix3, Vector3};

use super::{homogeneous, normalize, null_vector_9, ransac, Estimator, NoModel, Point, RansacConfig, RansacResult};

fn eight_point_rows(x0: &[Point], x1: &[Point]) -> Vec<[f64; 9]> {
    x0.iter()
        .zip(x1)
        .map(|(p, q)| {
            let (x, y, u, v) = (p[0], p[1], q[0], q[1]);
            [u * x, u * y, u, v * x, v * y, v, x, y, 1.0]
        })
        .collect()
}

/// Closest matrix with singular values `(s1, s2, 0)` (rank 2) or, with `essential`,
/// `(1, 1, 0)`.
fn project(m: Matrix3<f64>, essential: bool) -> Option<Matrix3<f64>> {
    let svd = nalgebra::SVD::try_new(m, true, true, f64::EPSILON, 1000)?;
    let (u, vt) = (svd.u?, svd.v_t?);
    let s = svd.singular_values;
    let d = if essential { Vector3::new(1.0, 1.0, 0.0) } else { Vector3::new(s[0], s[1], 0.0) };
    Some(u * Matrix3::from_diagonal(&d) * vt)
}

/// Normalised 8-point fundamental matrix (`x1ᵀ F x0 = 0`), rank 2.
pub fn eight_point_fundamental(x0: &[Point], x1: &[Point]) -> Option<Matrix3<f64>> {
    if x0.len() < 8 || x0.len() != x1.len() {
        return None;
    }
    let (t0, n0) = normalize(x0)?;
    let (t1, n1) = normalize(x1)?;
    let f = null_vector_9(&eight_point_rows(&n0, &n1))?;
    let f = project(Matrix3::from_row_slice(f.as_slice()), false)?;
    let f = t1.transpose() * f * t0;
    let norm = f.norm();
    (norm > 0.0 && norm.is_finite()).then(|| f / norm)
}

/// 8-point essential matrix from calibrated (normalised-camera) points.
pub fn eight_point_essential(x0: &[Point], x1: &[Point]) -> Option<Matrix3<f64>> {
    if x0.len() < 8 || x0.len() != x1.len() {
        return None;
    }
    let e = null_vector_9(&eight_point_rows(x0, x1))?;
    project(Matrix3::from_row_slice(e.as_slice()), true)
}

/// Sampson distance of `x1ᵀ F x0 = 0` (first-order geometric error).
pub fn sampson(f: &Matrix3<f64>, p0: &Point, p1: &Point) -> f64 {
    let (a, b) = (homogeneous(p0), homogeneous(p1));
    let fa = f * a;
    let ftb = f.transpose() * b;
    let num = b.dot(&fa);
    let den = fa.x * fa.x + fa.y * fa.y + ftb.x * ftb.x + ftb.y * ftb.y;
    if den <= 0.0 { f64::INFINITY } else { (num * num / den).sqrt() }
}

/// Fundamental matrices; residual is the Sampson distance in pixels.
#[derive(Debug, Clone, Copy, Default)]
pub struct FundamentalEstimator;

impl Estimator for FundamentalEstimator {
    type Model = Matrix3<f64>;
    const SAMPLE_SIZE: usize = 8;

    fn fit(&self, x0: &[Point], x1: &[Point]) -> Vec<Matrix3<f64>> {
        eight_point_fundamental(x0, x1).into_iter().collect()
    }

    fn residual(&self, f: &Matrix3<f64>, p0: &Point, p1: &Point) -> f64 {
        sampson(f, p0, p1)
    }
}

/// Essential matrices on calibrated points; the residual (Sampson distance) is scaled
/// by `focal` so that the threshold stays in pixels.
#[derive(Debug, Clone, Copy)]
pub struct EssentialEstimator {
    /// Mean focal length in pixels (scales the Sampson residual back to pixels).
    pub focal: f64,
}

impl Estimator for EssentialEstimator {
    type Model = Matrix3<f64>;
    const SAMPLE_SIZE: usize = 8;

    fn fit(&self, x0: &[Point], x1: &[Point]) -> Vec<Matrix3<f64>> {
        eight_point_essential(x0, x1).into_iter().collect()
    }

    fn residual(&self, e: &Matrix3<f64>, p0: &Point, p1: &Point) -> f64 {
        sampson(e, p0, p1) * self.focal
    }
}

/// Robust fundamental matrix (pixel coordinates).
pub fn find_fundamental(x0: &[Point], x1: &[Point], cfg: &RansacConfig) -> Result<RansacResult<Matrix3<f64>>, NoModel> {
    ransac(&FundamentalEstimator, x0, x1, cfg)
}

/// Pixel → normalised camera coordinates with intrinsics `k`.
pub fn to_camera(k: &Matrix3<f64>, points: &[Point]) -> Option<Vec<Point>> {
    let ki = k.try_inverse()?;
    points
        .iter()
        .map(|p| {
            let q = ki * homogeneous(p);
            (q.z.abs() > 1e-15).then(|| [q.x / q.z, q.y / q.z])
        })
        .collect()
}

/// A relative pose `x1 = R·x0 + t` (t of unit length) with its inliers.
#[derive(Debug, Clone, PartialEq)]
pub struct RelativePose {
    /// Rotation `R` from camera 0 to camera 1.
    pub rotation: Matrix3<f64>,
    /// Translation direction `t` (unit length).
    pub translation: Vector3<f64>,
    /// The essential matrix it was decomposed from.
    pub essential: Matrix3<f64>,
    /// Inlier mask, one entry per correspondence.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub num_inliers: usize,
}

/// Linear triangulation of one point; returns its depths in both cameras.
fn depths(r: &Matrix3<f64>, t: &Vector3<f64>, p0: &Point, p1: &Point) -> Option<(f64, f64)> {
    // Solve d0·R·a − d1·b = −t in least squares.
    let (a, b) = (r * homogeneous(p0), homogeneous(p1));
    let m = nalgebra::Matrix3x2::from_columns(&[a, -b]);
    let sol = (m.transpose() * m).try_inverse()? * m.transpose() * (-t);
    Some((sol[0], sol[1]))
}

/// The one of the four `(R, t)` of `e` that puts most inliers in front of both cameras.
pub fn recover_pose(e: &Matrix3<f64>, x0: &[Point], x1: &[Point], mask: &[bool]) -> Option<(Matrix3<f64>, Vector3<f64>, usize)> {
    let svd = nalgebra::SVD::try_new(*e, true, true, f64::EPSILON, 1000)?;
    let (mut u, mut vt) = (svd.u?, svd.v_t?);
    if u.determinant() < 0.0 {
        u = -u;
    }
    if vt.determinant() < 0.0 {
        vt = -vt;
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let t = u.column(2).into_owned();
    let candidates = [(u * w * vt, t), (u * w * vt, -t), (u * w.transpose() * vt, t), (u * w.transpose() * vt, -t)];
    candidates
        .into_iter()
        .map(|(r, t)| {
            let front = (0..x0.len())
                .filter(|&i| mask[i] && depths(&r, &t, &x0[i], &x1[i]).is_some_and(|(d0, d1)| d0 > 0.0 && d1 > 0.0))
                .count();
            (r, t, front)
        })
        .max_by_key(|c| c.2)
}

/// Robust relative pose from pixel correspondences and intrinsics: essential matrix
/// in RANSAC (threshold in pixels), then cheirality.
pub fn find_relative_pose(
    x0: &[Point],
    x1: &[Point],
    k0: &Matrix3<f64>,
    k1: &Matrix3<f64>,
    cfg: &RansacConfig,
) -> Result<RelativePose, NoModel> {
    let (c0, c1) = (to_camera(k0, x0).ok_or(NoModel::Degenerate)?, to_camera(k1, x1).ok_or(NoModel::Degenerate)?);
    let focal = (k0[(0, 0)] + k0[(1, 1)] + k1[(0, 0)] + k1[(1, 1)]) / 4.0;
    let r = ransac(&EssentialEstimator { focal }, &c0, &c1, cfg)?;
    let (rotation, translation, _) = recover_pose(&r.model, &c0, &c1, &r.inliers).ok_or(NoModel::Degenerate)?;
    Ok(RelativePose { rotation, translation, essential: r.model, inliers: r.inliers, num_inliers: r.num_inliers })
}

/// Angle in degrees between two rotations.
pub fn rotation_error_deg(r_est: &Matrix3<f64>, r_gt: &Matrix3<f64>) -> f64 {
    let c = (((r_est.transpose() * r_gt).trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
    c.acos().to_degrees()
}

/// Angle in degrees between translation directions, up to sign (as SuperGlue's eval).
pub fn translation_error_deg(t_est: &Vector3<f64>, t_gt: &Vector3<f64>) -> f64 {
    let n = t_est.norm() * t_gt.norm();
    if n <= 0.0 {
        return 180.0;
    }
    let a = (t_est.dot(t_gt) / n).clamp(-1.0, 1.0).acos().to_degrees();
    a.min(180.0 - a)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pooling::SplitMix64;
    use nalgebra::Rotation3;

    struct Scene {
        x0: Vec<Point>,
        x1: Vec<Point>,
        k: Matrix3<f64>,
        r: Matrix3<f64>,
        t: Vector3<f64>,
    }

    fn scene(n: usize, outliers: usize, noise: f64, seed: u64) -> Scene {
        let mut rng = SplitMix64::new(seed);
        let mut u = move || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        let r = Rotation3::from_euler_angles(0.05, -0.2, 0.03).into_inner();
        let t = Vector3::new(1.0, 0.1, 0.2).normalize();
        let (mut x0, mut x1) = (Vec::new(), Vec::new());
        while x0.len() < n {
            let pw = Vector3::new(u() * 8.0 - 4.0, u() * 6.0 - 3.0, 4.0 + u() * 8.0);
            let pc = r * pw + t;
            if pc.z <= 0.1 {
                continue;
            }
            let (a, b) = (k * pw, k * pc);
            x0.push([a.x / a.z, a.y / a.z]);
            let mut q = [b.x / b.z + noise * (u() - 0.5), b.y / b.z + noise * (u() - 0.5)];
            if x0.len() <= outliers {
                q = [u() * 640.0, u() * 480.0];
            }
            x1.push(q);
        }
        Scene { x0, x1, k, r, t }
    }

    #[test]
    fn exact_essential_and_pose() {
        let s = scene(30, 0, 0.0, 3);
        let (c0, c1) = (to_camera(&s.k, &s.x0).expect("K"), to_camera(&s.k, &s.x1).expect("K"));
        let e = eight_point_essential(&c0, &c1).expect("model");
        let (r, t, front) = recover_pose(&e, &c0, &c1, &[true; 30]).expect("pose");
        assert_eq!(front, 30);
        assert!(rotation_error_deg(&r, &s.r) < 1e-6);
        assert!(translation_error_deg(&t, &s.t) < 1e-6);
        let f = eight_point_fundamental(&s.x0, &s.x1).expect("F");
        assert!(s.x0.iter().zip(&s.x1).all(|(p, q)| sampson(&f, p, q) < 1e-6));
    }

    #[test]
    fn ransac_pose_with_outliers_and_noise() {
        let s = scene(300, 90, 1.0, 4);
        let cfg = RansacConfig { threshold: 1.0, ..Default::default() };
        let pose = find_relative_pose(&s.x0, &s.x1, &s.k, &s.k, &cfg).expect("pose");
        let err = rotation_error_deg(&pose.rotation, &s.r).max(translation_error_deg(&pose.translation, &s.t));
        assert!(err < 2.0, "pose error {err}°");
        assert!(pose.inliers[..90].iter().filter(|&&b| b).count() < 10, "outliers kept");
        let f = find_fundamental(&s.x0, &s.x1, &cfg).expect("F");
        assert!(f.num_inliers >= 190, "{}", f.num_inliers);
    }

    #[test]
    fn too_few_points() {
        let s = scene(7, 0, 0.0, 5);
        assert_eq!(
            find_relative_pose(&s.x0, &s.x1, &s.k, &s.k, &RansacConfig::default()),
            Err(NoModel::TooFewPoints { needed: 8, got: 7 })
        );
    }
}
