//! Multi-head attention (SPEC §4): contiguous head layout (channel `c` in head
//! `c / (C/H)`), scaled dot-product scores, softmax over keys.
//!
//! Heads are strided column slices of the projected features (no per-head copies).
//! Queries are processed in row blocks, so the `[H, M, N]` score tensor never exists
//! at once; blocks and heads run in parallel.

use std::sync::Mutex;

use candle_core::Result as CResult;
use candle_nn::VarBuilder;
use rayon::prelude::*;

use crate::error::Result;
use crate::kernels::{exp_fast, exp_sub_accumulate, softmax_rows, sum_in_order, Ctx, Matrix, Precision, SharedMut, View};
use crate::mlp::Linear;

/// Query rows per block: a `BLOCK × N` score block stays in L2 for N ≲ 4096.
const BLOCK: usize = 64;

fn record(slot: &Mutex<Option<crate::Error>>, r: Result<()>) {
    if let (Err(e), Ok(mut s)) = (r, slot.lock()) {
        s.get_or_insert(e);
    }
}

fn take(slot: Mutex<Option<crate::Error>>) -> Result<()> {
    match slot.into_inner() {
        Ok(Some(e)) => Err(e),
        _ => Ok(()),
    }
}

/// Whether the fused narrow-head kernels take this call (head width `d`, `n` keys), and in
/// bf16 or not. At head width 64 beyond 4096 keys the fused kernels stream every head's
/// keys once per 16 query rows and lose to the general path's 64-row blocks (measured
/// 0.80× at 8192 keypoints, C = 256); bf16 always takes them.
fn fused(ctx: &Ctx, d: usize, n: usize) -> Option<bool> {
    let bf16 = ctx.precision == Precision::Bf16;
    let worth = d <= 32 || n <= 4096 || bf16;
    (ctx.fused && worth && crate::attention_fused::available(d)).then_some(bf16)
}

/// `softmax(q·kᵀ/√d)·v` for every head: `q` `[M, C]`, `k`, `v` `[N, C]` → `[M, C]`.
/// With `col_sums`, also `Σ_h Σ_i A[h, i, j]` `[N]` (for attentional pooling).
pub fn attention(ctx: &Ctx, q: View, k: View, v: View, heads: usize, col_sums: bool) -> Result<(Matrix, Option<Vec<f32>>)> {
    let (m, n, c) = (q.rows, k.rows, q.cols);
    let d = c / heads;
    if let Some(bf16) = fused(ctx, d, n) {
        ctx.add_macs(2 * (m * n * c) as u64);
        return crate::attention_fused::attention(q, k, v, heads, col_sums, bf16);
    }
    let scale = 1.0 / (d as f32).sqrt();
    let mut out = Matrix::zeros(m, c);
    let blocks = m.div_ceil(BLOCK);
    let dst = SharedMut(out.data.as_mut_ptr());
    let err = Mutex::new(None);
    // Column sums are kept per task and added in task order afterwards, so that they do
    // not depend on how rayon split the work (reproducible across thread counts).
    let per_task: Vec<Vec<f32>> = (0..heads * blocks)
        .into_par_iter()
        .map_init(Vec::new, |s, t| {
            let (h, b) = (t % heads, t / heads);
            let (r0, r1) = (b * BLOCK, ((b + 1) * BLOCK).min(m));
            s.resize(BLOCK * n, 0.0);
            let mut cs = if col_sums { vec![0.0f32; n] } else { Vec::new() };
            let mut run = || -> Result<()> {
                let qb = q.rows(r0, r1).cols(h * d, (h + 1) * d);
                ctx.gemm(s, n, qb, false, k.cols(h * d, (h + 1) * d), true, scale, false, false)?;
                let rows = r1 - r0;
                softmax_rows(&mut s[..rows * n], n);
                if col_sums {
                    for row in s[..rows * n].chunks_exact(n) {
                        for (a, p) in cs.iter_mut().zip(row) {
                            *a += p;
                        }
                    }
                }
                let probs = View { data: s, rows, cols: n, stride: n };
                // SAFETY: task (h, b) alone writes rows r0..r1, columns h·d..(h+1)·d.
                unsafe { ctx.gemm_ptr(dst.at(r0 * c + h * d), c, probs, false, v.cols(h * d, (h + 1) * d), false, 1.0, false, false) }
            };
            record(&err, run());
            cs
        })
        .collect();
    take(err)?;
    Ok((out, col_sums.then(|| sum_in_order(&per_task, n))))
}

