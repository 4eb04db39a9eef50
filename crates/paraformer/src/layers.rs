//! Attention layers: ParaFormer's parallel layer (SPEC §5, paper §"Parallel Attention")
//! and SuperGlue's serial attentional propagation (SPEC §6).

use candle_core::Result as CResult;
use candle_nn::VarBuilder;

use crate::attention::{attention, cross_attention_shared, Attention, Projections};
use crate::config::{LayerKind, ParallelSwitches};
use crate::error::Result;
use crate::kernels::{gelu, layer_norm, Ctx, Matrix, Precision, View};
use crate::mlp::{add_assign, read, with_room, Linear, Mlp};

/// The parallel layer's projections, prefix `attn`. With sharing on, `proj` and
/// `merge` serve both branches; with it off, `self_*` and `cross_*` are separate.
#[derive(Debug, Clone)]
pub struct ParallelAttention {
    self_proj: Projections,
    cross_proj: Option<Projections>,
    self_merge: Linear,
    cross_merge: Linear,
    share_attention_weights: bool,
    heads: usize,
}

impl ParallelAttention {
    pub fn new(c: usize, heads: usize, sw: ParallelSwitches, vb: VarBuilder) -> CResult<Self> {
        let (self_proj, cross_proj) = if sw.share_qkv {
            (Projections::new(c, vb.pp("proj"))?, None)
        } else {
            (Projections::new(c, vb.pp("self_proj"))?, Some(Projections::new(c, vb.pp("cross_proj"))?))
        };
        let (self_merge, cross_merge) = if sw.share_merge {
            let m = Linear::new(c, c, vb.pp("merge"))?.with_bf16();
            (m.clone(), m)
        } else {
            (Linear::new(c, c, vb.pp("self_merge"))?.with_bf16(), Linear::new(c, c, vb.pp("cross_merge"))?.with_bf16())
        };
        Ok(Self { self_proj, cross_proj, self_merge, cross_merge, share_attention_weights: sw.share_attention_weights, heads })
    }
}

/// Linear(3C→2C) `fuse.0` → LayerNorm `fuse.1` → GELU(erf) → Linear(2C→C) `fuse.3`.
#[derive(Debug, Clone)]
pub struct Fuse {
    l0: Linear,
    norm_weight: Vec<f32>,
    norm_bias: Vec<f32>,
    l3: Linear,
}

impl Fuse {
    pub fn new(c: usize, vb: VarBuilder) -> CResult<Self> {
        let n = vb.pp(1);
        Ok(Self {
            l0: Linear::new(3 * c, 2 * c, vb.pp(0))?.with_bf16(),
            norm_weight: read(&n, &[2 * c], "weight")?,
            norm_bias: read(&n, &[2 * c], "bias")?,
            l3: Linear::new(2 * c, c, vb.pp(3))?.with_bf16(),
        })
    }

    pub fn forward(&self, ctx: &Ctx, x: View) -> Result<Matrix> {
        let mut h = self.l0.forward(ctx, x)?;
        layer_norm(&mut h.data, h.cols, &self.norm_weight, &self.norm_bias, 1e-5);
        gelu(&mut h.data);
        self.l3.forward(ctx, h.view())
    }
}

/// Output of one parallel layer: both updated feature sets and, when asked for, the
/// self-attention column sums `Σ_h Σ_i A[h, i, j]` of each image (attentional pooling).
pub struct ParallelOutput {
    pub x: Matrix,
    pub y: Matrix,
    pub col_sums: Option<(Vec<f32>, Vec<f32>)>,
}

/// One parallel attention layer, prefix `layers.{l}` or `stages.{s}.layers.{j}`.
#[derive(Debug, Clone)]
pub struct ParallelLayer {
    attn: ParallelAttention,
    fuse: Fuse,
}

impl ParallelLayer {
    pub fn new(c: usize, heads: usize, sw: ParallelSwitches, vb: VarBuilder) -> CResult<Self> {
        Ok(Self { attn: ParallelAttention::new(c, heads, sw, vb.pp("attn"))?, fuse: Fuse::new(c, vb.pp("fuse"))? })
    }

    /// Self- and cross-attention of both images at once; `x` `[M, C]`, `y` `[N, C]`.
    pub fn forward(&self, ctx: &Ctx, x: &Matrix, y: &Matrix, want_col_sums: bool) -> Result<ParallelOutput> {
        if want_col_sums && ctx.precision == Precision::Bf16 {
            // Its column sums choose the keypoints ParaFormer-U's pooling keeps, a discrete
            // choice that bf16 rounding would flip: this layer runs in fp32.
            let fp32 = Ctx::with_precision(Precision::Fp32);
            let out = self.forward_in(&fp32, x, y, true);
            ctx.add_macs(fp32.macs());
            return out;
        }
        self.forward_in(ctx, x, y, want_col_sums)
    }

