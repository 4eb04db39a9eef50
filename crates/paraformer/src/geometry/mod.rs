//! Two-view geometry for evaluating matches (kornia-style): an [`Estimator`] trait, a
//! RANSAC driver with adaptive iteration count and local optimisation, and owned
//! results. Degenerate input (too few or collinear points) gives [`NoModel`], not a panic.

pub mod epipolar;
pub mod homography;

use nalgebra::{Matrix3, SMatrix, Vector3};

use crate::pooling::SplitMix64;

/// A 2-D point `(x, y)` in pixels.
pub type Point = [f64; 2];

/// Why no model could be estimated.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NoModel {
    /// Fewer correspondences than one minimal sample.
    #[error("need at least {needed} correspondences, got {got}")]
    TooFewPoints {
        /// Points one minimal sample needs.
        needed: usize,
        /// Points given.
        got: usize,
    },
    /// Every sample was degenerate.
    #[error("the correspondences are degenerate (collinear or coincident points)")]
    Degenerate,
    /// No hypothesis had the minimum number of inliers (given here).
    #[error("no hypothesis reached the minimum of {0} inliers")]
    NoConsensus(usize),
    /// The [`RansacConfig`] cannot find a model (see [`RansacConfig::validate`]).
    #[error("invalid RANSAC parameters: {0}")]
    InvalidConfig(String),
}

/// RANSAC parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct RansacConfig {
    /// Inlier threshold on the estimator's residual (pixels).
    pub threshold: f64,
    /// Desired probability of drawing one all-inlier sample.
    pub confidence: f64,
    /// Upper bound on hypotheses.
    pub max_iterations: usize,
    /// Refit on all inliers (iterated) after the search.
    pub local_optimization: bool,
    /// Seed of the sampler (results are deterministic).
    pub seed: u64,
}

impl Default for RansacConfig {
    fn default() -> Self {
        Self { threshold: 3.0, confidence: 0.999, max_iterations: 10_000, local_optimization: true, seed: 0 }
    }
}

impl RansacConfig {
    /// An error naming the field unless the threshold is finite and positive, the confidence
    /// in (0, 1) and at least one hypothesis is allowed: otherwise no point could be an inlier
    /// (or every one), and the adaptive count would be meaningless.
    pub fn validate(&self) -> crate::Result<()> {
        if !(self.threshold.is_finite() && self.threshold > 0.0) {
            return Err(crate::Error::input("threshold", format!("{}: expected a positive number of pixels", self.threshold)));
        }
        if !(self.confidence > 0.0 && self.confidence < 1.0) {
            return Err(crate::Error::input("confidence", format!("{}: expected a probability in (0, 1), e.g. 0.999", self.confidence)));
        }
        if self.max_iterations == 0 {
            return Err(crate::Error::input("max_iterations", "0: expected at least 1"));
        }
        Ok(())
    }
}

/// A model fitted by RANSAC, with its inlier mask.
#[derive(Debug, Clone, PartialEq)]
pub struct RansacResult<M> {
    /// The best model, refitted on its inliers.
    pub model: M,
    /// Inlier mask, one entry per correspondence.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub num_inliers: usize,
    /// Hypotheses drawn.
    pub iterations: usize,
}

/// A minimal-sample model family.
pub trait Estimator {
    /// What one hypothesis is (a 3×3 matrix for homographies and epipolar geometry).
    type Model: Clone;
    /// Points per minimal sample.
    const SAMPLE_SIZE: usize;
    /// Models through the given correspondences (minimal or more, least squares).
    fn fit(&self, x0: &[Point], x1: &[Point]) -> Vec<Self::Model>;
    /// Residual of one correspondence under a model (compared with the threshold).
    fn residual(&self, model: &Self::Model, p0: &Point, p1: &Point) -> f64;
}

