//! Homography by normalised DLT (4+ points) inside RANSAC; residual is the transfer
//! error `‖H·p0 − p1‖` in image 1 (pixels).

use nalgebra::Matrix3;

use super::{homogeneous, normalize, null_vector_9, ransac, Estimator, NoModel, Point, RansacConfig, RansacResult};

/// Maps `p` by `h` (with the projective division); `None` at infinity.
pub fn apply(h: &Matrix3<f64>, p: &Point) -> Option<Point> {
    let q = h * homogeneous(p);
    (q.z.abs() > 1e-15).then(|| [q.x / q.z, q.y / q.z])
}

/// Normalised DLT through 4 or more correspondences; `None` when degenerate.
pub fn dlt(x0: &[Point], x1: &[Point]) -> Option<Matrix3<f64>> {
    if x0.len() < 4 || x0.len() != x1.len() {
        return None;
    }
    let (t0, n0) = normalize(x0)?;
    let (t1, n1) = normalize(x1)?;
    let rows: Vec<[f64; 9]> = n0
        .iter()
        .zip(&n1)
        .flat_map(|(p, q)| {
            let (x, y, u, v) = (p[0], p[1], q[0], q[1]);
            [[-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u], [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v]]
        })
        .collect();
    let h = null_vector_9(&rows)?;
    let hn = Matrix3::from_row_slice(h.as_slice());
    let h = t1.try_inverse()? * hn * t0;
    let scale = h[(2, 2)];
    if !scale.is_finite() || scale.abs() < 1e-15 {
        return h.iter().all(|v| v.is_finite()).then_some(h);
    }
    Some(h / scale)
}

/// The homography model family.
#[derive(Debug, Clone, Copy, Default)]
pub struct HomographyEstimator;

impl Estimator for HomographyEstimator {
    type Model = Matrix3<f64>;
    const SAMPLE_SIZE: usize = 4;

    fn fit(&self, x0: &[Point], x1: &[Point]) -> Vec<Matrix3<f64>> {
        // A minimal sample with three collinear points gives a degenerate homography.
        if x0.len() == 4 && (has_collinear_triple(x0) || has_collinear_triple(x1)) {
            return Vec::new();
        }
        dlt(x0, x1).into_iter().collect()
    }

    fn residual(&self, h: &Matrix3<f64>, p0: &Point, p1: &Point) -> f64 {
        apply(h, p0).map_or(f64::INFINITY, |q| ((q[0] - p1[0]).powi(2) + (q[1] - p1[1]).powi(2)).sqrt())
    }
}

fn has_collinear_triple(p: &[Point]) -> bool {
    let area = |a: &Point, b: &Point, c: &Point| ((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])).abs();
    let scale = p.iter().flat_map(|q| q.iter()).fold(1.0f64, |m, v| m.max(v.abs()));
    let tol = 1e-9 * scale * scale;
    (0..4).any(|skip| {
        let t: Vec<&Point> = p.iter().enumerate().filter(|(i, _)| *i != skip).map(|(_, q)| q).collect();
        area(t[0], t[1], t[2]) <= tol
    })
}

/// Robust homography from correspondences.
pub fn find_homography(x0: &[Point], x1: &[Point], cfg: &RansacConfig) -> Result<RansacResult<Matrix3<f64>>, NoModel> {
    ransac(&HomographyEstimator, x0, x1, cfg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pooling::SplitMix64;

    fn truth() -> Matrix3<f64> {
        Matrix3::new(0.9, 0.1, 30.0, -0.05, 1.1, -12.0, 2e-4, -1e-4, 1.0)
    }

    fn scene(n: usize, outliers: usize, noise: f64, seed: u64) -> (Vec<Point>, Vec<Point>) {
        let mut rng = SplitMix64::new(seed);
        let mut u = move || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let h = truth();
        let mut x0 = Vec::new();
        let mut x1 = Vec::new();
        for i in 0..n {
            let p = [u() * 640.0, u() * 480.0];
            let q = if i < outliers { [u() * 640.0, u() * 480.0] } else { apply(&h, &p).unwrap_or([0.0, 0.0]) };
            x0.push(p);
            x1.push([q[0] + noise * (u() - 0.5), q[1] + noise * (u() - 0.5)]);
        }
        (x0, x1)
    }

    #[test]
    fn dlt_recovers_an_exact_homography() {
        let (x0, x1) = scene(10, 0, 0.0, 1);
        let h = dlt(&x0, &x1).expect("model");
        assert!((h - truth()).abs().max() < 1e-8, "{h}");
    }

    #[test]
    fn ransac_rejects_outliers() {
        let (x0, x1) = scene(200, 80, 1.0, 2);
        let r = find_homography(&x0, &x1, &RansacConfig::default()).expect("model");
        assert!(r.num_inliers >= 115 && r.num_inliers <= 125, "{} inliers", r.num_inliers);
        assert!(r.inliers[80..].iter().filter(|&&b| b).count() >= 115);
        for p in [[0.0, 0.0], [640.0, 480.0], [320.0, 100.0]] {
            let (a, b) = (apply(&r.model, &p).expect("finite"), apply(&truth(), &p).expect("finite"));
            assert!((a[0] - b[0]).hypot(a[1] - b[1]) < 1.5);
        }
    }

    /// Parameters under which no model is meaningful are named, not reported as a failed
    /// search (a threshold of 0 used to read as "no hypothesis reached 4 inliers").
    #[test]
    fn invalid_ransac_parameters_are_named() {
        let (x0, x1) = scene(30, 0, 0.5, 3);
        let ok = RansacConfig::default();
        assert!(ok.validate().is_ok() && find_homography(&x0, &x1, &ok).is_ok());
        let bad = [
            (RansacConfig { threshold: 0.0, ..ok.clone() }, "threshold"),
            (RansacConfig { threshold: -1.0, ..ok.clone() }, "threshold"),
            (RansacConfig { threshold: f64::NAN, ..ok.clone() }, "threshold"),
            (RansacConfig { confidence: 0.0, ..ok.clone() }, "confidence"),
            (RansacConfig { confidence: 1.5, ..ok.clone() }, "confidence"),
            (RansacConfig { confidence: f64::NAN, ..ok.clone() }, "confidence"),
            (RansacConfig { max_iterations: 0, ..ok.clone() }, "max_iterations"),
        ];
        for (cfg, field) in bad {
            assert!(cfg.validate().expect_err(field).to_string().contains(field), "{cfg:?}");
            match find_homography(&x0, &x1, &cfg) {
                Err(NoModel::InvalidConfig(m)) => assert!(m.contains(field), "{m}"),
                other => panic!("{cfg:?}: {other:?}"),
            }
        }
    }

    #[test]
    fn degenerate_input_gives_no_model() {
        let x: Vec<Point> = (0..3).map(|i| [i as f64, 0.0]).collect();
        assert_eq!(find_homography(&x, &x, &RansacConfig::default()), Err(NoModel::TooFewPoints { needed: 4, got: 3 }));
        let line: Vec<Point> = (0..20).map(|i| [i as f64 * 3.0, i as f64 * 2.0 + 1.0]).collect();
        assert!(find_homography(&line, &line, &RansacConfig::default()).is_err());
        let same = vec![[5.0, 5.0]; 10];
        assert!(find_homography(&same, &same, &RansacConfig::default()).is_err());
    }
}
