//! SuperGlue's optimal matching layer (SPEC §8): couplings with a dustbin row and
//! column, and log-domain Sinkhorn normalisation.

use rayon::prelude::*;

pub use crate::kernels::Matrix;
use crate::kernels::{axpy, axpy_bf16, dot, dot_bf16, exp_row, exp_row_bf16, logsumexp_plus};

/// How the kernel `K` of the scaling-domain iterations is stored: f32, or bf16 (half the
/// memory traffic of the sweeps, which are bound by it; sums stay f32).
trait KernelStore: Copy + Default + Send + Sync {
    fn fill(z: &[f32], f: f32, g: &[f32], k: &mut [Self]);
    fn dot(k: &[Self], b: &[f32]) -> f32;
    fn axpy(alpha: f32, k: &[Self], y: &mut [f32]);
}

impl KernelStore for f32 {
    fn fill(z: &[f32], f: f32, g: &[f32], k: &mut [f32]) {
        exp_row(z, f, g, k)
    }
    fn dot(k: &[f32], b: &[f32]) -> f32 {
        dot(k, b)
    }
    fn axpy(alpha: f32, k: &[f32], y: &mut [f32]) {
        axpy(alpha, k, y)
    }
}

impl KernelStore for u16 {
    fn fill(z: &[f32], f: f32, g: &[f32], k: &mut [u16]) {
        exp_row_bf16(z, f, g, k)
    }
    fn dot(k: &[u16], b: &[f32]) -> f32 {
        dot_bf16(k, b)
    }
    fn axpy(alpha: f32, k: &[u16], y: &mut [f32]) {
        axpy_bf16(alpha, k, y)
    }
}

/// Rows per parallel task of the scaling-domain sweep (fixed, for reproducible sums).
const TASK_ROWS: usize = 32;

/// The couplings' dustbins and SPEC §8's marginals: fills the last row and column of
/// `z` with `bin_score`; returns `(norm, log_mu, log_nu)`.
fn couplings_and_marginals(z: &mut Matrix, bin_score: f32) -> (f32, Vec<f32>, Vec<f32>) {
    let (r, c) = (z.rows, z.cols);
    let (m, n) = (r - 1, c - 1);
    for i in 0..r {
        z.data[i * c + n] = bin_score;
    }
    z.data[m * c..].fill(bin_score);
    let (mf, nf) = (m as f32, n as f32);
    let norm = -(mf + nf).ln();
    let mut log_mu = vec![norm; r];
    log_mu[m] = nf.ln() + norm;
    let mut log_nu = vec![norm; c];
    log_nu[n] = mf.ln() + norm;
    (norm, log_mu, log_nu)
}

/// Largest |log| a scaling may reach before it is absorbed into the kernel.
const ABSORB: f32 = 30.0;

/// In place: `z` `[M+1, N+1]` holds the scores in its inner block on entry (the last
/// row and column are overwritten with `bin_score`) and the log assignment on return.
///
/// The iterates are SPEC §8's log-domain ones, computed in the scaling domain with
/// log-domain stabilisation: with potentials `f, g` absorbed into the kernel
/// `K = exp(Z + f ⊕ g)` and scalings `a, b`, SPEC's `u = f + log a`, `v = g + log b`.
/// One sweep over K per iteration updates `a` row by row (`a_i = μ_i / K_i·b`) and
/// accumulates `Kᵀa` for `b` in the same pass; `K` is rebuilt (one exp pass) only
/// when a scaling leaves `[e^−30, e^30]`. The result is assembled in the log domain,
/// so entries far below the maximum stay exact.
pub fn log_optimal_transport_inplace(z: &mut Matrix, bin_score: f32, iters: usize) {
    optimal_transport::<f32>(z, bin_score, iters)
}

/// [`log_optimal_transport_inplace`] with the kernel `K` stored in bf16 (`Precision::Bf16`):
/// the same iterations, potentials and log-domain assembly; only `K`'s entries carry
/// bf16 rounding (2^-9 relative), which the normalisation averages out.
pub fn log_optimal_transport_inplace_bf16(z: &mut Matrix, bin_score: f32, iters: usize) {
    optimal_transport::<u16>(z, bin_score, iters)
}

