//! Fused fp32 attention (head width 16, 32, 64 or 96) on CPUs with AVX2 and
//! FMA but no AVX-512, as most laptops have: the design of [`crate::attention_fused`]
//! (SPEC §4–§5) with 8-lane registers. The same packing (queries pre-scaled by
//! `log2(e)/√d`, keys in 16-column panels), strips of 16 query rows whose scores stay in
//! L1/L2, an unnormalised softmax divided out after the value product, and the shared
//! cross attention's online column softmax merged over fixed row blocks. The register
//! tiles are smaller (16 ymm registers against 32 zmm) and `2^x` builds its power of two
//! from exponent bits (no `vscalefps`).
//!
//! Every sum is taken in a fixed order, so results do not depend on the thread count.

#[cfg(target_arch = "x86_64")]
pub(crate) use x86::{attention, cross_attention_shared};

#[cfg(target_arch = "x86_64")]
mod x86 {
use std::arch::x86_64::*;

use rayon::prelude::*;

use crate::attention_fused::x86::{head_values, merge_columns, pack, ColumnState, CrossTasks, HeadValues, Packed, StripOut, MAX_D, NEG, STRIP};
use crate::error::Result;
use crate::kernels::{internal, sum_in_order, Matrix, SharedMut, View};

/// Whether these kernels run here and serve head width `d`: the fused kernels' own
/// condition, which the AVX-512 ones share.
fn runs(d: usize) -> bool {
    crate::attention_fused::x86::available(d)
}

// ---- vector helpers -----------------------------------------------------------------

/// `2^x` to 2.4e-7 relative error (the degree-5 minimax of the AVX-512 kernels on
/// [−½, ½]); 0 below −126.5 and at most 2^−126 below −126 (the AVX-512 kernels flush below
/// −150), NaN stays NaN; above 127 it saturates at about 2^127 instead of +∞ (the softmax
/// passes only x ≤ 0, its scores less their row maximum). Rounding by the 1.5·2^23 shift
/// leaves the integer part in the low mantissa bits, so no compare, round or conversion is
/// needed: the softmax's exponentials were a third of the kernels' time.
#[inline(always)]
unsafe fn exp2v(x: __m256) -> __m256 {
    const SHIFT: f32 = 12_582_912.0; // 1.5·2^23
    // max/min return their second operand (x) when x is NaN, so NaN propagates. At −127 the
    // power below is the float with exponent bits 0: the result is exactly 0.
    let x = _mm256_min_ps(_mm256_set1_ps(127.0), _mm256_max_ps(_mm256_set1_ps(-127.0), x));
    let t = _mm256_add_ps(x, _mm256_set1_ps(SHIFT));
    let f = _mm256_sub_ps(x, _mm256_sub_ps(t, _mm256_set1_ps(SHIFT)));
    let coef = [1.000_000_1f32, 0.693_146_94, 0.240_221_2, 0.055_507_13, 0.009_675_541, 0.001_327_647_1];
    let mut p = _mm256_set1_ps(coef[5]);
    for &c in coef[..5].iter().rev() {
        p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(c));
    }
    // 2^n for n in [−127, 127] as the float with biased exponent n + 127: the low bits of t
    // hold n (the shift's own bits leave the word when shifted by 23).
    let pow = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(_mm256_castps_si256(t), _mm256_set1_epi32(127))));
    _mm256_mul_ps(p, pow)
}

/// `y = 2^x` for 8 values, for the tests.
#[cfg(test)]
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn exp2_of(x: &[f32; 8], y: &mut [f32; 8]) {
    _mm256_storeu_ps(y.as_mut_ptr(), exp2v(_mm256_loadu_ps(x.as_ptr())));
}

/// All-ones lanes where column `j0 + lane` lies below `n`.
#[inline(always)]
unsafe fn valid(n: usize, j0: usize) -> __m256 {
    let idx = _mm256_add_epi32(_mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7), _mm256_set1_epi32(j0.min(i32::MAX as usize) as i32));
    _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_set1_epi32(n.min(i32::MAX as usize) as i32), idx))
}

#[inline(always)]
unsafe fn hmax(v: __m256) -> f32 {
    let m = _mm_max_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let m = _mm_max_ps(m, _mm_movehl_ps(m, m));
    _mm_cvtss_f32(_mm_max_ss(m, _mm_shuffle_ps::<1>(m, m)))
}

#[inline(always)]
unsafe fn hsum(v: __m256) -> f32 {
    let m = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let m = _mm_add_ps(m, _mm_movehl_ps(m, m));
    _mm_cvtss_f32(_mm_add_ss(m, _mm_shuffle_ps::<1>(m, m)))
}

// ---- micro-kernels ------------------------------------------------------------------

/// Register tiles of 6 rows (or columns) × 16: 12 accumulators, with registers left for
/// two operand loads and a broadcast (16 ymm in all); 16 rows take tiles of 6, 6 and 4.
const TILES: [(usize, usize); 3] = [(0, 6), (6, 6), (12, 4)];

