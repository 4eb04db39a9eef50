//! The matcher network and its public entry point: encoder (SPEC §3), attention
//! body (SPEC §5–§7), final projection and optimal matching layer (SPEC §8).

use std::path::Path;

use std::time::Instant;

use candle_nn::VarBuilder;

use crate::config::{Config, ModelKind};
use crate::error::{Error, Result};
use crate::features::Features;
use crate::kernels::{Ctx, Matrix, Precision};
use crate::layers::{ParallelLayer, SerialLayer};
use crate::mlp::Linear;
use crate::pooling::{Pool, Unpool};
use crate::sinkhorn::{extract_matches, log_optimal_transport_inplace, log_optimal_transport_inplace_bf16, Matches};
use crate::wave_pe::PositionEncoder;
use crate::weights::Weights;

/// ParaFormer-U's body: five stages, two pools and two unpools.
#[derive(Debug, Clone)]
pub struct UNet {
    stages: Vec<Vec<ParallelLayer>>,
    pools: Vec<Pool>,
    unpools: Vec<Unpool>,
}

/// Features of both images and, when asked for, the last self-attention column sums.
type StageOutput = (Matrix, Matrix, Option<(Vec<f32>, Vec<f32>)>);

impl UNet {
    /// Builds the five stages and their poolings from `vb` (SPEC §6).
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
            .map(|p| Pool::new(dims[p], dims[p + 1], cfg, p, vb.pp(format!("pools.{p}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let unpools = (0..2)
            .map(|q| Unpool::new(dims[q + 2], dims[q + 3], vb.pp(format!("unpools.{q}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self { stages, pools, unpools })
    }

    /// Runs stage `s`; with `col_sums`, returns the last layer's self-attention column sums.
    fn stage(&self, ctx: &Ctx, s: usize, x: Matrix, y: Matrix, col_sums: bool) -> Result<StageOutput> {
        let (mut x, mut y, mut sums) = (x, y, None);
        let depth = self.stages[s].len();
        for (j, layer) in self.stages[s].iter().enumerate() {
            let o = layer.forward(ctx, &x, &y, col_sums && j + 1 == depth)?;
            (x, y, sums) = (o.x, o.y, o.col_sums);
        }
        Ok((x, y, sums))
    }

    /// Runs the U-Net on the features of both images.
    pub fn forward(&self, ctx: &Ctx, x: Matrix, y: Matrix) -> Result<(Matrix, Matrix)> {
        let (mut x, mut y) = (x, y);
        let mut skips = Vec::with_capacity(2);
        let mut indices = Vec::with_capacity(2);
        for p in 0..2 {
            let pool = &self.pools[p];
            let (sx, sy, sums) = self.stage(ctx, p, x, y, pool.needs_col_sums())?;
            let (cx, cy) = (sums.as_ref().map(|s| s.0.as_slice()), sums.as_ref().map(|s| s.1.as_slice()));
            let (nx, ix) = pool.forward(ctx, &sx, cx, 0)?;
            let (ny, iy) = pool.forward(ctx, &sy, cy, 1)?;
            skips.push((sx, sy));
            indices.push((ix, iy));
            (x, y) = (nx, ny);
        }
        for q in 0..2 {
            let (sx, sy, _) = self.stage(ctx, 2 + q, x, y, false)?;
            let (skip_x, skip_y) = &skips[1 - q];
            let (ix, iy) = &indices[1 - q];
            x = self.unpools[q].forward(ctx, &sx, ix, skip_x)?;
            y = self.unpools[q].forward(ctx, &sy, iy, skip_y)?;
        }
        let (x, y, _) = self.stage(ctx, 4, x, y, false)?;
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

/// Wall-clock seconds per part of one `match_pair`, and the multiply-accumulates done.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Profile {
    /// `input_proj` and position encoder, both images.
    pub encoder: f64,
    /// Attention layers (and ParaFormer-U's pooling).
    pub layers: f64,
    /// `final_proj` and the score matrix.
    pub final_projection: f64,
    /// Sinkhorn iterations.
    pub sinkhorn: f64,
    /// Match extraction.
    pub extraction: f64,
    /// Multiply-accumulates of every matrix product performed.
    pub macs: u64,
}

impl Profile {
    /// Seconds of the whole call.
    pub fn total(&self) -> f64 {
        self.encoder + self.layers + self.final_projection + self.sinkhorn + self.extraction
    }

    /// Everything but Sinkhorn and match extraction.
    pub fn network(&self) -> f64 {
        self.encoder + self.layers + self.final_projection
    }
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
    /// Builds the network of `cfg` from `vb` (tensor names as SPEC §2).
    pub fn new(cfg: &Config, vb: VarBuilder) -> candle_core::Result<Self> {
        let c = cfg.model_dim();
        let input_proj =
            if cfg.descriptor_dim != c { Some(Linear::new(cfg.descriptor_dim, c, vb.pp("input_proj"))?) } else { None };
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
        let final_proj = Linear::new(c, c, vb.pp("final_proj"))?;
        let bin_score = vb.get((), "bin_score")?.to_scalar::<f32>()?;
        Ok(Self { input_proj, encoder, body, final_proj, bin_score, dim: c })
    }

    fn embed(&self, ctx: &Ctx, f: &Features) -> Result<Matrix> {
        let mut d = Matrix::from_vec(f.len(), f.descriptor_dim, f.descriptors.clone())?;
        if let Some(p) = &self.input_proj {
            d = p.forward(ctx, d.view())?;
        }
        let pos = Matrix::from_vec(f.len(), 3, f.normalized_positions())?;
        self.encoder.forward(ctx, d, &pos)
    }

    /// The couplings `[M+1, N+1]`: scores `S = mdx·mdyᵀ / sqrt(C)` in the inner block
    /// (the dustbin row and column are left for Sinkhorn to fill).
    pub fn couplings(&self, ctx: &Ctx, f0: &Features, f1: &Features, profile: &mut Profile) -> Result<Matrix> {
        let t = Instant::now();
        let (x, y) = (self.embed(ctx, f0)?, self.embed(ctx, f1)?);
        profile.encoder = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (x, y) = match &self.body {
            Body::Superglue(layers) => layers.iter().try_fold((x, y), |(x, y), l| l.forward(ctx, &x, &y))?,
            Body::Paraformer(layers) => layers.iter().try_fold((x, y), |(x, y), l| {
                let o = l.forward(ctx, &x, &y, false)?;
                Ok::<_, Error>((o.x, o.y))
            })?,
            Body::ParaformerU(unet) => unet.forward(ctx, x, y)?,
        };
        profile.layers = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (mx, my) = (self.final_proj.forward(ctx, x.view())?, self.final_proj.forward(ctx, y.view())?);
        let (m, n) = (mx.rows, my.rows);
        let mut z = Matrix::zeros(m + 1, n + 1);
        let scale = 1.0 / (self.dim as f32).sqrt();
        ctx.gemm(&mut z.data, n + 1, mx.view(), false, my.view(), true, scale, false, true)?;
        profile.final_projection = t.elapsed().as_secs_f64();
        Ok(z)
    }
}

/// Options of one `match_pair` call.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MatchOptions {
    /// Also return the `[M+1, N+1]` log assignment.
    pub return_log_assignment: bool,
    /// Memory limit in bytes for this call (`None`: [`crate::memory::memory_limit`]).
    pub memory_limit: Option<u64>,
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

/// Trained weights embedded in the crate, by name (`training/README.md` tells how they
/// were made; [`Matcher::pretrained`] loads them). Both take XFeat features (64-d).
pub const PRETRAINED: &[(&str, &[u8])] = &[
    ("paraformer-xfeat", include_bytes!("../weights/paraformer-xfeat.safetensors")),
    ("paraformer-u-xfeat", include_bytes!("../weights/paraformer-u-xfeat.safetensors")),
];

/// A loaded matcher (SuperGlue, ParaFormer or ParaFormer-U). `Send + Sync`: share it
/// between threads freely.
#[derive(Debug, Clone)]
pub struct Matcher {
    config: Config,
    network: Network,
    precision: Precision,
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

    /// Embedded trained weights by name (see [`PRETRAINED`]); an unknown name is an
    /// error listing the known ones.
    pub fn pretrained(name: &str) -> Result<Self> {
        match PRETRAINED.iter().find(|(n, _)| *n == name) {
            Some((_, bytes)) => Self::from_bytes(bytes),
            None => Err(Error::input(
                "name",
                format!(
                    "no pretrained matcher `{name}`; available: {}",
                    if PRETRAINED.is_empty() { "none".to_string() } else { PRETRAINED.iter().map(|p| p.0).collect::<Vec<_>>().join(", ") }
                ),
            )),
        }
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
        Ok(Self { config, network, precision: Precision::Fp32 })
    }

    /// A matcher with deterministic random weights (for benchmarks and tests; it
    /// matches nothing meaningful).
    pub fn random(config: Config, seed: u64) -> Result<Self> {
        config.validate()?;
        let network = Network::new(&config, crate::weights::random_var_builder(seed))?;
        Ok(Self { config, network, precision: Precision::Fp32 })
    }

    /// The config in use (every field as the model uses it).
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// This matcher with its attention products in `precision`: [`Precision::Fp32`] (the
    /// default, SPEC's numbers) or [`Precision::Bf16`] (bf16 operands, fp32 accumulation,
    /// on CPUs with AVX-512 BF16; elsewhere it runs as fp32).
    pub fn with_precision(mut self, precision: Precision) -> Self {
        self.precision = precision;
        self
    }

    /// Sets the precision in place (see [`Matcher::with_precision`]).
    pub fn set_precision(&mut self, precision: Precision) {
        self.precision = precision;
    }

    /// The precision asked for (what runs is [`Precision::effective`] of it).
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Bytes a match of `m` × `n` keypoints needs at its peak; a call whose need exceeds
    /// the memory limit returns [`Error::Resource`] before allocating.
    pub fn memory_needed(&self, m: usize, n: usize) -> u64 {
        crate::memory::match_bytes(&self.config, m, n, rayon::current_num_threads())
    }

    /// Matches two images with the default options.
    pub fn match_pair(&self, f0: &Features, f1: &Features) -> Result<MatchOutput> {
        self.match_pair_with(f0, f1, MatchOptions::default())
    }

    /// Matches two images. Inputs are validated first; with no keypoints on either side
    /// the network is not run and every match is −1 (the log assignment, if asked
    /// for, is then all zeros: every keypoint lies in the dustbin with probability 1).
    pub fn match_pair_with(&self, f0: &Features, f1: &Features, opts: MatchOptions) -> Result<MatchOutput> {
        Ok(self.run(f0, f1, opts)?.0)
    }

    /// Like [`Matcher::match_pair_with`], also returning where the time went and the
    /// multiply-accumulates performed.
    pub fn profile(&self, f0: &Features, f1: &Features, opts: MatchOptions) -> Result<(MatchOutput, Profile)> {
        self.run(f0, f1, opts)
    }

    fn run(&self, f0: &Features, f1: &Features, opts: MatchOptions) -> Result<(MatchOutput, Profile)> {
        f0.validate(self.config.descriptor_dim, 0)?;
        f1.validate(self.config.descriptor_dim, 1)?;
        let (m, n) = (f0.len(), f1.len());
        let mut profile = Profile::default();
        let limit = opts.memory_limit.unwrap_or_else(crate::memory::memory_limit);
        let needed = self.memory_needed(m, n);
        crate::memory::check(format!("a match of {m} × {n} keypoints"), needed, limit)?;
        let (matches, p) = if m == 0 || n == 0 {
            (Matches::none(m, n), Matrix::zeros(m + 1, n + 1))
        } else {
            let ctx = Ctx::with_precision(self.precision);
            let mut z = self.network.couplings(&ctx, f0, f1, &mut profile)?;
            profile.macs = ctx.macs();
            let t = Instant::now();
            if ctx.precision == Precision::Bf16 {
                log_optimal_transport_inplace_bf16(&mut z, self.network.bin_score, self.config.sinkhorn_iterations);
            } else {
                log_optimal_transport_inplace(&mut z, self.network.bin_score, self.config.sinkhorn_iterations);
            }
            profile.sinkhorn = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let matches = extract_matches(&z, self.config.match_threshold);
            profile.extraction = t.elapsed().as_secs_f64();
            (matches, z)
        };
        let out = MatchOutput {
            matches0: matches.matches0,
            matches1: matches.matches1,
            matching_scores0: matches.matching_scores0,
            matching_scores1: matches.matching_scores1,
            log_assignment: opts.return_log_assignment.then_some(p),
        };
        Ok((out, profile))
    }
}
