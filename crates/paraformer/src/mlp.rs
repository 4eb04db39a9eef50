//! The one MLP helper (SPEC §2): Linear layers with eval-mode BatchNorm and ReLU in
//! between, named by `nn.Sequential` indices (`.0`, `.1`, `.3`, `.4`, …).

use candle_core::{Module, Result, Tensor, D};
use candle_nn::{Linear, VarBuilder};

/// Eval-mode BatchNorm1d over channels, folded into one scale and shift at load time.
#[derive(Debug, Clone)]
pub struct BatchNorm {
    scale: Tensor,
    shift: Tensor,
}

impl BatchNorm {
    pub const EPS: f64 = 1e-5;

    pub fn new(channels: usize, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get(channels, "weight")?;
        let bias = vb.get(channels, "bias")?;
        let running_mean = vb.get(channels, "running_mean")?;
        let running_var = vb.get(channels, "running_var")?;
        // (x − mean)/sqrt(var + eps)·w + b  =  x·scale + shift
        let scale = weight.broadcast_div(&(running_var + Self::EPS)?.sqrt()?)?;
        let shift = (bias - running_mean.mul(&scale)?)?;
        Ok(Self { scale, shift })
    }
}

impl Module for BatchNorm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        x.broadcast_mul(&self.scale)?.broadcast_add(&self.shift)
    }
}

/// `MLP([c0, …, cL])` applied to rows `[K, c0] → [K, cL]`.
#[derive(Debug, Clone)]
pub struct Mlp {
    linears: Vec<Linear>,
    norms: Vec<BatchNorm>,
}

impl Mlp {
    pub fn new(channels: &[usize], vb: VarBuilder) -> Result<Self> {
        let n = channels.len().saturating_sub(1);
        let mut linears = Vec::with_capacity(n);
        let mut norms = Vec::with_capacity(n.saturating_sub(1));
        for i in 0..n {
            linears.push(candle_nn::linear(channels[i], channels[i + 1], vb.pp(3 * i))?);
            if i + 1 < n {
                norms.push(BatchNorm::new(channels[i + 1], vb.pp(3 * i + 1))?);
            }
        }
        Ok(Self { linears, norms })
    }
}

impl Module for Mlp {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut x = x.clone();
        for (i, linear) in self.linears.iter().enumerate() {
            x = linear.forward(&x)?;
            if let Some(norm) = self.norms.get(i) {
                x = norm.forward(&x)?.relu()?;
            }
        }
        Ok(x)
    }
}

/// Concatenates row-aligned feature blocks along channels.
pub(crate) fn cat_channels(parts: &[&Tensor]) -> Result<Tensor> {
    Tensor::cat(parts, D::Minus1)
}
