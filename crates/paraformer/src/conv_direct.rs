//! Convolutions for XFeat's backbone (Potje et al., CVPR 2024, §3.1) on AVX-512 CPUs:
//! 3×3 with zero padding 1 at stride 1 or 2, and 1×1. Its layers have 1–128 channels on
//! large images, where im2col + GEMM spends more time writing the unfolded copy than
//! computing.
//!
//! Direct path: the input is copied once into zero-padded planes laid out so that every
//! tap of every output pixel is one constant offset from the pixel's flat index (for
//! stride 2, four planes by row and column parity; 1×1 reads the input in place). Output
//! pixels are a flat range cut into tiles of `NV`·16 pixels that run across row ends (the
//! padding columns in between are computed and dropped), so narrow maps waste no lanes.
//! A register tile of `CB` output channels × `NV` vectors accumulates over every input
//! channel and tap with broadcast weights; bias and ReLU are applied on the store.
//!
//! Winograd path (3×3, stride 1, ≥ [`WINOGRAD_MIN_CIN`] input channels): F(2×2, 3×3)
//! (Lavin & Gray, *Fast Algorithms for Convolutional Neural Networks*, CVPR 2016) on flat
//! blocks of 2×2 output tiles: 16 multiplies per tile and channel pair instead of 36.
//!
//! Each output value comes from one tile in a fixed order, so results do not depend on
//! the thread count.

/// Buffers recycled on this thread. A fresh allocation of megabytes costs a page fault
/// per 4 KiB on first touch, and faults taken by several threads at once contend: at
/// 640×480 they cost XFeat more than some of its convolutions.
pub mod pool {
    use std::cell::RefCell;

    thread_local! {
        static FREE: RefCell<Vec<Vec<f32>>> = const { RefCell::new(Vec::new()) };
    }

    /// At most this many bytes stay pooled per thread.
    const KEEP_BYTES: usize = 96 << 20;
    /// Smaller buffers are not worth pooling.
    const MIN_LEN: usize = 1 << 14;

    /// A buffer of `n` values whose contents are unspecified (zeros or values of an
    /// earlier use): for callers that overwrite every value.
    pub fn take(n: usize) -> Vec<f32> {
        let found = FREE.with(|f| {
            let mut f = f.borrow_mut();
            // The smallest pooled buffer that holds `n` values.
            let best = f.iter().enumerate().filter(|(_, v)| v.capacity() >= n).min_by_key(|(_, v)| v.capacity()).map(|(i, _)| i);
            best.map(|i| f.swap_remove(i))
        });
        let mut v = found.unwrap_or_default();
        v.truncate(n);
        v.resize(n, 0.0);
        v
    }

    /// Returns a buffer to this thread's pool (or frees it).
    pub fn give(v: Vec<f32>) {
        if v.capacity() < MIN_LEN {
            return;
        }
        FREE.with(|f| {
            let mut f = f.borrow_mut();
            f.push(v);
            // Over the budget: free the smallest first, keeping the large ones.
            while f.iter().map(|v| v.capacity() * 4).sum::<usize>() > KEEP_BYTES {
                if let Some(i) = f.iter().enumerate().min_by_key(|(_, v)| v.capacity()).map(|(i, _)| i) {
                    f.swap_remove(i);
                }
            }
        });
    }
}

/// One convolution's weights in the kernel's layout, built once at load time.
#[derive(Debug, Clone)]
pub struct DirectConv {
    cin: usize,
    cout: usize,
    /// Kernel side: 1 or 3.
    k: usize,
    stride: usize,
    /// Output channels per register tile (8, or 4 below 8 channels).
    cb: usize,
    /// `[⌈cout/cb⌉][cin][k·k][cb]`, zero-padded channels past `cout`: the tile's weights
    /// for one tap are contiguous.
    packed: Vec<f32>,
    /// For 3×3 stride-1 layers of at least [`WINOGRAD_MIN_CIN`] input channels: the
    /// Winograd F(2×2, 3×3) weights `G·g·Gᵀ` as `[⌈cout/8⌉][16][cin][8]`.
    winograd: Option<Vec<f32>>,
    bias: Vec<f32>,
    relu: bool,
}

