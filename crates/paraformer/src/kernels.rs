//! CPU kernels of the inference engine: strided matrix products (the `gemm` crate,
//! no copies for head slices or transposes), and vectorised exp, softmax,
//! logsumexp, GELU and LayerNorm. Element-wise kernels are compiled for AVX-512,
//! AVX2+FMA and baseline x86-64, and the best one is chosen at run time.

use std::sync::atomic::{AtomicU64, AtomicU8, Ordering};

use crate::error::{Error, Result};

/// A dense row-major `f32` matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct Matrix {
    pub rows: usize,
    pub cols: usize,
    pub data: Vec<f32>,
}

impl Matrix {
    pub fn zeros(rows: usize, cols: usize) -> Self {
        Self { rows, cols, data: vec![0.0; rows * cols] }
    }

    pub fn from_vec(rows: usize, cols: usize, data: Vec<f32>) -> Result<Self> {
        if data.len() != rows * cols {
            return Err(internal(format!("matrix {rows}×{cols} from {} values", data.len())));
        }
        Ok(Self { rows, cols, data })
    }

    pub fn get(&self, r: usize, c: usize) -> f32 {
        self.data[r * self.cols + c]
    }

    pub fn row(&self, r: usize) -> &[f32] {
        &self.data[r * self.cols..(r + 1) * self.cols]
    }

    pub fn view(&self) -> View<'_> {
        View { data: &self.data, rows: self.rows, cols: self.cols, stride: self.cols }
    }
}

/// A read-only strided view: `rows × cols`, row stride `stride`, column stride 1.
#[derive(Debug, Clone, Copy)]
pub struct View<'a> {
    pub data: &'a [f32],
    pub rows: usize,
    pub cols: usize,
    pub stride: usize,
}

impl<'a> View<'a> {
    /// Columns `c0..c1`.
    pub fn cols(&self, c0: usize, c1: usize) -> View<'a> {
        View { data: &self.data[c0.min(self.data.len())..], rows: self.rows, cols: c1 - c0, stride: self.stride }
    }

    /// Rows `r0..r1`.
    pub fn rows(&self, r0: usize, r1: usize) -> View<'a> {
        let start = (r0 * self.stride).min(self.data.len());
        View { data: &self.data[start..], rows: r1 - r0, cols: self.cols, stride: self.stride }
    }

    /// Whether every element of the view lies inside `data`.
    pub(crate) fn fits(&self) -> bool {
        self.rows == 0 || self.cols == 0 || (self.rows - 1) * self.stride + self.cols <= self.data.len()
    }

    pub fn row(&self, r: usize) -> &'a [f32] {
        &self.data[r * self.stride..r * self.stride + self.cols]
    }

    pub fn to_matrix(&self) -> Matrix {
        let mut data = Vec::with_capacity(self.rows * self.cols);
        for r in 0..self.rows {
            data.extend_from_slice(self.row(r));
        }
        Matrix { rows: self.rows, cols: self.cols, data }
    }
}

/// Element-wise sum of per-task vectors of length `n`, added in task order: the attention
/// kernels' column sums, the same for any thread count. Empty tasks are skipped.
pub(crate) fn sum_in_order(parts: &[Vec<f32>], n: usize) -> Vec<f32> {
    let mut sums = vec![0.0f32; n];
    for part in parts {
        for (a, p) in sums.iter_mut().zip(part) {
            *a += p;
        }
    }
    sums
}

pub(crate) fn internal(msg: String) -> Error {
    Error::Tensor(candle_core::Error::Msg(format!("internal shape error: {msg}")))
}

/// A raw output pointer shared by tasks that write disjoint regions.
#[derive(Clone, Copy)]
pub(crate) struct SharedMut(pub *mut f32);
// SAFETY: every user writes only its own disjoint rows/columns of the buffer.
unsafe impl Send for SharedMut {}
unsafe impl Sync for SharedMut {}

