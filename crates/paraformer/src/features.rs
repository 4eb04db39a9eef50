//! Per-image matcher inputs (SPEC §1): keypoints, scores, descriptors, image size;
//! their validation and the SuperGlue keypoint normalisation.

use std::path::Path;

use safetensors::{Dtype, SafeTensors};

use crate::error::{Error, Result};

/// How far outside the image a keypoint may lie, as a fraction of the larger side
/// (plus one pixel): room for border conventions, resized extraction and the SPEC test
/// vectors (up to 7.3% outside), yet a swapped (height, width) of a 4:3 image is caught.
pub const KEYPOINT_MARGIN: f32 = 0.1;

/// Keypoints and descriptors of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct Features {
    /// `[K, 2]` pixel coordinates `(x, y)`.
    pub keypoints: Vec<[f32; 2]>,
    /// `[K]` detection scores (1.0 when the detector has none).
    pub scores: Vec<f32>,
    /// `[K, D]` descriptors, row-major.
    pub descriptors: Vec<f32>,
    /// `D`, the width of one descriptor.
    pub descriptor_dim: usize,
    /// `(width, height)` of the image in pixels.
    pub image_size: (f32, f32),
}

impl Features {
    /// Builds features; `scores = None` means 1.0 for every keypoint.
    pub fn new(
        keypoints: Vec<[f32; 2]>,
        scores: Option<Vec<f32>>,
        descriptors: Vec<f32>,
        descriptor_dim: usize,
        image_size: (f32, f32),
    ) -> Self {
        let scores = scores.unwrap_or_else(|| vec![1.0; keypoints.len()]);
        Self { keypoints, scores, descriptors, descriptor_dim, image_size }
    }

