//! SuperGlue's optimal matching layer (SPEC §8): couplings with a dustbin row and
//! column, and log-domain Sinkhorn normalisation.

use rayon::prelude::*;

pub use crate::kernels::Matrix;
use crate::kernels::{axpy, dot, exp_row, exp_row_bf16, logsumexp_plus};

/// How the kernel `K` of the scaling-domain iterations is stored, per block of
/// `TASK_ROWS` rows: f32 row-major, or bf16 with pairs of rows interleaved
/// (`[rows/2][c][2]`, the layout `vdpbf16ps` reads). The sweeps are bound by memory
/// traffic and instruction count, which bf16 halves; every sum stays f32.
trait KernelStore: Copy + Default + Send + Sync {
    /// Width a row of `K` (and `b`, `Kᵀa`) is stored at for `c` columns; the padding is 0.
    fn stride(c: usize) -> usize;
    /// Values `K` needs for `rows` rows of stride `s`.
    fn len(rows: usize, s: usize) -> usize;
    /// `K_ij = exp(z_ij + f_i + g_j)` for the rows of one block (`c` columns of `z`, rows
    /// of `K` at stride `s`; the padding is left as it is).
    fn fill(z: &[f32], f: &[f32], g: &[f32], k: &mut [Self], c: usize, s: usize);
    /// For the rows of one block: `a_i = μ_i / (K b)_i`, then `acc += Σ_i a_i K_i`, over
    /// rows of stride `s`.
    fn sweep(k: &[Self], a: &mut [f32], mu: &[f32], b: &[f32], acc: &mut [f32], s: usize);
}

impl KernelStore for f32 {
    /// Whole 64-byte lines: with 2049 columns every vector load of a row crossed a line.
    fn stride(c: usize) -> usize {
        c.next_multiple_of(16)
    }
    fn len(rows: usize, s: usize) -> usize {
        rows * s
    }
    fn fill(z: &[f32], f: &[f32], g: &[f32], k: &mut [f32], c: usize, s: usize) {
        for ((zr, kr), &fi) in z.chunks_exact(c).zip(k.chunks_exact_mut(s)).zip(f) {
            exp_row(zr, fi, g, &mut kr[..c]);
        }
    }
    fn sweep(k: &[f32], a: &mut [f32], mu: &[f32], b: &[f32], acc: &mut [f32], c: usize) {
        #[cfg(target_arch = "x86_64")]
        if crate::kernels::simd_level() >= 4 {
            // SAFETY: AVX-512F and FMA checked just above; slices sized by `len`.
            return unsafe { sweep_f32_pairs(k, a, mu, b, acc, c) };
        }
        #[cfg(target_arch = "x86_64")]
        if crate::kernels::simd_level() == 3 {
            // SAFETY: AVX2 and FMA checked just above; slices sized by `len`.
            return unsafe { sweep_f32_pairs_avx2(k, a, mu, b, acc, c) };
        }
        for ((ai, kr), mui) in a.iter_mut().zip(k.chunks_exact(c)).zip(mu) {
            *ai = mui / dot(kr, b);
            axpy(*ai, kr, acc);
        }
    }
}

