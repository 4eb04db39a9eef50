//! Fused attention for narrow heads (head width 16, 32, 64 or 96) on AVX-512 CPUs (and, in
//! fp32, on AVX2 CPUs through [`crate::attention_fused_avx2`]'s 8-lane kernels): the same
//! results as [`crate::attention`] (SPEC §4–§5, softmax over keys; the shared cross
//! attention's transposed softmax), computed in one pass per strip of 16 query rows.
//!
//! At head width 16–32 a score costs as few as 32 multiply-accumulates, so the general
//! path (a GEMM for the scores, four passes for the softmax, a GEMM with a packed copy
//! of the probabilities) spends most of its time outside arithmetic. Here queries are
//! pre-scaled by `log2(e)/√d` (scores in base 2, one cheap `exp2`), the keys of each head
//! are packed once in 16-column panels, the score strip stays in L1/L2, the softmax is
//! unnormalised (rows are divided by their sums after the value product), and
//! register-tiled micro-kernels do both products. With `bf16`, both products take bf16
//! operands with fp32 accumulation (`vdpbf16ps`); maxima, exponentials and sums stay fp32.
//!
//! Every sum is taken in a fixed order (tasks are fixed blocks of rows, merged in
//! order), so results do not depend on the thread count.

#[cfg(target_arch = "x86_64")]
pub use x86::{attention, available, bf16_available, cross_attention_shared};

/// Elsewhere the general path serves every call.
#[cfg(not(target_arch = "x86_64"))]
pub fn available(_d: usize) -> bool {
    false
}

/// Elsewhere there is no bf16 path.
#[cfg(not(target_arch = "x86_64"))]
pub fn bf16_available() -> bool {
    false
}

/// Elsewhere never called ([`available`] is false): an error, not a panic.
#[cfg(not(target_arch = "x86_64"))]
pub fn attention(
    _q: crate::kernels::View,
    _k: crate::kernels::View,
    _v: crate::kernels::View,
    _heads: usize,
    _col_sums: bool,
    _bf16: bool,
) -> crate::error::Result<(crate::kernels::Matrix, Option<Vec<f32>>)> {
    Err(crate::kernels::internal("fused attention needs x86-64 with AVX-512".into()))
}

/// Elsewhere never called ([`available`] is false): an error, not a panic.
#[cfg(not(target_arch = "x86_64"))]
pub fn cross_attention_shared(
    _qx: crate::kernels::View,
    _ky: crate::kernels::View,
    _vx: crate::kernels::View,
    _vy: crate::kernels::View,
    _heads: usize,
    _bf16: bool,
) -> crate::error::Result<(crate::kernels::Matrix, crate::kernels::Matrix)> {
    Err(crate::kernels::internal("fused attention needs x86-64 with AVX-512".into()))
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod x86 {
use std::arch::x86_64::*;

use rayon::prelude::*;

use crate::error::Result;
use crate::kernels::{internal, sum_in_order, to_bf16, Matrix, SharedMut, View};

/// Query rows per strip: the unit of the score buffer (`STRIP × N` floats).
pub(crate) const STRIP: usize = 16;
/// Strips per column pass of the fp32 shared cross attention (see `cross_chunk`).
pub(crate) const CROSS_STRIPS: usize = 4;
/// Query rows per task of the shared cross attention (fixed, for reproducible sums).
pub(crate) const CROSS_ROWS: usize = 256;
/// At most this many cross-attention tasks per head: each holds an `N × d` column state
/// until the merge, so larger inputs get more rows per task (a function of `M` only).
pub(crate) const CROSS_TASKS: usize = 8;
/// The shared cross attention's split of `M` query rows into tasks per head: a whole number
/// of strips each, at least [`CROSS_ROWS`], at most [`CROSS_TASKS`] tasks (a function of `M` only).
#[derive(Clone, Copy)]
pub(crate) struct CrossTasks {
    m: usize,
    rows_per_task: usize,
}

impl CrossTasks {
    pub(crate) fn new(m: usize) -> Self {
        Self { m, rows_per_task: CROSS_ROWS.max(m.div_ceil(CROSS_TASKS).div_ceil(STRIP) * STRIP) }
    }

    /// Tasks per head.
    pub(crate) fn chunks(self) -> usize {
        self.m.div_ceil(self.rows_per_task)
    }

    /// Query rows `[start, end)` of task `ch`.
    pub(crate) fn rows(self, ch: usize) -> (usize, usize) {
        (ch * self.rows_per_task, ((ch + 1) * self.rows_per_task).min(self.m))
    }
}

/// The widest head the AVX-512 kernels take (96: LighterGlue's one head at width 96).
pub(crate) const MAX_D: usize = 96;
/// One strip's value product: 16 rows of up to [`MAX_D`] floats.
pub(crate) type StripOut = [[f32; MAX_D]; STRIP];

/// Start of a running column maximum: finite, so that `exp2(start − max)` is 0, not NaN.
pub(crate) const NEG: f32 = -1e30;

/// Whether the fused kernels serve head width `d` here (16, 32, 64 or 96): AVX-512F at run
/// time, or AVX2 and FMA for the fp32 kernels of [`crate::attention_fused_avx2`].
pub fn available(d: usize) -> bool {
    matches!(d, 16 | 32 | 64 | 96) && crate::kernels::simd_level() >= 3
}

/// Whether this CPU runs the bf16 kernels (AVX-512 BF16 at run time).
pub fn bf16_available() -> bool {
    crate::kernels::simd_level() >= 4 && std::is_x86_feature_detected!("avx512bf16") && std::is_x86_feature_detected!("avx512bw")
}

/// Whether this CPU runs the kernels the entry points would pick for `d` and `bf16`
/// (checked there: they are safe functions around `target_feature` code).
fn runs(d: usize, bf16: bool) -> bool {
    available(d) && (!bf16 || bf16_available())
}

// ---- packing ------------------------------------------------------------------------

/// The operands of one attention call, packed per head.
pub(crate) struct Packed {
    pub(crate) heads: usize,
    pub(crate) d: usize,
    /// Query rows and key columns, and both padded (rows to `STRIP`, columns to 32).
    pub(crate) m: usize,
    pub(crate) n: usize,
    pub(crate) mp: usize,
    pub(crate) np: usize,
    /// Row stride of the score strips: `np` plus a cache line, so that the 16 rows do not
    /// all fall into the same L1 sets (a power-of-two stride thrashes them).
    pub(crate) ld: usize,
    /// `[H][mp][d]` queries × `log2(e)/√d` (fp32), or as bf16 pairs when `bf16`.
    pub(crate) q: Vec<f32>,
    /// `[H][np/16][d][16]` keys transposed in 16-column panels; bf16: `[H][np/16][d/2][16][2]`.
    pub(crate) k: Vec<f32>,
    q16: Vec<u16>,
    k16: Vec<u16>,
    /// bf16 products on AMX tiles ([`crate::amx`]) instead of `vdpbf16ps`.
    pub(crate) amx: bool,
}

pub(crate) fn pack(q: View, k: View, heads: usize, bf16: bool) -> Packed {
    let (m, n, c) = (q.rows, k.rows, q.cols);
    let d = c / heads;
    let (mp, np) = (m.div_ceil(STRIP) * STRIP, n.div_ceil(32) * 32);
    let factor = std::f32::consts::LOG2_E / (d as f32).sqrt();
    let mut p = Packed { heads, d, m, n, mp, np, ld: np + 16, q: Vec::new(), k: Vec::new(), q16: Vec::new(), k16: Vec::new(), amx: false };
    if bf16 {
        p.amx = crate::amx::active();
        (p.q16, p.k16) = pack_as(q, k, heads, mp, np, |v| to_bf16(v * factor), to_bf16, |lane, c| (c / 2) * 32 + lane * 2 + c % 2);
    } else {
        (p.q, p.k) = pack_as(q, k, heads, mp, np, |v| v * factor, |v| v, |lane, c| c * 16 + lane);
    }
    p
}

/// Queries `[H][mp][d]` (`qv` of each value) and keys `[H][np/16][16·d]` (`kv` of each value
/// at `at(lane, channel)` of its panel), in parallel: a strip of queries or a panel of
/// keys per task.
#[allow(clippy::too_many_arguments)]
fn pack_as<T: Copy + Default + Send + Sync>(
    q: View,
    k: View,
    heads: usize,
    mp: usize,
    np: usize,
    qv: impl Fn(f32) -> T + Sync,
    kv: impl Fn(f32) -> T + Sync,
    at: impl Fn(usize, usize) -> usize + Sync,
) -> (Vec<T>, Vec<T>) {
    let (m, n, d) = (q.rows, k.rows, q.cols / heads);
    let (strips, panels) = (mp / STRIP, np / 16);
    let mut qp = vec![T::default(); heads * mp * d];
    let mut kp = vec![T::default(); heads * np * d];
    qp.par_chunks_mut(STRIP * d).enumerate().for_each(|(t, o)| {
        let (h, i0) = (t / strips, (t % strips) * STRIP);
        for i in i0..(i0 + STRIP).min(m) {
            for (x, &v) in o[(i - i0) * d..(i - i0 + 1) * d].iter_mut().zip(&q.row(i)[h * d..(h + 1) * d]) {
                *x = qv(v);
            }
        }
    });
    kp.par_chunks_mut(16 * d).enumerate().for_each(|(t, o)| {
        let (h, j0) = (t / panels, (t % panels) * 16);
        for j in j0..(j0 + 16).min(n) {
            for (c, &v) in k.row(j)[h * d..(h + 1) * d].iter().enumerate() {
                o[at(j - j0, c)] = kv(v);
            }
        }
    });
    (qp, kp)
}

/// Values of every head as bf16, `[H][half][d][2]` (pairs of rows interleaved, zero
/// beyond the rows; `half ≥ ceil(rows/2)`); fp32 reads the strided values in place.
fn pack_values_bf16(v: View, heads: usize, half: usize) -> Vec<u16> {
    let (n, c) = (v.rows, v.cols);
    let d = c / heads;
    let mut out = vec![0u16; heads * half * d * 2];
    out.par_chunks_mut(d * 2).enumerate().for_each(|(t, o)| {
        let (h, pair) = (t / half, t % half);
        for j in 2 * pair..(2 * pair + 2).min(n) {
            for (c, &x) in v.row(j)[h * d..(h + 1) * d].iter().enumerate() {
                o[c * 2 + j % 2] = to_bf16(x);
            }
        }
    });
    out
}

/// Values as the fp32 kernels read them: row `j` of head `h` at `data[h·head + j·stride..][..d]`.
#[derive(Clone, Copy)]
pub(crate) struct HeadValues<'a> {
    data: &'a [f32],
    head: usize,
    pub(crate) stride: usize,
}

impl HeadValues<'_> {
    /// No values: what the bf16 paths pass, whose kernels read packed bf16 values instead.
    pub(crate) const NONE: HeadValues<'static> = HeadValues { data: &[], head: 0, stride: 0 };

    /// Row `j` of head `h`.
    pub(crate) fn row(&self, h: usize, j: usize) -> *const f32 {
        self.data[h * self.head + j * self.stride..].as_ptr()
    }
}

