//! Gradient of softmax attention (SPEC §4: `softmax(q·kᵀ/√d)·v` per head) for training on
//! AVX-512 BF16 CPUs: given the forward's output `o` and row log-sum-exp `lse`, it returns
//! `dq`, `dk`, `dv` for an upstream gradient `do` without storing the probabilities.
//!
//! PyTorch's CPU flash-attention backward takes 2–5× its forward at the narrow heads of
//! the shipped models (width 32); this one recomputes the scores block by block, as the
//! flash-attention backward does (Dao, *FlashAttention-2*, 2023, Alg. 2): for each block of
//! keys, every strip of 16 queries rebuilds `P = exp(s − lse)` and `dP = do·vᵀ`, forms
//! `dS = P∘(dP − rowsum(do∘o))`, adds `dS·k` to `dq` and accumulates `Pᵀ·do` and `dSᵀ·q` for
//! the block's `dv` and `dk`, which stay in cache. All five products take bf16 operands with
//! fp32 accumulation (`vdpbf16ps`); exponentials and the softmax gradient are fp32.
//!
//! [`attention_forward_bf16`] is the matching forward: the output and the row log-sum-exp
//! that the backward needs, its scores from the same products, so the backward rebuilds
//! exactly the probabilities the forward used. `training/` calls both through
//! `paraformer._paraformer` (`train.py --native-attention`).

use crate::error::{Error, Result};

/// Keys per block: the block's `dk`, `dv` accumulators and packed operands stay in L1/L2.
#[cfg(target_arch = "x86_64")]
const KEY_BLOCK: usize = 256;

/// Bad arguments: the argument's name and what was expected.
fn invalid(argument: &str, reason: String) -> Error {
    Error::InvalidInput { argument: argument.into(), reason }
}

/// Whether this CPU runs [`attention_backward_bf16`] (AVX-512 F, BW and BF16).
pub fn available() -> bool {
    crate::attention_fused::bf16_available()
}

/// Softmax attention for `bh` independent heads, with the row log-sum-exp that
/// [`attention_backward_bf16`] takes: `q` is `[bh][n][d]`, `k` and `v` are `[bh][m][d]`
/// bf16 bits. Returns `(o, lse)`: `o = softmax(scale·q·kᵀ)·v` as bf16 bits `[bh][n][d]` and
/// `lse = log Σ_j exp(scale·q·k_j)` in fp32 `[bh][n]`.
///
/// Head widths 16, 32 and 64; errors as for the backward.
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
pub fn attention_forward_bf16(q: &[u16], k: &[u16], v: &[u16], bh: usize, n: usize, m: usize, d: usize, scale: f32) -> Result<(Vec<u16>, Vec<f32>)> {
    check(&[("q", q.len(), bh * n * d), ("k", k.len(), bh * m * d), ("v", v.len(), bh * m * d)], bh, n, m, d, scale)?;
    if m == 0 && n > 0 && bh > 0 {
        return Err(invalid("k", "no keys: the softmax over zero keys is undefined".into()));
    }
    require_cpu()?;
    let (mut o, mut lse) = (vec![0u16; bh * n * d], vec![0.0f32; bh * n]);
    if bh == 0 || n == 0 {
        return Ok((o, lse));
    }
    #[cfg(target_arch = "x86_64")]
    x86::run_forward(q, k, v, n, m, d, scale, &mut o, &mut lse);
    Ok((o, lse))
}

/// The argument checks both directions share: widths, lengths and the scale. The CPU is
/// checked after every argument ([`require_cpu`]), so a bad argument is named on any CPU.
fn check(sizes: &[(&str, usize, usize)], bh: usize, n: usize, m: usize, d: usize, scale: f32) -> Result<()> {
    if !matches!(d, 16 | 32 | 64) {
        return Err(invalid("d", format!("head width {d}: expected 16, 32 or 64")));
    }
    for &(name, got, want) in sizes {
        if got != want {
            return Err(invalid(name, format!("{got} values, expected {want} for bh={bh}, n={n}, m={m}, d={d}")));
        }
    }
    if !scale.is_finite() {
        return Err(invalid("scale", format!("{scale}: expected a finite number")));
    }
    Ok(())
}

