//! Position encoders (SPEC §3): SuperGlue's MLP keypoint encoder and ParaFormer's
//! Wave-PE (paper §"Wave-PE": amplitude from descriptors, phase from positions).

use candle_core::Result as CResult;
use candle_nn::VarBuilder;

use crate::config::PositionalEncoding;
use crate::error::Result;
use crate::kernels::{Ctx, Matrix};
use crate::mlp::{add_assign, Mlp};

/// MLP-PE, prefix `kenc`: `x⁰ = d + MLP([3, 32, 64, 128, 256, C])(p)`.
#[derive(Debug, Clone)]
pub struct KeypointEncoder {
    encoder: Mlp,
}

impl KeypointEncoder {
    pub fn new(c: usize, vb: VarBuilder) -> CResult<Self> {
        Ok(Self { encoder: Mlp::new(&[3, 32, 64, 128, 256, c], vb.pp("encoder"))? })
    }

    pub fn forward(&self, ctx: &Ctx, desc: Matrix, pos: &Matrix) -> Result<Matrix> {
        let mut x = desc;
        add_assign(&mut x, &self.encoder.forward(ctx, pos.view())?);
        Ok(x)
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
    pub fn new(c: usize, vb: VarBuilder) -> CResult<Self> {
        Ok(Self {
            // Under Precision::Bf16 the descriptor and wave MLPs may run in bf16; the phase
            // MLP reads keypoint positions, whose precision matters, and stays fp32.
            amplitude: Mlp::new(&[c, 4 * c, c], vb.pp("amplitude"))?.with_bf16(),
            phase: Mlp::new(&[3, c / 2, c], vb.pp("phase"))?,
            fuse: Mlp::new(&[2 * c, 4 * c, c], vb.pp("fuse"))?.with_bf16(),
        })
    }

    pub fn forward(&self, ctx: &Ctx, desc: Matrix, pos: &Matrix) -> Result<Matrix> {
        let a = self.amplitude.forward(ctx, desc.view())?;
        let theta = self.phase.forward(ctx, pos.view())?;
        let c = a.cols;
        let mut wave = Matrix::zeros(a.rows, 2 * c);
        for ((w, a), t) in wave.data.chunks_exact_mut(2 * c).zip(a.data.chunks_exact(c)).zip(theta.data.chunks_exact(c)) {
            for j in 0..c {
                let (s, co) = t[j].sin_cos();
                w[j] = a[j] * co;
                w[c + j] = a[j] * s;
            }
        }
        let mut x = desc;
        add_assign(&mut x, &self.fuse.forward(ctx, wave.view())?);
        Ok(x)
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
    pub fn new(kind: PositionalEncoding, c: usize, vb: VarBuilder) -> CResult<Self> {
        Ok(match kind {
            PositionalEncoding::Mlp => Self::Mlp(KeypointEncoder::new(c, vb.pp("kenc"))?),
            PositionalEncoding::Wave => Self::Wave(WavePe::new(c, vb.pp("wave_pe"))?),
        })
    }

    /// Descriptors `[K, C]` and normalised keypoints with scores `[K, 3]` → `[K, C]`.
    pub fn forward(&self, ctx: &Ctx, desc: Matrix, pos: &Matrix) -> Result<Matrix> {
        match self {
            Self::Mlp(e) => e.forward(ctx, desc, pos),
            Self::Wave(e) => e.forward(ctx, desc, pos),
        }
    }
}