/// fp32 values of every head with contiguous rows, `[H][rows][d]` in `buf`, where `v`'s rows
/// are strided (several heads, or a slice of a wider matrix): the value loops then stream
/// sequential lines instead of 2 lines in every `stride`. In place (no copy) otherwise.
pub(crate) fn head_values<'a>(v: View<'a>, heads: usize, buf: &'a mut Vec<f32>) -> HeadValues<'a> {
    let (n, d) = (v.rows, v.cols / heads);
    if v.stride == d {
        return HeadValues { data: v.data, head: d, stride: d };
    }
    // Every value is written below, so the buffer is not zeroed first.
    buf.clear();
    buf.reserve_exact(heads * n * d);
    buf.spare_capacity_mut()[..heads * n * d].par_chunks_mut(n * d).enumerate().for_each(|(h, out)| {
        for (j, o) in out.chunks_exact_mut(d).enumerate() {
            for (dst, &x) in o.iter_mut().zip(&v.row(j)[h * d..(h + 1) * d]) {
                dst.write(x);
            }
        }
    });
    // SAFETY: the loop above initialised all `heads·n·d` values (`n` rows of `d` per head).
    unsafe { buf.set_len(heads * n * d) };
    HeadValues { data: buf, head: n * d, stride: d }
}

// ---- vector helpers -----------------------------------------------------------------

/// `2^x` by range reduction and a polynomial `p(f) ≈ 2^f` on [−½, ½] (coefficients of
/// `f^0, f^1, …`): `2^x = 2^n·p(x − n)` with `vscalefps`; exactly 0 below −125, NaN stays NaN.
/// No subnormal results: sharp attention rows (trained LightGlue layers) have many scores
/// 90–100 below their maximum, and products that read subnormals take microcode assists
/// (the transplant's fp32 layers ran 2.6× slower with them).
#[inline(always)]
unsafe fn exp2_poly<const N: usize>(x: __m512, coef: [f32; N]) -> __m512 {
    // x ≥ −125 or NaN: 2^n·p with p ≥ 0.7 stays a normal float.
    let keep = _mm512_cmp_ps_mask::<_CMP_NLT_UQ>(x, _mm512_set1_ps(-125.0));
    // max(−160, x) returns x itself when x is NaN (second operand).
    let x = _mm512_max_ps(_mm512_set1_ps(-160.0), x);
    let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(x);
    let f = _mm512_sub_ps(x, n);
    let mut p = _mm512_set1_ps(coef[N - 1]);
    for &c in coef[..N - 1].iter().rev() {
        p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(c));
    }
    _mm512_maskz_mov_ps(keep, _mm512_scalef_ps(p, n))
}