/// RANSAC over `x0[i] ↔ x1[i]`.
pub fn ransac<E: Estimator>(est: &E, x0: &[Point], x1: &[Point], cfg: &RansacConfig) -> Result<RansacResult<E::Model>, NoModel> {
    if let Err(e) = cfg.validate() {
        return Err(NoModel::InvalidConfig(e.to_string()));
    }
    let n = x0.len().min(x1.len());
    let s = E::SAMPLE_SIZE;
    if n < s {
        return Err(NoModel::TooFewPoints { needed: s, got: n });
    }
    let mut rng = SplitMix64::new(cfg.seed ^ 0x5EED);
    let score = |m: &E::Model| -> (usize, Vec<bool>) {
        let mask: Vec<bool> = (0..n).map(|i| est.residual(m, &x0[i], &x1[i]) < cfg.threshold).collect();
        (mask.iter().filter(|&&b| b).count(), mask)
    };
    let mut best: Option<(E::Model, usize, Vec<bool>)> = None;
    let mut needed = cfg.max_iterations;
    let mut it = 0;
    let (mut s0, mut s1) = (vec![[0.0; 2]; s], vec![[0.0; 2]; s]);
    while it < needed.min(cfg.max_iterations) {
        it += 1;
        let idx = crate::pooling::random_indices(n, s, rng.next_u64());
        for (k, &i) in idx.iter().enumerate() {
            s0[k] = x0[i];
            s1[k] = x1[i];
        }
        for m in est.fit(&s0, &s1) {
            let (count, mask) = score(&m);
            if best.as_ref().is_none_or(|b| count > b.1) {
                let w = count as f64 / n as f64;
                needed = adaptive_iterations(w, s, cfg.confidence);
                best = Some((m, count, mask));
            }
        }
    }
    let Some((mut model, mut count, mut mask)) = best else { return Err(NoModel::Degenerate) };
    if count < s {
        return Err(NoModel::NoConsensus(s));
    }
    if cfg.local_optimization {
        // Refit on all inliers while that adds inliers.
        for _ in 0..10 {
            let (i0, i1): (Vec<Point>, Vec<Point>) = (0..n).filter(|&i| mask[i]).map(|i| (x0[i], x1[i])).unzip();
            let Some(refit) = est.fit(&i0, &i1).into_iter().next() else { break };
            let (c, m) = score(&refit);
            if c < count {
                break;
            }
            let grew = c > count;
            (model, count, mask) = (refit, c, m);
            if !grew {
                break;
            }
        }
    }
    Ok(RansacResult { model, inliers: mask, num_inliers: count, iterations: it })
}

/// Iterations for one all-inlier sample with probability `confidence`.
pub fn adaptive_iterations(inlier_ratio: f64, sample: usize, confidence: f64) -> usize {
    let p = inlier_ratio.powi(sample as i32);
    if p >= 1.0 - 1e-12 {
        return 1;
    }
    if p <= 0.0 {
        return usize::MAX;
    }
    let k = (1.0 - confidence).ln() / (1.0 - p).ln();
    if k.is_finite() { k.ceil().max(1.0) as usize } else { usize::MAX }
}

/// Hartley normalisation: centroid to the origin, mean distance √2. Returns the
/// transform and the normalised points, or `None` if all points coincide.
pub fn normalize(points: &[Point]) -> Option<(Matrix3<f64>, Vec<Point>)> {
    let n = points.len() as f64;
    let (cx, cy) = points.iter().fold((0.0, 0.0), |(a, b), p| (a + p[0] / n, b + p[1] / n));
    let mean = points.iter().map(|p| ((p[0] - cx).powi(2) + (p[1] - cy).powi(2)).sqrt()).sum::<f64>() / n;
    if mean.is_nan() || mean <= 1e-12 {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean;
    let t = Matrix3::new(s, 0.0, -s * cx, 0.0, s, -s * cy, 0.0, 0.0, 1.0);
    Some((t, points.iter().map(|p| [s * (p[0] - cx), s * (p[1] - cy)]).collect()))
}

/// The unit null vector of `rows` (each a 9-vector), by SVD of `AᵀA`; `None` if
/// the SVD fails or the null space has dimension > 1 (degenerate configuration).
pub(crate) fn null_vector_9(rows: &[[f64; 9]]) -> Option<SMatrix<f64, 9, 1>> {
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for r in rows {
        let v = SMatrix::<f64, 9, 1>::from_row_slice(r);
        ata += v * v.transpose();
    }
    let svd = nalgebra::SVD::try_new(ata, false, true, f64::EPSILON, 1000)?;
    let vt = svd.v_t?;
    let sv = svd.singular_values;
    // Two (near-)zero singular values: the points do not pin down a unique model.
    if sv[7] <= 1e-10 * sv[0].max(1e-300) {
        return None;
    }
    Some(vt.row(8).transpose())
}

/// `p` as a homogeneous column vector.
pub fn homogeneous(p: &Point) -> Vector3<f64> {
    Vector3::new(p[0], p[1], 1.0)
}