/// Scores of a strip: `s[r][j] = Σ_t q[r][t]·kᵀ[t][j]` for 16 rows and all `np` columns
/// (columns ≥ `n` set to −∞). Panel-major, so each key panel is read from L1 by every
/// row tile of the strip.
#[inline(always)]
unsafe fn scores<const D: usize>(q: *const f32, kp: *const f32, n: usize, np: usize, s: *mut f32, ld: usize) {
    for p in 0..np / 16 {
        let bp = kp.add(p * D * 16);
        let (m0, m1) = (valid(n, p * 16), valid(n, p * 16 + 8));
        let out = s.add(p * 16);
        scores_tile::<D, 6>(q, bp, out, ld, m0, m1);
        scores_tile::<D, 6>(q.add(6 * D), bp, out.add(6 * ld), ld, m0, m1);
        scores_tile::<D, 4>(q.add(12 * D), bp, out.add(12 * ld), ld, m0, m1);
    }
}

/// `R` rows of [`scores`] against one key panel.
#[inline(always)]
unsafe fn scores_tile<const D: usize, const R: usize>(q: *const f32, bp: *const f32, out: *mut f32, ld: usize, m0: __m256, m1: __m256) {
    let mut acc = [[_mm256_setzero_ps(); 2]; R];
    for t in 0..D {
        let b0 = _mm256_loadu_ps(bp.add(t * 16));
        let b1 = _mm256_loadu_ps(bp.add(t * 16 + 8));
        for (r, a) in acc.iter_mut().enumerate() {
            let x = _mm256_broadcast_ss(&*q.add(r * D + t));
            a[0] = _mm256_fmadd_ps(x, b0, a[0]);
            a[1] = _mm256_fmadd_ps(x, b1, a[1]);
        }
    }
    let neg = _mm256_set1_ps(f32::NEG_INFINITY);
    for (r, a) in acc.iter().enumerate() {
        let row = out.add(r * ld);
        _mm256_storeu_ps(row, _mm256_blendv_ps(neg, a[0], m0));
        _mm256_storeu_ps(row.add(8), _mm256_blendv_ps(neg, a[1], m1));
    }
}

/// `2^(s − max)` of row `s[..np]`, in place; returns the sum and the max. Four vectors per step: the
/// exponential is a chain of dependent operations, and independent chains side by side keep
/// both FMA pipes busy.
#[inline(always)]
unsafe fn exp_row(s: *mut f32, np: usize) -> (f32, f32) {
    let (mut m0, mut m1) = (_mm256_set1_ps(f32::NEG_INFINITY), _mm256_set1_ps(f32::NEG_INFINITY));
    for c in (0..np).step_by(16) {
        m0 = _mm256_max_ps(m0, _mm256_loadu_ps(s.add(c)));
        m1 = _mm256_max_ps(m1, _mm256_loadu_ps(s.add(c + 8)));
    }
    let top = hmax(_mm256_max_ps(m0, m1));
    let m = _mm256_set1_ps(top);
    let mut sum = [_mm256_setzero_ps(); 4];
    let mut c = 0;
    while c + 32 <= np {
        // No closures here: they would not inherit the caller's target features.
        let e = [
            exp2v(_mm256_sub_ps(_mm256_loadu_ps(s.add(c)), m)),
            exp2v(_mm256_sub_ps(_mm256_loadu_ps(s.add(c + 8)), m)),
            exp2v(_mm256_sub_ps(_mm256_loadu_ps(s.add(c + 16)), m)),
            exp2v(_mm256_sub_ps(_mm256_loadu_ps(s.add(c + 24)), m)),
        ];
        for (o, (a, x)) in sum.iter_mut().zip(e).enumerate() {
            *a = _mm256_add_ps(*a, x);
            _mm256_storeu_ps(s.add(c + 8 * o), x);
        }
        c += 32;
    }
    if c < np {
        let e = [exp2v(_mm256_sub_ps(_mm256_loadu_ps(s.add(c)), m)), exp2v(_mm256_sub_ps(_mm256_loadu_ps(s.add(c + 8)), m))];
        for (o, (a, x)) in sum.iter_mut().zip(e).enumerate() {
            *a = _mm256_add_ps(*a, x);
            _mm256_storeu_ps(s.add(c + 8 * o), x);
        }
    }
    (hsum(_mm256_add_ps(_mm256_add_ps(sum[0], sum[1]), _mm256_add_ps(sum[2], sum[3]))), top)
}

/// `out[r][..D] = Σ_j p[r][j]·v[j][..D]` for 16 rows (`v` strided), in tiles of up to
/// 6 rows × 16 columns ([`TILES`]).
#[inline(always)]
unsafe fn values<const D: usize>(p: *const f32, ld: usize, n: usize, v: *const f32, v_stride: usize, out: &mut StripOut) {
    const { assert!(D.is_multiple_of(16) && D <= MAX_D) };
    for c in (0..D).step_by(16) {
        for (r0, rows) in TILES {
            let mut tile = [[0.0f32; 16]; 6];
            if rows == 6 {
                values_tile::<6>(p.add(r0 * ld), ld, n, v.add(c), v_stride, &mut tile);
            } else {
                values_tile::<4>(p.add(r0 * ld), ld, n, v.add(c), v_stride, &mut tile);
            }
            for (o, t) in out[r0..r0 + rows].iter_mut().zip(&tile) {
                o[c..c + 16].copy_from_slice(t);
            }
        }
    }
}