/// `2^x` to 2.4e-7 relative error (degree-5 minimax).
#[inline(always)]
pub(crate) unsafe fn exp2v(x: __m512) -> __m512 {
    exp2_poly(x, [1.000_000_1, 0.693_146_94, 0.240_221_2, 0.055_507_13, 0.009_675_541, 0.001_327_647_1])
}

/// `2^x` to 7.5e-5 relative error (degree 3), for values that are rounded to bf16 next
/// (whose own rounding is 2e-3).
#[inline(always)]
unsafe fn exp2v_bf16(x: __m512) -> __m512 {
    exp2_poly(x, [0.999_928_06, 0.693_261, 0.242_611_13, 0.055_171_67])
}

/// Lanes `j0..j0+16` that lie below `n`.
#[inline(always)]
pub(crate) fn lane_mask(n: usize, j0: usize) -> __mmask16 {
    if n >= j0 + 16 {
        0xFFFF
    } else if n <= j0 {
        0
    } else {
        ((1u32 << (n - j0)) - 1) as __mmask16
    }
}

// ---- micro-kernels ------------------------------------------------------------------

/// Scores of a strip: `s[r][j] = Σ_t q[r][t]·kᵀ[t][j]` for 16 rows and all `np` columns
/// (columns ≥ `n` set to −∞). fp32 operands. Both 8-row tiles take a pair of key panels
/// in turn, so the second reads it from L1.
#[inline(always)]
unsafe fn scores_f32<const D: usize>(q: *const f32, kp: *const f32, n: usize, np: usize, s: *mut f32, ld: usize) {
    let neg = _mm512_set1_ps(f32::NEG_INFINITY);
    for p in (0..np / 16).step_by(2) {
        for rt in (0..STRIP).step_by(8) {
            let mut acc = [[_mm512_setzero_ps(); 2]; 8];
            let (b0p, b1p) = (kp.add(p * D * 16), kp.add((p + 1) * D * 16));
            for t in 0..D {
                let b0 = _mm512_loadu_ps(b0p.add(t * 16));
                let b1 = _mm512_loadu_ps(b1p.add(t * 16));
                for (r, a) in acc.iter_mut().enumerate() {
                    let x = _mm512_set1_ps(*q.add((rt + r) * D + t));
                    a[0] = _mm512_fmadd_ps(x, b0, a[0]);
                    a[1] = _mm512_fmadd_ps(x, b1, a[1]);
                }
            }
            store_tile(&acc, s.add(rt * ld + p * 16), ld, lane_mask(n, p * 16), lane_mask(n, p * 16 + 16), neg);
        }
    }
}

/// The same scores from bf16 pairs (`vdpbf16ps`, fp32 accumulation).
#[inline(always)]
pub(crate) unsafe fn scores_bf16<const D: usize>(q: *const u16, kp: *const u16, n: usize, np: usize, s: *mut f32, ld: usize) {
    let neg = _mm512_set1_ps(f32::NEG_INFINITY);
    for rt in (0..STRIP).step_by(8) {
        for p in (0..np / 16).step_by(2) {
            let mut acc = [[_mm512_setzero_ps(); 2]; 8];
            let (b0p, b1p) = (kp.add(p * D * 16), kp.add((p + 1) * D * 16));
            for t2 in 0..D / 2 {
                let b0: __m512bh = std::mem::transmute(_mm512_loadu_si512(b0p.add(t2 * 32) as *const _));
                let b1: __m512bh = std::mem::transmute(_mm512_loadu_si512(b1p.add(t2 * 32) as *const _));
                for (r, a) in acc.iter_mut().enumerate() {
                    let pair = (q.add((rt + r) * D + 2 * t2) as *const i32).read_unaligned();
                    let x: __m512bh = std::mem::transmute(_mm512_set1_epi32(pair));
                    a[0] = _mm512_dpbf16_ps(a[0], x, b0);
                    a[1] = _mm512_dpbf16_ps(a[1], x, b1);
                }
            }
            store_tile(&acc, s.add(rt * ld + p * 16), ld, lane_mask(n, p * 16), lane_mask(n, p * 16 + 16), neg);
        }
    }
}

#[inline(always)]
unsafe fn store_tile(acc: &[[__m512; 2]; 8], s: *mut f32, ld: usize, m0: __mmask16, m1: __mmask16, neg: __m512) {
    for (r, a) in acc.iter().enumerate() {
        _mm512_storeu_ps(s.add(r * ld), _mm512_mask_blend_ps(m0, neg, a[0]));
        _mm512_storeu_ps(s.add(r * ld + 16), _mm512_mask_blend_ps(m1, neg, a[1]));
    }
}

/// `2^(s − max)` of row `s[..np]`, in place, or with `p16` as bf16 there instead (`s`
/// then keeps the scores); returns the sum.
#[inline(always)]
unsafe fn exp_row(s: *mut f32, np: usize, p16: Option<*mut u16>) -> f32 {
    // Four independent maxima (`np` is a multiple of 32): one chain waited on each
    // `vmaxps`'s latency, a tenth of the self attention's time at head width 16.
    let mut mx = [_mm512_set1_ps(f32::NEG_INFINITY); 4];
    let mut c = 0;
    while c + 64 <= np {
        for (k, m) in mx.iter_mut().enumerate() {
            *m = _mm512_max_ps(*m, _mm512_loadu_ps(s.add(c + 16 * k)));
        }
        c += 64;
    }
    if c < np {
        mx[0] = _mm512_max_ps(mx[0], _mm512_loadu_ps(s.add(c)));
        mx[1] = _mm512_max_ps(mx[1], _mm512_loadu_ps(s.add(c + 16)));
    }
    let m = _mm512_set1_ps(_mm512_reduce_max_ps(_mm512_max_ps(_mm512_max_ps(mx[0], mx[1]), _mm512_max_ps(mx[2], mx[3]))));
    let (mut sum0, mut sum1) = (_mm512_setzero_ps(), _mm512_setzero_ps());
    let bf16 = p16.is_some();
    for c in (0..np).step_by(32) {
        let (x0, x1) = (_mm512_sub_ps(_mm512_loadu_ps(s.add(c)), m), _mm512_sub_ps(_mm512_loadu_ps(s.add(c + 16)), m));
        let (e0, e1) = if bf16 { (exp2v_bf16(x0), exp2v_bf16(x1)) } else { (exp2v(x0), exp2v(x1)) };
        sum0 = _mm512_add_ps(sum0, e0);
        sum1 = _mm512_add_ps(sum1, e1);
        match p16 {
            Some(p) => _mm512_storeu_si512(p.add(c) as *mut _, std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(e1, e0))),
            None => {
                _mm512_storeu_ps(s.add(c), e0);
                _mm512_storeu_ps(s.add(c + 16), e1);
            }
        }
    }
    _mm512_reduce_add_ps(_mm512_add_ps(sum0, sum1))
}

/// Accumulator registers of the fp32 value products' tiles (of 32; the rest hold values).
const TILE_ACC: usize = 24;