/// Winograd pays where the channel sums are long enough to hide its transforms.
pub const WINOGRAD_MIN_CIN: usize = 16;

/// `G·g·Gᵀ` of one 3×3 kernel (row-major) for F(2×2, 3×3), row-major 4×4.
fn winograd_kernel(g: &[f32]) -> [f32; 16] {
    const G: [[f32; 3]; 4] = [[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 1.0]];
    let mut gg = [[0.0f32; 3]; 4];
    for (i, row) in gg.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| G[i][k] * g[k * 3 + j]).sum();
        }
    }
    let mut out = [0.0f32; 16];
    for i in 0..4 {
        for j in 0..4 {
            out[i * 4 + j] = (0..3).map(|k| gg[i][k] * G[j][k]).sum();
        }
    }
    out
}

impl DirectConv {
    /// `weight`: `[cout, cin, k, k]` row-major; `bias`: `[cout]`. `None` where the kernel
    /// does not serve this shape or CPU (the caller keeps its general path): `k` must be
    /// 3 (stride 1 or 2) or 1 (stride 1).
    pub fn new(weight: &[f32], bias: &[f32], cin: usize, cout: usize, k: usize, stride: usize, relu: bool) -> Option<Self> {
        let shape_ok = matches!((k, stride), (3, 1) | (3, 2) | (1, 1));
        if !available() || !shape_ok || cin == 0 || cout == 0 || weight.len() != cout * cin * k * k || bias.len() != cout {
            return None;
        }
        let cb = if cout >= 8 { 8 } else { 4 };
        let taps = k * k;
        let mut packed = vec![0.0f32; cout.div_ceil(cb) * cb * cin * taps];
        for co in 0..cout {
            let (b, c) = (co / cb, co % cb);
            for ci in 0..cin {
                for t in 0..taps {
                    packed[((b * cin + ci) * taps + t) * cb + c] = weight[(co * cin + ci) * taps + t];
                }
            }
        }
        let winograd = (k == 3 && stride == 1 && cb == 8 && cin >= WINOGRAD_MIN_CIN).then(|| {
            let mut v = vec![0.0f32; cout.div_ceil(8) * 8 * 16 * cin];
            for co in 0..cout {
                for ci in 0..cin {
                    let u = winograd_kernel(&weight[(co * cin + ci) * 9..][..9]);
                    for (xi, &val) in u.iter().enumerate() {
                        v[(((co / 8) * 16 + xi) * cin + ci) * 8 + co % 8] = val;
                    }
                }
            }
            v
        });
        Some(Self { cin, cout, k, stride, cb, packed, winograd, bias: bias.to_vec(), relu })
    }

    /// Output channels.
    pub fn cout(&self) -> usize {
        self.cout
    }

    /// Output side lengths for an `h × w` input.
    pub fn output_size(&self, h: usize, w: usize) -> (usize, usize) {
        let p = self.k / 2;
        ((h + 2 * p - self.k) / self.stride + 1, (w + 2 * p - self.k) / self.stride + 1)
    }

    /// Convolves `cin` planes of `h × w` (row-major, plane after plane; `h, w ≥ 1`) into
    /// `cout` planes of [`DirectConv::output_size`]. The buffer comes from [`pool`].
    pub fn forward(&self, x: &[f32], h: usize, w: usize) -> Vec<f32> {
        #[cfg(target_arch = "x86_64")]
        {
            x86::forward(self, x, h, w)
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            // Never built elsewhere (`new` returns None).
            let _ = (x, h, w);
            Vec::new()
        }
    }
}