/// `R` rows × 16 columns of [`values`]: `tile[r] = Σ_j p[r][j]·v[j][..16]`.
#[inline(always)]
unsafe fn values_tile<const R: usize>(p: *const f32, ld: usize, n: usize, v: *const f32, v_stride: usize, tile: &mut [[f32; 16]; 6]) {
    let mut acc = [[_mm256_setzero_ps(); 2]; R];
    for j in 0..n {
        let vp = v.add(j * v_stride);
        let (v0, v1) = (_mm256_loadu_ps(vp), _mm256_loadu_ps(vp.add(8)));
        for (r, a) in acc.iter_mut().enumerate() {
            let x = _mm256_broadcast_ss(&*p.add(r * ld + j));
            a[0] = _mm256_fmadd_ps(x, v0, a[0]);
            a[1] = _mm256_fmadd_ps(x, v1, a[1]);
        }
    }
    for (t, a) in tile.iter_mut().zip(&acc) {
        _mm256_storeu_ps(t.as_mut_ptr(), a[0]);
        _mm256_storeu_ps(t.as_mut_ptr().add(8), a[1]);
    }
}

/// Softmax over the keys of the strip's rows and the value product: rows `r0..r0+rows`
/// of columns `h·D..(h+1)·D` of `dst` (row stride `H·D`). Returns each row's `1/Σ` and
/// maximum; `s` then holds the unnormalised probabilities `2^(s − max)`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
unsafe fn strip_rows<const D: usize>(pk: &Packed, h: usize, r0: usize, rows: usize, s: &mut [f32], vp: HeadValues, dst: SharedMut) -> ([f32; STRIP], [f32; STRIP]) {
    let (n, np, ld, c) = (pk.n, pk.np, pk.ld, pk.heads * D);
    let (mut inv, mut top) = ([0.0f32; STRIP], [0.0f32; STRIP]);
    for r in 0..STRIP {
        let (sum, mx) = exp_row(s.as_mut_ptr().add(r * ld), np);
        (inv[r], top[r]) = (1.0 / sum, mx);
    }
    let mut out: StripOut = [[0.0; MAX_D]; STRIP];
    values::<D>(s.as_ptr(), ld, n, vp.row(h, 0), vp.stride, &mut out);
    for (r, o) in out.iter().enumerate().take(rows) {
        let row = dst.at((r0 + r) * c + h * D);
        for (t, x) in o[..D].iter().enumerate() {
            *row.add(t) = x * inv[r];
        }
    }
    (inv, top)
}

/// Scores of the 16 query rows from `r0` of head `h` into the strip `s`.
#[inline(always)]
unsafe fn strip_scores<const D: usize>(pk: &Packed, h: usize, r0: usize, s: &mut [f32]) {
    scores::<D>(pk.q.as_ptr().add((h * pk.mp + r0) * D), pk.k.as_ptr().add(h * pk.np * D), pk.n, pk.np, s.as_mut_ptr(), pk.ld);
}

// ---- self attention -----------------------------------------------------------------

/// `softmax(q·kᵀ/√d)·v` for every head, with optional column sums of the probabilities
/// (`Σ_h Σ_i A[h,i,j]`), as [`crate::attention::attention`] in fp32; an error where this
/// CPU lacks AVX2 and FMA or the head width is not 16, 32, 64 or 96.
pub fn attention(q: View, k: View, v: View, heads: usize, col_sums: bool) -> Result<(Matrix, Option<Vec<f32>>)> {
    let (m, n, c) = (q.rows, k.rows, q.cols);
    if k.cols != c || v.cols != c || v.rows != n || heads == 0 || c % heads != 0 || !v.fits() || !runs(c / heads) {
        return Err(internal(format!("fused AVX2 attention q {m}×{c}, k {}×{}, v {}×{}, {heads} heads", k.rows, k.cols, v.rows, v.cols)));
    }
    let mut out = Matrix::zeros(m, c);
    if m == 0 || n == 0 {
        return Ok((out, col_sums.then(|| vec![0.0; n])));
    }
    let pk = pack(q, k, heads, false);
    // Values of each head in contiguous rows: the value product streams them once per
    // 6-row tile, so they should stay in L2 (rows of the projections are 3C apart).
    let mut vbuf = Vec::new();
    let vp = head_values(v, heads, &mut vbuf);
    let (d, strips) = (pk.d, pk.mp / STRIP);
    let dst = SharedMut(out.data.as_mut_ptr());
    let per_task: Vec<Vec<f32>> = (0..heads * strips)
        .into_par_iter()
        .map_init(
            || vec![0.0f32; STRIP * pk.ld],
            |s, t| {
                let (h, st) = (t % heads, t / heads);
                let mut cs = if col_sums { vec![0.0f32; n] } else { Vec::new() };
                // SAFETY: AVX2 and FMA were checked on entry; task (h, st) alone writes
                // rows st·16.. of columns h·d..(h+1)·d of `out`.
                unsafe {
                    match d {
                        16 => self_strip::<16>(&pk, vp, h, st, dst, s, &mut cs),
                        32 => self_strip::<32>(&pk, vp, h, st, dst, s, &mut cs),
                        64 => self_strip::<64>(&pk, vp, h, st, dst, s, &mut cs),
                        _ => self_strip::<96>(&pk, vp, h, st, dst, s, &mut cs),
                    }
                }
                cs
            },
        )
        .collect();
    Ok((out, col_sums.then(|| sum_in_order(&per_task, n))))
}