/// Rows (or columns) per register tile of the fp32 value products at `dv = D/16`: 16 accumulators
/// for D ≤ 64, and 4 × 6 = 24 at D = 96, where 2 × 6 = 12 made every strip read each value
/// row eight times (0.91× the layers' time with 4 × 6). Each output still sums over keys in order.
const fn value_tile(dv: usize) -> usize {
    if dv == 6 {
        4
    } else {
        16 / dv
    }
}

/// `out[r][..D] = inv[r] · Σ_j p[r][j]·v[j][..D]` for 16 rows (fp32; `v` strided).
#[inline(always)]
unsafe fn values_f32<const D: usize>(p: *const f32, ld: usize, n: usize, v: *const f32, v_stride: usize, out: &mut StripOut) {
    const { assert!(D.is_multiple_of(16) && D <= MAX_D) };
    let dv = D / 16;
    // Tiles of R rows × D columns with R·dv accumulators (see `value_tile`).
    let rows = value_tile(dv);
    // Blocks of keys whose values stay in L1 while every row tile reads them; a tile's
    // sums continue from `out` (zero on entry), so each output sums over keys in order.
    for j0 in (0..n).step_by(VALUE_KEYS) {
        for r0 in (0..STRIP).step_by(rows) {
            let mut acc = [_mm512_setzero_ps(); TILE_ACC];
            for r in 0..rows {
                for c in 0..dv {
                    acc[r * dv + c] = _mm512_loadu_ps(out[r0 + r].as_ptr().add(c * 16));
                }
            }
            for j in j0..(j0 + VALUE_KEYS).min(n) {
                let vp = v.add(j * v_stride);
                let mut vr = [_mm512_setzero_ps(); MAX_D / 16];
                for (c, x) in vr.iter_mut().enumerate().take(dv) {
                    *x = _mm512_loadu_ps(vp.add(c * 16));
                }
                for r in 0..rows {
                    let a = _mm512_set1_ps(*p.add((r0 + r) * ld + j));
                    for c in 0..dv {
                        acc[r * dv + c] = _mm512_fmadd_ps(a, vr[c], acc[r * dv + c]);
                    }
                }
            }
            for r in 0..rows {
                for c in 0..dv {
                    _mm512_storeu_ps(out[r0 + r].as_mut_ptr().add(c * 16), acc[r * dv + c]);
                }
            }
        }
    }
}

/// Keys per block of [`values_f32`]: at head width 96, 24 KB of values (L1 holds 32–48 KB).
const VALUE_KEYS: usize = 64;

/// The same from bf16 probabilities `p16` (`[16][np]`) and values packed by
/// [`pack_values_bf16`] (pairs of rows; `n` rounded up to even, padding is zero).
#[inline(always)]
pub(crate) unsafe fn values_bf16<const D: usize>(p16: *const u16, ld: usize, n: usize, v16: *const u16, out: &mut StripOut) {
    let dv = D / 16;
    let rows = 16 / dv;
    for r0 in (0..STRIP).step_by(rows) {
        let mut acc = [_mm512_setzero_ps(); 16];
        for j2 in 0..n.div_ceil(2) {
            let vp = v16.add(j2 * D * 2);
            let mut vr: [__m512bh; MAX_D / 16] = [std::mem::transmute::<__m512i, __m512bh>(_mm512_setzero_si512()); MAX_D / 16];
            for (c, x) in vr.iter_mut().enumerate().take(dv) {
                *x = std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(vp.add(c * 32) as *const _));
            }
            for r in 0..rows {
                let pair = (p16.add((r0 + r) * ld + 2 * j2) as *const i32).read_unaligned();
                let a: __m512bh = std::mem::transmute(_mm512_set1_epi32(pair));
                for c in 0..dv {
                    acc[r * dv + c] = _mm512_dpbf16_ps(acc[r * dv + c], a, vr[c]);
                }
            }
        }
        for r in 0..rows {
            for c in 0..dv {
                _mm512_storeu_ps(out[r0 + r].as_mut_ptr().add(c * 16), acc[r * dv + c]);
            }
        }
    }
}

// ---- self attention -----------------------------------------------------------------

/// `softmax(q·kᵀ/√d)·v` for every head, with optional column sums of the probabilities
/// (`Σ_h Σ_i A[h,i,j]`), as [`crate::attention::attention`]; an error where this CPU
/// lacks the kernels ([`available`], and [`bf16_available`] for `bf16`).
pub fn attention(q: View, k: View, v: View, heads: usize, col_sums: bool, bf16: bool) -> Result<(Matrix, Option<Vec<f32>>)> {
    if crate::kernels::simd_level() == 3 {
        // AVX2 without AVX-512: the fp32 kernels (bf16 runs as fp32 on such CPUs).
        return crate::attention_fused_avx2::attention(q, k, v, heads, col_sums);
    }
    let (m, n, c) = (q.rows, k.rows, q.cols);
    if k.cols != c || v.cols != c || v.rows != n || heads == 0 || c % heads != 0 || !v.fits() || !runs(c / heads, bf16) {
        return Err(internal(format!("fused attention q {m}×{c}, k {}×{}, v {}×{}, {heads} heads", k.rows, k.cols, v.rows, v.cols)));
    }
    // Column sums need the fp32 probabilities, which the bf16 path does not keep.
    let bf16 = bf16 && !col_sums;
    let mut out = Matrix::zeros(m, c);
    if m == 0 || n == 0 {
        return Ok((out, col_sums.then(|| vec![0.0; n])));
    }
    let pk = pack(q, k, heads, bf16);
    // Padded to `np` rows: the tile kernels read whole blocks of 32 keys.
    let v16 = if bf16 { pack_values_bf16(v, heads, pk.np / 2) } else { Vec::new() };
    let mut vbuf = Vec::new();
    let v = if bf16 { HeadValues::NONE } else { head_values(v, heads, &mut vbuf) };
    let d = pk.d;
    let strips = pk.mp / STRIP;
    let dst = SharedMut(out.data.as_mut_ptr());
    let per_task: Vec<Vec<f32>> = (0..heads * strips)
        .into_par_iter()
        .map_init(
            || (vec![0.0f32; STRIP * pk.ld], vec![0u16; if bf16 { STRIP * pk.ld } else { 0 }]),
            |(s, p16), t| {
                let (h, st) = (t % heads, t / heads);
                let mut cs = if col_sums { vec![0.0f32; n] } else { Vec::new() };
                // SAFETY: AVX-512 (and BF16 for `bf16`) was checked on entry; task
                // (h, st) alone writes rows st·16.. of columns h·d..(h+1)·d of `out`.
                let job = SelfJob { pk: &pk, v, v16: &v16, h, st, dst };
                unsafe {
                    match (d, bf16) {
                        (16, false) => self_strip_f32::<16>(&job, s, &mut cs),
                        (32, false) => self_strip_f32::<32>(&job, s, &mut cs),
                        (64, false) => self_strip_f32::<64>(&job, s, &mut cs),
                        (_, false) => self_strip_f32::<96>(&job, s, &mut cs),
                        (16, true) => self_strip_bf16::<16>(&job, s, p16, &mut cs),
                        (32, true) => self_strip_bf16::<32>(&job, s, p16, &mut cs),
                        (64, true) => self_strip_bf16::<64>(&job, s, p16, &mut cs),
                        (_, true) => self_strip_bf16::<96>(&job, s, p16, &mut cs),
                    }
                }
                cs
            },
        )
        .collect();
    Ok((out, col_sums.then(|| sum_in_order(&per_task, n))))
}