impl SharedMut {
    /// The pointer `offset` values in (a method, so closures capture the whole wrapper).
    ///
    /// # Safety
    /// `offset` must lie inside the buffer.
    pub(crate) unsafe fn at(self, offset: usize) -> *mut f32 {
        // SAFETY: the caller keeps `offset` inside the buffer.
        unsafe { self.0.add(offset) }
    }
}

/// Arithmetic of the matcher's heavy products.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub enum Precision {
    /// fp32 everywhere (the default; SPEC's numbers).
    #[default]
    Fp32,
    /// bf16 operands with fp32 accumulation, where the CPU has AVX-512 BF16 (see
    /// [`Precision::effective`]), on AMX tiles where it also has AMX-BF16 ([`crate::amx`]):
    /// the attention products at head widths 16, 32, 64 and 96,
    /// the attention layers' Linear layers, Wave-PE's descriptor and wave MLPs, and
    /// Sinkhorn's kernel. Softmax, maxima and sums, LayerNorm, the position MLPs, the
    /// final projection, the score matrix and every layer whose attention column sums
    /// choose ParaFormer-U's pooled keypoints stay fp32.
    Bf16,
}

impl Precision {
    /// Parses `"fp32"` or `"bf16"`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "fp32" => Ok(Self::Fp32),
            "bf16" => Ok(Self::Bf16),
            other => Err(Error::InvalidInput { argument: "precision".into(), reason: format!("`{other}`; expected \"fp32\" or \"bf16\"") }),
        }
    }

    /// The name `parse` reads.
    pub fn name(self) -> &'static str {
        match self {
            Self::Fp32 => "fp32",
            Self::Bf16 => "bf16",
        }
    }

    /// What runs on this CPU: bf16 needs AVX-512 BF16 and falls back to fp32 without it.
    pub fn effective(self) -> Self {
        match self {
            Self::Bf16 if crate::attention_fused::bf16_available() => Self::Bf16,
            _ => Self::Fp32,
        }
    }
}

/// Per-call engine state: the thread count, the attention precision, and a count of the
/// multiply-accumulates of every matrix product performed (checked against `flops`).
#[derive(Debug)]
pub struct Ctx {
    pub threads: usize,
    /// Arithmetic of the heavy products (already [`Precision::effective`]).
    pub precision: Precision,
    /// Use the fused narrow-head attention kernels where they apply (off: the general path,
    /// the reference the fused kernels are tested against).
    pub fused: bool,
    macs: AtomicU64,
}

impl Default for Ctx {
    fn default() -> Self {
        Self { threads: rayon::current_num_threads().max(1), precision: Precision::Fp32, fused: true, macs: AtomicU64::new(0) }
    }
}

impl Ctx {
    /// A context with the given attention precision (downgraded to what the CPU runs).
    pub fn with_precision(precision: Precision) -> Self {
        Self { precision: precision.effective(), ..Self::default() }
    }

    /// Counts multiply-accumulates done outside [`Ctx::gemm`] (the fused kernels).
    pub fn add_macs(&self, macs: u64) {
        self.macs.fetch_add(macs, Ordering::Relaxed);
    }

    pub fn macs(&self) -> u64 {
        self.macs.load(Ordering::Relaxed)
    }

    /// `dst (+)= scale · op(a) · op(b)` where `op(a)` is `a` `[m, k]` (or, when
    /// `a_t`, `a` is given as its transpose `[k, m]`), likewise `b` `[k, n]` / `[n, k]`.
    /// `dst` has row stride `dst_stride`. Runs on all threads when `parallel`.
    #[allow(clippy::too_many_arguments)]
    pub fn gemm(
        &self,
        dst: &mut [f32],
        dst_stride: usize,
        a: View,
        a_t: bool,
        b: View,
        b_t: bool,
        scale: f32,
        accumulate: bool,
        parallel: bool,
    ) -> Result<()> {
        let (m, n) = (if a_t { a.cols } else { a.rows }, if b_t { b.rows } else { b.cols });
        if m > 0 && n > 0 && (m - 1) * dst_stride + n > dst.len() {
            return Err(internal(format!("gemm output {m}×{n} (stride {dst_stride}) in {} values", dst.len())));
        }
        // SAFETY: the destination was bounds-checked just above.
        unsafe { self.gemm_ptr(dst.as_mut_ptr(), dst_stride, a, a_t, b, b_t, scale, accumulate, parallel) }
    }

