//! Model configuration (SPEC §9): which matcher, its widths and depths, ablation
//! switches, and the matching-layer parameters. Stored as JSON under the
//! `paraformer.config` metadata key of a weights file.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// The metadata key of a weights file that holds the config JSON.
pub const CONFIG_METADATA_KEY: &str = "paraformer.config";

/// Which network a config describes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelKind {
    /// SuperGlue: serial self/cross attention layers (SPEC §6).
    Superglue,
    /// ParaFormer: parallel attention layers (SPEC §5).
    Paraformer,
    /// ParaFormer-U: a U-Net of parallel layers with pooling (SPEC §7).
    ParaformerU,
}

/// Position encoder (SPEC §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PositionalEncoding {
    /// SuperGlue's keypoint encoder, `kenc.encoder`.
    Mlp,
    /// ParaFormer's Wave-PE, `wave_pe`.
    Wave,
}

/// Pooling of ParaFormer-U (SPEC §7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Pooling {
    /// Column sums of the last self-attention map.
    Attentional,
    /// Graph U-Net's projection score, `pools.{p}.score`.
    Gpool,
    /// Seeded random subset (SplitMix64 Fisher–Yates).
    Random,
}

/// One SuperGlue layer: attention within an image or across the pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LayerKind {
    /// Self-attention within each image (`"self"`).
    #[serde(rename = "self")]
    SelfAttention,
    /// Cross-attention between the images (`"cross"`).
    #[serde(rename = "cross")]
    Cross,
}

/// Sharing switches of the parallel attention layer (the paper's ablation, SPEC §5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ParallelSwitches {
    /// One set of q/k/v projections for self- and cross-attention.
    pub share_qkv: bool,
    /// One merge projection for self- and cross-attention messages.
    pub share_merge: bool,
    /// Cross-attention of Y reuses the transposed score matrix of X.
    pub share_attention_weights: bool,
}

impl Default for ParallelSwitches {
    fn default() -> Self {
        Self { share_qkv: true, share_merge: true, share_attention_weights: true }
    }
}

/// Largest width (descriptor, model, stage) a config may ask for.
pub const MAX_WIDTH: usize = 16_384;
/// Most layers (or layers per stage) a config may ask for.
pub const MAX_LAYERS: usize = 1_024;
/// Most Sinkhorn iterations a config may ask for.
pub const MAX_SINKHORN_ITERATIONS: usize = 100_000;

/// A matcher configuration. Absent JSON fields take the SPEC §9 defaults; unknown
/// fields are an error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawConfig")]
pub struct Config {
    /// Which network.
    pub model: ModelKind,
    /// Width `D` of the input descriptors; `input_proj` exists when `D ≠ C`.
    pub descriptor_dim: usize,
    /// Model width `C` (ignored by ParaFormer-U, whose `C = stage_dims[0]`).
    pub dim: usize,
    /// Attention heads `H`; every width must be divisible by it.
    pub num_heads: usize,
    /// Number of parallel layers (ParaFormer).
    pub num_layers: usize,
    /// Serial layer sequence (SuperGlue); its length is the number of layers.
    pub layer_names: Vec<LayerKind>,
    /// Position encoder.
    pub positional_encoding: PositionalEncoding,
    /// Parallel layers per U-Net stage (ParaFormer-U, five stages).
    pub stage_depths: Vec<usize>,
    /// Width per U-Net stage (ParaFormer-U, five stages).
    pub stage_dims: Vec<usize>,
    /// Pooling method of ParaFormer-U.
    pub pooling: Pooling,
    /// Sharing switches of the parallel layers.
    pub parallel: ParallelSwitches,
    /// Seed of random pooling.
    pub pooling_seed: u64,
    /// Sinkhorn iterations of the optimal matching layer.
    pub sinkhorn_iterations: usize,
    /// Minimum matching score of a kept match.
    pub match_threshold: f32,
}

/// The JSON form: every field optional so that absent ones take defaults.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    model: Option<ModelKind>,
    descriptor_dim: Option<usize>,
    dim: Option<usize>,
    num_heads: Option<usize>,
    num_layers: Option<usize>,
    layer_names: Option<Vec<LayerKind>>,
    positional_encoding: Option<PositionalEncoding>,
    stage_depths: Option<Vec<usize>>,
    stage_dims: Option<Vec<usize>>,
    pooling: Option<Pooling>,
    parallel: Option<ParallelSwitches>,
    pooling_seed: Option<u64>,
    sinkhorn_iterations: Option<usize>,
    match_threshold: Option<f32>,
}

impl TryFrom<RawConfig> for Config {
    type Error = String;