/// Whether the kernel runs here (AVX-512F at run time).
pub fn available() -> bool {
    cfg!(target_arch = "x86_64") && crate::kernels::simd_level() >= 4
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use rayon::prelude::*;

    use super::{pool, DirectConv};
    use crate::kernels::SharedMut;

    /// Pixels per vector.
    const L: usize = 16;
    /// Vectors per register tile for 8 output channels (24 accumulators) and for 4 (24).
    const NV8: usize = 3;
    const NV4: usize = 6;

    /// The input arranged for flat tiles: `nbufs` groups of `cin` planes of `plane`
    /// values at `data`; output pixel `(oy, ox)` has flat index `f = oy·pitch + ox`
    /// (columns `ox ≥ wo` are padding) and reads tap `t` of channel `ci` at
    /// `data[(taps[t].0·cin + ci)·plane + f − origin + taps[t].1]`.
    struct Layout<'a> {
        data: &'a [f32],
        plane: usize,
        pitch: usize,
        origin: usize,
        taps: Vec<(usize, usize)>,
    }

    /// Padded copies for 3×3 kernels, in `buf` (from the pool; every value written):
    /// `split` = false: one group of zero-padded rows, `ho` output rows; `split` = true:
    /// four groups by row and column parity of the padded image (stride 2, and the 4×4
    /// Winograd patches of 2×2 output tiles), `ho` rows of outputs or tiles.
    #[allow(clippy::too_many_arguments)]
    fn layout<'a>(cin: usize, split: bool, x: &[f32], h: usize, w: usize, ho: usize, tile: usize, buf: &'a mut Vec<f32>) -> Layout<'a> {
        let (pitch, nbufs, reach) = if !split { (w + 2, 1, 2 * (w + 2) + 2) } else { ((w - 1) / 2 + 2, 4, (w - 1) / 2 + 3) };
        // Room for the last tile's full loads at the farthest tap.
        let plane = ((ho * pitch).div_ceil(tile) * tile + reach).div_ceil(L) * L;
        *buf = pool::take(nbufs * cin * plane);
        // One parallel pass over every (group, channel) plane.
        buf.par_chunks_mut(plane).enumerate().for_each(|(i, dst)| {
            let (bi, ci) = (i / cin, i % cin);
            let src = &x[ci * h * w..(ci + 1) * h * w];
            if !split {
                // Padded row r holds input row r − 1 at columns 1..=w.
                dst[..pitch + 1].fill(0.0);
                for (y, line) in src.chunks_exact(w).enumerate() {
                    let row = &mut dst[(y + 1) * pitch + 1..];
                    row[..w].copy_from_slice(line);
                    // Right padding of this row and left padding of the next.
                    row[w..w + 2].fill(0.0);
                }
                dst[(h + 1) * pitch + 1..].fill(0.0);
            } else {
                // Group (row parity rp, column parity cp): row m, column j holds padded
                // pixel (2m + rp, 2j + cp) = input (2m + rp − 1, 2j + cp − 1).
                let (rp, cp) = (bi / 2, bi % 2);
                for m in 0..=ho {
                    let row = &mut dst[m * pitch..(m + 1) * pitch];
                    match (2 * m + rp).checked_sub(1).filter(|&r| r < h) {
                        None => row.fill(0.0),
                        Some(iy) => {
                            let line = &src[iy * w..(iy + 1) * w];
                            // cp = 1: j ↦ input column 2j; cp = 0: j ≥ 1 ↦ 2j − 1.
                            let n = if cp == 1 { w.div_ceil(2) } else { w / 2 };
                            let first = 1 - cp;
                            row[..first].fill(0.0);
                            row[first..first + n].iter_mut().zip(line[first..].iter().step_by(2)).for_each(|(d, v)| *d = *v);
                            row[first + n..].fill(0.0);
                        }
                    }
                }
                dst[(ho + 1) * pitch..].fill(0.0);
            }
        });
        let taps = if !split {
            (0..9).map(|t| (0, (t / 3) * pitch + t % 3)).collect()
        } else {
            // ky = 0, 1, 2: even rows at m = oy, odd rows at oy, even rows at oy + 1;
            // kx = 0, 1, 2: even columns at j = ox, odd at ox, even at ox + 1.
            (0..9)
                .map(|t| {
                    let (ky, kx) = (t / 3, t % 3);
                    ([0, 2, 0][ky] + [0, 1, 0][kx], [0, 0, pitch][ky] + [0, 0, 1][kx])
                })
                .collect()
        };
        Layout { data: buf, plane, pitch, origin: 0, taps }
    }

    pub(super) fn forward(conv: &DirectConv, x: &[f32], h: usize, w: usize) -> Vec<f32> {
        if let Some(v) = &conv.winograd {
            return winograd(conv, v, x, h, w);
        }
        let (ho, wo) = conv.output_size(h, w);
        let tile = L * if conv.cb == 8 { NV8 } else { NV4 };
        // Every output value is written below.
        let mut out = pool::take(conv.cout * ho * wo);
        let dst = SharedMut(out.as_mut_ptr());
        let mut scratch = Vec::new();
        if conv.k == 1 {
            // 1×1: full tiles read the input in place; the last, partial tile reads a
            // zero-padded copy of its pixels (loads must stay inside the buffer).
            let p = h * w;
            let full = p / tile;
            let whole = Layout { data: x, plane: p, pitch: w, origin: 0, taps: vec![(0, 0)] };
            run(conv, &whole, 0..full, ho, wo, dst);
            if full * tile < p {
                scratch = pool::take(conv.cin * tile);
                for (ci, d) in scratch.chunks_exact_mut(tile).enumerate() {
                    let rest = &x[ci * p + full * tile..(ci + 1) * p];
                    d[..rest.len()].copy_from_slice(rest);
                    d[rest.len()..].fill(0.0);
                }
                let tail = Layout { data: &scratch, plane: tile, pitch: w, origin: full * tile, taps: vec![(0, 0)] };
                run(conv, &tail, full..full + 1, ho, wo, dst);
            }
        } else {
            let lay = layout(conv.cin, conv.stride == 2, x, h, w, ho, tile, &mut scratch);
            let tiles = (ho * lay.pitch).div_ceil(tile);
            run(conv, &lay, 0..tiles, ho, wo, dst);
        }
        pool::give(scratch);
        out
    }

    /// Tiles `tiles` of every output channel, in parallel over fixed chunks of tiles.
    fn run(conv: &DirectConv, lay: &Layout, tiles: std::ops::Range<usize>, ho: usize, wo: usize, dst: SharedMut) {
        // Fixed task boundaries (a function of the shape only).
        let per_task = tiles.len().div_ceil(32).max(1);
        let tasks = tiles.len().div_ceil(per_task);
        (0..tasks).into_par_iter().for_each(|task| {
            let range = tiles.start + task * per_task..(tiles.start + (task + 1) * per_task).min(tiles.end);
            // SAFETY: AVX-512F is present (`DirectConv::new` checked); loads stay inside
            // the layout (padded planes sized for the last tile at the farthest tap, or
            // only full tiles of an unpadded plane); each tile stores only its own
            // output pixels.
            unsafe {
                match (conv.cb, conv.k) {
                    (8, 3) => tiles_of::<8, NV8, 9>(conv, lay, range, ho, wo, dst),
                    (8, _) => tiles_of::<8, NV8, 1>(conv, lay, range, ho, wo, dst),
                    (_, 3) => tiles_of::<4, NV4, 9>(conv, lay, range, ho, wo, dst),
                    _ => tiles_of::<4, NV4, 1>(conv, lay, range, ho, wo, dst),
                }
            }
        });
    }

    /// The output-row segments of one vector of 16 flat pixels (one per row it touches,
    /// up to 16 on maps narrower than a vector): (output offset of lane 0, mask of the
    /// lanes in that row).
    #[derive(Clone, Copy)]
    struct Segments {
        n: usize,
        seg: [(isize, __mmask16); L],
    }

    fn segments(f: usize, pitch: usize, ho: usize, wo: usize) -> Segments {
        segments_in(f, pitch, ho, wo, wo, 0)
    }

    /// [`segments`] of a flat grid whose row `oy`, column `ox` is output value
    /// `oy·row_stride + base + ox`.
    fn segments_in(f: usize, pitch: usize, ho: usize, wo: usize, row_stride: usize, base: usize) -> Segments {
        let mut out = Segments { n: 0, seg: [(0, 0); L] };
        let (mut oy, mut ox, mut lane) = (f / pitch, f % pitch, 0);
        while lane < L && oy < ho {
            let in_row = (pitch - ox).min(L - lane);
            if ox < wo {
                let valid = (wo - ox).min(in_row);
                let mask = (((1u32 << valid) - 1) << lane) as __mmask16;
                out.seg[out.n] = ((oy * row_stride + base + ox) as isize - lane as isize, mask);
                out.n += 1;
            }
            lane += in_row;
            oy += 1;
            ox = 0;
        }
        out
    }

    #[target_feature(enable = "avx512f")]
    unsafe fn tiles_of<const CB: usize, const NV: usize, const TAPS: usize>(
        conv: &DirectConv,
        lay: &Layout,
        range: std::ops::Range<usize>,
        ho: usize,
        wo: usize,
        dst: SharedMut,
    ) {
        let cin = conv.cin;
        let zero = _mm512_setzero_ps();
        // Tap t of channel ci at flat index f: srcs[t] + ci·plane + f.
        let mut srcs = [std::ptr::null::<f32>(); TAPS];
        for (p, &(group, off)) in srcs.iter_mut().zip(&lay.taps) {
            *p = lay.data.as_ptr().wrapping_add(group * cin * lay.plane + off).wrapping_sub(lay.origin);
        }
        // A vector of more than one row segment only where rows are narrower than 16 or
        // it straddles a row end; `segments` covers every case.
        let vec_segments: Vec<[Segments; NV]> = range
            .clone()
            .map(|t| std::array::from_fn(|n| segments(t * NV * L + n * L, lay.pitch, ho, wo)))
            .collect();
        for b in 0..conv.cout.div_ceil(CB) {
            let wb = conv.packed.as_ptr().add(b * cin * TAPS * CB);
            let mut bias = [zero; CB];
            for (c, v) in bias.iter_mut().enumerate() {
                *v = _mm512_set1_ps(conv.bias.get(b * CB + c).copied().unwrap_or(0.0));
            }
            for (t, segs) in range.clone().zip(&vec_segments) {
                let f0 = t * NV * L;
                let mut acc = [[zero; NV]; CB];
                for (a, &bv) in acc.iter_mut().zip(&bias) {
                    *a = [bv; NV];
                }
                for ci in 0..cin {
                    let wc = wb.add(ci * TAPS * CB);
                    for (ti, &src) in srcs.iter().enumerate() {
                        let src = src.wrapping_add(ci * lay.plane + f0);
                        let mut v = [zero; NV];
                        for (n, vn) in v.iter_mut().enumerate() {
                            *vn = _mm512_loadu_ps(src.add(n * L));
                        }
                        let wt = wc.add(ti * CB);
                        for (c, a) in acc.iter_mut().enumerate() {
                            let wv = _mm512_set1_ps(*wt.add(c));
                            for n in 0..NV {
                                a[n] = _mm512_fmadd_ps(wv, v[n], a[n]);
                            }
                        }
                    }
                }
                for (c, a) in acc.iter().enumerate() {
                    let co = b * CB + c;
                    if co >= conv.cout {
                        break;
                    }
                    let plane = dst.at(co * ho * wo);
                    for (&an, sg) in a.iter().zip(segs) {
                        let v = if conv.relu { _mm512_max_ps(an, zero) } else { an };
                        for &(off, mask) in &sg.seg[..sg.n] {
                            // Masked-off lanes are never accessed, so the base may lie
                            // before the row.
                            _mm512_mask_storeu_ps(plane.wrapping_offset(off), mask, v);
                        }
                    }
                }
            }
        }
    }

    /// Flat 2×2 output tiles per Winograd block: 3 vectors of 16.
    const WV: usize = 3;
    const WT: usize = WV * L;

    /// 3×3 stride-1 convolution by Winograd F(2×2, 3×3): per block of 48 flat tiles, the
    /// input transform `Bᵀ·d·B` of every channel, 16 products of `[8 × cin]·[cin × 48]`
    /// per block of 8 output channels (the same register tile as the direct kernel), and
    /// the output transform `Aᵀ·m·A` with bias and ReLU on the store. 36 multiplies per
    /// output pair of channels become 16 per 2×2 outputs' 4.
    fn winograd(conv: &DirectConv, v: &[f32], x: &[f32], h: usize, w: usize) -> Vec<f32> {
        let (th, tw) = (h.div_ceil(2), w.div_ceil(2));
        let mut scratch = Vec::new();
        // Patch value (r, c) of tile (ty, tx) is padded pixel (2ty + r, 2tx + c): the
        // parity groups of the stride-2 layout, at flat tile index ty·pitch + tx.
        let lay = layout(conv.cin, true, x, h, w, th, WT, &mut scratch);
        debug_assert_eq!(lay.pitch, tw + 1);
        let mut out = pool::take(conv.cout * h * w);
        let dst = SharedMut(out.as_mut_ptr());
        let blocks = (th * lay.pitch).div_ceil(WT);
        let per_task = blocks.div_ceil(32).max(1);
        (0..blocks.div_ceil(per_task)).into_par_iter().for_each(|task| {
            let range = task * per_task..((task + 1) * per_task).min(blocks);
            let mut u = pool::take(conv.cin * 16 * WT);
            let mut m = pool::take(16 * 8 * WT);
            for blk in range {
                // SAFETY: AVX-512F is present (`DirectConv::new` checked); loads stay in
                // the padded layout (sized for the last block at the farthest patch
                // offset) and the scratch buffers; stores only touch this block's outputs.
                unsafe { winograd_block(conv, v, &lay, blk, h, w, &mut u, &mut m, dst) };
            }
            pool::give(u);
            pool::give(m);
        });
        pool::give(scratch);
        out
    }

    #[target_feature(enable = "avx512f")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn winograd_block(conv: &DirectConv, v: &[f32], lay: &Layout, blk: usize, h: usize, w: usize, u: &mut [f32], m: &mut [f32], dst: SharedMut) {
        let cin = conv.cin;
        let g0 = blk * WT;
        let zero = _mm512_setzero_ps();
        // Input transform, vectorised over 16 tiles: U = Bᵀ·d·B.
        for ci in 0..cin {
            for n in 0..WV {
                let mut d = [[zero; 4]; 4];
                for (r, row) in d.iter_mut().enumerate() {
                    for (c, val) in row.iter_mut().enumerate() {
                        let group = (r % 2) * 2 + c % 2;
                        let at = (group * cin + ci) * lay.plane + (r / 2) * lay.pitch + c / 2 + g0 + n * L;
                        *val = _mm512_loadu_ps(lay.data.as_ptr().add(at));
                    }
                }
                // Rows: t0 = d0 − d2, t1 = d1 + d2, t2 = d2 − d1, t3 = d1 − d3.
                let mut t = [[zero; 4]; 4];
                for c in 0..4 {
                    t[0][c] = _mm512_sub_ps(d[0][c], d[2][c]);
                    t[1][c] = _mm512_add_ps(d[1][c], d[2][c]);
                    t[2][c] = _mm512_sub_ps(d[2][c], d[1][c]);
                    t[3][c] = _mm512_sub_ps(d[1][c], d[3][c]);
                }
                let base = u.as_mut_ptr().add(ci * 16 * WT + n * L);
                for (r, tr) in t.iter().enumerate() {
                    let cols = [
                        _mm512_sub_ps(tr[0], tr[2]),
                        _mm512_add_ps(tr[1], tr[2]),
                        _mm512_sub_ps(tr[2], tr[1]),
                        _mm512_sub_ps(tr[1], tr[3]),
                    ];
                    for (c, &val) in cols.iter().enumerate() {
                        _mm512_storeu_ps(base.add((r * 4 + c) * WT), val);
                    }
                }
            }
        }
        // Where each output vector goes: per vector n, half (tiles 0–7 or 8–15) and tile
        // row i, the output rows and columns (2·tx, 2·tx + 1) of its 8 tiles.
        let mut segs = [[[Segments { n: 0, seg: [(0, 0); L] }; 2]; 2]; WV];
        for (n, per_n) in segs.iter_mut().enumerate() {
            for (half, per_half) in per_n.iter_mut().enumerate() {
                for (i, sg) in per_half.iter_mut().enumerate() {
                    let f = 2 * (g0 + n * L) + half * L;
                    let rows = if i == 0 { h.div_ceil(2) } else { h / 2 };
                    *sg = segments_in(f, 2 * lay.pitch, rows, w, 2 * w, i * w);
                }
            }
        }
        let lo = _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
        let hi = _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
        for b in 0..conv.cout.div_ceil(8) {
            // The 16 products of this block of 8 output channels.
            for xi in 0..16 {
                let vb = v.as_ptr().add((b * 16 + xi) * cin * 8);
                let mut acc = [[zero; WV]; 8];
                for ci in 0..cin {
                    let src = u.as_ptr().add((ci * 16 + xi) * WT);
                    let mut x = [zero; WV];
                    for (n, xn) in x.iter_mut().enumerate() {
                        *xn = _mm512_loadu_ps(src.add(n * L));
                    }
                    let wt = vb.add(ci * 8);
                    for (c, a) in acc.iter_mut().enumerate() {
                        let wv = _mm512_set1_ps(*wt.add(c));
                        for n in 0..WV {
                            a[n] = _mm512_fmadd_ps(wv, x[n], a[n]);
                        }
                    }
                }
                for (c, a) in acc.iter().enumerate() {
                    for (n, &an) in a.iter().enumerate() {
                        _mm512_storeu_ps(m.as_mut_ptr().add((xi * 8 + c) * WT + n * L), an);
                    }
                }
            }
            // Output transform Y = Aᵀ·m·A, bias, ReLU, store.
            for c in 0..8 {
                let co = b * 8 + c;
                if co >= conv.cout {
                    break;
                }
                let bias = _mm512_set1_ps(conv.bias[co]);
                let plane = dst.at(co * h * w);
                for (n, segs_n) in segs.iter().enumerate() {
                    let ld = |xi: usize| _mm512_loadu_ps(m.as_ptr().add((xi * 8 + c) * WT + n * L));
                    // Rows of Aᵀ·m: s0 = m0 + m1 + m2, s1 = m1 − m2 − m3 (per column).
                    let sr: [[__m512; 4]; 2] = [
                        std::array::from_fn(|col| _mm512_add_ps(_mm512_add_ps(ld(col), ld(4 + col)), ld(8 + col))),
                        std::array::from_fn(|col| _mm512_sub_ps(_mm512_sub_ps(ld(4 + col), ld(8 + col)), ld(12 + col))),
                    ];
                    for (i, s) in sr.iter().enumerate() {
                        let mut y0 = _mm512_add_ps(_mm512_add_ps(_mm512_add_ps(s[0], s[1]), s[2]), bias);
                        let mut y1 = _mm512_add_ps(_mm512_sub_ps(_mm512_sub_ps(s[1], s[2]), s[3]), bias);
                        if conv.relu {
                            y0 = _mm512_max_ps(y0, zero);
                            y1 = _mm512_max_ps(y1, zero);
                        }
                        let halves = [_mm512_permutex2var_ps(y0, lo, y1), _mm512_permutex2var_ps(y0, hi, y1)];
                        for (half, &val) in halves.iter().enumerate() {
                            let sg = &segs_n[half][i];
                            for &(off, mask) in &sg.seg[..sg.n] {
                                _mm512_mask_storeu_ps(plane.wrapping_offset(off), mask, val);
                            }
                        }
                    }
                }
            }
        }
    }

}