/// One strip of self attention: rows `st·16..` of head `h`, and their probabilities
/// summed per column into `cs` when it is not empty.
#[target_feature(enable = "avx2,fma")]
unsafe fn self_strip<const D: usize>(pk: &Packed, vp: HeadValues, h: usize, st: usize, dst: SharedMut, s: &mut [f32], cs: &mut [f32]) {
    let r0 = st * STRIP;
    let rows = STRIP.min(pk.m - r0);
    strip_scores::<D>(pk, h, r0, s);
    let (inv, _) = strip_rows::<D>(pk, h, r0, rows, s, vp, dst);
    for (r, iv) in inv.iter().enumerate().take(if cs.is_empty() { 0 } else { rows }) {
        for (a, e) in cs.iter_mut().zip(&s[r * pk.ld..r * pk.ld + pk.n]) {
            *a += e * iv;
        }
    }
}

// ---- shared cross attention ---------------------------------------------------------

/// Cross attention with attention-weight sharing in fp32, as
/// [`crate::attention::cross_attention_shared`]: `(softmax_rows(S)·vy, softmax_rows(Sᵀ)·vx)`
/// with `S = qx·kyᵀ/√d` per head.
pub fn cross_attention_shared(qx: View, ky: View, vx: View, vy: View, heads: usize) -> Result<(Matrix, Matrix)> {
    let (m, n, c) = (qx.rows, ky.rows, qx.cols);
    if ky.cols != c || vx.cols != c || vy.cols != c || vx.rows != m || vy.rows != n || heads == 0 || c % heads != 0 || !vx.fits() || !vy.fits() || !runs(c / heads) {
        return Err(internal(format!("fused AVX2 cross attention qx {m}×{c}, ky {n}×{}, {heads} heads", ky.cols)));
    }
    let (mut out_x, mut out_y) = (Matrix::zeros(m, c), Matrix::zeros(n, c));
    if m == 0 || n == 0 {
        return Ok((out_x, out_y));
    }
    let pk = pack(qx, ky, heads, false);
    let (mut vxbuf, mut vybuf) = (Vec::new(), Vec::new());
    let (vx, vyp) = (head_values(vx, heads, &mut vxbuf), head_values(vy, heads, &mut vybuf));
    let d = pk.d;
    let split = CrossTasks::new(m);
    let chunks = split.chunks();
    let dx = SharedMut(out_x.data.as_mut_ptr());
    let states: Vec<ColumnState> = (0..heads * chunks)
        .into_par_iter()
        .map(|t| {
            let (h, ch) = (t % heads, t / heads);
            let rows = split.rows(ch);
            // SAFETY: AVX2 and FMA were checked on entry; task (h, ch) alone writes rows
            // `rows` of columns h·d..(h+1)·d of `out_x`.
            // The one-scale pass, or where a column's share fell too low for it, the exact
            // pass with running column maxima (both write the same rows of `out_x`).
            unsafe {
                match d {
                    16 => cross_chunk_one_scale::<16>(&pk, vx, vyp, h, rows, dx).unwrap_or_else(|| cross_chunk::<16>(&pk, vx, vyp, h, rows, dx)),
                    32 => cross_chunk_one_scale::<32>(&pk, vx, vyp, h, rows, dx).unwrap_or_else(|| cross_chunk::<32>(&pk, vx, vyp, h, rows, dx)),
                    64 => cross_chunk_one_scale::<64>(&pk, vx, vyp, h, rows, dx).unwrap_or_else(|| cross_chunk::<64>(&pk, vx, vyp, h, rows, dx)),
                    _ => cross_chunk_one_scale::<96>(&pk, vx, vyp, h, rows, dx).unwrap_or_else(|| cross_chunk::<96>(&pk, vx, vyp, h, rows, dx)),
                }
            }
        })
        .collect();
    merge_columns(&states, heads, chunks, d, &mut out_y);
    Ok((out_x, out_y))
}

/// 2^−100: below this share of the task's largest score a column's sum would lose
/// precision (or vanish) in [`cross_chunk_one_scale`], which then gives way to the exact pass.
const ONE_SCALE_FLOOR: f32 = f32::from_bits((127 - 100) << 23);