    /// `k` random keypoints in a 640×480 image with random `d`-wide descriptors and
    /// scores, from a SplitMix64 stream: inputs for benchmarks and tests (they match
    /// nothing meaningful).
    pub fn random(k: usize, d: usize, seed: u64) -> Self {
        let mut rng = crate::pooling::SplitMix64::new(seed);
        let mut next = move || (rng.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
        let kpts = (0..k).map(|_| [next() * 640.0, next() * 480.0]).collect();
        let scores = (0..k).map(|_| next()).collect();
        let desc = (0..k * d).map(|_| next() - 0.5).collect();
        Features::new(kpts, Some(scores), desc, d, (640.0, 480.0))
    }

    /// Number of keypoints `K`.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// True when there are no keypoints.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }

    /// Checks shapes against `descriptor_dim`, that every value is finite and that the
    /// keypoints lie within `image_size` (up to a margin of [`KEYPOINT_MARGIN`]).
    /// `image` (0 or 1) is appended to argument names in errors, e.g. `descriptors1`.
    pub fn validate(&self, descriptor_dim: usize, image: usize) -> Result<()> {
        let k = self.len();
        let name = |a: &str| format!("{a}{image}");
        if self.scores.len() != k {
            return Err(Error::input(name("scores"), format!("expected shape [{k}], got [{}]", self.scores.len())));
        }
        if self.descriptor_dim != descriptor_dim {
            return Err(Error::input(
                name("descriptors"),
                format!("expected shape [{k}, {descriptor_dim}] (descriptor_dim of the model), got [{k}, {}]", self.descriptor_dim),
            ));
        }
        if self.descriptors.len() != k * descriptor_dim {
            return Err(Error::input(
                name("descriptors"),
                format!("expected shape [{k}, {descriptor_dim}] = {} values, got {} values", k * descriptor_dim, self.descriptors.len()),
            ));
        }
        let (w, h) = self.image_size;
        if !(w.is_finite() && h.is_finite() && w > 0.0 && h > 0.0) {
            return Err(Error::input(name("image_size"), format!("expected a positive finite (width, height), got ({w}, {h})")));
        }
        if let Some(i) = self.keypoints.iter().position(|p| !(p[0].is_finite() && p[1].is_finite())) {
            return Err(Error::input(name("keypoints"), format!("row {i} is not finite (NaN or Inf)")));
        }
        // Far outside the image means the size or the coordinates are wrong (a swapped
        // (height, width), another image's size, normalised keypoints): the positional
        // encoding would then silently mislead the match. Edge conventions fit the margin.
        let margin = KEYPOINT_MARGIN * w.max(h) + 1.0;
        if let Some(i) = self.keypoints.iter().position(|p| p[0] < -margin || p[0] > w + margin || p[1] < -margin || p[1] > h + margin) {
            let [x, y] = self.keypoints[i];
            return Err(Error::input(
                name("keypoints"),
                format!(
                    "row {i} ({x}, {y}) lies outside the {w} × {h} image; expected pixel coordinates (x, y) within it \
                     and the size of the image they were detected in, as (width, height)"
                ),
            ));
        }
        if let Some(i) = self.scores.iter().position(|s| !s.is_finite()) {
            return Err(Error::input(name("scores"), format!("entry {i} is not finite (NaN or Inf)")));
        }
        if let Some(i) = self.descriptors.iter().position(|d| !d.is_finite()) {
            return Err(Error::input(name("descriptors"), format!("row {} is not finite (NaN or Inf)", i / descriptor_dim.max(1))));
        }
        Ok(())
    }

    /// `[(x−cx)/s, (y−cy)/s, score]` per keypoint, `c = (w/2, h/2)`, `s = 0.7·max(w, h)`.
    pub fn normalized_positions(&self) -> Vec<f32> {
        let (w, h) = self.image_size;
        let (cx, cy, scale) = (w / 2.0, h / 2.0, 0.7 * w.max(h));
        self.keypoints
            .iter()
            .zip(&self.scores)
            .flat_map(|(p, &s)| [(p[0] - cx) / scale, (p[1] - cy) / scale, s])
            .collect()
    }
}

/// Little-endian `f32` values from raw tensor bytes (a trailing partial value is ignored).
pub fn f32_from_le(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

/// The shape and values of an `F32` tensor, `None` when absent, an error naming the
/// tensor when it has another dtype.
pub(crate) fn f32_tensor(st: &SafeTensors, name: &str) -> Result<Option<(Vec<usize>, Vec<f32>)>> {
    let Ok(view) = st.tensor(name) else { return Ok(None) };
    if view.dtype() != Dtype::F32 {
        return Err(Error::input(name, format!("expected F32, got {:?}", view.dtype())));
    }
    Ok(Some((view.shape().to_vec(), f32_from_le(view.data()))))
}

/// One image's features stored as `keypoints` `[K, 2]`, `descriptors` `[K, D]`,
/// `image_size` `[2]` and optional `scores` `[K]`, under the names `name(field)` —
/// the layout of pair files and of features files.
pub(crate) fn features_from_safetensors(st: &SafeTensors, name: impl Fn(&str) -> String) -> Result<Features> {
    let need = |field: &str| -> Result<(Vec<usize>, Vec<f32>)> {
        let n = name(field);
        f32_tensor(st, &n)?.ok_or_else(|| Error::input(n, "missing"))
    };
    let (kshape, k) = need("keypoints")?;
    if kshape.len() != 2 || kshape[1] != 2 {
        return Err(Error::input(name("keypoints"), format!("expected shape [K, 2], got {kshape:?}")));
    }
    let (dshape, d) = need("descriptors")?;
    if dshape.len() != 2 {
        return Err(Error::input(name("descriptors"), format!("expected shape [K, D], got {dshape:?}")));
    }
    let (_, size) = need("image_size")?;
    if size.len() != 2 {
        return Err(Error::input(name("image_size"), "expected 2 values (width, height)"));
    }
    let scores = f32_tensor(st, &name("scores"))?.map(|(_, s)| s);
    let kpts = k.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
    Ok(Features::new(kpts, scores, d, dshape[1], (size[0], size[1])))
}

/// Reads a pair file: a safetensors file with `keypoints0/1` `[K,2]`, `scores0/1` `[K]`
/// (optional), `descriptors0/1` `[K,D]` and `image_size0/1` `[2]` (width, height),
/// all f32 — the input format of the SPEC test vectors.
pub fn read_pair_file(path: impl AsRef<Path>) -> Result<(Features, Features)> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| Error::Io { path: path.to_path_buf(), source })?;
    read_pair_bytes(&bytes)
}

/// [`read_pair_file`] from bytes.
pub fn read_pair_bytes(bytes: &[u8]) -> Result<(Features, Features)> {
    let st = SafeTensors::deserialize(bytes).map_err(|e| Error::WeightsFormat(e.to_string()))?;
    let one = |i: usize| features_from_safetensors(&st, |field| format!("{field}{i}"));
    Ok((one(0)?, one(1)?))
}