    /// [`Ctx::gemm`] into a raw destination.
    ///
    /// # Safety
    /// `dst` must be valid for writes of `op(a).rows × op(b).cols` values at row stride
    /// `dst_stride`, and no one else may access those values during the call.
    #[allow(clippy::too_many_arguments)]
    pub(crate) unsafe fn gemm_ptr(
        &self,
        dst: *mut f32,
        dst_stride: usize,
        a: View,
        a_t: bool,
        b: View,
        b_t: bool,
        scale: f32,
        accumulate: bool,
        parallel: bool,
    ) -> Result<()> {
        let (m, k) = if a_t { (a.cols, a.rows) } else { (a.rows, a.cols) };
        let (kb, n) = if b_t { (b.cols, b.rows) } else { (b.rows, b.cols) };
        if k != kb || !a.fits() || !b.fits() {
            return Err(internal(format!("gemm [{m}×{k}]·[{kb}×{n}]")));
        }
        if m == 0 || n == 0 {
            return Ok(());
        }
        if k == 0 {
            if !accumulate {
                for r in 0..m {
                    // SAFETY: inside the caller's promised destination.
                    unsafe { std::slice::from_raw_parts_mut(dst.add(r * dst_stride), n).fill(0.0) };
                }
            }
            return Ok(());
        }
        self.macs.fetch_add((m * n * k) as u64, Ordering::Relaxed);
        let (a_rs, a_cs) = if a_t { (1isize, a.stride as isize) } else { (a.stride as isize, 1isize) };
        let (b_rs, b_cs) = if b_t { (1isize, b.stride as isize) } else { (b.stride as isize, 1isize) };
        let par = if parallel && self.threads > 1 && m * n * k >= 1 << 20 {
            gemm::Parallelism::Rayon(self.threads)
        } else {
            gemm::Parallelism::None
        };
        // SAFETY: `a` and `b` were bounds-checked for these strides; `dst` is the caller's promise.
        unsafe {
            gemm::gemm(
                m, n, k, dst, 1, dst_stride as isize, accumulate, a.data.as_ptr(), a_cs, a_rs, b.data.as_ptr(), b_cs,
                b_rs, 1.0, scale, false, false, false, par,
            );
        }
        Ok(())
    }
}

// ---- run-time dispatch ----------------------------------------------------------

/// Caps the SIMD level of the project's own kernels: `avx512`, `avx2` or `baseline`. It
/// never raises the level above what the CPU has, and the linear layers' `gemm` crate picks
/// its own; for running, testing and timing the narrower kernels on a wider CPU.
pub const SIMD_ENV: &str = "PARAFORMER_SIMD";

/// The levels [`SIMD_ENV`] names, widest first.
const SIMD_NAMES: [(&str, u8); 3] = [("avx512", 4), ("avx2", 3), ("baseline", 0)];

/// An error naming [`SIMD_ENV`] when it holds anything but a level's name (the dispatch
/// itself cannot report it: it runs such a value as unset).
pub fn check_env() -> Result<()> {
    match std::env::var_os(SIMD_ENV) {
        None => Ok(()),
        Some(v) if SIMD_NAMES.iter().any(|(name, _)| v == *name) => Ok(()),
        Some(v) => Err(Error::InvalidInput { argument: SIMD_ENV.into(), reason: format!("{v:?}: expected \"avx512\", \"avx2\" or \"baseline\"") }),
    }
}

