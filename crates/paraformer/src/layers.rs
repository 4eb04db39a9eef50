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
///
/// A message whose columns of `fuse.0` are all zero adds exactly nothing to the update:
/// its branch is closed, `l0` keeps only the open inputs, and the layer does not compute
/// that attention (weights with LightGlue's serial layout, one attention per layer).
#[derive(Debug, Clone)]
pub struct Fuse {
    l0: Linear,
    /// Whether the self and the cross message reach the update.
    open: [bool; 2],
    norm_weight: Vec<f32>,
    norm_bias: Vec<f32>,
    l3: Linear,
}

impl Fuse {
    pub fn new(c: usize, vb: VarBuilder) -> CResult<Self> {
        Self::build(c, vb, true)
    }

    /// `detect_closed: false` computes every branch (the tests' reference).
    fn build(c: usize, vb: VarBuilder, detect_closed: bool) -> CResult<Self> {
        let n = vb.pp(1);
        let v0 = vb.pp(0);
        let w = read(&v0, &[2 * c, 3 * c], "weight")?;
        let open = [1, 2].map(|b| {
            !detect_closed || w.chunks_exact(3 * c).any(|row| row[b * c..(b + 1) * c].iter().any(|&v| v != 0.0))
        });
        let full = Linear::from_weight(&w, read(&v0, &[2 * c], "bias")?, 3 * c, 2 * c);
        let keep: Vec<_> = std::iter::once(0..c)
            .chain((0..2).filter(|&b| open[b]).map(|b| (b + 1) * c..(b + 2) * c))
            .collect();
        let l0 = if open == [true, true] { full } else { full.keep_inputs(&keep) };
        Ok(Self {
            l0: l0.with_bf16(),
            open,
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
        Self::build(c, heads, sw, vb, true)
    }

    fn build(c: usize, heads: usize, sw: ParallelSwitches, vb: VarBuilder, detect_closed: bool) -> CResult<Self> {
        Ok(Self {
            attn: ParallelAttention::new(c, heads, sw, vb.pp("attn"))?,
            fuse: Fuse::build(c, vb.pp("fuse"), detect_closed)?,
        })
    }

    /// Whether the (self, cross) messages reach the update (see [`Fuse`]).
    pub fn open_branches(&self) -> [bool; 2] {
        self.fuse.open
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
        let [self_open, cross_open] = self.fuse.open;
        // Pooling reads the self-attention even where its message is closed.
        let need_self = self_open || want_col_sums;
        let need_px = need_self || a.cross_proj.is_none();
        let (px, py) = if need_px {
            (a.self_proj.qkv(ctx, x.view())?, a.self_proj.qkv(ctx, y.view())?)
        } else {
            (Matrix::zeros(0, 0), Matrix::zeros(0, 0))
        };
        fn qkv_of(p: &Matrix, c: usize, i: usize) -> View<'_> {
            p.view().cols(i * c, (i + 1) * c)
        }
        let qkv = |p, i| qkv_of(p, c, i);
        let ((self_x, cs_x), (self_y, cs_y)) = if need_self {
            (
                attention(ctx, qkv(&px, 0), qkv(&px, 1), qkv(&px, 2), h, want_col_sums)?,
                attention(ctx, qkv(&py, 0), qkv(&py, 1), qkv(&py, 2), h, want_col_sums)?,
            )
        } else {
            ((Matrix::zeros(0, 0), None), (Matrix::zeros(0, 0), None))
        };
        let (cross_x, cross_y) = match &a.cross_proj {
            _ if !cross_open => (Matrix::zeros(0, 0), Matrix::zeros(0, 0)),
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

    /// `f + fuse([f, merge(self), merge(cross)])`; the merges write straight into the concat,
    /// which holds the open messages only.
    fn update(&self, ctx: &Ctx, f: &Matrix, self_msg: &Matrix, cross_msg: &Matrix) -> Result<Matrix> {
        let c = f.cols;
        let open = self.fuse.open;
        let width = c * (1 + open.iter().filter(|&&o| o).count());
        let mut cat = with_room(f, width - c);
        let mut at = c;
        for (is_open, merge, msg) in [(open[0], &self.attn.self_merge, self_msg), (open[1], &self.attn.cross_merge, cross_msg)] {
            if is_open {
                merge.forward_into(ctx, msg.view(), &mut cat.data[at..], width)?;
                at += c;
            }
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Shape, Tensor};

    /// Random weights (`random_var_builder`) with the columns `block` (1 = self message,
    /// 2 = cross message) of every `fuse.0.weight` set to zero.
    struct ClosedBackend {
        seed: u64,
        blocks: Vec<usize>,
    }

    impl candle_nn::var_builder::SimpleBackend for ClosedBackend {
        fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, _d: DType, _dev: &Device) -> CResult<Tensor> {
            let t = crate::weights::random_var_builder(self.seed).get(s.clone(), name)?;
            if !name.ends_with("fuse.0.weight") {
                return Ok(t);
            }
            let (rows, cols) = s.dims2()?;
            let c = cols / 3;
            let mut v: Vec<f32> = t.flatten_all()?.to_vec1()?;
            for row in v.chunks_exact_mut(cols) {
                for &b in &self.blocks {
                    row[b * c..(b + 1) * c].iter_mut().for_each(|w| *w = 0.0);
                }
            }
            Tensor::from_vec(v, (rows, cols), &Device::Cpu)
        }

        fn get_unchecked(&self, name: &str, _d: DType, _dev: &Device) -> CResult<Tensor> {
            Err(candle_core::Error::Msg(format!("need a shape for `{name}`")))
        }

        fn contains_tensor(&self, _name: &str) -> bool {
            true
        }
    }

    fn features(rows: usize, c: usize, seed: u32) -> Matrix {
        let v = (0..rows * c).map(|i| (((i as u32).wrapping_mul(2654435761).wrapping_add(seed) >> 8) as f32 / 16777216.0) - 0.5);
        Matrix::from_vec(rows, c, v.collect()).unwrap_or_else(|_| Matrix::zeros(0, 0))
    }

    /// A layer whose self or cross message meets only zero fuse columns skips that branch
    /// and still computes what the whole layer computes (SPEC §5), with every sharing
    /// switch and with pooling's column sums.
    #[test]
    fn closed_branches_are_skipped_and_change_nothing() {
        let (c, heads) = (16, 2);
        let (x, y) = (features(23, c, 1), features(17, c, 2));
        let switches = [
            ParallelSwitches::default(),
            ParallelSwitches { share_qkv: false, share_merge: false, ..Default::default() },
            ParallelSwitches { share_qkv: false, share_merge: false, share_attention_weights: false },
        ];
        for sw in switches {
            for blocks in [vec![1], vec![2], vec![1, 2]] {
                for want_col_sums in [false, true] {
                    let vb = || VarBuilder::from_backend(Box::new(ClosedBackend { seed: 5, blocks: blocks.clone() }), DType::F32, Device::Cpu);
                    let skip = ParallelLayer::build(c, heads, sw, vb().pp("layers.0"), true).expect("layer");
                    let full = ParallelLayer::build(c, heads, sw, vb().pp("layers.0"), false).expect("layer");
                    assert_eq!(skip.open_branches(), [!blocks.contains(&1), !blocks.contains(&2)]);
                    assert_eq!(full.open_branches(), [true, true]);
                    let ctx = Ctx::with_precision(Precision::Fp32);
                    let a = skip.forward(&ctx, &x, &y, want_col_sums).expect("skip");
                    let b = full.forward(&ctx, &x, &y, want_col_sums).expect("full");
                    let label = format!("{sw:?} closed {blocks:?} col sums {want_col_sums}");
                    for (p, q, input) in [(&a.x, &b.x, &x), (&a.y, &b.y, &y)] {
                        let diff = p.data.iter().zip(&q.data).map(|(u, v)| (u - v).abs()).fold(0.0, f32::max);
                        assert!(diff < 1e-5, "{label}: {diff}");
                        assert!(p.data.iter().zip(&input.data).any(|(u, v)| (u - v).abs() > 1e-3), "{label}: no update");
                    }
                    assert_eq!(a.col_sums.is_some(), want_col_sums, "{label}");
                    if let (Some(s), Some(t)) = (a.col_sums, b.col_sums) {
                        assert_eq!(s, t, "{label}");
                    }
                    // The work skipped: one attention fewer per closed branch.
                    if !want_col_sums {
                        let (cs, cf) = (Ctx::with_precision(Precision::Fp32), Ctx::with_precision(Precision::Fp32));
                        skip.forward(&cs, &x, &y, false).expect("skip");
                        full.forward(&cf, &x, &y, false).expect("full");
                        assert!(cs.macs() < cf.macs(), "{label}: {} >= {}", cs.macs(), cf.macs());
                    }
                }
            }
        }
    }
}