/// Cross-attention with attention-weight sharing (SPEC §5): per head the scores
/// `S = qx·kyᵀ/√d` are formed once, in row blocks; rows give `softmax_rows(S)·vy`
/// and columns, through an online softmax over the blocks, `softmax_rows(Sᵀ)·vx`.
pub fn cross_attention_shared(ctx: &Ctx, qx: View, ky: View, vx: View, vy: View, heads: usize) -> Result<(Matrix, Matrix)> {
    let (m, n, c) = (qx.rows, ky.rows, qx.cols);
    let d = c / heads;
    if let Some(bf16) = fused(ctx, d, n.max(m)) {
        ctx.add_macs(3 * (m * n * c) as u64);
        return crate::attention_fused::cross_attention_shared(qx, ky, vx, vy, heads, bf16);
    }
    let scale = 1.0 / (d as f32).sqrt();
    let (mut out_x, mut out_y) = (Matrix::zeros(m, c), Matrix::zeros(n, c));
    let (dx, dy) = (SharedMut(out_x.data.as_mut_ptr()), SharedMut(out_y.data.as_mut_ptr()));
    let err = Mutex::new(None);
    (0..heads).into_par_iter().for_each(|h| {
        let run = || -> Result<()> {
            let (qh, kh, vxh, vyh) = (qx.cols(h * d, (h + 1) * d), ky.cols(h * d, (h + 1) * d), vx.cols(h * d, (h + 1) * d), vy.cols(h * d, (h + 1) * d));
            let mut s = vec![0.0f32; BLOCK * n];
            let mut e = vec![0.0f32; BLOCK * n];
            let mut col_max = vec![f32::NEG_INFINITY; n];
            let mut block_max = vec![f32::NEG_INFINITY; n];
            let mut col_sum = vec![0.0f32; n];
            let mut acc_y = vec![0.0f32; n * d];
            for r0 in (0..m).step_by(BLOCK) {
                let r1 = (r0 + BLOCK).min(m);
                let rows = r1 - r0;
                ctx.gemm(&mut s, n, qh.rows(r0, r1), false, kh, true, scale, false, false)?;
                block_max.fill(f32::NEG_INFINITY);
                for row in s[..rows * n].chunks_exact(n) {
                    for (bm, v) in block_max.iter_mut().zip(row) {
                        *bm = bm.max(*v);
                    }
                }
                // Rescale what earlier blocks accumulated where the column maximum grew.
                for j in 0..n {
                    if block_max[j] > col_max[j] {
                        if col_max[j] > f32::NEG_INFINITY {
                            let f = exp_fast(col_max[j] - block_max[j]);
                            col_sum[j] *= f;
                            for a in &mut acc_y[j * d..(j + 1) * d] {
                                *a *= f;
                            }
                        }
                        col_max[j] = block_max[j];
                    }
                }
                for (srow, erow) in s[..rows * n].chunks_exact(n).zip(e.chunks_exact_mut(n)) {
                    exp_sub_accumulate(srow, &col_max, erow, &mut col_sum);
                }
                // acc_y += Eᵀ·vx_block
                let eb = View { data: &e, rows, cols: n, stride: n };
                ctx.gemm(&mut acc_y, d, eb, true, vxh.rows(r0, r1), false, 1.0, true, false)?;
                softmax_rows(&mut s[..rows * n], n);
                let probs = View { data: &s, rows, cols: n, stride: n };
                // SAFETY: head h alone writes columns h·d..(h+1)·d of out_x.
                unsafe { ctx.gemm_ptr(dx.at(r0 * c + h * d), c, probs, false, vyh, false, 1.0, false, false)? };
            }
            for (j, (acc, s)) in acc_y.chunks_exact(d).zip(&col_sum).enumerate() {
                for (t, a) in acc.iter().enumerate() {
                    // SAFETY: head h alone writes columns h·d..(h+1)·d of out_y; j·c + h·d + t < n·c.
                    unsafe { *dy.at(j * c + h * d + t) = a / s };
                }
            }
            Ok(())
        };
        record(&err, run());
    });
    take(err)?;
    Ok((out_x, out_y))
}

/// The q, k, v projections `proj.{0,1,2}` (or `self_proj`, `cross_proj`), held as one
/// Linear with outputs `[q | k | v]`.
#[derive(Debug, Clone)]
pub struct Projections {
    qkv: Linear,
    pub dim: usize,
}

impl Projections {
    pub fn new(c: usize, vb: VarBuilder) -> CResult<Self> {
        let p = (Linear::new(c, c, vb.pp(0))?, Linear::new(c, c, vb.pp(1))?, Linear::new(c, c, vb.pp(2))?);
        Ok(Self { qkv: Linear::concat(&[&p.0, &p.1, &p.2]).with_bf16(), dim: c })
    }

    /// `[q | k | v]` of `x` `[K, 3C]`.
    pub fn qkv(&self, ctx: &Ctx, x: View) -> Result<Matrix> {
        self.qkv.forward(ctx, x)
    }

    /// Projections `first..last` (0 = q, 1 = k, 2 = v) of `x`, side by side.
    pub fn part(&self, ctx: &Ctx, x: View, first: usize, last: usize) -> Result<Matrix> {
        self.qkv.forward_cols(ctx, x, first * self.dim, (last + 1) * self.dim)
    }
}

/// SuperGlue's multi-headed attention, prefix `attn`: `proj.{0,1,2}` and `merge`.
#[derive(Debug, Clone)]
pub struct Attention {
    proj: Projections,
    merge: Linear,
    heads: usize,
}

impl Attention {
    pub fn new(c: usize, heads: usize, vb: VarBuilder) -> CResult<Self> {
        Ok(Self { proj: Projections::new(c, vb.pp("proj"))?, merge: Linear::new(c, c, vb.pp("merge"))?.with_bf16(), heads })
    }

    /// `merge(attn(q(x), k(src), v(src)))` written into `dst` (row stride `dst_stride`).
    pub fn forward_into(&self, ctx: &Ctx, x: View, src: View, dst: &mut [f32], dst_stride: usize) -> Result<()> {
        let c = self.proj.dim;
        let q = self.proj.part(ctx, x, 0, 0)?;
        let kv = self.proj.part(ctx, src, 1, 2)?;
        let (msg, _) = attention(ctx, q.view(), kv.view().cols(0, c), kv.view().cols(c, 2 * c), self.heads, false)?;
        self.merge.forward_into(ctx, msg.view(), dst, dst_stride)
    }
}