    fn try_from(r: RawConfig) -> std::result::Result<Self, String> {
        let model = r.model.unwrap_or(ModelKind::Paraformer);
        let d = Config::defaults(model);
        let cfg = Config {
            model,
            descriptor_dim: r.descriptor_dim.unwrap_or(d.descriptor_dim),
            dim: r.dim.unwrap_or(d.dim),
            num_heads: r.num_heads.unwrap_or(d.num_heads),
            num_layers: r.num_layers.unwrap_or(d.num_layers),
            layer_names: r.layer_names.unwrap_or(d.layer_names),
            positional_encoding: r.positional_encoding.unwrap_or(d.positional_encoding),
            stage_depths: r.stage_depths.unwrap_or(d.stage_depths),
            stage_dims: r.stage_dims.unwrap_or(d.stage_dims),
            pooling: r.pooling.unwrap_or(d.pooling),
            parallel: r.parallel.unwrap_or(d.parallel),
            pooling_seed: r.pooling_seed.unwrap_or(d.pooling_seed),
            sinkhorn_iterations: r.sinkhorn_iterations.unwrap_or(d.sinkhorn_iterations),
            match_threshold: r.match_threshold.unwrap_or(d.match_threshold),
        };
        cfg.validate().map_err(|e| match e {
            Error::Config(s) => s,
            other => other.to_string(),
        })?;
        Ok(cfg)
    }
}

impl Config {
    /// SPEC §9 defaults for a model kind (full paper widths).
    fn defaults(model: ModelKind) -> Config {
        Config {
            model,
            descriptor_dim: 256,
            dim: 256,
            num_heads: 4,
            num_layers: 9,
            layer_names: [LayerKind::SelfAttention, LayerKind::Cross].repeat(9),
            positional_encoding: match model {
                ModelKind::Superglue => PositionalEncoding::Mlp,
                _ => PositionalEncoding::Wave,
            },
            stage_depths: vec![2, 1, 2, 1, 2],
            stage_dims: vec![256, 384, 128, 384, 256],
            pooling: Pooling::Attentional,
            parallel: ParallelSwitches::default(),
            pooling_seed: 0,
            sinkhorn_iterations: 100,
            match_threshold: 0.2,
        }
    }

    /// SuperGlue at the paper's width: MLP-PE and 18 alternating serial layers.
    pub fn superglue() -> Config {
        Config::defaults(ModelKind::Superglue)
    }

    /// ParaFormer at the paper's width: Wave-PE and 9 parallel layers.
    pub fn paraformer() -> Config {
        Config::defaults(ModelKind::Paraformer)
    }

    /// ParaFormer-U at the paper's widths: stages `[2,1,2,1,2]` × `[256,384,128,384,256]`.
    pub fn paraformer_u() -> Config {
        Config::defaults(ModelKind::ParaformerU)
    }

    /// A preset by name: `superglue`, `paraformer` or `paraformer_u` (`paraformer-u`).
    pub fn preset(name: &str) -> Result<Config> {
        match name {
            "superglue" => Ok(Config::superglue()),
            "paraformer" => Ok(Config::paraformer()),
            "paraformer_u" | "paraformer-u" => Ok(Config::paraformer_u()),
            other => Err(Error::Config(format!(
                "unknown preset `{other}`; expected one of superglue, paraformer, paraformer_u"
            ))),
        }
    }

    /// Parses a config from JSON (absent fields take the defaults).
    pub fn from_json(json: &str) -> Result<Config> {
        serde_json::from_str(json).map_err(|e| Error::Config(e.to_string()))
    }

    /// The config as JSON, with every field written out.
    pub fn to_json(&self) -> String {
        // Serialising plain data to a String cannot fail.
        serde_json::to_string(self).unwrap_or_default()
    }

    /// JSON of the fields this model uses (`to_json` writes every field): SuperGlue has no
    /// stages, pooling or parallel switches; ParaFormer no `layer_names` or stages;
    /// ParaFormer-U no `dim`, `num_layers` or `layer_names`. Reading it back with
    /// [`Config::from_json`] gives the same model.
    pub fn to_json_used(&self) -> String {
        let mut v = serde_json::to_value(self).unwrap_or_default();
        let unused: &[&str] = match self.model {
            ModelKind::Superglue => &["stage_depths", "stage_dims", "pooling", "pooling_seed", "parallel", "num_layers"],
            ModelKind::Paraformer => &["layer_names", "stage_depths", "stage_dims", "pooling", "pooling_seed"],
            ModelKind::ParaformerU => &["dim", "num_layers", "layer_names"],
        };
        if let Some(map) = v.as_object_mut() {
            for k in unused {
                map.remove(*k);
            }
        }
        v.to_string()
    }

    /// The model width `C` that the encoder and `final_proj` use.
    pub fn model_dim(&self) -> usize {
        match self.model {
            ModelKind::ParaformerU => self.stage_dims.first().copied().unwrap_or(0),
            _ => self.dim,
        }
    }