/// 0 = baseline, 3 = AVX2+FMA, 4 = AVX-512: what the CPU has, capped by [`SIMD_ENV`].
pub(crate) fn simd_level() -> u8 {
    static LEVEL: AtomicU8 = AtomicU8::new(u8::MAX);
    let l = LEVEL.load(Ordering::Relaxed);
    if l != u8::MAX {
        return l;
    }
    #[cfg(target_arch = "x86_64")]
    let l = if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        4
    } else if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        3
    } else {
        0
    };
    #[cfg(not(target_arch = "x86_64"))]
    let l = 0;
    let cap = std::env::var(SIMD_ENV).ok().and_then(|v| SIMD_NAMES.iter().find(|(name, _)| *name == v).map(|&(_, level)| level));
    let l = l.min(cap.unwrap_or(4));
    LEVEL.store(l, Ordering::Relaxed);
    l
}

/// The SIMD level the project's kernels run at: "avx512", "avx2" or "baseline".
pub fn simd_name() -> &'static str {
    match simd_level() {
        4 => "avx512",
        3 => "avx2",
        _ => "baseline",
    }
}

/// Defines a kernel from an `#[inline(always)]` body, compiled three times and
/// dispatched on the CPU's features.
macro_rules! multiversion {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),*) $(-> $ret:ty)? $body:block) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn body($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx2,fma")]
                unsafe fn v4($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }
                #[target_feature(enable = "avx2,fma")]
                unsafe fn v3($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }
                match simd_level() {
                    // SAFETY: the CPU supports the features these versions were compiled for.
                    4 => return unsafe { v4($($arg),*) },
                    3 => return unsafe { v3($($arg),*) },
                    _ => {}
                }
            }
            body($($arg),*)
        }
    };
}

const LANES: usize = 16;

/// `exp(x)` to ~2e-7 relative error, branch-free so that it vectorises.
#[inline(always)]
pub fn exp_fast(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const MAGIC: f32 = 12_582_912.0; // 1.5·2^23: adding it rounds to an integer
    const LN2_HI: f32 = 0.693_359_4; // ln 2 split so that n·LN2_HI is exact (Cody–Waite)
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * LOG2E + MAGIC;
    let n = shifted - MAGIC;
    // The integer n sits in the low mantissa bits of `shifted` (no float→int cast).
    let ni = shifted.to_bits() as i32 - MAGIC.to_bits() as i32;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    // e^r on |r| ≤ ln2/2: Taylor series to degree 7.
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (0.166_666_67
                    + r * (0.041_666_668 + r * (0.008_333_334 + r * (0.001_388_888_9 + r * 0.000_198_412_7))))));
    p * f32::from_bits(((ni + 127) << 23) as u32)
}

/// Elements per stack-buffered chunk of the two-step (map, then reduce) kernels.
const CHUNK: usize = 256;

#[inline(always)]
fn max_of(x: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; LANES];
    let tail = x.len() - x.len() % LANES;
    for i in (0..tail).step_by(LANES) {
        let c = &x[i..i + LANES];
        for l in 0..LANES {
            // A select (not f32::max) so that it maps onto vmaxps.
            acc[l] = if c[l] > acc[l] { c[l] } else { acc[l] };
        }
    }
    let mut m = f32::NEG_INFINITY;
    for &v in acc.iter().chain(&x[tail..]) {
        m = if v > m { v } else { m };
    }
    m
}

#[inline(always)]
fn sum_of(x: &[f32]) -> f32 {
    let mut acc = [0.0f32; LANES];
    let tail = x.len() - x.len() % LANES;
    for i in (0..tail).step_by(LANES) {
        let c = &x[i..i + LANES];
        for l in 0..LANES {
            acc[l] += c[l];
        }
    }
    acc.iter().sum::<f32>() + x[tail..].iter().sum::<f32>()
}

multiversion! {
    /// Softmax of every row of `data` (`rows × cols`, contiguous), in place.
    pub fn softmax_rows(data: &mut [f32], cols: usize) {
        if cols == 0 {
            return;
        }
        for row in data.chunks_exact_mut(cols) {
            let m = max_of(row);
            for v in row.iter_mut() {
                *v = exp_fast(*v - m);
            }
            let inv = 1.0 / sum_of(row);
            for v in row.iter_mut() {
                *v *= inv;
            }
        }
    }
}