/// One task of the shared cross attention with one scale for every column: the row pass
/// leaves `2^(s_ij − m_i)` in the strip (`m_i` the row's maximum), and since
/// `2^(s_ij − g) = 2^(s_ij − m_i)·2^(m_i − g)` for the task's running maximum `g`, the column
/// direction reuses those exponentials with `vx_i` scaled by `2^(m_i − g)`: no column maxima
/// and no second exponential per score. Each column's sum and products are brought back to
/// their own scale for [`merge_columns`] (by a power of two, exactly). `None` where a column's
/// sum fell below [`ONE_SCALE_FLOOR`] (scores spread over more than ~100 binary orders, or
/// not finite): the caller runs the exact [`cross_chunk`] instead.
#[target_feature(enable = "avx2,fma")]
unsafe fn cross_chunk_one_scale<const D: usize>(pk: &Packed, vx: HeadValues, vyp: HeadValues, h: usize, (first, last): (usize, usize), dx: SharedMut) -> Option<ColumnState> {
    let (n, np, ld) = (pk.n, pk.np, pk.ld);
    let (mut sum, mut acc) = (vec![0.0f32; np], vec![0.0f32; np * D]);
    let mut s = vec![0.0f32; STRIP * ld];
    let mut g = NEG;
    for r0 in (first..last).step_by(STRIP) {
        let rows = STRIP.min(last - r0);
        strip_scores::<D>(pk, h, r0, &mut s);
        let (_, top) = strip_rows::<D>(pk, h, r0, rows, &mut s, vyp, dx);
        let strip_top = top[..rows].iter().fold(NEG, |a, &b| a.max(b));
        if strip_top > g {
            // A larger maximum: what was summed so far moves to the new scale.
            if g > NEG {
                let f = (g - strip_top).exp2();
                sum.iter_mut().chain(acc.iter_mut()).for_each(|x| *x *= f);
            }
            g = strip_top;
        }
        let mut w = [0.0f32; STRIP];
        let mut xs: StripOut = [[0.0; MAX_D]; STRIP];
        for r in 0..rows {
            w[r] = (top[r] - g).exp2();
            let row = std::slice::from_raw_parts(vx.row(h, r0 + r), D);
            for (x, v) in xs[r].iter_mut().zip(row) {
                *x = v * w[r];
            }
        }
        column_sums(s.as_ptr(), ld, np, rows, &w, &mut sum);
        for j0 in (0..np).step_by(16) {
            for c in (0..D).step_by(16) {
                for (jt, cols) in TILES {
                    let (ep, ap) = (s.as_ptr().add(j0 + jt), acc.as_mut_ptr().add((j0 + jt) * D + c));
                    if cols == 6 {
                        column_tile::<D, 6>(ep, ld, rows, xs.as_ptr().cast::<f32>().add(c), MAX_D, ap);
                    } else {
                        column_tile::<D, 4>(ep, ld, rows, xs.as_ptr().cast::<f32>().add(c), MAX_D, ap);
                    }
                }
            }
        }
    }
    let mut max = vec![g; n];
    for j in 0..n {
        if sum[j].is_nan() || sum[j] < ONE_SCALE_FLOOR {
            return None;
        }
        // The sum's binary exponent e: sum and products times 2^−e, the maximum g + e.
        let e = ((sum[j].to_bits() >> 23) & 0xff) as i32 - 127;
        let scale = f32::from_bits(((127 - e) as u32) << 23);
        sum[j] *= scale;
        acc[j * D..(j + 1) * D].iter_mut().for_each(|a| *a *= scale);
        max[j] = g + e as f32;
    }
    sum.truncate(n);
    acc.truncate(n * D);
    Some(ColumnState { max, sum, acc })
}

/// Whether every task of [`cross_attention_shared`] on these inputs takes the one-scale
/// pass (for the tests: each path must be seen to run).
#[cfg(test)]
pub(super) fn one_scale_holds(qx: View, ky: View, vx: View, vy: View, heads: usize) -> bool {
    let (m, d) = (qx.rows, qx.cols / heads);
    let pk = pack(qx, ky, heads, false);
    let (mut vxbuf, mut vybuf) = (Vec::new(), Vec::new());
    let (vx, vyp) = (head_values(vx, heads, &mut vxbuf), head_values(vy, heads, &mut vybuf));
    let mut scratch = Matrix::zeros(m, qx.cols);
    let dx = SharedMut(scratch.data.as_mut_ptr());
    let split = CrossTasks::new(m);
    (0..heads * split.chunks()).all(|t| {
        let (h, ch) = (t % heads, t / heads);
        let rows = split.rows(ch);
        // SAFETY: the tests call this only where AVX2 and FMA are present.
        unsafe {
            match d {
                16 => cross_chunk_one_scale::<16>(&pk, vx, vyp, h, rows, dx).is_some(),
                32 => cross_chunk_one_scale::<32>(&pk, vx, vyp, h, rows, dx).is_some(),
                64 => cross_chunk_one_scale::<64>(&pk, vx, vyp, h, rows, dx).is_some(),
                _ => cross_chunk_one_scale::<96>(&pk, vx, vyp, h, rows, dx).is_some(),
            }
        }
    })
}