fn optimal_transport<K: KernelStore>(z: &mut Matrix, bin_score: f32, iters: usize) {
    let (r, c) = (z.rows, z.cols);
    let (norm, log_mu, log_nu) = couplings_and_marginals(z, bin_score);
    if iters == 0 {
        // SPEC: u = v = 0 before the first iteration.
        z.data.par_iter_mut().for_each(|p| *p -= norm);
        return;
    }
    let mu: Vec<f32> = log_mu.iter().map(|v| v.exp()).collect();
    let nu: Vec<f32> = log_nu.iter().map(|v| v.exp()).collect();

    // Start with each row's maximum absorbed, so that K ≤ 1.
    let mut f: Vec<f32> = z.data.par_chunks(c).map(|row| -row.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b))).collect();
    let mut g = vec![0.0f32; c];
    let mut k = vec![K::default(); r * c];
    let rebuild = |k: &mut [K], f: &[f32], g: &[f32]| {
        k.par_chunks_mut(c).zip(z.data.par_chunks(c)).zip(f.par_iter()).for_each(|((kr, zr), &fi)| K::fill(zr, fi, g, kr));
    };
    rebuild(&mut k, &f, &g);
    let mut a = vec![1.0f32; r];
    let mut b = vec![1.0f32; c];
    // Kᵀa is summed per block of TASK_ROWS rows, then over the blocks in order: the same
    // additions in the same order whatever the thread count, so results are reproducible.
    let blocks = r.div_ceil(TASK_ROWS);
    let mut partial = vec![0.0f32; blocks * c];
    let mut kta = vec![0.0f32; c];
    for it in 0..iters {
        // a_i = μ_i / (K b)_i, and Kᵀa accumulated in the same sweep.
        partial
            .par_chunks_mut(c)
            .zip(a.par_chunks_mut(TASK_ROWS))
            .zip(k.par_chunks(TASK_ROWS * c))
            .zip(mu.par_chunks(TASK_ROWS))
            .for_each(|(((acc, ac), kc), muc)| {
                acc.fill(0.0);
                for ((ai, kr), mui) in ac.iter_mut().zip(kc.chunks_exact(c)).zip(muc) {
                    *ai = mui / K::dot(kr, &b);
                    K::axpy(*ai, kr, acc);
                }
            });
        kta.fill(0.0);
        for acc in partial.chunks_exact(c) {
            axpy(1.0, acc, &mut kta);
        }
        for ((bj, nuj), s) in b.iter_mut().zip(&nu).zip(&kta) {
            *bj = nuj / s;
        }
        let out_of_range = |s: &[f32]| s.iter().any(|v| v.ln().abs().is_nan() || v.ln().abs() > ABSORB);
        if it + 1 < iters && (out_of_range(&a) || out_of_range(&b)) {
            for (fi, ai) in f.iter_mut().zip(&mut a) {
                *fi += ai.ln();
                *ai = 1.0;
            }
            for (gj, bj) in g.iter_mut().zip(&mut b) {
                *gj += bj.ln();
                *bj = 1.0;
            }
            rebuild(&mut k, &f, &g);
        }
    }
    let u: Vec<f32> = f.iter().zip(&a).map(|(fi, ai)| fi + ai.ln()).collect();
    let v: Vec<f32> = g.iter().zip(&b).map(|(gj, bj)| gj + bj.ln()).collect();
    z.data.par_chunks_mut(c).zip(u.par_iter()).for_each(|(row, ui)| {
        for (p, vj) in row.iter_mut().zip(&v) {
            *p += ui + vj - norm;
        }
    });
}