/// One strip of self attention: rows `st·16..` of head `h`.
struct SelfJob<'a> {
    pk: &'a Packed,
    v: HeadValues<'a>,
    v16: &'a [u16],
    h: usize,
    st: usize,
    dst: SharedMut,
}

#[target_feature(enable = "avx512f")]
unsafe fn self_strip_f32<const D: usize>(job: &SelfJob, s: &mut [f32], cs: &mut [f32]) {
    self_strip::<D, false>(job, s, &mut [], cs)
}

#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn self_strip_bf16<const D: usize>(job: &SelfJob, s: &mut [f32], p16: &mut [u16], cs: &mut [f32]) {
    self_strip::<D, true>(job, s, p16, cs)
}

/// Scores of the 16 query rows from `r0` of head `h` into the strip `s`.
#[inline(always)]
unsafe fn strip_scores<const D: usize, const BF: bool>(pk: &Packed, h: usize, r0: usize, s: &mut [f32]) {
    let (q, k) = ((h * pk.mp + r0) * D, h * pk.np * D);
    if BF && pk.amx {
        crate::amx::scores::<D>(pk.q16.as_ptr().add(q), pk.k16.as_ptr().add(k), pk.n, pk.np, s.as_mut_ptr(), pk.ld);
    } else if BF {
        scores_bf16::<D>(pk.q16.as_ptr().add(q), pk.k16.as_ptr().add(k), pk.n, pk.np, s.as_mut_ptr(), pk.ld);
    } else {
        scores_f32::<D>(pk.q.as_ptr().add(q), pk.k.as_ptr().add(k), pk.n, pk.np, s.as_mut_ptr(), pk.ld);
    }
}

/// Softmax over the keys of the strip's rows and the value product: rows `r0..r0+rows`
/// of columns `h·D..(h+1)·D` of `dst` (row stride `H·D`). Returns each row's `1/Σ`; with
/// fp32, `s` then holds the unnormalised probabilities.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
unsafe fn strip_rows<const D: usize, const BF: bool>(
    pk: &Packed,
    h: usize,
    r0: usize,
    rows: usize,
    s: &mut [f32],
    p16: &mut [u16],
    v: HeadValues,
    v16: &[u16],
    dst: SharedMut,
) -> [f32; STRIP] {
    let (n, np, ld, c) = (pk.n, pk.np, pk.ld, pk.heads * D);
    let mut inv = [0.0f32; STRIP];
    for (r, iv) in inv.iter_mut().enumerate() {
        let p = BF.then(|| p16.as_mut_ptr().add(r * ld));
        *iv = 1.0 / exp_row(s.as_mut_ptr().add(r * ld), np, p);
    }
    let mut out: StripOut = [[0.0; MAX_D]; STRIP];
    if BF {
        // Values of head h: `np/2` pairs of rows (see `pack_values_bf16`).
        let vh = v16.as_ptr().add(h * np * D);
        if pk.amx {
            crate::amx::values::<D>(p16.as_ptr(), ld, n, vh, &mut out);
        } else {
            values_bf16::<D>(p16.as_ptr(), ld, n, vh, &mut out);
        }
    } else {
        values_f32::<D>(s.as_ptr(), ld, n, v.row(h, 0), v.stride, &mut out);
    }
    for (r, o) in out.iter().enumerate().take(rows) {
        let row = dst.at((r0 + r) * c + h * D);
        for (t, x) in o[..D].iter().enumerate() {
            *row.add(t) = x * inv[r];
        }
    }
    inv
}

#[inline(always)]
unsafe fn self_strip<const D: usize, const BF: bool>(job: &SelfJob, s: &mut [f32], p16: &mut [u16], cs: &mut [f32]) {
    let SelfJob { pk, v, v16, h, st, dst } = *job;
    let (n, ld) = (pk.n, pk.ld);
    let r0 = st * STRIP;
    let rows = STRIP.min(pk.m - r0);
    strip_scores::<D, BF>(pk, h, r0, s);
    let inv = strip_rows::<D, BF>(pk, h, r0, rows, s, p16, v, v16, dst);
    if !cs.is_empty() {
        // Probabilities of the valid rows, summed per column (always fp32: see `attention`).
        for (r, iv) in inv.iter().enumerate().take(rows) {
            let srow = &s[r * ld..r * ld + n];
            for (a, e) in cs.iter_mut().zip(srow) {
                *a += e * iv;
            }
        }
    }
}

// ---- shared cross attention ---------------------------------------------------------

/// Column-direction state of one task: running maxima, sums and `Σ_i e_ij·vx_i`.
pub(crate) struct ColumnState {
    pub(crate) max: Vec<f32>,
    pub(crate) sum: Vec<f32>,
    pub(crate) acc: Vec<f32>,
}

