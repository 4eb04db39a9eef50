//! Attention layers: ParaFormer's parallel layer (SPEC §5, paper §"Parallel Attention")
//! and SuperGlue's serial attentional propagation (SPEC §6).

use candle_core::{Module, Result, Tensor};
use candle_nn::{LayerNorm, Linear, VarBuilder};

use crate::attention::{apply, attend, scores, softmax, Attention, Projections};
use crate::config::{LayerKind, ParallelSwitches};
use crate::mlp::{cat_channels, Mlp};

/// The parallel layer's projections, prefix `attn`. With sharing on, `proj` and
/// `merge` serve both branches; with it off, `self_*` and `cross_*` are separate.
#[derive(Debug, Clone)]
pub struct ParallelAttention {
    self_proj: Projections,
    cross_proj: Projections,
    self_merge: Linear,
    cross_merge: Linear,
    share_attention_weights: bool,
}

impl ParallelAttention {
    pub fn new(c: usize, heads: usize, sw: ParallelSwitches, vb: VarBuilder) -> Result<Self> {
        let (self_proj, cross_proj) = if sw.share_qkv {
            let p = Projections::new(c, heads, vb.pp("proj"))?;
            (p.clone(), p)
        } else {
            (Projections::new(c, heads, vb.pp("self_proj"))?, Projections::new(c, heads, vb.pp("cross_proj"))?)
        };
        let (self_merge, cross_merge) = if sw.share_merge {
            let m = candle_nn::linear(c, c, vb.pp("merge"))?;
            (m.clone(), m)
        } else {
            (candle_nn::linear(c, c, vb.pp("self_merge"))?, candle_nn::linear(c, c, vb.pp("cross_merge"))?)
        };
        Ok(Self { self_proj, cross_proj, self_merge, cross_merge, share_attention_weights: sw.share_attention_weights })
    }
}

/// Linear(3C→2C) → LayerNorm → GELU(erf) → Linear(2C→C), prefix `fuse`.
#[derive(Debug, Clone)]
pub struct Fuse {
    l0: Linear,
    l1: LayerNorm,
    l3: Linear,
}

impl Fuse {
    pub fn new(c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            l0: candle_nn::linear(3 * c, 2 * c, vb.pp(0))?,
            l1: candle_nn::layer_norm(2 * c, 1e-5, vb.pp(1))?,
            l3: candle_nn::linear(2 * c, c, vb.pp(3))?,
        })
    }
}

impl Module for Fuse {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.l3.forward(&self.l1.forward(&self.l0.forward(x)?)?.gelu_erf()?)
    }
}

/// Output of one parallel layer: both updated feature sets and the self-attention
/// probabilities `[H, K, K]` of each image (used by attentional pooling).
pub struct ParallelOutput {
    pub x: Tensor,
    pub y: Tensor,
    pub self_probs_x: Tensor,
    pub self_probs_y: Tensor,
}

/// One parallel attention layer, prefix `layers.{l}` or `stages.{s}.layers.{j}`.
#[derive(Debug, Clone)]
pub struct ParallelLayer {
    attn: ParallelAttention,
    fuse: Fuse,
}

impl ParallelLayer {
    pub fn new(c: usize, heads: usize, sw: ParallelSwitches, vb: VarBuilder) -> Result<Self> {
        Ok(Self { attn: ParallelAttention::new(c, heads, sw, vb.pp("attn"))?, fuse: Fuse::new(c, vb.pp("fuse"))? })
    }

    /// Self- and cross-attention of both images at once; `x` `[M, C]`, `y` `[N, C]`.
    pub fn forward(&self, x: &Tensor, y: &Tensor) -> Result<ParallelOutput> {
        let a = &self.attn;
        let (self_x, self_probs_x) = attend(&a.self_proj.q(x)?, &a.self_proj.k(x)?, &a.self_proj.v(x)?)?;
        let (self_y, self_probs_y) = attend(&a.self_proj.q(y)?, &a.self_proj.k(y)?, &a.self_proj.v(y)?)?;
        let (qx, ky, vx, vy) = (a.cross_proj.q(x)?, a.cross_proj.k(y)?, a.cross_proj.v(x)?, a.cross_proj.v(y)?);
        let s = scores(&qx, &ky)?;
        let cross_x = apply(&softmax(&s)?, &vy)?;
        let cross_y = if a.share_attention_weights {
            apply(&softmax(&s.transpose(1, 2)?.contiguous()?)?, &vx)?
        } else {
            attend(&a.cross_proj.q(y)?, &a.cross_proj.k(x)?, &vx)?.0
        };
        let update = |f: &Tensor, s_msg: &Tensor, c_msg: &Tensor| -> Result<Tensor> {
            let m = cat_channels(&[f, &a.self_merge.forward(s_msg)?, &a.cross_merge.forward(c_msg)?])?;
            f + self.fuse.forward(&m)?
        };
        Ok(ParallelOutput {
            x: update(x, &self_x, &cross_x)?,
            y: update(y, &self_y, &cross_y)?,
            self_probs_x,
            self_probs_y,
        })
    }
}

/// One SuperGlue layer, prefix `gnn.layers.{l}`: `x' = x + mlp([x, merge(attn)])`.
#[derive(Debug, Clone)]
pub struct SerialLayer {
    attn: Attention,
    mlp: Mlp,
    kind: LayerKind,
}

impl SerialLayer {
    pub fn new(c: usize, heads: usize, kind: LayerKind, vb: VarBuilder) -> Result<Self> {
        Ok(Self { attn: Attention::new(c, heads, vb.pp("attn"))?, mlp: Mlp::new(&[2 * c, 2 * c, c], vb.pp("mlp"))?, kind })
    }

    pub fn forward(&self, x: &Tensor, y: &Tensor) -> Result<(Tensor, Tensor)> {
        let (src_x, src_y) = match self.kind {
            LayerKind::SelfAttention => (x, y),
            LayerKind::Cross => (y, x),
        };
        let dx = self.mlp.forward(&cat_channels(&[x, &self.attn.forward(x, src_x)?])?)?;
        let dy = self.mlp.forward(&cat_channels(&[y, &self.attn.forward(y, src_y)?])?)?;
        Ok(((x + dx)?, (y + dy)?))
    }
}