/// [`KernelStore::sweep`] for f32 rows on AVX-512, two rows at a time: both products with
/// `b` in one pass (four independent FMA chains), then `acc += a_i K_i + a_i+1 K_i+1` in
/// one pass, so `acc` is loaded and stored once per pair of rows.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,fma")]
unsafe fn sweep_f32_pairs(k: &[f32], a: &mut [f32], mu: &[f32], b: &[f32], acc: &mut [f32], c: usize) {
    use std::arch::x86_64::*;
    let rows = a.len().min(k.len() / c.max(1));
    let full = c / 16 * 16;
    let tail = ((1u32 << (c - full)) - 1) as __mmask16;
    let bp = b.as_ptr();
    let yp = acc.as_mut_ptr();
    let mut i = 0;
    while i < rows {
        let two = i + 1 < rows;
        let k0 = k.as_ptr().add(i * c);
        // The second row of an odd last one is the first again, its result unused.
        let k1 = if two { k0.add(c) } else { k0 };
        let z = _mm512_setzero_ps();
        let (mut d0, mut d0b, mut d1, mut d1b) = (z, z, z, z);
        let mut j = 0;
        while j + 32 <= full {
            let (b0, b1) = (_mm512_loadu_ps(bp.add(j)), _mm512_loadu_ps(bp.add(j + 16)));
            d0 = _mm512_fmadd_ps(_mm512_loadu_ps(k0.add(j)), b0, d0);
            d0b = _mm512_fmadd_ps(_mm512_loadu_ps(k0.add(j + 16)), b1, d0b);
            d1 = _mm512_fmadd_ps(_mm512_loadu_ps(k1.add(j)), b0, d1);
            d1b = _mm512_fmadd_ps(_mm512_loadu_ps(k1.add(j + 16)), b1, d1b);
            j += 32;
        }
        if j < full {
            let b0 = _mm512_loadu_ps(bp.add(j));
            d0 = _mm512_fmadd_ps(_mm512_loadu_ps(k0.add(j)), b0, d0);
            d1 = _mm512_fmadd_ps(_mm512_loadu_ps(k1.add(j)), b0, d1);
        }
        if full < c {
            let b0 = _mm512_maskz_loadu_ps(tail, bp.add(full));
            d0b = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(tail, k0.add(full)), b0, d0b);
            d1b = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(tail, k1.add(full)), b0, d1b);
        }
        let a0 = mu[i] / _mm512_reduce_add_ps(_mm512_add_ps(d0, d0b));
        a[i] = a0;
        let a1 = if two {
            a[i + 1] = mu[i + 1] / _mm512_reduce_add_ps(_mm512_add_ps(d1, d1b));
            a[i + 1]
        } else {
            0.0
        };
        let (v0, v1) = (_mm512_set1_ps(a0), _mm512_set1_ps(a1));
        // acc + a_i K_i (+ a_i+1 K_i+1 when there is a second row).
        let update = |y: __m512, x0: __m512, x1: __m512| {
            let y = _mm512_fmadd_ps(v0, x0, y);
            if two {
                _mm512_fmadd_ps(v1, x1, y)
            } else {
                y
            }
        };
        let mut j = 0;
        while j < full {
            let y = update(_mm512_loadu_ps(yp.add(j)), _mm512_loadu_ps(k0.add(j)), _mm512_loadu_ps(k1.add(j)));
            _mm512_storeu_ps(yp.add(j), y);
            j += 16;
        }
        if full < c {
            let x = |p: *const f32| _mm512_maskz_loadu_ps(tail, p);
            let y = update(x(yp.add(full)), x(k0.add(full)), x(k1.add(full)));
            _mm512_mask_storeu_ps(yp.add(full), tail, y);
        }
        i += 2;
    }
}