multiversion! {
    /// Softmax down every column of `data` (`rows × cols`, row-major), in place: column
    /// `j` becomes the softmax of `data[r·cols + j]` over `r`. Vectorised across columns.
    pub fn softmax_columns(data: &mut [f32], rows: usize, cols: usize) {
        if rows == 0 || cols == 0 {
            return;
        }
        let mut j0 = 0;
        while j0 < cols {
            let n = LANES.min(cols - j0);
            let (mut m, mut s) = ([f32::NEG_INFINITY; LANES], [0.0f32; LANES]);
            if n == LANES {
                for r in 0..rows {
                    let x = &data[r * cols + j0..][..LANES];
                    for c in 0..LANES {
                        m[c] = m[c].max(x[c]);
                    }
                }
                for r in 0..rows {
                    let x = &mut data[r * cols + j0..][..LANES];
                    for c in 0..LANES {
                        x[c] = exp_fast(x[c] - m[c]);
                        s[c] += x[c];
                    }
                }
                for r in 0..rows {
                    let x = &mut data[r * cols + j0..][..LANES];
                    for c in 0..LANES {
                        x[c] /= s[c];
                    }
                }
            } else {
                for c in 0..n {
                    let col = |r: usize| r * cols + j0 + c;
                    let mc = (0..rows).map(|r| data[col(r)]).fold(f32::NEG_INFINITY, f32::max);
                    let mut sc = 0.0;
                    for r in 0..rows {
                        let e = exp_fast(data[col(r)] - mc);
                        data[col(r)] = e;
                        sc += e;
                    }
                    for r in 0..rows {
                        data[col(r)] /= sc;
                    }
                }
            }
            j0 += n;
        }
    }
}

multiversion! {
    /// `log Σ_j exp(a_j + b_j)`.
    pub fn logsumexp_plus(a: &[f32], b: &[f32]) -> f32 {
        let n = a.len().min(b.len());
        let (a, b) = (&a[..n], &b[..n]);
        let mut buf = [0.0f32; CHUNK];
        let mut m = f32::NEG_INFINITY;
        for (ca, cb) in a.chunks(CHUNK).zip(b.chunks(CHUNK)) {
            let t = &mut buf[..ca.len()];
            for ((t, x), y) in t.iter_mut().zip(ca).zip(cb) {
                *t = x + y;
            }
            let cm = max_of(t);
            m = if cm > m { cm } else { m };
        }
        if m == f32::NEG_INFINITY {
            return m;
        }
        let mut s = 0.0f32;
        for (ca, cb) in a.chunks(CHUNK).zip(b.chunks(CHUNK)) {
            let t = &mut buf[..ca.len()];
            for ((t, x), y) in t.iter_mut().zip(ca).zip(cb) {
                *t = exp_fast(x + y - m);
            }
            s += sum_of(t);
        }
        m + s.ln()
    }
}

multiversion! {
    /// `out_j = exp(s_j − m_j)`, and `sums_j += out_j`.
    pub fn exp_sub_accumulate(s: &[f32], m: &[f32], out: &mut [f32], sums: &mut [f32]) {
        let n = s.len().min(m.len()).min(out.len()).min(sums.len());
        for j in 0..n {
            let e = exp_fast(s[j] - m[j]);
            out[j] = e;
            sums[j] += e;
        }
    }
}

multiversion! {
    /// `Σ_j a_j · b_j`.
    pub fn dot(a: &[f32], b: &[f32]) -> f32 {
        let n = a.len().min(b.len());
        let tail = n - n % LANES;
        let mut acc = [0.0f32; LANES];
        for i in (0..tail).step_by(LANES) {
            let (ca, cb) = (&a[i..i + LANES], &b[i..i + LANES]);
            for l in 0..LANES {
                acc[l] += ca[l] * cb[l];
            }
        }
        acc.iter().sum::<f32>() + a[tail..n].iter().zip(&b[tail..n]).map(|(x, y)| x * y).sum::<f32>()
    }
}