/// The kernels need AVX-512 F/BW/BF16 at run time.
fn require_cpu() -> Result<()> {
    if !available() {
        return Err(invalid("attention_bf16", "this CPU lacks AVX-512 BF16".into()));
    }
    Ok(())
}

/// Gradients of attention for `bh` independent heads: `q`, `o`, `d_o` are `[bh][n][d]` and
/// `k`, `v` are `[bh][m][d]` bf16 values (raw bits), `lse` is `[bh][n]` — the natural-log
/// sum of `exp(scale·q·kᵀ)` over each row — and `scale` the factor of the scores
/// (`1/√d`). Returns `(dq, dk, dv)` as bf16 bits (rounded to nearest even from fp32 sums),
/// in the layouts of `q`, `k` and `v`: the dtype of the operands, as PyTorch's bf16
/// backward returns them.
///
/// Head widths 16, 32 and 64. Errors name the argument whose length or width is wrong,
/// and say so where this CPU lacks the instructions ([`available`]).
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
pub fn attention_backward_bf16(
    q: &[u16],
    k: &[u16],
    v: &[u16],
    o: &[u16],
    d_o: &[u16],
    lse: &[f32],
    bh: usize,
    n: usize,
    m: usize,
    d: usize,
    scale: f32,
) -> Result<(Vec<u16>, Vec<u16>, Vec<u16>)> {
    check(&[("q", q.len(), bh * n * d), ("k", k.len(), bh * m * d), ("v", v.len(), bh * m * d), ("o", o.len(), bh * n * d), ("d_o", d_o.len(), bh * n * d), ("lse", lse.len(), bh * n)], bh, n, m, d, scale)?;
    if let Some(i) = lse.iter().position(|x| !x.is_finite()) {
        return Err(invalid("lse", format!("value {} at index {i} is not finite", lse[i])));
    }
    require_cpu()?;
    let (mut dq, mut dk, mut dv) = (vec![0u16; bh * n * d], vec![0u16; bh * m * d], vec![0u16; bh * m * d]);
    if bh == 0 || n == 0 || m == 0 {
        return Ok((dq, dk, dv));
    }
    #[cfg(target_arch = "x86_64")]
    x86::run(Inputs { q, k, v, o, d_o, lse, n, m, d, scale }, &mut dq, &mut dk, &mut dv);
    Ok((dq, dk, dv))
}