    fn forward_in(&self, ctx: &Ctx, x: &Matrix, y: &Matrix, want_col_sums: bool) -> Result<ParallelOutput> {
        let a = &self.attn;
        let (h, c) = (a.heads, x.cols);
        let (px, py) = (a.self_proj.qkv(ctx, x.view())?, a.self_proj.qkv(ctx, y.view())?);
        fn qkv_of(p: &Matrix, c: usize, i: usize) -> View<'_> {
            p.view().cols(i * c, (i + 1) * c)
        }
        let qkv = |p, i| qkv_of(p, c, i);
        let (self_x, cs_x) = attention(ctx, qkv(&px, 0), qkv(&px, 1), qkv(&px, 2), h, want_col_sums)?;
        let (self_y, cs_y) = attention(ctx, qkv(&py, 0), qkv(&py, 1), qkv(&py, 2), h, want_col_sums)?;
        let (cross_x, cross_y) = match &a.cross_proj {
            // Shared q/k/v: the cross branch reuses the self projections.
            None => {
                if a.share_attention_weights {
                    cross_attention_shared(ctx, qkv(&px, 0), qkv(&py, 1), qkv(&px, 2), qkv(&py, 2), h)?
                } else {
                    let (cx, _) = attention(ctx, qkv(&px, 0), qkv(&py, 1), qkv(&py, 2), h, false)?;
                    let (cy, _) = attention(ctx, qkv(&py, 0), qkv(&px, 1), qkv(&px, 2), h, false)?;
                    (cx, cy)
                }
            }
            // Separate cross projections: only those the branch needs (SPEC §10).
            Some(cp) => {
                let (qx, ky) = (cp.part(ctx, x.view(), 0, 0)?, cp.part(ctx, y.view(), 1, 1)?);
                let (vx, vy) = (cp.part(ctx, x.view(), 2, 2)?, cp.part(ctx, y.view(), 2, 2)?);
                if a.share_attention_weights {
                    cross_attention_shared(ctx, qx.view(), ky.view(), vx.view(), vy.view(), h)?
                } else {
                    let (qy, kx) = (cp.part(ctx, y.view(), 0, 0)?, cp.part(ctx, x.view(), 1, 1)?);
                    let (cx, _) = attention(ctx, qx.view(), ky.view(), vy.view(), h, false)?;
                    let (cy, _) = attention(ctx, qy.view(), kx.view(), vx.view(), h, false)?;
                    (cx, cy)
                }
            }
        };
        let x2 = self.update(ctx, x, &self_x, &cross_x)?;
        let y2 = self.update(ctx, y, &self_y, &cross_y)?;
        let col_sums = match (cs_x, cs_y) {
            (Some(a), Some(b)) => Some((a, b)),
            _ => None,
        };
        Ok(ParallelOutput { x: x2, y: y2, col_sums })
    }

    /// `f + fuse([f, merge(self), merge(cross)])`; the merges write straight into the concat.
    fn update(&self, ctx: &Ctx, f: &Matrix, self_msg: &Matrix, cross_msg: &Matrix) -> Result<Matrix> {
        let c = f.cols;
        let mut cat = with_room(f, 2 * c);
        self.attn.self_merge.forward_into(ctx, self_msg.view(), &mut cat.data[c..], 3 * c)?;
        self.attn.cross_merge.forward_into(ctx, cross_msg.view(), &mut cat.data[2 * c..], 3 * c)?;
        let mut out = self.fuse.forward(ctx, cat.view())?;
        add_assign(&mut out, f);
        Ok(out)
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
    pub fn new(c: usize, heads: usize, kind: LayerKind, vb: VarBuilder) -> CResult<Self> {
        Ok(Self { attn: Attention::new(c, heads, vb.pp("attn"))?, mlp: Mlp::new(&[2 * c, 2 * c, c], vb.pp("mlp"))?.with_bf16(), kind })
    }

    fn update(&self, ctx: &Ctx, f: &Matrix, src: &Matrix) -> Result<Matrix> {
        let c = f.cols;
        let mut cat = with_room(f, c);
        self.attn.forward_into(ctx, f.view(), src.view(), &mut cat.data[c..], 2 * c)?;
        let mut out = self.mlp.forward(ctx, cat.view())?;
        add_assign(&mut out, f);
        Ok(out)
    }

    pub fn forward(&self, ctx: &Ctx, x: &Matrix, y: &Matrix) -> Result<(Matrix, Matrix)> {
        let (src_x, src_y) = match self.kind {
            LayerKind::SelfAttention => (x, y),
            LayerKind::Cross => (y, x),
        };
        Ok((self.update(ctx, x, src_x)?, self.update(ctx, y, src_y)?))
    }
}