multiversion! {
    /// `y += alpha · x`.
    pub fn axpy(alpha: f32, x: &[f32], y: &mut [f32]) {
        for (y, x) in y.iter_mut().zip(x) {
            *y += alpha * x;
        }
    }
}

/// f32 → bf16, round to nearest even (finite inputs), as `vcvtne2ps2bf16` does.
#[inline(always)]
pub(crate) fn to_bf16(x: f32) -> u16 {
    let b = x.to_bits();
    ((b + 0x7FFF + ((b >> 16) & 1)) >> 16) as u16
}

multiversion! {
    /// `k_j = exp(z_j + f + g_j)` for one row, stored as bf16.
    pub fn exp_row_bf16(z: &[f32], f: f32, g: &[f32], k: &mut [u16]) {
        for ((k, z), g) in k.iter_mut().zip(z).zip(g) {
            *k = to_bf16(exp_fast(z + f + g));
        }
    }
}

multiversion! {
    /// `k_j = exp(z_j + f + g_j)` for one row.
    pub fn exp_row(z: &[f32], f: f32, g: &[f32], k: &mut [f32]) {
        for ((k, z), g) in k.iter_mut().zip(z).zip(g) {
            *k = exp_fast(z + f + g);
        }
    }
}

/// `erf(x)` to 1.5e-7 absolute (Abramowitz & Stegun 7.1.26), vectorisable.
#[inline(always)]
fn erf_fast(x: f32) -> f32 {
    let a = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * a);
    let y = 1.0
        - t * (0.254_829_6 + t * (-0.284_496_74 + t * (1.421_413_7 + t * (-1.453_152_1 + t * 1.061_405_4))))
            * exp_fast(-a * a);
    y.copysign(x)
}

multiversion! {
    /// Exact (erf) GELU in place.
    pub fn gelu(x: &mut [f32]) {
        for v in x.iter_mut() {
            *v = 0.5 * *v * (1.0 + erf_fast(*v * std::f32::consts::FRAC_1_SQRT_2));
        }
    }
}

multiversion! {
    /// ReLU in place.
    pub fn relu(x: &mut [f32]) {
        for v in x.iter_mut() {
            *v = v.max(0.0);
        }
    }
}

