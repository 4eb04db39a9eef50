//! Linear layers and the one MLP helper (SPEC §2): Linear layers with eval-mode
//! BatchNorm and ReLU in between, named by `nn.Sequential` indices (`.0`, `.1`, `.3`, …).
//! Weights are stored transposed (`[in, out]`) for the GEMM, and each BatchNorm is
//! folded into the Linear before it at load time.

use candle_core::Result as CResult;
use candle_nn::VarBuilder;

use crate::error::Result;
use crate::kernels::{relu, Ctx, Matrix, Precision, View};

/// Reads a tensor of the given shape as a flat `Vec<f32>`.
pub(crate) fn read(vb: &VarBuilder, shape: &[usize], name: &str) -> CResult<Vec<f32>> {
    vb.get(shape, name)?.flatten_all()?.to_vec1()
}

/// `y = x·Wᵀ + b`, PyTorch layout in the file (`weight` `[out, in]`, `bias` `[out]`).
#[derive(Debug, Clone)]
pub struct Linear {
    /// `Wᵀ`, `[in, out]` row-major.
    wt: Vec<f32>,
    bias: Vec<f32>,
    pub in_dim: usize,
    pub out_dim: usize,
    /// Runs in bf16 under `Precision::Bf16` (the attention layers' Linears; encoders and
    /// the final projection stay fp32).
    bf16: bool,
    /// `Wᵀ` packed for the bf16 product, made on first use.
    packed: std::sync::OnceLock<Vec<u16>>,
}

impl Linear {
    pub fn new(in_dim: usize, out_dim: usize, vb: VarBuilder) -> CResult<Self> {
        let w = read(&vb, &[out_dim, in_dim], "weight")?;
        Ok(Self::from_weight(&w, read(&vb, &[out_dim], "bias")?, in_dim, out_dim))
    }

    /// From a weight already read (`[out, in]`, PyTorch layout) and its bias.
    pub(crate) fn from_weight(w: &[f32], bias: Vec<f32>, in_dim: usize, out_dim: usize) -> Self {
        let mut wt = vec![0.0; in_dim * out_dim];
        for o in 0..out_dim {
            for i in 0..in_dim {
                wt[i * out_dim + o] = w[o * in_dim + i];
            }
        }
        Self { wt, bias, in_dim, out_dim, bf16: false, packed: Default::default() }
    }

    /// This layer, allowed to run in bf16 when the context asks for it.
    pub fn with_bf16(mut self) -> Self {
        self.bf16 = true;
        self
    }

    /// Several Linear layers on the same input, as one with their outputs side by side.
    pub fn concat(parts: &[&Linear]) -> Linear {
        let in_dim = parts.first().map_or(0, |p| p.in_dim);
        let out_dim = parts.iter().map(|p| p.out_dim).sum();
        let mut wt = Vec::with_capacity(in_dim * out_dim);
        for i in 0..in_dim {
            for p in parts {
                wt.extend_from_slice(&p.wt[i * p.out_dim..(i + 1) * p.out_dim]);
            }
        }
        let bias = parts.iter().flat_map(|p| p.bias.iter().copied()).collect();
        let bf16 = parts.iter().all(|p| p.bf16);
        Linear { wt, bias, in_dim, out_dim, bf16, packed: Default::default() }
    }

    /// This layer on the input columns `keep` only (in order): the others' weights are
    /// dropped, for inputs that are known to meet zero weights.
    pub fn keep_inputs(&self, keep: &[std::ops::Range<usize>]) -> Linear {
        let mut wt = Vec::new();
        for r in keep {
            wt.extend_from_slice(&self.wt[r.start * self.out_dim..r.end * self.out_dim]);
        }
        let in_dim = keep.iter().map(|r| r.len()).sum();
        Linear { wt, bias: self.bias.clone(), in_dim, out_dim: self.out_dim, bf16: self.bf16, packed: Default::default() }
    }

    /// Folds a following per-channel affine map `y·scale + shift` into the layer.
    fn fold_affine(&mut self, scale: &[f32], shift: &[f32]) {
        for row in self.wt.chunks_exact_mut(self.out_dim) {
            for (w, s) in row.iter_mut().zip(scale) {
                *w *= s;
            }
        }
        for ((b, s), t) in self.bias.iter_mut().zip(scale).zip(shift) {
            *b = *b * s + t;
        }
    }

    /// Output columns `c0..c1` only, written into `dst` (row stride `dst_stride`).
    pub fn forward_cols_into(&self, ctx: &Ctx, x: View, c0: usize, c1: usize, dst: &mut [f32], dst_stride: usize) -> Result<()> {
        let n = c1 - c0;
        for r in 0..x.rows {
            dst[r * dst_stride..r * dst_stride + n].copy_from_slice(&self.bias[c0..c1]);
        }
        self.accumulate(ctx, x, c0, c1, dst, dst_stride)
    }