/// `sum_j += Σ_r e[r][j]·w_r` for the `rows` rows of the strip (row stride `ld`), 32 columns
/// per step: four independent chains of FMAs.
#[inline(always)]
unsafe fn column_sums(e: *const f32, ld: usize, np: usize, rows: usize, w: &[f32; STRIP], sum: &mut [f32]) {
    for j in (0..np).step_by(32) {
        let sp = sum.as_mut_ptr().add(j);
        let mut a = [_mm256_loadu_ps(sp), _mm256_loadu_ps(sp.add(8)), _mm256_loadu_ps(sp.add(16)), _mm256_loadu_ps(sp.add(24))];
        for (r, &wr) in w.iter().enumerate().take(rows) {
            let (x, er) = (_mm256_set1_ps(wr), e.add(r * ld + j));
            for (o, av) in a.iter_mut().enumerate() {
                *av = _mm256_fmadd_ps(_mm256_loadu_ps(er.add(8 * o)), x, *av);
            }
        }
        for (o, av) in a.iter().enumerate() {
            _mm256_storeu_ps(sp.add(8 * o), *av);
        }
    }
}

/// One task of the shared cross attention: rows `first..last` of head `h`; returns its
/// column state (running maxima, sums and `Σ_i e_ij·vx_i`) for the merge.
#[target_feature(enable = "avx2,fma")]
unsafe fn cross_chunk<const D: usize>(pk: &Packed, vx: HeadValues, vyp: HeadValues, h: usize, (first, last): (usize, usize), dx: SharedMut) -> ColumnState {
    let (np, ld) = (pk.np, pk.ld);
    let mut st = ColumnState { max: vec![NEG; np], sum: vec![0.0; np], acc: vec![0.0; np * D] };
    let mut s = vec![0.0f32; STRIP * ld];
    let mut factor = vec![0.0f32; np];
    for r0 in (first..last).step_by(STRIP) {
        let rows = STRIP.min(last - r0);
        strip_scores::<D>(pk, h, r0, &mut s);
        // Columns: new running maxima over the valid rows; rescale what grew.
        let sp = s.as_ptr();
        let mut grew = false;
        for j in (0..np).step_by(8) {
            let old = _mm256_loadu_ps(st.max.as_ptr().add(j));
            let mut bm = old;
            for r in 0..rows {
                bm = _mm256_max_ps(bm, _mm256_loadu_ps(sp.add(r * ld + j)));
            }
            // Exactly 1 where the maximum stayed (`exp2v(0)` is 1 + 1.2e-7: see the AVX-512 kernel).
            let up = _mm256_cmp_ps::<_CMP_NEQ_UQ>(bm, old);
            let f = _mm256_blendv_ps(_mm256_set1_ps(1.0), exp2v(_mm256_sub_ps(old, bm)), up);
            _mm256_storeu_ps(st.max.as_mut_ptr().add(j), bm);
            _mm256_storeu_ps(factor.as_mut_ptr().add(j), f);
            _mm256_storeu_ps(st.sum.as_mut_ptr().add(j), _mm256_mul_ps(f, _mm256_loadu_ps(st.sum.as_ptr().add(j))));
            grew |= _mm256_movemask_ps(up) != 0;
        }
        if grew && r0 > first {
            for (j, &f) in factor.iter().enumerate() {
                if f != 1.0 {
                    for a in &mut st.acc[j * D..(j + 1) * D] {
                        *a *= f;
                    }
                }
            }
        }
        column_values::<D>(sp, np, ld, rows, &mut st, vx.row(h, r0), vx.stride);
        // Rows: softmax over the keys, values of image 1.
        strip_rows::<D>(pk, h, r0, rows, &mut s, vyp, dx);
    }
    let n = pk.n;
    st.max.truncate(n);
    st.sum.truncate(n);
    st.acc.truncate(n * D);
    st
}

/// Column direction of one strip: `e_rj = 2^(s_rj − max_j)`, `sum_j += Σ_r e_rj` and
/// `acc_j += Σ_r e_rj·vx_r`, for 16 columns at a time in tiles of up to 6 columns × 16
/// channels ([`TILES`]): 12 accumulators.
#[inline(always)]
unsafe fn column_values<const D: usize>(s: *const f32, np: usize, ld: usize, rows: usize, st: &mut ColumnState, vx: *const f32, vx_stride: usize) {
    let mut e = [[0.0f32; 16]; STRIP];
    for j0 in (0..np).step_by(16) {
        // Both halves of two rows per step: four independent exponentials (see exp_row).
        let mx = [_mm256_loadu_ps(st.max.as_ptr().add(j0)), _mm256_loadu_ps(st.max.as_ptr().add(j0 + 8))];
        let mut sum = [_mm256_loadu_ps(st.sum.as_ptr().add(j0)), _mm256_loadu_ps(st.sum.as_ptr().add(j0 + 8))];
        let mut r = 0;
        while r < rows {
            let pair = if r + 1 < rows { 2 } else { 1 };
            let (a, b) = (s.add(r * ld + j0), s.add((r + pair - 1) * ld + j0));
            let x = [
                exp2v(_mm256_sub_ps(_mm256_loadu_ps(a), mx[0])),
                exp2v(_mm256_sub_ps(_mm256_loadu_ps(a.add(8)), mx[1])),
                exp2v(_mm256_sub_ps(_mm256_loadu_ps(b), mx[0])),
                exp2v(_mm256_sub_ps(_mm256_loadu_ps(b.add(8)), mx[1])),
            ];
            for dr in 0..pair {
                for h in 0..2 {
                    sum[h] = _mm256_add_ps(sum[h], x[2 * dr + h]);
                    _mm256_storeu_ps(e[r + dr].as_mut_ptr().add(8 * h), x[2 * dr + h]);
                }
            }
            r += pair;
        }
        for (h, v) in sum.iter().enumerate() {
            _mm256_storeu_ps(st.sum.as_mut_ptr().add(j0 + 8 * h), *v);
        }
        for c in (0..D).step_by(16) {
            for (jt, cols) in TILES {
                let acc = st.acc.as_mut_ptr().add((j0 + jt) * D + c);
                let ep = e.as_ptr().cast::<f32>().add(jt);
                if cols == 6 {
                    column_tile::<D, 6>(ep, 16, rows, vx.add(c), vx_stride, acc);
                } else {
                    column_tile::<D, 4>(ep, 16, rows, vx.add(c), vx_stride, acc);
                }
            }
        }
    }
}