multiversion! {
    /// LayerNorm of every row (`cols` wide) in place, with affine `weight`, `bias`.
    pub fn layer_norm(x: &mut [f32], cols: usize, weight: &[f32], bias: &[f32], eps: f32) {
        if cols == 0 {
            return;
        }
        for row in x.chunks_exact_mut(cols) {
            let mean = row.iter().sum::<f32>() / cols as f32;
            let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / cols as f32;
            let inv = 1.0 / (var + eps).sqrt();
            for ((v, w), b) in row.iter_mut().zip(weight).zip(bias) {
                *v = (*v - mean) * inv * w + b;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_fast_is_accurate() {
        let mut worst = 0.0f32;
        let mut x = -80.0f32;
        while x < 80.0 {
            let rel = ((exp_fast(x) as f64 - (x as f64).exp()) / (x as f64).exp()).abs() as f32;
            worst = worst.max(rel);
            x += 0.0137;
        }
        assert!(worst < 5e-7, "max relative error {worst}");
        assert!(exp_fast(-1e4) >= 0.0 && exp_fast(-1e4) < 1e-37);
    }

    #[test]
    fn softmax_and_logsumexp_match_the_definition() {
        let cols = 37;
        let mut data: Vec<f32> = (0..3 * cols).map(|i| ((i * 31 % 17) as f32 - 8.0) * 1.7).collect();
        let orig = data.clone();
        softmax_rows(&mut data, cols);
        for r in 0..3 {
            let row = &orig[r * cols..(r + 1) * cols];
            let m = row.iter().cloned().fold(f32::NEG_INFINITY, f32::max) as f64;
            let z: f64 = row.iter().map(|&v| (v as f64 - m).exp()).sum();
            for c in 0..cols {
                let want = ((row[c] as f64 - m).exp() / z) as f32;
                assert!((data[r * cols + c] - want).abs() < 1e-6);
            }
            let b: Vec<f32> = (0..cols).map(|j| j as f32 * 0.1).collect();
            let lse = logsumexp_plus(row, &b) as f64;
            let want = row.iter().zip(&b).map(|(&a, &b)| ((a + b) as f64).exp()).sum::<f64>().ln();
            assert!((lse - want).abs() < 1e-5, "{lse} vs {want}");
        }
    }

    #[test]
    fn softmax_columns_matches_the_definition() {
        // 37 columns: two full vectors and a tail.
        let (rows, cols) = (65, 37);
        let mut x: Vec<f32> = (0..rows * cols).map(|i| ((i * 7919) % 1000) as f32 / 50.0 - 10.0).collect();
        let want: Vec<f32> = (0..rows * cols)
            .map(|i| {
                let (r, c) = (i / cols, i % cols);
                let m = (0..rows).map(|q| x[q * cols + c] as f64).fold(f64::NEG_INFINITY, f64::max);
                let z: f64 = (0..rows).map(|q| (x[q * cols + c] as f64 - m).exp()).sum();
                ((x[r * cols + c] as f64 - m).exp() / z) as f32
            })
            .collect();
        softmax_columns(&mut x, rows, cols);
        let worst = x.iter().zip(&want).map(|(a, b)| ((a - b) / b.max(1e-30)).abs()).fold(0.0f32, f32::max);
        assert!(worst < 1e-5, "relative error {worst}");
    }

    #[test]
    fn gelu_matches_erf_form() {
        let mut x: Vec<f32> = (-60..60).map(|i| i as f32 * 0.1).collect();
        let orig = x.clone();
        gelu(&mut x);
        for (g, v) in x.iter().zip(orig) {
            // Reference erf by its Taylor/continued form is not in std; use a tight series.
            let z = v as f64 / std::f64::consts::SQRT_2;
            let erf = erf_series(z);
            let want = 0.5 * v as f64 * (1.0 + erf);
            assert!((*g as f64 - want).abs() < 1e-6, "gelu({v}) = {g}, want {want}");
        }
    }

    fn erf_series(z: f64) -> f64 {
        // erf(z) = 2/√π Σ (−1)^n z^(2n+1) / (n! (2n+1)), enough terms for |z| ≤ 4.3.
        let mut sum = 0.0;
        let mut term = z;
        for n in 0..200 {
            sum += term / (2 * n + 1) as f64;
            term *= -z * z / (n + 1) as f64;
        }
        2.0 / std::f64::consts::PI.sqrt() * sum
    }

    #[test]
    fn gemm_with_strides_and_transposes() {
        let ctx = Ctx::default();
        let a = Matrix::from_vec(2, 3, vec![1., 2., 3., 4., 5., 6.]).unwrap_or_else(|_| Matrix::zeros(0, 0));
        let bt = Matrix::from_vec(2, 3, vec![1., 0., 1., 0., 1., 0.]).unwrap_or_else(|_| Matrix::zeros(0, 0));
        let mut dst = vec![10.0f32; 4];
        ctx.gemm(&mut dst, 2, a.view(), false, bt.view(), true, 1.0, true, false).expect("shapes agree");
        assert_eq!(dst, vec![14., 12., 20., 15.]);
        assert_eq!(ctx.macs(), 12);
        assert!(ctx.gemm(&mut dst, 2, a.view(), false, a.view(), false, 1.0, false, false).is_err());
        // aᵀ·a: [3×2]·[2×3]
        let mut d2 = vec![0.0f32; 9];
        ctx.gemm(&mut d2, 3, a.view(), true, a.view(), false, 1.0, false, false).expect("shapes agree");
        assert_eq!(d2, vec![17., 22., 27., 22., 29., 36., 27., 36., 45.]);
    }
}