/// [`sweep_f32_pairs`] for AVX2 and FMA (8 lanes; the column tail past a multiple of 8 in
/// scalar FMAs). The portable row-by-row sweep it replaces there ran one row's product as
/// two FMA chains, bound by their latency, and loaded and stored `acc` once per row.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn sweep_f32_pairs_avx2(k: &[f32], a: &mut [f32], mu: &[f32], b: &[f32], acc: &mut [f32], c: usize) {
    use std::arch::x86_64::*;
    #[inline(always)]
    unsafe fn hsum(v: __m256) -> f32 {
        let m = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
        let m = _mm_add_ps(m, _mm_movehl_ps(m, m));
        _mm_cvtss_f32(_mm_add_ss(m, _mm_shuffle_ps::<1>(m, m)))
    }
    let rows = a.len().min(k.len() / c.max(1));
    let full = c / 8 * 8;
    let bp = b.as_ptr();
    let yp = acc.as_mut_ptr();
    let mut i = 0;
    while i < rows {
        let two = i + 1 < rows;
        let k0 = k.as_ptr().add(i * c);
        // The second row of an odd last one is the first again, its result unused.
        let k1 = if two { k0.add(c) } else { k0 };
        let z = _mm256_setzero_ps();
        let (mut d0, mut d0b, mut d1, mut d1b) = (z, z, z, z);
        let mut j = 0;
        while j + 16 <= full {
            let (b0, b1) = (_mm256_loadu_ps(bp.add(j)), _mm256_loadu_ps(bp.add(j + 8)));
            d0 = _mm256_fmadd_ps(_mm256_loadu_ps(k0.add(j)), b0, d0);
            d0b = _mm256_fmadd_ps(_mm256_loadu_ps(k0.add(j + 8)), b1, d0b);
            d1 = _mm256_fmadd_ps(_mm256_loadu_ps(k1.add(j)), b0, d1);
            d1b = _mm256_fmadd_ps(_mm256_loadu_ps(k1.add(j + 8)), b1, d1b);
            j += 16;
        }
        if j < full {
            let b0 = _mm256_loadu_ps(bp.add(j));
            d0 = _mm256_fmadd_ps(_mm256_loadu_ps(k0.add(j)), b0, d0);
            d1 = _mm256_fmadd_ps(_mm256_loadu_ps(k1.add(j)), b0, d1);
        }
        let (mut t0, mut t1) = (hsum(_mm256_add_ps(d0, d0b)), hsum(_mm256_add_ps(d1, d1b)));
        for j in full..c {
            t0 = (*k0.add(j)).mul_add(*bp.add(j), t0);
            t1 = (*k1.add(j)).mul_add(*bp.add(j), t1);
        }
        let a0 = mu[i] / t0;
        a[i] = a0;
        let a1 = if two {
            a[i + 1] = mu[i + 1] / t1;
            a[i + 1]
        } else {
            0.0
        };
        // acc + a_i K_i (+ a_i+1 K_i+1 when there is a second row).
        let (v0, v1) = (_mm256_set1_ps(a0), _mm256_set1_ps(a1));
        let mut j = 0;
        while j < full {
            let mut y = _mm256_fmadd_ps(v0, _mm256_loadu_ps(k0.add(j)), _mm256_loadu_ps(yp.add(j)));
            if two {
                y = _mm256_fmadd_ps(v1, _mm256_loadu_ps(k1.add(j)), y);
            }
            _mm256_storeu_ps(yp.add(j), y);
            j += 8;
        }
        for j in full..c {
            let mut y = a0.mul_add(*k0.add(j), *yp.add(j));
            if two {
                y = a1.mul_add(*k1.add(j), y);
            }
            *yp.add(j) = y;
        }
        i += 2;
    }
}

impl KernelStore for u16 {
    /// A pair of rows then spans whole 64-byte lines, as in f32.
    fn stride(c: usize) -> usize {
        c.next_multiple_of(16)
    }
    fn len(rows: usize, s: usize) -> usize {
        rows.div_ceil(2) * 2 * s
    }
    fn fill(z: &[f32], f: &[f32], g: &[f32], k: &mut [u16], c: usize, s: usize) {
        let mut row = vec![0u16; c];
        for (i, (zr, &fi)) in z.chunks_exact(c).zip(f).enumerate() {
            exp_row_bf16(zr, fi, g, &mut row);
            let pair = &mut k[(i / 2) * 2 * s..(i / 2 + 1) * 2 * s];
            for (j, &x) in row.iter().enumerate() {
                pair[2 * j + i % 2] = x;
            }
        }
    }
    fn sweep(k: &[u16], a: &mut [f32], mu: &[f32], b: &[f32], acc: &mut [f32], c: usize) {
        #[cfg(target_arch = "x86_64")]
        if crate::gemm_bf16::available() {
            // SAFETY: AVX-512 BF16 checked just above; slices sized by `len`.
            return unsafe { sweep_bf16_pairs(k, a, mu, b, acc, c) };
        }
        sweep_pairs_scalar(k, a, mu, b, acc, c)
    }
}

