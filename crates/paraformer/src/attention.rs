//! Multi-head attention pieces (SPEC §4): contiguous head layout (channel `c` in head
//! `c / (C/H)`), scaled dot-product scores, softmax over keys.

use candle_core::{Module, Result, Tensor};
use candle_nn::{Linear, VarBuilder};

/// `[K, C]` → `[H, K, C/H]` (contiguous).
pub fn split_heads(x: &Tensor, heads: usize) -> Result<Tensor> {
    let (k, c) = x.dims2()?;
    x.reshape((k, heads, c / heads))?.transpose(0, 1)?.contiguous()
}

/// `[H, K, C/H]` → `[K, C]`.
pub fn merge_heads(x: &Tensor) -> Result<Tensor> {
    let (h, k, d) = x.dims3()?;
    x.transpose(0, 1)?.contiguous()?.reshape((k, h * d))
}

/// Scaled scores `Q·Kᵀ / sqrt(C/H)` per head: `[H, M, d]`, `[H, N, d]` → `[H, M, N]`.
pub fn scores(q: &Tensor, k: &Tensor) -> Result<Tensor> {
    let d = q.dim(2)?;
    let scale = 1.0 / (d as f64).sqrt();
    (q.matmul(&k.t()?)? * scale)?.contiguous()
}

/// Softmax over the last axis (keys).
pub fn softmax(s: &Tensor) -> Result<Tensor> {
    candle_nn::ops::softmax_last_dim(s)
}

/// Probabilities `[H, M, N]` times values `[H, N, d]`, heads merged → `[M, C]`.
pub fn apply(probs: &Tensor, v: &Tensor) -> Result<Tensor> {
    merge_heads(&probs.matmul(v)?)
}

/// Full attention of queries on keys/values (head-split inputs); returns the
/// merged-head message `[M, C]` and the probabilities `[H, M, N]`.
pub fn attend(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<(Tensor, Tensor)> {
    let probs = softmax(&scores(q, k)?)?;
    Ok((apply(&probs, v)?, probs))
}

/// The q, k, v projections `proj.{0,1,2}` (or `self_proj`, `cross_proj`).
#[derive(Debug, Clone)]
pub struct Projections {
    proj: [Linear; 3],
    heads: usize,
}

impl Projections {
    pub fn new(c: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        let lin = |i: usize| candle_nn::linear(c, c, vb.pp(i));
        Ok(Self { proj: [lin(0)?, lin(1)?, lin(2)?], heads })
    }

    pub fn q(&self, x: &Tensor) -> Result<Tensor> {
        split_heads(&self.proj[0].forward(x)?, self.heads)
    }

    pub fn k(&self, x: &Tensor) -> Result<Tensor> {
        split_heads(&self.proj[1].forward(x)?, self.heads)
    }

    pub fn v(&self, x: &Tensor) -> Result<Tensor> {
        split_heads(&self.proj[2].forward(x)?, self.heads)
    }
}

/// SuperGlue's multi-headed attention, prefix `attn`: `proj.{0,1,2}` and `merge`.
#[derive(Debug, Clone)]
pub struct Attention {
    proj: Projections,
    merge: Linear,
}

impl Attention {
    pub fn new(c: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { proj: Projections::new(c, heads, vb.pp("proj"))?, merge: candle_nn::linear(c, c, vb.pp("merge"))? })
    }

    /// `merge(attn(q(x), k(src), v(src)))` → `[M, C]`.
    pub fn forward(&self, x: &Tensor, src: &Tensor) -> Result<Tensor> {
        let (msg, _) = attend(&self.proj.q(x)?, &self.proj.k(src)?, &self.proj.v(src)?)?;
        self.merge.forward(&msg)
    }
}
