//! Direct convolution (3×3 with zero padding 1 at stride 1 or 2, and 1×1) on AVX-512 CPUs,
//! for XFeat's backbone (Potje et al., CVPR 2024, §3.1): its layers have 1–128 channels
//! on large images, where im2col + GEMM spends more time writing the unfolded copy than
//! computing.
//!
//! The input is copied once into zero-padded planes laid out so that every tap of every
//! output pixel is one constant offset from the pixel's flat index (for stride 2, six
//! planes: one per kernel row and column parity). Output pixels are then a flat range,
//! cut into tiles of `NV`·16 pixels that run across row ends (the padding columns in
//! between are computed and dropped), so narrow maps waste no lanes. A register tile of
//! `CB` output channels × `NV` vectors accumulates over every input channel and tap with
//! broadcast weights; bias and ReLU are applied on the store. Each output value comes
//! from one tile in a fixed order, so results do not depend on the thread count.

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
    bias: Vec<f32>,
    relu: bool,
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
        Some(Self { cin, cout, k, stride, cb, packed, bias: bias.to_vec(), relu })
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

    /// The input rearranged for flat tiles: `bufs` of `[cin][plane]`; output pixel
    /// `(oy, ox)` has flat index `f = oy·pitch + ox` (columns `ox ≥ wo` are padding) and
    /// reads tap `t` at `bufs[taps[t].0][ci·plane + f + taps[t].1]`.
    struct Layout {
        bufs: Vec<Vec<f32>>,
        plane: usize,
        pitch: usize,
        taps: Vec<(usize, usize)>,
    }

    fn layout(conv: &DirectConv, x: &[f32], h: usize, w: usize, ho: usize, tile: usize) -> Layout {
        let cin = conv.cin;
        let (pitch, nbufs, reach) = match (conv.k, conv.stride) {
            (1, _) => (w, 1, 0),
            (3, 1) => (w + 2, 1, 2 * (w + 2) + 2),
            _ => ((w - 1) / 2 + 2, 4, (w - 1) / 2 + 3),
        };
        // Room for the last tile's full loads at the farthest tap.
        let plane = ((ho * pitch).div_ceil(tile) * tile + reach).div_ceil(L) * L;
        let mut bufs: Vec<Vec<f32>> = (0..nbufs).map(|_| pool::take(cin * plane)).collect();
        for (bi, buf) in bufs.iter_mut().enumerate() {
            buf.par_chunks_mut(plane).enumerate().for_each(|(ci, dst)| {
                let src = &x[ci * h * w..(ci + 1) * h * w];
                // Every value of `dst` is written: data, or zeros for padding and slack
                // (pooled buffers hold stale values).
                match (conv.k, conv.stride) {
                    (1, _) => {
                        dst[..h * w].copy_from_slice(src);
                        dst[h * w..].fill(0.0);
                    }
                    (3, 1) => {
                        // Padded row r holds input row r − 1 at columns 1..=w.
                        dst[..pitch + 1].fill(0.0);
                        for (y, line) in src.chunks_exact(w).enumerate() {
                            let row = &mut dst[(y + 1) * pitch + 1..];
                            row[..w].copy_from_slice(line);
                            // Right padding of this row and left padding of the next.
                            row[w..w + 2].fill(0.0);
                        }
                        dst[(h + 1) * pitch + 1..].fill(0.0);
                    }
                    _ => {
                        // Buffer (row parity rp, column parity cp): row m, column j holds
                        // padded pixel (2m + rp, 2j + cp) = input (2m + rp − 1, 2j + cp − 1).
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
                }
            });
        }
        let taps = match (conv.k, conv.stride) {
            (1, _) => vec![(0, 0)],
            (3, 1) => (0..9).map(|t| (0, (t / 3) * pitch + t % 3)).collect(),
            // ky = 0, 1, 2: even rows at m = oy, odd rows at oy, even rows at oy + 1;
            // kx = 0, 1, 2: even columns at j = ox, odd at ox, even at ox + 1.
            _ => (0..9)
                .map(|t| {
                    let (ky, kx) = (t / 3, t % 3);
                    ([0, 2, 0][ky] + [0, 1, 0][kx], [0, 0, pitch][ky] + [0, 0, 1][kx])
                })
                .collect(),
        };
        Layout { bufs, plane, pitch, taps }
    }

    pub(super) fn forward(conv: &DirectConv, x: &[f32], h: usize, w: usize) -> Vec<f32> {
        let (ho, wo) = conv.output_size(h, w);
        let tile = L * if conv.cb == 8 { NV8 } else { NV4 };
        let lay = layout(conv, x, h, w, ho, tile);
        // Every output value is written below.
        let mut out = pool::take(conv.cout * ho * wo);
        let dst = SharedMut(out.as_mut_ptr());
        let tiles = (ho * lay.pitch).div_ceil(tile);
        // Fixed task boundaries (a function of the shape only).
        let per_task = tiles.div_ceil(32).max(1);
        (0..tiles.div_ceil(per_task)).into_par_iter().for_each(|task| {
            let range = task * per_task..((task + 1) * per_task).min(tiles);
            // SAFETY: AVX-512F is present (`DirectConv::new` checked); loads stay inside
            // the padded planes (sized for the last tile at the farthest tap); each tile
            // stores only its own output pixels.
            unsafe {
                match (conv.cb, conv.k) {
                    (8, 3) => tiles_of::<8, NV8, 9>(conv, &lay, range, ho, wo, dst),
                    (8, _) => tiles_of::<8, NV8, 1>(conv, &lay, range, ho, wo, dst),
                    (_, 3) => tiles_of::<4, NV4, 9>(conv, &lay, range, ho, wo, dst),
                    _ => tiles_of::<4, NV4, 1>(conv, &lay, range, ho, wo, dst),
                }
            }
        });
        lay.bufs.into_iter().for_each(pool::give);
        out
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
        let mut out = Segments { n: 0, seg: [(0, 0); L] };
        let (mut oy, mut ox, mut lane) = (f / pitch, f % pitch, 0);
        while lane < L && oy < ho {
            let in_row = (pitch - ox).min(L - lane);
            if ox < wo {
                let valid = (wo - ox).min(in_row);
                let mask = (((1u32 << valid) - 1) << lane) as __mmask16;
                out.seg[out.n] = ((oy * wo + ox) as isize - lane as isize, mask);
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
        let mut srcs = [std::ptr::null::<f32>(); TAPS];
        for (p, &(buf, off)) in srcs.iter_mut().zip(&lay.taps) {
            *p = lay.bufs[buf].as_ptr().add(off);
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
                        let src = src.add(ci * lay.plane + f0);
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