/// [`KernelStore::sweep`] for bf16 pairs of rows on CPUs without AVX-512 BF16.
fn sweep_pairs_scalar(k: &[u16], a: &mut [f32], mu: &[f32], b: &[f32], acc: &mut [f32], c: usize) {
    for (p, pair) in k.chunks_exact(2 * c).enumerate() {
        for h in 0..2.min(a.len() - 2 * p) {
            let i = 2 * p + h;
            let kv = |j: usize| f32::from_bits((pair[2 * j + h] as u32) << 16);
            a[i] = mu[i] / (0..c).map(|j| kv(j) * b[j]).sum::<f32>();
            for (j, y) in acc.iter_mut().enumerate() {
                *y += a[i] * kv(j);
            }
        }
    }
}

/// [`KernelStore::sweep`] for bf16 pairs of rows: both rows' products with `b` from one
/// load (the low and high halves of each 32-bit lane), and `acc += a_i K_i + a_i+1 K_i+1`
/// as one `vdpbf16ps` with the pair `(a_i, a_i+1)` rounded to bf16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn sweep_bf16_pairs(k: &[u16], a: &mut [f32], mu: &[f32], b: &[f32], acc: &mut [f32], c: usize) {
    use std::arch::x86_64::*;
    let full = c / 16 * 16;
    let hi_mask = _mm512_set1_epi32(0xFFFF_0000u32 as i32);
    for (p, pair) in k.chunks_exact(2 * c).enumerate() {
        let rows = 2.min(a.len() - 2 * p);
        let (mut d0, mut d1) = (_mm512_setzero_ps(), _mm512_setzero_ps());
        let kp = pair.as_ptr();
        for j in (0..full).step_by(16) {
            let x = _mm512_loadu_si512(kp.add(2 * j) as *const _);
            let bj = _mm512_loadu_ps(b.as_ptr().add(j));
            d0 = _mm512_fmadd_ps(_mm512_castsi512_ps(_mm512_slli_epi32::<16>(x)), bj, d0);
            d1 = _mm512_fmadd_ps(_mm512_castsi512_ps(_mm512_and_si512(x, hi_mask)), bj, d1);
        }
        let (mut s0, mut s1) = (_mm512_reduce_add_ps(d0), _mm512_reduce_add_ps(d1));
        for j in full..c {
            s0 += f32::from_bits((pair[2 * j] as u32) << 16) * b[j];
            s1 += f32::from_bits((pair[2 * j + 1] as u32) << 16) * b[j];
        }
        a[2 * p] = mu[2 * p] / s0;
        let a1 = if rows == 2 {
            a[2 * p + 1] = mu[2 * p + 1] / s1;
            a[2 * p + 1]
        } else {
            0.0
        };
        let a0 = a[2 * p];
        let a_pair = crate::kernels::to_bf16(a0) as u32 | (crate::kernels::to_bf16(a1) as u32) << 16;
        let ap = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(a_pair as i32));
        for j in (0..full).step_by(16) {
            let x = std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(kp.add(2 * j) as *const _));
            let y = acc.as_mut_ptr().add(j);
            _mm512_storeu_ps(y, _mm512_dpbf16_ps(_mm512_loadu_ps(y), ap, x));
        }
        for j in full..c {
            acc[j] += a0 * f32::from_bits((pair[2 * j] as u32) << 16) + a1 * f32::from_bits((pair[2 * j + 1] as u32) << 16);
        }
    }
}

/// `len` zeroed values starting on a 64-byte line (the vector has room to shift to it),
/// so that the sweeps' row loads never straddle two lines.
struct LineAligned<T> {
    data: Vec<T>,
    start: usize,
    len: usize,
}