/// `C` columns × 16 channels of the column products: `acc[jj] += Σ_r e[r][jj]·vx_r` (`e`
/// at the tile's first column, row stride `e_ld`; `acc` at that column's channel block,
/// row stride `D`).
#[inline(always)]
unsafe fn column_tile<const D: usize, const C: usize>(e: *const f32, e_ld: usize, rows: usize, vx: *const f32, vx_stride: usize, acc: *mut f32) {
    let mut t = [[_mm256_setzero_ps(); 2]; C];
    for r in 0..rows {
        let (vp, er) = (vx.add(r * vx_stride), e.add(r * e_ld));
        let (v0, v1) = (_mm256_loadu_ps(vp), _mm256_loadu_ps(vp.add(8)));
        for (jj, a) in t.iter_mut().enumerate() {
            let x = _mm256_broadcast_ss(&*er.add(jj));
            a[0] = _mm256_fmadd_ps(x, v0, a[0]);
            a[1] = _mm256_fmadd_ps(x, v1, a[1]);
        }
    }
    for (jj, a) in t.iter().enumerate() {
        let ap = acc.add(jj * D);
        _mm256_storeu_ps(ap, _mm256_add_ps(_mm256_loadu_ps(ap), a[0]));
        _mm256_storeu_ps(ap.add(8), _mm256_add_ps(_mm256_loadu_ps(ap.add(8)), a[1]));
    }
}
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use crate::attention::{attention as general_attention, cross_attention_shared as general_cross};
    use crate::attention_fused::tests::{general, max_diff, random};

    /// The AVX2 kernels, called directly (so they are checked on AVX-512 CPUs too), against
    /// the general path: odd sizes (padding of rows and columns), every head width, more rows
    /// than one cross-attention task.
    #[test]
    fn avx2_kernels_match_the_general_path() {
        if crate::kernels::simd_level() < 3 {
            eprintln!("skipped: no AVX2 and FMA here");
            return;
        }
        for &(m, n, c, heads, amp) in &[(77, 53, 64, 4, 1.0), (600, 301, 64, 2, 2.0), (33, 517, 128, 2, 1.5), (5, 1, 32, 2, 1.0), (300, 300, 64, 1, 3.0), (2100, 40, 64, 2, 1.0), (77, 53, 96, 1, 1.0), (300, 517, 192, 2, 2.0)] {
            let (q, k, v) = (random(m, c, 1, amp), random(n, c, 2, amp), random(n, c, 3, 1.0));
            let (vx, ky) = (random(m, c, 4, 1.0), random(n, c, 5, amp));
            let (want, want_cs) = general_attention(&general(), q.view(), k.view(), v.view(), heads, true).expect("general");
            let (got, got_cs) = super::attention(q.view(), k.view(), v.view(), heads, true).expect("avx2");
            let (want_cs, got_cs) = (want_cs.expect("sums"), got_cs.expect("sums"));
            assert!(max_diff(&want.data, &got.data) < 2e-6, "self {m}×{n} c{c} h{heads}: {}", max_diff(&want.data, &got.data));
            assert!(max_diff(&want_cs, &got_cs) < 1e-5 * m as f32, "col sums: {}", max_diff(&want_cs, &got_cs));
            let (wx, wy) = general_cross(&general(), q.view(), ky.view(), vx.view(), v.view(), heads).expect("general");
            let (gx, gy) = super::cross_attention_shared(q.view(), ky.view(), vx.view(), v.view(), heads).expect("avx2");
            assert!(max_diff(&wx.data, &gx.data) < 2e-6, "cross x {m}×{n}: {}", max_diff(&wx.data, &gx.data));
            assert!(max_diff(&wy.data, &gy.data) < 2e-6, "cross y {m}×{n}: {}", max_diff(&wy.data, &gy.data));
        }
    }

    /// The shared cross attention's one-scale pass and its exact fallback: ordinary scores
    /// take the first, one query row with scores ~300 binary orders above the rest (so some
    /// columns' share falls under 2^−100) the second; both match the general path.
    #[test]
    fn avx2_cross_attention_falls_back_where_one_scale_cannot_hold() {
        if crate::kernels::simd_level() < 3 {
            eprintln!("skipped: no AVX2 and FMA here");
            return;
        }
        let (m, n, c, heads) = (300, 200, 64, 2);
        let (ky, vx, vy) = (random(n, c, 5, 2.0), random(m, c, 4, 1.0), random(n, c, 3, 1.0));
        let mut q = random(m, c, 1, 2.0);
        let ordinary = super::x86::one_scale_holds(q.view(), ky.view(), vx.view(), vy.view(), heads);
        for x in &mut q.data[7 * c..8 * c] {
            *x *= 60.0;
        }
        let spread = super::x86::one_scale_holds(q.view(), ky.view(), vx.view(), vy.view(), heads);
        assert!(ordinary && !spread, "one scale holds: ordinary {ordinary}, spread {spread}");
        let (wx, wy) = general_cross(&general(), q.view(), ky.view(), vx.view(), vy.view(), heads).expect("general");
        let (gx, gy) = super::cross_attention_shared(q.view(), ky.view(), vx.view(), vy.view(), heads).expect("avx2");
        // Scores 60× the others: the running maxima rescale often, and the rounding of those
        // rescales reaches 1.9–2.1e-6 here (values of size ~1).
        assert!(max_diff(&wx.data, &gx.data) < 3e-6, "cross x: {}", max_diff(&wx.data, &gx.data));
        assert!(max_diff(&wy.data, &gy.data) < 3e-6, "cross y: {}", max_diff(&wy.data, &gy.data));
    }

    /// Head widths the kernels do not serve, and mismatched shapes, are errors.
    #[test]
    fn avx2_kernels_refuse_other_shapes() {
        let (q, k) = (random(8, 48, 1, 1.0), random(9, 48, 2, 1.0));
        assert!(super::attention(q.view(), k.view(), k.view(), 2, false).is_err(), "head width 24");
        assert!(super::attention(q.view(), k.view(), q.view(), 3, false).is_err(), "v rows differ from k rows");
        assert!(super::cross_attention_shared(q.view(), k.view(), k.view(), k.view(), 3).is_err(), "vx rows differ from qx rows");
        assert!(super::cross_attention_shared(q.view(), k.view(), q.view(), k.view(), 0).is_err(), "no heads");
    }

    /// `2^x` against the standard library over the range the softmax sees, with the flush
    /// to 0 below −126.5 (tiny below −126), −∞ → 0 and NaN kept.
    #[test]
    fn exp2_is_accurate_flushes_and_keeps_nan() {
        if crate::kernels::simd_level() < 3 {
            eprintln!("skipped: no AVX2 and FMA here");
            return;
        }
        let xs: Vec<f32> = (0..4000).map(|i| -130.0 + i as f32 * 0.0331).chain([0.0, -126.0, -127.0, -1e30, f32::NEG_INFINITY, f32::NAN, 3.7, 127.0, 127.4, 200.0, f32::INFINITY]).collect();
        for chunk in xs.chunks(8) {
            let mut x = [0.0f32; 8];
            x[..chunk.len()].copy_from_slice(chunk);
            let mut y = [0.0f32; 8];
            // SAFETY: AVX2 and FMA checked above.
            unsafe { super::x86::exp2_of(&x, &mut y) };
            for (a, b) in x.iter().zip(&y) {
                if a.is_nan() {
                    assert!(b.is_nan(), "2^NaN gave {b}");
                } else if *a > 127.0 {
                    assert!(b.is_finite() && *b >= 2f32.powi(127), "2^{a} saturates at 2^127: {b}");
                } else if *a < -126.5 {
                    assert_eq!(*b, 0.0, "2^{a} is flushed to 0");
                } else if *a < -126.0 {
                    assert!((0.0..=f32::MIN_POSITIVE).contains(b), "2^{a}: {b}, expected at most 2^-126");
                } else {
                    let want = (*a as f64).exp2();
                    assert!(((*b as f64) - want).abs() <= 3e-7 * want, "2^{a}: {b} against {want}");
                }
            }
        }
    }

    /// Results do not depend on the thread count.
    #[test]
    fn avx2_kernels_are_reproducible_across_thread_counts() {
        if crate::kernels::simd_level() < 3 {
            eprintln!("skipped: no AVX2 and FMA here");
            return;
        }
        let (q, k, v) = (random(700, 64, 7, 2.0), random(650, 64, 8, 2.0), random(650, 64, 9, 1.0));
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            pool.install(|| {
                let (a, s) = super::attention(q.view(), k.view(), v.view(), 2, true).expect("self");
                let (x, y) = super::cross_attention_shared(q.view(), k.view(), q.view(), v.view(), 2).expect("cross");
                (a.data, s, x.data, y.data)
            })
        };
        assert!(run(1) == run(3));
    }
}