    /// `dst += x·Wᵀ` for output columns `c0..c1`.
    fn accumulate(&self, ctx: &Ctx, x: View, c0: usize, c1: usize, dst: &mut [f32], dst_stride: usize) -> Result<()> {
        #[cfg(target_arch = "x86_64")]
        if self.bf16 && ctx.precision == Precision::Bf16 && c0.is_multiple_of(16) && crate::gemm_bf16::available() {
            ctx.add_macs((x.rows * (c1 - c0) * self.in_dim) as u64);
            let wp = self.packed.get_or_init(|| crate::gemm_bf16::pack_weights(&self.wt, self.in_dim, self.out_dim));
            return crate::gemm_bf16::gemm_acc(dst, dst_stride, x, wp, self.in_dim, self.out_dim, c0, c1);
        }
        let w = View { data: &self.wt, rows: self.in_dim, cols: self.out_dim, stride: self.out_dim }.cols(c0, c1);
        ctx.gemm(dst, dst_stride, x, false, w, false, 1.0, true, true)
    }

    /// `x·Wᵀ + b` into `dst` with row stride `dst_stride`.
    pub fn forward_into(&self, ctx: &Ctx, x: View, dst: &mut [f32], dst_stride: usize) -> Result<()> {
        self.forward_cols_into(ctx, x, 0, self.out_dim, dst, dst_stride)
    }

    /// Output columns `c0..c1` as a new matrix.
    pub fn forward_cols(&self, ctx: &Ctx, x: View, c0: usize, c1: usize) -> Result<Matrix> {
        let n = c1 - c0;
        // Start from the bias rows (one write, no zero-fill), then accumulate x·W.
        let mut data = Vec::with_capacity(x.rows * n);
        for _ in 0..x.rows {
            data.extend_from_slice(&self.bias[c0..c1]);
        }
        self.accumulate(ctx, x, c0, c1, &mut data, n)?;
        Matrix::from_vec(x.rows, n, data)
    }

    pub fn forward(&self, ctx: &Ctx, x: View) -> Result<Matrix> {
        self.forward_cols(ctx, x, 0, self.out_dim)
    }
}

/// `MLP([c0, …, cL])` on rows `[K, c0] → [K, cL]`; BatchNorm folded into the Linear layers.
#[derive(Debug, Clone)]
pub struct Mlp {
    linears: Vec<Linear>,
}

impl Mlp {
    pub const BN_EPS: f32 = 1e-5;

    /// This MLP with every Linear allowed to run in bf16 (see [`Linear::with_bf16`]).
    pub fn with_bf16(mut self) -> Self {
        self.linears = self.linears.into_iter().map(Linear::with_bf16).collect();
        self
    }

    pub fn new(channels: &[usize], vb: VarBuilder) -> CResult<Self> {
        let n = channels.len().saturating_sub(1);
        let mut linears = Vec::with_capacity(n);
        for i in 0..n {
            let mut lin = Linear::new(channels[i], channels[i + 1], vb.pp(3 * i))?;
            if i + 1 < n {
                // Eval-mode BatchNorm: (y − mean)/sqrt(var + eps)·w + b = y·scale + shift.
                let c = channels[i + 1];
                let bn = vb.pp(3 * i + 1);
                let (w, b) = (read(&bn, &[c], "weight")?, read(&bn, &[c], "bias")?);
                let (mean, var) = (read(&bn, &[c], "running_mean")?, read(&bn, &[c], "running_var")?);
                let scale: Vec<f32> = w.iter().zip(&var).map(|(w, v)| w / (v + Self::BN_EPS).sqrt()).collect();
                let shift: Vec<f32> = b.iter().zip(&mean).zip(&scale).map(|((b, m), s)| b - m * s).collect();
                lin.fold_affine(&scale, &shift);
            }
            linears.push(lin);
        }
        Ok(Self { linears })
    }

    pub fn forward(&self, ctx: &Ctx, x: View) -> Result<Matrix> {
        let mut h: Option<Matrix> = None;
        for (i, lin) in self.linears.iter().enumerate() {
            let mut out = lin.forward(ctx, h.as_ref().map_or(x, Matrix::view))?;
            if i + 1 < self.linears.len() {
                relu(&mut out.data);
            }
            h = Some(out);
        }
        Ok(h.unwrap_or_else(|| x.to_matrix()))
    }
}

/// `f` `[K, C]` copied into the first `C` columns of a zeroed `[K, C + extra]` matrix,
/// the concat buffer that message projections then write into.
pub(crate) fn with_room(f: &Matrix, extra: usize) -> Matrix {
    let c = f.cols;
    let mut cat = Matrix::zeros(f.rows, c + extra);
    for (dst, src) in cat.data.chunks_exact_mut(c + extra).zip(f.data.chunks_exact(c)) {
        dst[..c].copy_from_slice(src);
    }
    cat
}

/// `a += b` element-wise (residual connections).
pub(crate) fn add_assign(a: &mut Matrix, b: &Matrix) {
    for (x, y) in a.data.iter_mut().zip(&b.data) {
        *x += y;
    }
}
