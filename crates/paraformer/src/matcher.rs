//! The matcher network and its public entry point: encoder (SPEC §3), attention
//! body (SPEC §5–§7), final projection and optimal matching layer (SPEC §8).

use std::path::Path;

use candle_core::{Device, Module, Tensor};
use candle_nn::{Linear, VarBuilder};

use crate::config::{Config, ModelKind};
use crate::error::{Error, Result};
use crate::features::Features;
use crate::layers::{ParallelLayer, SerialLayer};
use crate::pooling::{Pool, Unpool};
use crate::sinkhorn::{extract_matches, log_optimal_transport, Matches, Matrix};
use crate::wave_pe::PositionEncoder;
use crate::weights::Weights;

/// ParaFormer-U's body: five stages, two pools and two unpools.
#[derive(Debug, Clone)]
pub struct UNet {
    stages: Vec<Vec<ParallelLayer>>,
    pools: Vec<Pool>,
    unpools: Vec<Unpool>,
}

impl UNet {
    pub fn new(cfg: &Config, vb: VarBuilder) -> candle_core::Result<Self> {
        let (dims, heads) = (&cfg.stage_dims, cfg.num_heads);
        let stages = (0..5)
            .map(|s| {
                (0..cfg.stage_depths[s])
                    .map(|j| ParallelLayer::new(dims[s], heads, cfg.parallel, vb.pp(format!("stages.{s}.layers.{j}"))))
                    .collect()
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let pools = (0..2)
            .map(|p| Pool::new(dims[p], dims[p + 1], cfg.pooling, cfg.pooling_seed, p, vb.pp(format!("pools.{p}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let unpools = (0..2)
            .map(|q| Unpool::new(dims[q + 2], dims[q + 3], vb.pp(format!("unpools.{q}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self { stages, pools, unpools })
    }

    /// Runs a stage; returns the features and the last layer's self-attention probabilities.
    fn stage(&self, s: usize, x: Tensor, y: Tensor) -> candle_core::Result<(Tensor, Tensor, Option<(Tensor, Tensor)>)> {
        let (mut x, mut y, mut probs) = (x, y, None);
        for layer in &self.stages[s] {
            let o = layer.forward(&x, &y)?;
            (x, y, probs) = (o.x, o.y, Some((o.self_probs_x, o.self_probs_y)));
        }
        Ok((x, y, probs))
    }

    pub fn forward(&self, x: &Tensor, y: &Tensor) -> candle_core::Result<(Tensor, Tensor)> {
        let (mut x, mut y) = (x.clone(), y.clone());
        let mut skips = Vec::with_capacity(2);
        let mut indices = Vec::with_capacity(2);
        for p in 0..2 {
            let (sx, sy, probs) = self.stage(p, x, y)?;
            let (px, py) = (probs.as_ref().map(|p| &p.0), probs.as_ref().map(|p| &p.1));
            let (nx, ix) = self.pools[p].forward(&sx, px, 0)?;
            let (ny, iy) = self.pools[p].forward(&sy, py, 1)?;
            skips.push((sx, sy));
            indices.push((ix, iy));
            (x, y) = (nx, ny);
        }
        for q in 0..2 {
            let (sx, sy, _) = self.stage(2 + q, x, y)?;
            let (skip_x, skip_y) = &skips[1 - q];
            let (ix, iy) = &indices[1 - q];
            x = self.unpools[q].forward(&sx, ix, skip_x)?;
            y = self.unpools[q].forward(&sy, iy, skip_y)?;
        }
        let (x, y, _) = self.stage(4, x, y)?;
        Ok((x, y))
    }
}

/// The attention body of each model.
#[derive(Debug, Clone)]
pub enum Body {
    /// `gnn.layers.{l}`.
    Superglue(Vec<SerialLayer>),
    /// `layers.{l}`.
    Paraformer(Vec<ParallelLayer>),
    /// `stages`, `pools`, `unpools`.
    ParaformerU(UNet),
}

/// The whole network, one field per top-level weight prefix.
#[derive(Debug, Clone)]
pub struct Network {
    input_proj: Option<Linear>,
    encoder: PositionEncoder,
    body: Body,
    final_proj: Linear,
    bin_score: f32,
    dim: usize,
}

impl Network {
    pub fn new(cfg: &Config, vb: VarBuilder) -> candle_core::Result<Self> {
        let c = cfg.model_dim();
        let input_proj =
            if cfg.descriptor_dim != c { Some(candle_nn::linear(cfg.descriptor_dim, c, vb.pp("input_proj"))?) } else { None };
        let encoder = PositionEncoder::new(cfg.positional_encoding, c, vb.clone())?;
        let body = match cfg.model {
            ModelKind::Superglue => Body::Superglue(
                cfg.layer_names
                    .iter()
                    .enumerate()
                    .map(|(l, &kind)| SerialLayer::new(c, cfg.num_heads, kind, vb.pp(format!("gnn.layers.{l}"))))
                    .collect::<candle_core::Result<_>>()?,
            ),
            ModelKind::Paraformer => Body::Paraformer(
                (0..cfg.num_layers)
                    .map(|l| ParallelLayer::new(c, cfg.num_heads, cfg.parallel, vb.pp(format!("layers.{l}"))))
                    .collect::<candle_core::Result<_>>()?,
            ),
            ModelKind::ParaformerU => Body::ParaformerU(UNet::new(cfg, vb.clone())?),
        };
        let final_proj = candle_nn::linear(c, c, vb.pp("final_proj"))?;
        let bin_score = vb.get((), "bin_score")?.to_scalar::<f32>()?;
        Ok(Self { input_proj, encoder, body, final_proj, bin_score, dim: c })
    }

    fn embed(&self, f: &Features) -> candle_core::Result<Tensor> {
        let dev = Device::Cpu;
        let mut d = Tensor::from_slice(&f.descriptors, (f.len(), f.descriptor_dim), &dev)?;
        if let Some(p) = &self.input_proj {
            d = p.forward(&d)?;
        }
        let pos = Tensor::from_vec(f.normalized_positions(), (f.len(), 3), &dev)?;
        self.encoder.forward(&d, &pos)
    }

    /// The score matrix `S = mdx·mdyᵀ / sqrt(C)` `[M, N]`, row-major.
    pub fn scores(&self, f0: &Features, f1: &Features) -> candle_core::Result<Vec<f32>> {
        let (x, y) = (self.embed(f0)?, self.embed(f1)?);
        let (x, y) = match &self.body {
            Body::Superglue(layers) => layers.iter().try_fold((x, y), |(x, y), l| l.forward(&x, &y))?,
            Body::Paraformer(layers) => layers.iter().try_fold((x, y), |(x, y), l| {
                let o = l.forward(&x, &y)?;
                Ok::<_, candle_core::Error>((o.x, o.y))
            })?,
            Body::ParaformerU(unet) => unet.forward(&x, &y)?,
        };
        let (mx, my) = (self.final_proj.forward(&x)?, self.final_proj.forward(&y)?);
        let s = (mx.matmul(&my.t()?)? / (self.dim as f64).sqrt())?;
        s.flatten_all()?.to_vec1()
    }
}

/// Options of one `match_pair` call.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MatchOptions {
    /// Also return the `[M+1, N+1]` log assignment.
    pub return_log_assignment: bool,
}

/// The result of matching two images.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchOutput {
    /// `[M]` index into image 1 for each keypoint of image 0, −1 if unmatched.
    pub matches0: Vec<i64>,
    /// `[N]` index into image 0 for each keypoint of image 1, −1 if unmatched.
    pub matches1: Vec<i64>,
    /// `[M]` match confidence (0 where not mutual).
    pub matching_scores0: Vec<f32>,
    /// `[N]` match confidence (0 where not mutual).
    pub matching_scores1: Vec<f32>,
    /// `[M+1, N+1]` log assignment including dustbins, when asked for.
    pub log_assignment: Option<Matrix>,
}

impl MatchOutput {
    /// Matched index pairs `(i, j)`, in order of `i`.
    pub fn pairs(&self) -> Vec<(usize, usize)> {
        self.matches0
            .iter()
            .enumerate()
            .filter_map(|(i, &j)| usize::try_from(j).ok().map(|j| (i, j)))
            .collect()
    }
}

/// A loaded matcher (SuperGlue, ParaFormer or ParaFormer-U). `Send + Sync`: share it
/// between threads freely.
#[derive(Debug, Clone)]
pub struct Matcher {
    config: Config,
    network: Network,
}

impl Matcher {
    /// Loads a weights file whose metadata holds the config.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self> {
        Self::from_weights(&Weights::from_file(path)?)
    }

    /// Loads safetensors bytes whose metadata holds the config.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        Self::from_weights(&Weights::from_bytes(bytes)?)
    }

    /// Uses the config stored in the weights' metadata.
    pub fn from_weights(weights: &Weights) -> Result<Self> {
        let config = weights.config().cloned().ok_or(Error::MissingConfig)?;
        Self::new(config, weights)
    }

    /// Builds a matcher from an explicit config (the file's metadata is not used).
    pub fn new(config: Config, weights: &Weights) -> Result<Self> {
        config.validate()?;
        let network = weights.build(|vb| Network::new(&config, vb))?;
        Ok(Self { config, network })
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Matches two images with the default options.
    pub fn match_pair(&self, f0: &Features, f1: &Features) -> Result<MatchOutput> {
        self.match_pair_with(f0, f1, MatchOptions::default())
    }

    /// Matches two images. Inputs are validated first; with no keypoints on either side
    /// the network is not run and every match is −1 (the log assignment, if asked
    /// for, is then all zeros: every keypoint lies in the dustbin with probability 1).
    pub fn match_pair_with(&self, f0: &Features, f1: &Features, opts: MatchOptions) -> Result<MatchOutput> {
        f0.validate(self.config.descriptor_dim, 0)?;
        f1.validate(self.config.descriptor_dim, 1)?;
        let (m, n) = (f0.len(), f1.len());
        let (matches, p) = if m == 0 || n == 0 {
            (Matches::none(m, n), Matrix { rows: m + 1, cols: n + 1, data: vec![0.0; (m + 1) * (n + 1)] })
        } else {
            let s = self.network.scores(f0, f1)?;
            let p = log_optimal_transport(&s, m, n, self.network.bin_score, self.config.sinkhorn_iterations);
            (extract_matches(&p, self.config.match_threshold), p)
        };
        Ok(MatchOutput {
            matches0: matches.matches0,
            matches1: matches.matches1,
            matching_scores0: matches.matching_scores0,
            matching_scores1: matches.matching_scores1,
            log_assignment: opts.return_log_assignment.then_some(p),
        })
    }
}