/// SPEC §8 verbatim (log domain, one logsumexp per row and column and iteration):
/// the reference that the fast version is tested against.
pub fn log_optimal_transport_reference(z: &mut Matrix, bin_score: f32, iters: usize) {
    let (r, c) = (z.rows, z.cols);
    let (norm, log_mu, log_nu) = couplings_and_marginals(z, bin_score);
    let mut zt = vec![0.0f32; r * c];
    for j in 0..c {
        for i in 0..r {
            zt[j * r + i] = z.data[i * c + j];
        }
    }
    let (mut u, mut v) = (vec![0.0f32; r], vec![0.0f32; c]);
    for _ in 0..iters {
        for i in 0..r {
            u[i] = log_mu[i] - logsumexp_plus(&z.data[i * c..(i + 1) * c], &v);
        }
        for j in 0..c {
            v[j] = log_nu[j] - logsumexp_plus(&zt[j * r..(j + 1) * r], &u);
        }
    }
    for (row, ui) in z.data.chunks_exact_mut(c).zip(&u) {
        for (p, vj) in row.iter_mut().zip(&v) {
            *p += ui + vj - norm;
        }
    }
}

/// Mutual-best matches from a log assignment (SPEC §8).
#[derive(Debug, Clone, PartialEq)]
pub struct Matches {
    /// `[M]` index into image 1, −1 if unmatched.
    pub matches0: Vec<i64>,
    /// `[N]` index into image 0, −1 if unmatched.
    pub matches1: Vec<i64>,
    /// `[M]` match confidence (0 where unmatched).
    pub matching_scores0: Vec<f32>,
    /// `[N]` match confidence (0 where unmatched).
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
    for (j, &i) in idx1.iter().enumerate() {
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

/// The log assignment `P` `[M+1, N+1]` for scores `S` `[M, N]` (row-major) and the
/// dustbin score, after `iters` Sinkhorn iterations.
fn log_optimal_transport(scores: &[f32], m: usize, n: usize, bin_score: f32, iters: usize) -> Matrix {
    let mut z = Matrix::zeros(m + 1, n + 1);
    for i in 0..m {
        z.data[i * (n + 1)..i * (n + 1) + n].copy_from_slice(&scores[i * n..(i + 1) * n]);
    }
    log_optimal_transport_inplace(&mut z, bin_score, iters);
    z
}

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
    fn fast_sinkhorn_equals_the_log_domain_reference() {
        // Ordinary, wide (±150, forcing absorptions) and lopsided score ranges.
        for (m, n, spread, bin) in [(40, 57, 6.0, 1.0), (33, 20, 300.0, -40.0), (64, 9, 60.0, 90.0), (1, 5, 10.0, 0.0)] {
            let s: Vec<f32> = scores(m, n).iter().map(|v| v * spread / 6.0).collect();
            for iters in [0, 1, 7, 100] {
                let mut fast = Matrix::zeros(m + 1, n + 1);
                for i in 0..m {
                    fast.data[i * (n + 1)..i * (n + 1) + n].copy_from_slice(&s[i * n..(i + 1) * n]);
                }
                let mut slow = fast.clone();
                log_optimal_transport_inplace(&mut fast, bin, iters);
                log_optimal_transport_reference(&mut slow, bin, iters);
                let d = fast.data.iter().zip(&slow.data).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
                let scale = slow.data.iter().fold(1.0f32, |a, b| a.max(b.abs()));
                assert!(d <= 1e-4 * scale.max(1.0) / 10.0 + 2e-5, "M={m} N={n} spread={spread} iters={iters}: {d}");
            }
        }
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

    #[test]
    fn bf16_kernel_stays_close_to_f32() {
        let (m, n) = (120, 97);
        let sc = scores(m, n);
        let want = log_optimal_transport(&sc, m, n, 0.3, 50);
        let mut z = Matrix::zeros(m + 1, n + 1);
        for i in 0..m {
            z.data[i * (n + 1)..i * (n + 1) + n].copy_from_slice(&sc[i * n..(i + 1) * n]);
        }
        log_optimal_transport_inplace_bf16(&mut z, 0.3, 50);
        let worst = want.data.iter().zip(&z.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        // K's entries carry 2^-9 relative error; the potentials absorb it to ~1e-2 in the log.
        assert!(worst < 2e-2, "max |Δ log P| = {worst}");
    }
}