#[cfg(test)]
mod tests {
    use super::*;

    /// Plain nested loops: zero padding k/2, the given stride.
    fn reference(x: &[f32], wgt: &[f32], bias: &[f32], dims: (usize, usize, usize, usize, usize, usize), relu: bool) -> Vec<f32> {
        let (cin, cout, h, w, k, s) = dims;
        let p = k / 2;
        let (ho, wo) = ((h + 2 * p - k) / s + 1, (w + 2 * p - k) / s + 1);
        let mut out = vec![0.0f32; cout * ho * wo];
        for co in 0..cout {
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut acc = bias[co] as f64;
                    for ci in 0..cin {
                        for ky in 0..k {
                            for kx in 0..k {
                                let (iy, ix) = ((oy * s + ky) as isize - p as isize, (ox * s + kx) as isize - p as isize);
                                if iy >= 0 && ix >= 0 && (iy as usize) < h && (ix as usize) < w {
                                    let xv = x[(ci * h + iy as usize) * w + ix as usize] as f64;
                                    acc += xv * wgt[((co * cin + ci) * k + ky) * k + kx] as f64;
                                }
                            }
                        }
                    }
                    out[(co * ho + oy) * wo + ox] = if relu { acc.max(0.0) as f32 } else { acc as f32 };
                }
            }
        }
        out
    }

    fn values(n: usize, seed: u32) -> Vec<f32> {
        let mut s = seed.wrapping_mul(2654435761).wrapping_add(1);
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                (s % 2001) as f32 / 1000.0 - 1.0
            })
            .collect()
    }

    #[test]
    fn direct_convolution_equals_nested_loops() {
        if !available() {
            println!("skipped: no AVX-512 on this CPU (the im2col path serves it)");
            return;
        }
        // Odd and even sides, maps narrower than a vector and wider than a tile, both
        // strides, 1×1, and channel counts that fill tiles partly (1, 4, 5, 65).
        let cases = [
            (1, 4, 9, 70, 3, 1),
            (4, 8, 10, 37, 3, 2),
            (3, 16, 5, 48, 3, 1),
            (24, 64, 7, 33, 3, 2),
            (2, 24, 1, 1, 3, 1),
            (2, 8, 1, 1, 3, 2),
            (5, 8, 6, 97, 3, 2),
            (7, 5, 3, 4, 3, 1),
            (64, 65, 6, 10, 1, 1),
            (8, 1, 3, 50, 1, 1),
            (3, 8, 20, 3, 3, 2),
            (2, 4, 17, 2, 3, 1),
            (4, 8, 9, 5, 1, 1),
            (3, 8, 3, 16, 1, 1),
            (2, 4, 4, 48, 1, 1),
            // Winograd (3×3, stride 1, ≥ 16 input channels): odd and even sides.
            (16, 8, 7, 9, 3, 1),
            (24, 24, 12, 40, 3, 1),
            (32, 16, 5, 3, 3, 1),
            (16, 8, 1, 1, 3, 1),
            (64, 64, 10, 37, 3, 1),
            (128, 16, 3, 20, 3, 1),
        ];
        for &(cin, cout, h, w, k, s) in &cases {
            let x = values(cin * h * w, (cin * 31 + w) as u32);
            let wgt = values(cout * cin * k * k, cout as u32);
            let bias = values(cout, 7);
            for relu in [false, true] {
                let conv = DirectConv::new(&wgt, &bias, cin, cout, k, s, relu).expect("served shape");
                let got = conv.forward(&x, h, w);
                let want = reference(&x, &wgt, &bias, (cin, cout, h, w, k, s), relu);
                assert_eq!(got.len(), want.len());
                let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-4, "cin {cin} cout {cout} {h}×{w} k {k} stride {s}: max error {worst}");
            }
        }
    }

    #[test]
    fn unserved_shapes_are_declined() {
        assert!(DirectConv::new(&[0.0; 8 * 9], &[0.0; 8], 1, 8, 3, 3, true).is_none(), "stride 3");
        assert!(DirectConv::new(&[0.0; 8 * 4], &[0.0; 8], 1, 8, 2, 1, true).is_none(), "2×2 kernel");
        assert!(DirectConv::new(&[0.0; 8], &[0.0; 8], 1, 8, 3, 1, true).is_none(), "wrong weight length");
        assert!(DirectConv::new(&[0.0; 8], &[0.0; 8], 1, 8, 1, 2, true).is_none(), "strided 1×1");
    }
}