/// The checked arguments of one call.
#[cfg(target_arch = "x86_64")]
struct Inputs<'a> {
    q: &'a [u16],
    k: &'a [u16],
    v: &'a [u16],
    o: &'a [u16],
    d_o: &'a [u16],
    lse: &'a [f32],
    n: usize,
    m: usize,
    d: usize,
    scale: f32,
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use rayon::prelude::*;

    use super::{Inputs, KEY_BLOCK};
    use crate::attention_fused::x86::{exp2v, lane_mask, scores_bf16, values_bf16, StripOut, MAX_D, STRIP};
    use crate::kernels::to_bf16;

    fn bf16_to_f32(x: u16) -> f32 {
        f32::from_bits((x as u32) << 16)
    }

    /// One head's operands, packed for the micro-kernels (zero padding throughout).
    struct Head {
        /// Queries and upstream gradients as rows `[np][d]` (`np`: `n` rounded up to 16).
        q: Vec<u16>,
        d_o: Vec<u16>,
        /// The same as interleaved pairs of rows `[np/2][d][2]` (the `dk`, `dv` products).
        q2: Vec<u16>,
        d_o2: Vec<u16>,
        /// Keys and values in 16-column panels `[mp/16][d/2][16][2]` (`mp`: `m` rounded up
        /// to 32), the layout of the fused forward's scores.
        kp: Vec<u16>,
        vp: Vec<u16>,
        /// Keys as interleaved pairs of rows `[mp/2][d][2]` (the `dq` product).
        k2: Vec<u16>,
        /// Per row: `lse·log2(e)` and `Σ_c do·o` (padding rows 0).
        lse2: Vec<f32>,
        delta: Vec<f32>,
    }

    fn rows(src: &[u16], count: usize, padded: usize, d: usize) -> Vec<u16> {
        let mut out = vec![0u16; padded * d];
        out[..count * d].copy_from_slice(&src[..count * d]);
        out
    }

    /// Rows `2i` and `2i+1` interleaved value by value: `[padded/2][d][2]`.
    fn pairs(src: &[u16], count: usize, padded: usize, d: usize) -> Vec<u16> {
        let mut out = vec![0u16; padded * d];
        for (pair, dst) in out.chunks_exact_mut(2 * d).enumerate().take(count.div_ceil(2)) {
            let a = &src[2 * pair * d..(2 * pair + 1) * d];
            let b = if 2 * pair + 1 < count { &src[(2 * pair + 1) * d..(2 * pair + 2) * d] } else { &[][..] };
            for (c, x) in dst.chunks_exact_mut(2).enumerate() {
                x[0] = a[c];
                x[1] = b.get(c).copied().unwrap_or(0);
            }
        }
        out
    }

    /// Panels of 16 rows, transposed by pairs of columns: `[padded/16][d/2][16][2]`.
    fn panels(src: &[u16], count: usize, padded: usize, d: usize) -> Vec<u16> {
        let mut out = vec![0u16; padded * d];
        for (panel, dst) in out.chunks_exact_mut(16 * d).enumerate().take(count.div_ceil(16)) {
            for lane in 0..16.min(count - panel * 16) {
                let row = &src[(panel * 16 + lane) * d..(panel * 16 + lane + 1) * d];
                for (c2, x) in row.chunks_exact(2).enumerate() {
                    dst[c2 * 32 + lane * 2] = x[0];
                    dst[c2 * 32 + lane * 2 + 1] = x[1];
                }
            }
        }
        out
    }

    fn pack(x: &Inputs, h: usize) -> Head {
        let (n, m, d) = (x.n, x.m, x.d);
        let (np, mp) = (n.div_ceil(STRIP) * STRIP, m.div_ceil(32) * 32);
        let (qs, ks) = (h * n * d..(h + 1) * n * d, h * m * d..(h + 1) * m * d);
        let (q, k, v, o, d_o) = (&x.q[qs.clone()], &x.k[ks.clone()], &x.v[ks], &x.o[qs.clone()], &x.d_o[qs]);
        let mut lse2 = vec![0.0f32; np];
        let mut delta = vec![0.0f32; np];
        for i in 0..n {
            lse2[i] = x.lse[h * n + i] * std::f32::consts::LOG2_E;
            delta[i] = (0..d).map(|c| bf16_to_f32(d_o[i * d + c]) * bf16_to_f32(o[i * d + c])).sum();
        }
        Head {
            q: rows(q, n, np, d),
            d_o: rows(d_o, n, np, d),
            q2: pairs(q, n, np, d),
            d_o2: pairs(d_o, n, np, d),
            kp: panels(k, m, mp, d),
            vp: panels(v, m, mp, d),
            k2: pairs(k, m, mp, d),
            lse2,
            delta,
        }
    }

    /// Every head in parallel; each task writes its own head's slices.
    pub(super) fn run(x: Inputs, dq: &mut [u16], dk: &mut [u16], dv: &mut [u16]) {
        let (n, m, d) = (x.n, x.m, x.d);
        dq.par_chunks_mut(n * d).zip(dk.par_chunks_mut(m * d)).zip(dv.par_chunks_mut(m * d)).enumerate().for_each(|(h, ((dq, dk), dv))| {
            let head = pack(&x, h);
            // SAFETY: `attention_backward_bf16` checked AVX-512 F/BW/BF16 at run time and
            // every length; the buffers below are sized for the packed layouts.
            unsafe {
                match d {
                    16 => head_bf16::<16>(&head, n, m, x.scale, dq, dk, dv),
                    32 => head_bf16::<32>(&head, n, m, x.scale, dq, dk, dv),
                    _ => head_bf16::<64>(&head, n, m, x.scale, dq, dk, dv),
                }
            }
        });
    }

    /// The forward for every head in parallel; each task writes its own head's slices.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn run_forward(q: &[u16], k: &[u16], v: &[u16], n: usize, m: usize, d: usize, scale: f32, o: &mut [u16], lse: &mut [f32]) {
        o.par_chunks_mut(n * d).zip(lse.par_chunks_mut(n)).enumerate().for_each(|(h, (o, lse))| {
            let (np, mp) = (n.div_ceil(STRIP) * STRIP, m.div_ceil(32) * 32);
            let (qs, ks) = (h * n * d..(h + 1) * n * d, h * m * d..(h + 1) * m * d);
            let qr = rows(&q[qs], n, np, d);
            let kp = panels(&k[ks.clone()], m, mp, d);
            let v2 = pairs(&v[ks], m, mp, d);
            // SAFETY: `attention_forward_bf16` checked AVX-512 F/BW/BF16 and every length.
            unsafe {
                match d {
                    16 => forward_bf16::<16>(&qr, &kp, &v2, n, m, scale, o, lse),
                    32 => forward_bf16::<32>(&qr, &kp, &v2, n, m, scale, o, lse),
                    _ => forward_bf16::<64>(&qr, &kp, &v2, n, m, scale, o, lse),
                }
            }
        });
    }

    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    unsafe fn forward_bf16<const D: usize>(q: &[u16], kp: &[u16], v2: &[u16], n: usize, m: usize, scale: f32, o: &mut [u16], lse: &mut [f32]) {
        let mp = m.div_ceil(32) * 32;
        let ld = mp + 16;
        let mut s = vec![0.0f32; STRIP * ld];
        let mut p16 = vec![0u16; STRIP * ld];
        let f = scale * std::f32::consts::LOG2_E;
        let factor = _mm512_set1_ps(f);
        let mut out: StripOut = [[0.0; MAX_D]; STRIP];
        for r0 in (0..n).step_by(STRIP) {
            scores_bf16::<D>(q.as_ptr().add(r0 * D), kp.as_ptr(), m, mp, s.as_mut_ptr(), ld);
            let mut sums = [0.0f32; STRIP];
            let mut maxes = [0.0f32; STRIP];
            for r in 0..STRIP {
                let row = s.as_ptr().add(r * ld);
                let mut mx = _mm512_set1_ps(f32::NEG_INFINITY);
                for c in (0..mp).step_by(16) {
                    mx = _mm512_max_ps(mx, _mm512_loadu_ps(row.add(c)));
                }
                let top = _mm512_reduce_max_ps(mx) * f; // finite: every row has a valid key
                let shift = _mm512_set1_ps(top);
                let mut sum = _mm512_setzero_ps();
                for c in (0..mp).step_by(32) {
                    let e0 = exp2v(_mm512_fmsub_ps(_mm512_loadu_ps(row.add(c)), factor, shift));
                    let e1 = exp2v(_mm512_fmsub_ps(_mm512_loadu_ps(row.add(c + 16)), factor, shift));
                    // The sum is of the bf16-rounded probabilities the value product uses.
                    let pair = _mm512_cvtne2ps_pbh(e1, e0);
                    sum = _mm512_add_ps(sum, _mm512_add_ps(bf16_low(pair), bf16_high(pair)));
                    _mm512_storeu_si512(p16.as_mut_ptr().add(r * ld + c) as *mut _, std::mem::transmute::<__m512bh, __m512i>(pair));
                }
                sums[r] = _mm512_reduce_add_ps(sum);
                maxes[r] = top;
            }
            values_bf16::<D>(p16.as_ptr(), ld, m, v2.as_ptr(), &mut out);
            for r in 0..STRIP.min(n - r0) {
                let inv = 1.0 / sums[r];
                for (dst, x) in o[(r0 + r) * D..(r0 + r + 1) * D].iter_mut().zip(&out[r][..D]) {
                    *dst = to_bf16(x * inv);
                }
                lse[r0 + r] = (maxes[r] + sums[r].log2()) * std::f32::consts::LN_2;
            }
        }
    }

    /// The first and last 16 bf16 values of `x` as fp32.
    #[inline(always)]
    unsafe fn bf16_low(x: __m512bh) -> __m512 {
        let lo = _mm512_castsi512_si256(std::mem::transmute::<__m512bh, __m512i>(x));
        _mm512_castsi512_ps(_mm512_slli_epi32::<16>(_mm512_cvtepu16_epi32(lo)))
    }

    #[inline(always)]
    unsafe fn bf16_high(x: __m512bh) -> __m512 {
        let hi = _mm512_extracti64x4_epi64::<1>(std::mem::transmute::<__m512bh, __m512i>(x));
        _mm512_castsi512_ps(_mm512_slli_epi32::<16>(_mm512_cvtepu16_epi32(hi)))
    }

    /// Interleaves two rows' 16 values each into 16 bf16 pairs `[a0, b0, a1, b1, …]`.
    #[inline(always)]
    unsafe fn interleave(a: __m512, b: __m512) -> __m512i {
        let idx = _mm512_set_epi16(
            31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8, 23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0,
        );
        let packed: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(b, a));
        _mm512_permutexvar_epi16(idx, packed)
    }

    /// `P = 2^(s·factor − lse₂)` of 16 scores, zero outside `mask`.
    #[inline(always)]
    unsafe fn probability(s: *const f32, factor: __m512, lse2: __m512, mask: __mmask16) -> __m512 {
        _mm512_maskz_mov_ps(mask, exp2v(_mm512_fmsub_ps(_mm512_loadu_ps(s), factor, lse2)))
    }

    /// `acc[j][..D] += Σ_{pairs p<8} (a2[p][j][0]·b2[p][..][0] + a2[p][j][1]·b2[p][..][1])` for
    /// columns `j < cols` (a multiple of 4): the 16 rows of a strip reduced into per-key
    /// accumulators. `a2` has row-pair stride `lda` (u16), `b2` is `[8][D][2]`.
    #[inline(always)]
    unsafe fn reduce_rows<const D: usize>(a2: *const u16, lda: usize, b2: *const u16, acc: *mut f32, cols: usize) {
        let dv = D / 16;
        for j0 in (0..cols).step_by(4) {
            let mut c = [[_mm512_setzero_ps(); 4]; 4];
            for (jj, cj) in c.iter_mut().enumerate() {
                for (t, x) in cj.iter_mut().enumerate().take(dv) {
                    *x = _mm512_loadu_ps(acc.add((j0 + jj) * D + t * 16));
                }
            }
            for p in 0..STRIP / 2 {
                let mut b: [__m512bh; 4] = [std::mem::transmute::<__m512i, __m512bh>(_mm512_setzero_si512()); 4];
                for (t, x) in b.iter_mut().enumerate().take(dv) {
                    *x = std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(b2.add(p * D * 2 + t * 32) as *const _));
                }
                for (jj, cj) in c.iter_mut().enumerate() {
                    let pair = (a2.add(p * lda + (j0 + jj) * 2) as *const i32).read_unaligned();
                    let a: __m512bh = std::mem::transmute(_mm512_set1_epi32(pair));
                    for t in 0..dv {
                        cj[t] = _mm512_dpbf16_ps(cj[t], a, b[t]);
                    }
                }
            }
            for (jj, cj) in c.iter().enumerate() {
                for (t, x) in cj.iter().enumerate().take(dv) {
                    _mm512_storeu_ps(acc.add((j0 + jj) * D + t * 16), *x);
                }
            }
        }
    }

    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    unsafe fn head_bf16<const D: usize>(hd: &Head, n: usize, m: usize, scale: f32, dq: &mut [u16], dk: &mut [u16], dv: &mut [u16]) {
        let np = n.div_ceil(STRIP) * STRIP;
        let ld = KEY_BLOCK + 16; // score rows: a block plus a cache line (no power-of-two stride)
        let mut s = vec![0.0f32; STRIP * ld];
        let mut dp = vec![0.0f32; STRIP * ld];
        let mut ds = vec![0u16; STRIP * ld]; // dS rows (the dq product)
        let mut p2 = vec![0u16; STRIP * KEY_BLOCK]; // P and dS as row pairs `[8][KEY_BLOCK][2]`
        let mut ds2 = vec![0u16; STRIP * KEY_BLOCK];
        let mut dq_acc = vec![0.0f32; np * D];
        let mut dk_blk = vec![0.0f32; KEY_BLOCK * D];
        let mut dv_blk = vec![0.0f32; KEY_BLOCK * D];
        let factor = _mm512_set1_ps(scale * std::f32::consts::LOG2_E);
        let mut out: StripOut = [[0.0; MAX_D]; STRIP];
        for j0 in (0..m).step_by(KEY_BLOCK) {
            let cols = KEY_BLOCK.min(m - j0); // valid keys of the block
            let width = cols.div_ceil(32) * 32; // packed (zero-padded) keys of the block
            dk_blk[..width * D].fill(0.0);
            dv_blk[..width * D].fill(0.0);
            for r0 in (0..np).step_by(STRIP) {
                // Scores and dP of the strip against the block (columns ≥ cols are −∞).
                scores_bf16::<D>(hd.q.as_ptr().add(r0 * D), hd.kp.as_ptr().add(j0 * D), cols, width, s.as_mut_ptr(), ld);
                scores_bf16::<D>(hd.d_o.as_ptr().add(r0 * D), hd.vp.as_ptr().add(j0 * D), cols, width, dp.as_mut_ptr(), ld);
                for pr in 0..STRIP / 2 {
                    let (ra, rb) = (2 * pr, 2 * pr + 1);
                    let (la, lb) = (_mm512_set1_ps(hd.lse2[r0 + ra]), _mm512_set1_ps(hd.lse2[r0 + rb]));
                    let (da, db) = (_mm512_set1_ps(hd.delta[r0 + ra]), _mm512_set1_ps(hd.delta[r0 + rb]));
                    for c0 in (0..width).step_by(16) {
                        let mask = lane_mask(cols, c0);
                        let pa = probability(s.as_ptr().add(ra * ld + c0), factor, la, mask);
                        let pb = probability(s.as_ptr().add(rb * ld + c0), factor, lb, mask);
                        let ga = _mm512_maskz_mul_ps(mask, pa, _mm512_sub_ps(_mm512_loadu_ps(dp.as_ptr().add(ra * ld + c0)), da));
                        let gb = _mm512_maskz_mul_ps(mask, pb, _mm512_sub_ps(_mm512_loadu_ps(dp.as_ptr().add(rb * ld + c0)), db));
                        _mm256_storeu_si256(ds.as_mut_ptr().add(ra * ld + c0) as *mut _, std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(ga)));
                        _mm256_storeu_si256(ds.as_mut_ptr().add(rb * ld + c0) as *mut _, std::mem::transmute::<__m256bh, __m256i>(_mm512_cvtneps_pbh(gb)));
                        _mm512_storeu_si512(p2.as_mut_ptr().add(pr * KEY_BLOCK * 2 + c0 * 2) as *mut _, interleave(pa, pb));
                        _mm512_storeu_si512(ds2.as_mut_ptr().add(pr * KEY_BLOCK * 2 + c0 * 2) as *mut _, interleave(ga, gb));
                    }
                }
                // dq rows += dS·k (pairs of keys; the block's padding keys are zero).
                values_bf16::<D>(ds.as_ptr(), ld, cols, hd.k2.as_ptr().add(j0 * D), &mut out);
                for (r, o) in out.iter().enumerate() {
                    for (a, x) in dq_acc[(r0 + r) * D..(r0 + r + 1) * D].iter_mut().zip(&o[..D]) {
                        *a += x;
                    }
                }
                // The block's dv += Pᵀ·do and dk += dSᵀ·q over the strip's rows.
                reduce_rows::<D>(p2.as_ptr(), KEY_BLOCK * 2, hd.d_o2.as_ptr().add(r0 * D), dv_blk.as_mut_ptr(), width);
                reduce_rows::<D>(ds2.as_ptr(), KEY_BLOCK * 2, hd.q2.as_ptr().add(r0 * D), dk_blk.as_mut_ptr(), width);
            }
            for ((k, v), (a, b)) in dk[j0 * D..(j0 + cols) * D].iter_mut().zip(&mut dv[j0 * D..(j0 + cols) * D]).zip(dk_blk.iter().zip(&dv_blk)) {
                *k = to_bf16(a * scale);
                *v = to_bf16(*b);
            }
        }
        for (o, a) in dq.iter_mut().zip(&dq_acc[..n * D]) {
            *o = to_bf16(a * scale);
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    fn to_bf16(x: f32) -> u16 {
        crate::kernels::to_bf16(x)
    }

    fn from_bf16(x: u16) -> f64 {
        f32::from_bits((x as u32) << 16) as f64
    }

    fn random(len: usize, seed: u64, amp: f32) -> Vec<u16> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..len)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                to_bf16(((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 2.0 * amp)
            })
            .collect()
    }

    /// Float64 attention forward and backward on the bf16 values: (o, lse, dq, dk, dv).
    #[allow(clippy::type_complexity, clippy::too_many_arguments)]
    fn reference(q: &[u16], k: &[u16], v: &[u16], d_o: &[u16], bh: usize, n: usize, m: usize, d: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
        let scale = 1.0 / (d as f64).sqrt();
        let (mut o, mut lse) = (vec![0.0; bh * n * d], vec![0.0; bh * n]);
        let (mut dq, mut dk, mut dv) = (vec![0.0; bh * n * d], vec![0.0; bh * m * d], vec![0.0; bh * m * d]);
        for h in 0..bh {
            let (qo, ko) = (h * n * d, h * m * d);
            for i in 0..n {
                let s: Vec<f64> = (0..m).map(|j| (0..d).map(|c| from_bf16(q[qo + i * d + c]) * from_bf16(k[ko + j * d + c])).sum::<f64>() * scale).collect();
                let mx = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let l = mx + s.iter().map(|x| (x - mx).exp()).sum::<f64>().ln();
                lse[h * n + i] = l;
                let p: Vec<f64> = s.iter().map(|x| (x - l).exp()).collect();
                for c in 0..d {
                    o[qo + i * d + c] = (0..m).map(|j| p[j] * from_bf16(v[ko + j * d + c])).sum();
                }
                let g = |c: usize| from_bf16(d_o[qo + i * d + c]);
                let dpv: Vec<f64> = (0..m).map(|j| (0..d).map(|c| g(c) * from_bf16(v[ko + j * d + c])).sum()).collect();
                let delta: f64 = (0..m).map(|j| p[j] * dpv[j]).sum();
                for j in 0..m {
                    let dsj = p[j] * (dpv[j] - delta);
                    for c in 0..d {
                        dq[qo + i * d + c] += dsj * from_bf16(k[ko + j * d + c]) * scale;
                        dk[ko + j * d + c] += dsj * from_bf16(q[qo + i * d + c]) * scale;
                        dv[ko + j * d + c] += p[j] * g(c);
                    }
                }
            }
        }
        (o, lse, dq, dk, dv)
    }

    /// Odd sizes cross strip, pair and key-block edges; n ≠ m as in cross attention.
    const SHAPES: [(usize, usize, usize, usize); 4] = [(2, 37, 301, 32), (1, 16, 32, 16), (3, 50, 7, 64), (1, 300, 260, 32)];

    /// `(q, k, v, d_o)` for `(bh, n, m, d)`, seeded from `seed`..`seed + 3`.
    fn operands(bh: usize, n: usize, m: usize, d: usize, seed: u64) -> [Vec<u16>; 4] {
        [random(bh * n * d, seed, 2.0), random(bh * m * d, seed + 1, 2.0), random(bh * m * d, seed + 2, 1.0), random(bh * n * d, seed + 3, 1.0)]
    }

    /// Each of `dq`, `dk`, `dv` within 1% (relative L2) of the reference.
    fn assert_gradients(got: [&[u16]; 3], want: [&[f64]; 3], what: &str) {
        for ((name, got), want) in ["dq", "dk", "dv"].iter().zip(got).zip(want) {
            let e = rel_error(got, want);
            assert!(e < 0.01, "{name} {what}: relative error {e}");
        }
    }

    fn rel_error(a: &[u16], b: &[f64]) -> f64 {
        let num: f64 = a.iter().zip(b).map(|(x, y)| (from_bf16(*x) - y).powi(2)).sum();
        let den: f64 = b.iter().map(|y| y * y).sum();
        (num / den).sqrt()
    }

    #[test]
    fn matches_a_float64_reference() {
        if !available() {
            eprintln!("skipped: this CPU lacks AVX-512 BF16");
            return;
        }
        for (bh, n, m, d) in SHAPES {
            let [q, k, v, d_o] = operands(bh, n, m, d, 1);
            let (o, lse, rq, rk, rv) = reference(&q, &k, &v, &d_o, bh, n, m, d);
            let o16: Vec<u16> = o.iter().map(|&x| to_bf16(x as f32)).collect();
            let lse32: Vec<f32> = lse.iter().map(|&x| x as f32).collect();
            let (dq, dk, dv) = attention_backward_bf16(&q, &k, &v, &o16, &d_o, &lse32, bh, n, m, d, 1.0 / (d as f32).sqrt()).unwrap();
            assert_gradients([&dq, &dk, &dv], [&rq, &rk, &rv], &format!("for bh={bh} n={n} m={m} d={d}"));
        }
    }

    #[test]
    fn forward_matches_a_float64_reference_and_feeds_the_backward() {
        if !available() {
            eprintln!("skipped: this CPU lacks AVX-512 BF16");
            return;
        }
        for (bh, n, m, d) in SHAPES {
            let [q, k, v, d_o] = operands(bh, n, m, d, 5);
            let (ro, rlse, rq, rk, rv) = reference(&q, &k, &v, &d_o, bh, n, m, d);
            let scale = 1.0 / (d as f32).sqrt();
            let (o, lse) = attention_forward_bf16(&q, &k, &v, bh, n, m, d, scale).unwrap();
            let e = rel_error(&o, &ro);
            assert!(e < 0.01, "o for bh={bh} n={n} m={m} d={d}: relative error {e}");
            let worst = lse.iter().zip(&rlse).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
            assert!(worst < 2e-3, "lse for bh={bh} n={n} m={m} d={d}: off by {worst}");
            let (dq, dk, dv) = attention_backward_bf16(&q, &k, &v, &o, &d_o, &lse, bh, n, m, d, scale).unwrap();
            assert_gradients([&dq, &dk, &dv], [&rq, &rk, &rv], &format!("after the forward, bh={bh} n={n} m={m} d={d}"));
        }
    }

    #[test]
    fn rejects_bad_arguments_by_name() {
        let x = vec![0u16; 2 * 4 * 16];
        let l = vec![0.0f32; 2 * 4];
        let err = |r: Result<(Vec<u16>, Vec<u16>, Vec<u16>)>| r.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err(attention_backward_bf16(&x, &x, &x, &x, &x, &l, 2, 4, 4, 8, 0.25)).contains("`d`"));
        assert!(err(attention_backward_bf16(&x[1..], &x, &x, &x, &x, &l, 2, 4, 4, 16, 0.25)).contains("`q`"));
        assert!(err(attention_backward_bf16(&x, &x, &x, &x, &x, &l[1..], 2, 4, 4, 16, 0.25)).contains("`lse`"));
        assert!(err(attention_backward_bf16(&x, &x, &x, &x, &x, &l, 2, 4, 4, 16, f32::NAN)).contains("`scale`"));
        let mut bad = l.clone();
        bad[3] = f32::INFINITY;
        assert!(err(attention_backward_bf16(&x, &x, &x, &x, &x, &bad, 2, 4, 4, 16, 0.25)).contains("`lse`"));
        let fwd = |r: Result<(Vec<u16>, Vec<f32>)>| r.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(fwd(attention_forward_bf16(&x, &x, &x[2..], 2, 4, 4, 16, 0.25)).contains("`v`"));
        assert!(fwd(attention_forward_bf16(&x, &x, &x, 2, 4, 4, 12, 0.25)).contains("`d`"));
        assert!(fwd(attention_forward_bf16(&x, &[], &[], 2, 4, 0, 16, 0.25)).contains("`k`"));
        // Without AVX-512 BF16, valid arguments get the CPU's error rather than a wrong result.
        if !available() {
            assert!(fwd(attention_forward_bf16(&x, &x, &x, 2, 4, 4, 16, 0.25)).contains("AVX-512 BF16"));
            assert!(err(attention_backward_bf16(&x, &x, &x, &x, &x, &l, 2, 4, 4, 16, 0.25)).contains("AVX-512 BF16"));
        }
    }
}