    /// Checks that the widths and depths describe a buildable network.
    pub fn validate(&self) -> Result<()> {
        let err = |s: String| Err(Error::Config(s));
        // Bounds far above any real model, checked before anything is allocated.
        let too_big = |name: &str, v: usize, max: usize| -> Result<()> {
            if v > max {
                return Err(Error::Config(format!("{name} = {v} is beyond the supported maximum of {max}")));
            }
            Ok(())
        };
        too_big("descriptor_dim", self.descriptor_dim, MAX_WIDTH)?;
        too_big("dim", self.dim, MAX_WIDTH)?;
        too_big("num_heads", self.num_heads, MAX_WIDTH)?;
        too_big("num_layers", self.num_layers, MAX_LAYERS)?;
        too_big("layer_names (count)", self.layer_names.len(), MAX_LAYERS)?;
        too_big("sinkhorn_iterations", self.sinkhorn_iterations, MAX_SINKHORN_ITERATIONS)?;
        for (s, (&c, &d)) in self.stage_dims.iter().zip(&self.stage_depths).enumerate() {
            too_big(&format!("stage_dims[{s}]"), c, MAX_WIDTH)?;
            too_big(&format!("stage_depths[{s}]"), d, MAX_LAYERS)?;
        }
        if self.num_heads == 0 {
            return err("num_heads must be at least 1".into());
        }
        if self.descriptor_dim == 0 {
            return err("descriptor_dim must be at least 1".into());
        }
        if !self.match_threshold.is_finite() {
            return err(format!("match_threshold must be finite, got {}", self.match_threshold));
        }
        let check_width = |name: &str, c: usize| -> Result<()> {
            if c == 0 || !c.is_multiple_of(self.num_heads) {
                return Err(Error::Config(format!(
                    "{name} = {c} must be a positive multiple of num_heads = {}",
                    self.num_heads
                )));
            }
            Ok(())
        };
        match self.model {
            ModelKind::ParaformerU => {
                if self.stage_dims.len() != 5 || self.stage_depths.len() != 5 {
                    return err(format!(
                        "paraformer_u needs 5 stage_dims and 5 stage_depths, got {} and {}",
                        self.stage_dims.len(),
                        self.stage_depths.len()
                    ));
                }
                for (s, &c) in self.stage_dims.iter().enumerate() {
                    check_width(&format!("stage_dims[{s}]"), c)?;
                }
                // Skip connections add stage 1 to stage 3 and stage 0 to stage 4.
                if self.stage_dims[1] != self.stage_dims[3] || self.stage_dims[0] != self.stage_dims[4] {
                    return err(format!(
                        "stage_dims {:?} must satisfy dims[1] == dims[3] and dims[0] == dims[4] for the skip connections",
                        self.stage_dims
                    ));
                }
                // Attentional pooling reads the last self-attention map of stages 0 and 1.
                if self.pooling == Pooling::Attentional && (self.stage_depths[0] == 0 || self.stage_depths[1] == 0) {
                    return err(format!(
                        "attentional pooling needs stage_depths[0] and stage_depths[1] >= 1, got {:?}",
                        self.stage_depths
                    ));
                }
            }
            _ => check_width("dim", self.dim)?,
        }
        if self.positional_encoding == PositionalEncoding::Wave && self.model_dim() < 2 {
            return err("Wave-PE needs a model width of at least 2".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn absent_fields_take_spec_defaults() {
        let c = Config::from_json(r#"{"model": "superglue"}"#).expect("valid");
        assert_eq!(c, Config::superglue());
        assert_eq!(c.positional_encoding, PositionalEncoding::Mlp);
        assert_eq!(c.layer_names.len(), 18);
        let p = Config::from_json("{}").expect("valid");
        assert_eq!(p.model, ModelKind::Paraformer);
        assert_eq!(p.positional_encoding, PositionalEncoding::Wave);
        assert_eq!((p.sinkhorn_iterations, p.match_threshold, p.num_layers), (100, 0.2, 9));
        let u = Config::from_json(r#"{"model": "paraformer_u", "parallel": {"share_qkv": false}}"#).expect("valid");
        assert_eq!(u.model_dim(), 256);
        assert!(!u.parallel.share_qkv && u.parallel.share_merge);
    }

    #[test]
    fn json_round_trip_and_presets() {
        for name in ["superglue", "paraformer", "paraformer_u"] {
            let c = Config::preset(name).expect("preset");
            assert_eq!(Config::from_json(&c.to_json()).expect("round trip"), c);
        }
        assert!(Config::preset("lightglue").is_err());
    }

    #[test]
    fn bad_values_are_named() {
        let e = Config::from_json(r#"{"dim": 30, "num_heads": 4}"#).expect_err("30 % 4 != 0");
        assert!(e.to_string().contains("dim = 30"), "{e}");
        let e = Config::from_json(r#"{"model": "paraformer_u", "stage_dims": [8, 16, 8, 12, 8]}"#).expect_err("skip dims");
        assert!(e.to_string().contains("skip"), "{e}");
        let e = Config::from_json(r#"{"pooling": "max"}"#).expect_err("unknown variant");
        assert!(e.to_string().contains("max"), "{e}");
    }
}