/// Cross attention with attention-weight sharing, as
/// [`crate::attention::cross_attention_shared`]: `(softmax_rows(S)·vy, softmax_rows(Sᵀ)·vx)`
/// with `S = qx·kyᵀ/√d` per head.
pub fn cross_attention_shared(qx: View, ky: View, vx: View, vy: View, heads: usize, bf16: bool) -> Result<(Matrix, Matrix)> {
    if crate::kernels::simd_level() == 3 {
        return crate::attention_fused_avx2::cross_attention_shared(qx, ky, vx, vy, heads);
    }
    let (m, n, c) = (qx.rows, ky.rows, qx.cols);
    if ky.cols != c || vx.cols != c || vy.cols != c || vx.rows != m || vy.rows != n || heads == 0 || c % heads != 0 || !vx.fits() || !vy.fits() || !runs(c / heads, bf16) {
        return Err(internal(format!("fused cross attention qx {m}×{c}, ky {n}×{}, {heads} heads", ky.cols)));
    }
    if bf16 && crate::amx::active() {
        // On AMX tiles the scores cost little next to the softmax: the column direction is
        // cheaper as a second row pass over Sᵀ = ky·qxᵀ than as running column states.
        let (out_x, _) = attention(qx, ky, vy, heads, false, true)?;
        let (out_y, _) = attention(ky, qx, vx, heads, false, true)?;
        return Ok((out_x, out_y));
    }
    let (mut out_x, mut out_y) = (Matrix::zeros(m, c), Matrix::zeros(n, c));
    if m == 0 || n == 0 {
        return Ok((out_x, out_y));
    }
    let pk = pack(qx, ky, heads, bf16);
    let vy16 = if bf16 { pack_values_bf16(vy, heads, pk.np / 2) } else { Vec::new() };
    let vx16 = if bf16 { pack_values_bf16(vx, heads, m.div_ceil(2)) } else { Vec::new() };
    let (mut vxbuf, mut vybuf) = (Vec::new(), Vec::new());
    let (vx, vy) = if bf16 { (HeadValues::NONE, HeadValues::NONE) } else { (head_values(vx, heads, &mut vxbuf), head_values(vy, heads, &mut vybuf)) };
    let d = pk.d;
    let split = CrossTasks::new(m);
    let chunks = split.chunks();
    let dx = SharedMut(out_x.data.as_mut_ptr());
    let states: Vec<ColumnState> = (0..heads * chunks)
        .into_par_iter()
        .map(|t| {
            let (h, ch) = (t % heads, t / heads);
            // SAFETY: AVX-512 (and BF16 for `bf16`) was checked on entry; task (h, ch)
            // alone writes rows `split.rows(ch)` of columns h·d..(h+1)·d of `out_x`.
            let job = CrossJob { pk: &pk, vx, vy, vx16: &vx16, vy16: &vy16, h, rows: split.rows(ch), dx };
            unsafe {
                match (d, bf16) {
                    (16, false) => cross_chunk_f32::<16>(&job),
                    (32, false) => cross_chunk_f32::<32>(&job),
                    (64, false) => cross_chunk_f32::<64>(&job),
                    (_, false) => cross_chunk_f32::<96>(&job),
                    (16, true) => cross_chunk_bf16::<16>(&job),
                    (32, true) => cross_chunk_bf16::<32>(&job),
                    (64, true) => cross_chunk_bf16::<64>(&job),
                    (_, true) => cross_chunk_bf16::<96>(&job),
                }
            }
        })
        .collect();
    merge_columns(&states, heads, chunks, d, &mut out_y);
    Ok((out_x, out_y))
}

/// Merges the column states of each head's chunks (`states[chunk · heads + h]`) in order,
/// each rescaled to the overall column maximum, into `out_y` `[N, H·d]`.
pub(crate) fn merge_columns(states: &[ColumnState], heads: usize, chunks: usize, d: usize, out_y: &mut Matrix) {
    let c = out_y.cols;
    // Rows of image 1 in parallel (each row's sums in the same order as before).
    out_y.data.par_chunks_mut(c).enumerate().for_each(|(j, row)| {
        for h in 0..heads {
            let parts = || (0..chunks).map(|ch| &states[ch * heads + h]);
            let mx = parts().fold(NEG, |a, s| a.max(s.max[j]));
            let mut sum = 0.0f32;
            let mut acc = [0.0f32; MAX_D];
            for s in parts() {
                let f = (std::f32::consts::LN_2 * (s.max[j] - mx)).exp();
                sum += s.sum[j] * f;
                for (a, x) in acc[..d].iter_mut().zip(&s.acc[j * d..(j + 1) * d]) {
                    *a += x * f;
                }
            }
            for (o, a) in row[h * d..(h + 1) * d].iter_mut().zip(&acc[..d]) {
                *o = a / sum;
            }
        }
    });
}

/// One task of the shared cross attention: rows `rows.0..rows.1` of head `h`.
struct CrossJob<'a> {
    pk: &'a Packed,
    vx: HeadValues<'a>,
    vy: HeadValues<'a>,
    vx16: &'a [u16],
    vy16: &'a [u16],
    h: usize,
    rows: (usize, usize),
    dx: SharedMut,
}

#[target_feature(enable = "avx512f")]
unsafe fn cross_chunk_f32<const D: usize>(job: &CrossJob) -> ColumnState {
    cross_chunk::<D, false>(job)
}

#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn cross_chunk_bf16<const D: usize>(job: &CrossJob) -> ColumnState {
    cross_chunk::<D, true>(job)
}

#[inline(always)]
unsafe fn cross_chunk<const D: usize, const BF: bool>(job: &CrossJob) -> ColumnState {
    let CrossJob { pk, vx, vy, vx16, vy16, h, rows: (first, last), dx } = *job;
    let (np, ld) = (pk.np, pk.ld);
    let mut st = ColumnState { max: vec![NEG; np], sum: vec![0.0; np], acc: vec![0.0; np * D] };
    // fp32 takes the column direction over CROSS_STRIPS strips at once: the column sums
    // `acc` (N × D, in L2) are read and written once per group rather than per strip.
    let group = if BF { 1 } else { CROSS_STRIPS };
    let mut s = vec![0.0f32; group * STRIP * ld];
    let mut p16 = vec![0u16; if BF { STRIP * ld } else { 0 }];
    let mut factor = vec![0.0f32; np];
    for r0 in (first..last).step_by(group * STRIP) {
        let rows = (group * STRIP).min(last - r0);
        for g in 0..rows.div_ceil(STRIP) {
            strip_scores::<D, BF>(pk, h, r0 + g * STRIP, &mut s[g * STRIP * ld..]);
        }
        // Columns: new running maxima over the valid rows; rescale what grew. The factor is
        // exactly 1 where the maximum stayed (`exp2v(0)` is 1 + 1.2e-7, which made every
        // column's sums look grown and rescaled them all on every strip).
        let sp = s.as_ptr();
        let mut grew = false;
        for j in (0..np).step_by(16) {
            let old = _mm512_loadu_ps(st.max.as_ptr().add(j));
            let mut bm = old;
            for r in 0..rows {
                bm = _mm512_max_ps(bm, _mm512_loadu_ps(sp.add(r * ld + j)));
            }
            let up = _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(bm, old);
            let f = _mm512_mask_blend_ps(up, _mm512_set1_ps(1.0), exp2v(_mm512_sub_ps(old, bm)));
            _mm512_storeu_ps(st.max.as_mut_ptr().add(j), bm);
            _mm512_storeu_ps(factor.as_mut_ptr().add(j), f);
            _mm512_storeu_ps(st.sum.as_mut_ptr().add(j), _mm512_mul_ps(f, _mm512_loadu_ps(st.sum.as_ptr().add(j))));
            grew |= up != 0;
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
        if BF {
            // Pairs of rows r0, r0+1, … (r0 is even): pair index r0/2 of the packed values.
            column_values_bf16::<D>(sp, np, ld, rows, &mut st, vx16.as_ptr().add((h * pk.m.div_ceil(2) + r0 / 2) * D * 2));
        } else {
            column_values::<D>(sp, np, ld, rows, &mut st, vx.row(h, r0), vx.stride);
        }
        // Rows: softmax over the keys, values of image 1, a strip at a time.
        for g in 0..rows.div_ceil(STRIP) {
            let sg = &mut s[g * STRIP * ld..];
            strip_rows::<D, BF>(pk, h, r0 + g * STRIP, STRIP.min(rows - g * STRIP), sg, &mut p16, vy, vy16, dx);
        }
    }
    let n = pk.n;
    st.max.truncate(n);
    st.sum.truncate(n);
    st.acc.truncate(n * D);
    st
}

/// [`column_values`] with bf16 products: `e` is rounded to bf16 and paired along rows,
/// `vx16` holds the strip's values packed by [`pack_values_bf16`]; maxima and sums stay fp32.
#[inline(always)]
unsafe fn column_values_bf16<const D: usize>(s: *const f32, np: usize, ld: usize, rows: usize, st: &mut ColumnState, vx16: *const u16) {
    let dv = D / 16;
    let cols = 16 / dv;
    // Lane k of the result takes 16-bit lane idx[k]: e_r[0], e_r+1[0], e_r[1], e_r+1[1], …
    let idx = _mm512_set_epi16(
        31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8, 23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0,
    );
    let pairs = rows.div_ceil(2);
    let mut e = [[0u32; 16]; STRIP / 2];
    for j0 in (0..np).step_by(16) {
        let mx = _mm512_loadu_ps(st.max.as_ptr().add(j0));
        let mut sum = _mm512_loadu_ps(st.sum.as_ptr().add(j0));
        for (p, ep) in e.iter_mut().enumerate().take(pairs) {
            let r = 2 * p;
            let x0 = exp2v_bf16(_mm512_sub_ps(_mm512_loadu_ps(s.add(r * ld + j0)), mx));
            let x1 = if r + 1 < rows { exp2v_bf16(_mm512_sub_ps(_mm512_loadu_ps(s.add((r + 1) * ld + j0)), mx)) } else { _mm512_setzero_ps() };
            sum = _mm512_add_ps(sum, _mm512_add_ps(x0, x1));
            let both = std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(x1, x0));
            _mm512_storeu_si512(ep.as_mut_ptr() as *mut _, _mm512_permutexvar_epi16(idx, both));
        }
        _mm512_storeu_ps(st.sum.as_mut_ptr().add(j0), sum);
        for jt in (0..16).step_by(cols) {
            let mut acc = [_mm512_setzero_ps(); 16];
            for (p, ep) in e.iter().enumerate().take(pairs) {
                let vp = vx16.add(p * D * 2);
                let mut vr = [std::mem::transmute::<__m512i, __m512bh>(_mm512_setzero_si512()); MAX_D / 16];
                for (cc, x) in vr.iter_mut().enumerate().take(dv) {
                    *x = std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(vp.add(cc * 32) as *const _));
                }
                for jj in 0..cols {
                    let a = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(ep[jt + jj] as i32));
                    for cc in 0..dv {
                        acc[jj * dv + cc] = _mm512_dpbf16_ps(acc[jj * dv + cc], a, vr[cc]);
                    }
                }
            }
            for jj in 0..cols {
                let ap = st.acc.as_mut_ptr().add((j0 + jt + jj) * D);
                for cc in 0..dv {
                    _mm512_storeu_ps(ap.add(cc * 16), _mm512_add_ps(_mm512_loadu_ps(ap.add(cc * 16)), acc[jj * dv + cc]));
                }
            }
        }
    }
}