impl<T: Copy + Default> LineAligned<T> {
    fn new(len: usize) -> Self {
        let data = vec![T::default(); len + 64];
        let start = data.as_ptr().align_offset(64).min(64);
        Self { data, start, len }
    }
    fn as_mut_slice(&mut self) -> &mut [T] {
        &mut self.data[self.start..self.start + self.len]
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
    // K, b and Kᵀa at `stride ≥ c`; K's padding columns stay 0, so b's and Kᵀa's do too.
    let stride = K::stride(c);
    let mut k_store = LineAligned::<K>::new(K::len(r, stride));
    let k = k_store.as_mut_slice();
    let block = K::len(TASK_ROWS, stride);
    let rebuild = |k: &mut [K], f: &[f32], g: &[f32]| {
        k.par_chunks_mut(block)
            .zip(z.data.par_chunks(TASK_ROWS * c))
            .zip(f.par_chunks(TASK_ROWS))
            .for_each(|((kb, zb), fb)| K::fill(zb, fb, g, kb, c, stride));
    };
    rebuild(k, &f, &g);
    let mut a = vec![1.0f32; r];
    let mut b_store = LineAligned::<f32>::new(stride);
    let b = b_store.as_mut_slice();
    b[..c].fill(1.0);
    // Kᵀa is summed per block of TASK_ROWS rows, then over the blocks in order: the same
    // additions in the same order whatever the thread count, so results are reproducible.
    let blocks = r.div_ceil(TASK_ROWS);
    let mut partial_store = LineAligned::<f32>::new(blocks * stride);
    let partial = partial_store.as_mut_slice();
    let mut kta = vec![0.0f32; stride];
    for it in 0..iters {
        // a_i = μ_i / (K b)_i, and Kᵀa accumulated in the same sweep.
        partial
            .par_chunks_mut(stride)
            .zip(a.par_chunks_mut(TASK_ROWS))
            .zip(k.par_chunks(block))
            .zip(mu.par_chunks(TASK_ROWS))
            .for_each(|(((acc, ac), kc), muc)| {
                acc.fill(0.0);
                K::sweep(kc, ac, muc, b, acc, stride);
            });
        kta.fill(0.0);
        for acc in partial.chunks_exact(stride) {
            axpy(1.0, acc, &mut kta);
        }
        for ((bj, nuj), s) in b.iter_mut().zip(&nu).zip(&kta) {
            *bj = nuj / s;
        }
        // |ln s| > ABSORB (or NaN), without a logarithm per entry and iteration.
        let (lo, hi) = ((-ABSORB).exp(), ABSORB.exp());
        let out_of_range = |s: &[f32]| s.iter().any(|v| !(lo..=hi).contains(v));
        if it + 1 < iters && (out_of_range(&a) || out_of_range(&b[..c])) {
            for (fi, ai) in f.iter_mut().zip(&mut a) {
                *fi += ai.ln();
                *ai = 1.0;
            }
            for (gj, bj) in g.iter_mut().zip(b.iter_mut()) {
                *gj += bj.ln();
                *bj = 1.0;
            }
            rebuild(k, &f, &g);
        }
    }
    let u: Vec<f32> = f.iter().zip(&a).map(|(fi, ai)| fi + ai.ln()).collect();
    let v: Vec<f32> = g.iter().zip(b.iter()).map(|(gj, bj)| gj + bj.ln()).collect();
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
        // Ordinary, wide (±150, forcing absorptions) and lopsided score ranges; 32 columns
        // (a row stride without padding) over three row blocks.
        for (m, n, spread, bin) in [(40, 57, 6.0, 1.0), (33, 20, 300.0, -40.0), (64, 9, 60.0, 90.0), (1, 5, 10.0, 0.0), (70, 31, 20.0, 1.0)] {
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

    /// The AVX-512 and AVX2 pair sweeps against the portable one (odd rows, a column tail).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn f32_pair_sweep_matches_the_row_by_row_sweep() {
        if crate::kernels::simd_level() < 3 {
            eprintln!("skipped: no AVX2 here");
            return;
        }
        // Odd row counts (a last row without a partner) and widths around 16 and 32.
        for (rows, c) in [(7, 37), (1, 16), (4, 33), (5, 64), (3, 5)] {
            let k: Vec<f32> = scores(rows, c).iter().map(|v| (v * 0.3).exp()).collect();
            let (mu, b): (Vec<f32>, Vec<f32>) = ((0..rows).map(|i| 0.1 + i as f32 * 0.01).collect(), (0..c).map(|j| 1.0 + j as f32 * 0.02).collect());
            let (mut a0, mut acc0) = (vec![0.0f32; rows], vec![0.5f32; c]);
            let (mut a1, mut acc1) = (vec![0.0f32; rows], vec![0.5f32; c]);
            for ((ai, kr), mui) in a0.iter_mut().zip(k.chunks_exact(c)).zip(&mu) {
                *ai = mui / kr.iter().zip(&b).map(|(x, y)| x * y).sum::<f32>();
                acc0.iter_mut().zip(kr).for_each(|(y, x)| *y += *ai * x);
            }
            let (mut a2, mut acc2) = (vec![0.0f32; rows], vec![0.5f32; c]);
            // SAFETY: AVX2 and FMA checked above; slices sized for `rows × c`.
            unsafe { sweep_f32_pairs_avx2(&k, &mut a2, &mu, &b, &mut acc2, c) };
            for (x, y) in a0.iter().zip(&a2).chain(acc0.iter().zip(&acc2)) {
                assert!((x - y).abs() <= 1e-5 * x.abs(), "AVX2 {rows}×{c}: {x} vs {y}");
            }
            if crate::kernels::simd_level() < 4 {
                continue;
            }
            // SAFETY: AVX-512 checked just above; slices sized for `rows × c`.
            unsafe { sweep_f32_pairs(&k, &mut a1, &mu, &b, &mut acc1, c) };
            for (x, y) in a0.iter().zip(&a1).chain(acc0.iter().zip(&acc1)) {
                assert!((x - y).abs() <= 1e-5 * x.abs(), "{rows}×{c}: {x} vs {y}");
            }
        }
    }

    #[test]
    fn bf16_sweep_matches_the_portable_sweep() {
        if !crate::gemm_bf16::available() {
            eprintln!("skipped: no AVX-512 BF16 here");
            return;
        }
        let (rows, c) = (7, 37);
        let z: Vec<f32> = scores(rows, c).iter().map(|v| v * 0.3).collect();
        let (f, g) = (vec![0.0f32; rows], vec![0.0f32; c]);
        let mut k = vec![0u16; <u16 as KernelStore>::len(rows, c)];
        <u16 as KernelStore>::fill(&z, &f, &g, &mut k, c, c);
        let (mu, b): (Vec<f32>, Vec<f32>) = ((0..rows).map(|i| 0.1 + i as f32 * 0.01).collect(), (0..c).map(|j| 1.0 + j as f32 * 0.02).collect());
        let (mut a0, mut acc0) = (vec![0.0f32; rows], vec![0.0f32; c]);
        let (mut a1, mut acc1) = (vec![0.0f32; rows], vec![0.0f32; c]);
        sweep_pairs_scalar(&k, &mut a0, &mu, &b, &mut acc0, c);
        // SAFETY: AVX-512 BF16 checked above; slices sized by `len`.
        unsafe { sweep_bf16_pairs(&k, &mut a1, &mu, &b, &mut acc1, c) };
        for (x, y) in a0.iter().zip(&a1) {
            assert!((x - y).abs() <= 1e-5 * x.abs(), "a: {x} vs {y}");
        }
        // The SIMD sweep rounds each a_i to bf16 for Kᵀa: 2^-9 relative.
        for (x, y) in acc0.iter().zip(&acc1) {
            assert!((x - y).abs() <= 4e-3 * x.abs(), "Kᵀa: {x} vs {y}");
        }
    }
}
