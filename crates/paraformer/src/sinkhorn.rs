//! SuperGlue's optimal matching layer (SPEC §8): couplings with a dustbin row and
//! column, and log-domain Sinkhorn normalisation.

use rayon::prelude::*;

pub use crate::kernels::Matrix;
use crate::kernels::logsumexp_plus;

/// Rows handed to one rayon task at a time.
const MIN_ROWS: usize = 16;

/// The log assignment `P` `[M+1, N+1]` for scores `S` `[M, N]` (row-major) and the
/// dustbin score, after `iters` Sinkhorn iterations.
pub fn log_optimal_transport(scores: &[f32], m: usize, n: usize, bin_score: f32, iters: usize) -> Matrix {
    let mut z = Matrix::zeros(m + 1, n + 1);
    for i in 0..m {
        z.data[i * (n + 1)..i * (n + 1) + n].copy_from_slice(&scores[i * n..(i + 1) * n]);
    }
    log_optimal_transport_inplace(&mut z, bin_score, iters);
    z
}

/// In place: `z` `[M+1, N+1]` holds the scores in its inner block on entry (the last
/// row and column are overwritten with `bin_score`) and the log assignment on return.
/// Rows and columns run in parallel; each logsumexp is a vectorised contiguous pass
/// (columns through a transposed copy).
pub fn log_optimal_transport_inplace(z: &mut Matrix, bin_score: f32, iters: usize) {
    let (r, c) = (z.rows, z.cols);
    let (m, n) = (r - 1, c - 1);
    for i in 0..r {
        z.data[i * c + n] = bin_score;
    }
    z.data[m * c..].fill(bin_score);
    let mut zt = vec![0.0f32; r * c];
    zt.par_chunks_mut(r).enumerate().for_each(|(j, col)| {
        for (i, v) in col.iter_mut().enumerate() {
            *v = z.data[i * c + j];
        }
    });
    let (mf, nf) = (m as f32, n as f32);
    let norm = -(mf + nf).ln();
    let mut log_mu = vec![norm; r];
    log_mu[m] = nf.ln() + norm;
    let mut log_nu = vec![norm; c];
    log_nu[n] = mf.ln() + norm;
    let mut u = vec![0.0f32; r];
    let mut v = vec![0.0f32; c];
    for _ in 0..iters {
        u.par_iter_mut().with_min_len(MIN_ROWS).enumerate().for_each(|(i, ui)| {
            *ui = log_mu[i] - logsumexp_plus(&z.data[i * c..(i + 1) * c], &v);
        });
        v.par_iter_mut().with_min_len(MIN_ROWS).enumerate().for_each(|(j, vj)| {
            *vj = log_nu[j] - logsumexp_plus(&zt[j * r..(j + 1) * r], &u);
        });
    }
    z.data.par_chunks_mut(c).zip(u.par_iter()).for_each(|(row, ui)| {
        for (p, vj) in row.iter_mut().zip(&v) {
            *p += ui + vj - norm;
        }
    });
}

/// Mutual-best matches from a log assignment (SPEC §8).
#[derive(Debug, Clone, PartialEq)]
pub struct Matches {
    pub matches0: Vec<i64>,
    pub matches1: Vec<i64>,
    pub matching_scores0: Vec<f32>,
    pub matching_scores1: Vec<f32>,
}

impl Matches {
    /// Every keypoint unmatched.
    pub fn none(m: usize, n: usize) -> Self {
        Self { matches0: vec![-1; m], matches1: vec![-1; n], matching_scores0: vec![0.0; m], matching_scores1: vec![0.0; n] }
    }
}

/// Row and column maxima of the inner block, mutual check and threshold.
pub fn extract_matches(p: &Matrix, threshold: f32) -> Matches {
    let (m, n) = (p.rows - 1, p.cols - 1);
    if m == 0 || n == 0 {
        return Matches::none(m, n);
    }
    let mut max0 = vec![f32::NEG_INFINITY; m];
    let mut idx0 = vec![0usize; m];
    let mut max1 = vec![f32::NEG_INFINITY; n];
    let mut idx1 = vec![0usize; n];
    for i in 0..m {
        for (j, &val) in p.row(i)[..n].iter().enumerate() {
            // Strict `>` keeps the first maximum, like argmax.
            if val > max0[i] {
                max0[i] = val;
                idx0[i] = j;
            }
            if val > max1[j] {
                max1[j] = val;
                idx1[j] = i;
            }
        }
    }
    let mut out = Matches::none(m, n);
    let mut valid0 = vec![false; m];
    for i in 0..m {
        if idx1[idx0[i]] == i {
            let score = max0[i].exp();
            out.matching_scores0[i] = score;
            if score > threshold {
                valid0[i] = true;
                out.matches0[i] = idx0[i] as i64;
            }
        }
    }
    for j in 0..n {
        let i = idx1[j];
        if idx0[i] == j {
            out.matching_scores1[j] = out.matching_scores0[i];
            if valid0[i] {
                out.matches1[j] = i as i64;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scores(m: usize, n: usize) -> Vec<f32> {
        (0..m * n).map(|i| ((i * 7919 % 113) as f32 / 113.0 - 0.5) * 6.0).collect()
    }

    #[test]
    fn marginals_converge_to_mu_and_nu() {
        let (m, n) = (6, 9);
        let p = log_optimal_transport(&scores(m, n), m, n, 0.3, 500);
        // exp(P + norm) has row sums mu and column sums nu; P itself is shifted by −norm.
        let norm = -((m + n) as f32).ln();
        let row = |i: usize| p.row(i).iter().map(|v| (v + norm).exp()).sum::<f32>();
        let col = |j: usize| (0..m + 1).map(|i| (p.get(i, j) + norm).exp()).sum::<f32>();
        let total = (m + n) as f32;
        for i in 0..m {
            assert!((row(i) - 1.0 / total).abs() < 1e-4, "row {i}: {}", row(i));
        }
        assert!((row(m) - n as f32 / total).abs() < 1e-4);
        for j in 0..n {
            assert!((col(j) - 1.0 / total).abs() < 1e-4, "col {j}: {}", col(j));
        }
        assert!((col(n) - m as f32 / total).abs() < 1e-4);
    }

    #[test]
    fn clear_diagonal_is_matched_and_threshold_applies() {
        let n = 5;
        let mut s = vec![-4.0f32; n * n];
        for i in 0..n {
            s[i * n + i] = 6.0;
        }
        let p = log_optimal_transport(&s, n, n, 0.0, 100);
        let m = extract_matches(&p, 0.2);
        assert_eq!(m.matches0, vec![0, 1, 2, 3, 4]);
        assert_eq!(m.matches1, vec![0, 1, 2, 3, 4]);
        let none = extract_matches(&p, 0.999);
        assert_eq!(none.matches0, vec![-1; n]);
        // Mutual but below threshold: the score is still reported.
        assert!(none.matching_scores0.iter().all(|&s| s > 0.5));
    }
}