/// Column direction of up to [`CROSS_STRIPS`] strips: `e_rj = 2^(s_rj − max_j)`, `sum_j += Σ_r e_rj` and
/// `acc_j += Σ_r e_rj·vx_r` (fp32: these sums are few per column and stay exact enough).
#[inline(always)]
unsafe fn column_values<const D: usize>(s: *const f32, np: usize, ld: usize, rows: usize, st: &mut ColumnState, vx: *const f32, vx_stride: usize) {
    let dv = D / 16;
    let cols = value_tile(dv); // columns per register tile: cols·dv accumulators
    let mut e = [[0.0f32; 16]; CROSS_STRIPS * STRIP];
    for j0 in (0..np).step_by(16) {
        let mx = _mm512_loadu_ps(st.max.as_ptr().add(j0));
        let mut sum = _mm512_loadu_ps(st.sum.as_ptr().add(j0));
        for (r, er) in e.iter_mut().enumerate().take(rows) {
            let x = exp2v(_mm512_sub_ps(_mm512_loadu_ps(s.add(r * ld + j0)), mx));
            sum = _mm512_add_ps(sum, x);
            _mm512_storeu_ps(er.as_mut_ptr(), x);
        }
        _mm512_storeu_ps(st.sum.as_mut_ptr().add(j0), sum);
        for jt in (0..16).step_by(cols) {
            let mut acc = [_mm512_setzero_ps(); TILE_ACC];
            for (r, er) in e.iter().enumerate().take(rows) {
                let vp = vx.add(r * vx_stride);
                let mut vr = [_mm512_setzero_ps(); MAX_D / 16];
                for (cc, x) in vr.iter_mut().enumerate().take(dv) {
                    *x = _mm512_loadu_ps(vp.add(cc * 16));
                }
                for jj in 0..cols {
                    let a = _mm512_set1_ps(er[jt + jj]);
                    for cc in 0..dv {
                        acc[jj * dv + cc] = _mm512_fmadd_ps(a, vr[cc], acc[jj * dv + cc]);
                    }
                }
            }
            for jj in 0..cols {
                let ap = st.acc.as_mut_ptr().add((j0 + jt + jj) * D);
                for cc in 0..dv {
                    _mm512_storeu_ps(ap.add(cc * 16), _mm512_add_ps(_mm512_loadu_ps(ap.add(cc * 16)), acc[jj * dv + cc]));
                }
            }
        }
    }
}
}

