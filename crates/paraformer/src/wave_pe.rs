//! Position encoders (SPEC §3): SuperGlue's MLP keypoint encoder and ParaFormer's
//! Wave-PE (paper §"Wave-PE": amplitude from descriptors, phase from positions).

use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

use crate::config::PositionalEncoding;
use crate::mlp::{cat_channels, Mlp};

/// MLP-PE, prefix `kenc`: `x⁰ = d + MLP([3, 32, 64, 128, 256, C])(p)`.
#[derive(Debug, Clone)]
pub struct KeypointEncoder {
    encoder: Mlp,
}

impl KeypointEncoder {
    pub fn new(c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { encoder: Mlp::new(&[3, 32, 64, 128, 256, c], vb.pp("encoder"))? })
    }

    pub fn forward(&self, desc: &Tensor, pos: &Tensor) -> Result<Tensor> {
        desc + self.encoder.forward(pos)?
    }
}

/// Wave-PE, prefix `wave_pe`: `x⁰ = d + fuse([A⊙cos θ, A⊙sin θ])`.
#[derive(Debug, Clone)]
pub struct WavePe {
    amplitude: Mlp,
    phase: Mlp,
    fuse: Mlp,
}

impl WavePe {
    pub fn new(c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            amplitude: Mlp::new(&[c, 4 * c, c], vb.pp("amplitude"))?,
            phase: Mlp::new(&[3, c / 2, c], vb.pp("phase"))?,
            fuse: Mlp::new(&[2 * c, 4 * c, c], vb.pp("fuse"))?,
        })
    }

    pub fn forward(&self, desc: &Tensor, pos: &Tensor) -> Result<Tensor> {
        let a = self.amplitude.forward(desc)?;
        let theta = self.phase.forward(pos)?;
        let wave = cat_channels(&[&a.mul(&theta.cos()?)?, &a.mul(&theta.sin()?)?])?;
        desc + self.fuse.forward(&wave)?
    }
}

/// Either encoder, chosen by the config.
#[derive(Debug, Clone)]
pub enum PositionEncoder {
    Mlp(KeypointEncoder),
    Wave(WavePe),
}

impl PositionEncoder {
    /// Builds the encoder under its SPEC prefix (`kenc` or `wave_pe`).
    pub fn new(kind: PositionalEncoding, c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(match kind {
            PositionalEncoding::Mlp => Self::Mlp(KeypointEncoder::new(c, vb.pp("kenc"))?),
            PositionalEncoding::Wave => Self::Wave(WavePe::new(c, vb.pp("wave_pe"))?),
        })
    }

    /// `desc` `[K, C]`, normalised keypoints with scores `pos` `[K, 3]` → `[K, C]`.
    pub fn forward(&self, desc: &Tensor, pos: &Tensor) -> Result<Tensor> {
        match self {
            Self::Mlp(e) => e.forward(desc, pos),
            Self::Wave(e) => e.forward(desc, pos),
        }
    }
}