/// Test helpers shared with [`crate::attention_fused_avx2`]'s tests.
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) mod tests {
    use crate::attention::{attention, cross_attention_shared};
    use crate::kernels::{Ctx, Matrix, Precision};

    pub(crate) fn random(rows: usize, cols: usize, seed: u64, amp: f32) -> Matrix {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let data = (0..rows * cols)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 2.0 * amp
            })
            .collect();
        Matrix { rows, cols, data }
    }

    pub(crate) fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
    }

    pub(crate) fn general() -> Ctx {
        let mut ctx = Ctx::default();
        ctx.fused = false;
        ctx
    }

    /// `2^x` of the AVX-512 kernels: accurate over the softmax's range, exactly 0 (never a
    /// subnormal, which would slow every product reading it) below −125, NaN kept.
    #[test]
    fn exp2_flushes_below_the_normal_range_and_keeps_nan() {
        if crate::kernels::simd_level() < 4 {
            eprintln!("skipped: no AVX-512 here");
            return;
        }
        let xs: Vec<f32> = (0..4000).map(|i| -160.0 + i as f32 * 0.04).chain([f32::NAN, -1e30, 0.0]).collect();
        for chunk in xs.chunks(16) {
            let mut x = [0f32; 16];
            x[..chunk.len()].copy_from_slice(chunk);
            let mut y = [0f32; 16];
            // SAFETY: simd_level 4 means AVX-512F is present; both arrays hold 16 floats.
            unsafe {
                #[target_feature(enable = "avx512f")]
                unsafe fn run(x: &[f32; 16], y: &mut [f32; 16]) {
                    use std::arch::x86_64::*;
                    _mm512_storeu_ps(y.as_mut_ptr(), crate::attention_fused::x86::exp2v(_mm512_loadu_ps(x.as_ptr())));
                }
                run(&x, &mut y);
            }
            for (&xi, &yi) in x.iter().zip(&y).take(chunk.len()) {
                if xi.is_nan() {
                    assert!(yi.is_nan());
                } else if xi < -125.0 {
                    assert_eq!(yi, 0.0, "2^{xi}");
                } else {
                    assert!(yi.is_normal(), "2^{xi} = {yi:e} is not a normal float");
                    let want = (xi as f64).exp2();
                    assert!(((yi as f64 - want) / want).abs() < 5e-7, "2^{xi}: {yi:e} against {want:e}");
                }
            }
        }
    }

    /// The fused kernels against the general path: odd sizes (padding of rows and
    /// columns), every head width, more rows than one cross-attention task, large scores.
    #[test]
    fn fused_matches_the_general_path() {
        if !super::available(16) {
            eprintln!("skipped: no AVX2 or AVX-512 here");
            return;
        }
        for &(m, n, c, heads, amp) in &[(77, 53, 64, 4, 1.0), (600, 301, 64, 2, 2.0), (33, 517, 128, 2, 1.5), (5, 1, 32, 2, 1.0), (300, 300, 64, 1, 3.0), (2100, 40, 64, 2, 1.0), (77, 53, 96, 1, 1.0), (300, 517, 192, 2, 2.0)] {
            let (q, k, v) = (random(m, c, 1, amp), random(n, c, 2, amp), random(n, c, 3, 1.0));
            let (vx, ky) = (random(m, c, 4, 1.0), random(n, c, 5, amp));
            let (want, want_cs) = attention(&general(), q.view(), k.view(), v.view(), heads, true).expect("general");
            let (got, got_cs) = attention(&Ctx::default(), q.view(), k.view(), v.view(), heads, true).expect("fused");
            let (want_cs, got_cs) = (want_cs.expect("sums"), got_cs.expect("sums"));
            assert!(max_diff(&want.data, &got.data) < 2e-6, "self {m}×{n} c{c} h{heads}: {}", max_diff(&want.data, &got.data));
            assert!(max_diff(&want_cs, &got_cs) < 1e-5 * m as f32, "col sums: {}", max_diff(&want_cs, &got_cs));
            let (wx, wy) = cross_attention_shared(&general(), q.view(), ky.view(), vx.view(), v.view(), heads).expect("general");
            let (gx, gy) = cross_attention_shared(&Ctx::default(), q.view(), ky.view(), vx.view(), v.view(), heads).expect("fused");
            assert!(max_diff(&wx.data, &gx.data) < 2e-6, "cross x {m}×{n}: {}", max_diff(&wx.data, &gx.data));
            assert!(max_diff(&wy.data, &gy.data) < 2e-6, "cross y {m}×{n}: {}", max_diff(&wy.data, &gy.data));
            if super::bf16_available() {
                let bf = Ctx::with_precision(Precision::Bf16);
                let (b, _) = attention(&bf, q.view(), k.view(), v.view(), heads, false).expect("bf16");
                let (bx, by) = cross_attention_shared(&bf, q.view(), ky.view(), vx.view(), v.view(), heads).expect("bf16");
                // Column sums are asked for in fp32 even under bf16: the same as fp32's.
                let (b_cs, cs16) = attention(&bf, q.view(), k.view(), v.view(), heads, true).expect("bf16 with sums");
                assert_eq!(cs16.expect("sums"), got_cs, "bf16 column sums");
                assert_eq!(b_cs.data, got.data, "bf16 with column sums runs fp32");
                // bf16 operands: 8 significant bits, errors of a few 1e-3 on values of size ~1.
                for (name, w, g) in [("self", &want, &b), ("cross x", &wx, &bx), ("cross y", &wy, &by)] {
                    let e = max_diff(&w.data, &g.data);
                    assert!(e < 0.005 * amp, "bf16 {name} {m}×{n}: {e}");
                }
            }
        }
    }

    /// Values read from a slice of a wider matrix (as of a fused projection), at one head
    /// (rows strided, copied to contiguous rows) and two, in self and cross attention, by
    /// the AVX-512 kernels and their AVX2 twin.
    #[test]
    fn fused_reads_strided_values() {
        if !super::available(32) {
            eprintln!("skipped: no AVX2 or AVX-512 here");
            return;
        }
        for &(m, n, c, heads) in &[(70, 45, 32, 1), (40, 90, 64, 2), (33, 20, 96, 1)] {
            let (q, k) = (random(m, c, 1, 1.0), random(n, c, 2, 1.0));
            let (wide_x, wide_y) = (random(m, 3 * c, 3, 1.0), random(n, 3 * c, 4, 1.0));
            let (vx, vy) = (wide_x.view().cols(c, 2 * c), wide_y.view().cols(2 * c, 3 * c));
            let (want, _) = attention(&general(), q.view(), k.view(), vy, heads, false).expect("general");
            let (got, _) = attention(&Ctx::default(), q.view(), k.view(), vy, heads, false).expect("fused");
            assert!(max_diff(&want.data, &got.data) < 2e-6, "self c{c} h{heads}: {}", max_diff(&want.data, &got.data));
            let (wx, wy) = cross_attention_shared(&general(), q.view(), k.view(), vx, vy, heads).expect("general");
            let (gx, gy) = cross_attention_shared(&Ctx::default(), q.view(), k.view(), vx, vy, heads).expect("fused");
            assert!(max_diff(&wx.data, &gx.data) < 2e-6 && max_diff(&wy.data, &gy.data) < 2e-6, "cross c{c} h{heads}");
            // The AVX2 twin, called directly (it reads the values the same way).
            let (got, _) = crate::attention_fused_avx2::attention(q.view(), k.view(), vy, heads, false).expect("avx2");
            assert!(max_diff(&want.data, &got.data) < 2e-6, "avx2 self c{c} h{heads}");
            let (gx, gy) = crate::attention_fused_avx2::cross_attention_shared(q.view(), k.view(), vx, vy, heads).expect("avx2");
            assert!(max_diff(&wx.data, &gx.data) < 2e-6 && max_diff(&wy.data, &gy.data) < 2e-6, "avx2 cross c{c} h{heads}");
        }
    }

    /// Results do not depend on the thread count.
    #[test]
    fn fused_is_reproducible_across_thread_counts() {
        if !super::available(32) {
            eprintln!("skipped: no AVX2 or AVX-512 here");
            return;
        }
        let (q, k, v) = (random(700, 64, 7, 2.0), random(650, 64, 8, 2.0), random(650, 64, 9, 1.0));
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            pool.install(|| {
                let (a, s) = attention(&Ctx::default(), q.view(), k.view(), v.view(), 2, true).expect("self");
                let (x, y) = cross_attention_shared(&Ctx::default(), q.view(), k.view(), q.view(), v.view(), 2).expect("cross");
                (a.data, s, x.data, y.data)
            })
        };
        assert!(run(1) == run(3));
    }
}
