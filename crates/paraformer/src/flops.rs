//! Multiply-accumulate count of a forward pass (SPEC §10, the paper's Table 7 "FLOPs"):
//! every matrix product of the encoders, attention layers, pooling, final projection
//! and score matrix; not Sinkhorn, softmax, norms or activations.

use crate::config::{Config, LayerKind, ModelKind, PositionalEncoding};

/// MACs per part of the network for one pair of images.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Flops {
    /// `input_proj` and the position encoder, both images.
    pub encoder: u64,
    /// Attention layers, with ParaFormer-U's pooling and unpooling projections.
    pub layers: u64,
    /// `final_proj` and the `M × N` score matrix.
    pub final_projection: u64,
}

impl Flops {
    /// All multiply-accumulates of one forward pass.
    pub fn total(&self) -> u64 {
        self.encoder + self.layers + self.final_projection
    }
}

/// MACs of an MLP with these widths on `k` rows.
fn mlp(k: u64, widths: &[u64]) -> u64 {
    widths.windows(2).map(|w| k * w[0] * w[1]).sum()
}

/// One parallel layer on `m` and `n` rows of width `c`.
fn parallel_layer(cfg: &Config, m: u64, n: u64, c: u64) -> u64 {
    let sw = cfg.parallel;
    let proj = c * c;
    // Row-projections (counted in rows × C²): q/k/v, merges (2 per image), fuse (8C²).
    let mut rows = 3 * (m + n); // self q/k/v of both images (shared with cross when share_qkv)
    if !sw.share_qkv {
        rows += m + n + m + n; // cross q of X, k of Y, v of both
        if !sw.share_attention_weights {
            rows += n + m; // cross q of Y, k of X
        }
    }
    rows += 2 * (m + n);
    let fuse = (m + n) * 8 * c * c;
    // Products per head summed over heads: self QKᵀ and AV, cross scores and AV.
    let self_attn = 2 * (m * m + n * n) * c;
    let cross_scores = if sw.share_attention_weights { 1 } else { 2 };
    let cross = (cross_scores + 2) * m * n * c;
    rows * proj + fuse + self_attn + cross
}

/// One SuperGlue layer.
fn serial_layer(kind: LayerKind, m: u64, n: u64, c: u64) -> u64 {
    let one = |q: u64, s: u64| q * c * c + 2 * s * c * c + 2 * q * s * c + q * c * c + 6 * q * c * c;
    match kind {
        LayerKind::SelfAttention => one(m, m) + one(n, n),
        LayerKind::Cross => one(m, n) + one(n, m),
    }
}

/// The MAC count of matching `m` against `n` keypoints with `cfg` (0 if either is 0,
/// since the network is then not run).
pub fn flops(cfg: &Config, m: usize, n: usize) -> Flops {
    if m == 0 || n == 0 {
        return Flops::default();
    }
    let (m, n) = (m as u64, n as u64);
    let c = cfg.model_dim() as u64;
    let d = cfg.descriptor_dim as u64;
    let mut encoder = if d != c { (m + n) * d * c } else { 0 };
    encoder += match cfg.positional_encoding {
        PositionalEncoding::Mlp => mlp(m + n, &[3, 32, 64, 128, 256, c]),
        PositionalEncoding::Wave => {
            mlp(m + n, &[c, 4 * c, c]) + mlp(m + n, &[3, c / 2, c]) + mlp(m + n, &[2 * c, 4 * c, c])
        }
    };
    let layers = match cfg.model {
        ModelKind::Superglue => cfg.layer_names.iter().map(|&k| serial_layer(k, m, n, c)).sum(),
        ModelKind::Paraformer => cfg.num_layers as u64 * parallel_layer(cfg, m, n, c),
        ModelKind::ParaformerU => {
            let dims: Vec<u64> = cfg.stage_dims.iter().map(|&v| v as u64).collect();
            let half = |k: u64| k.div_ceil(2);
            // Keypoints per stage: full, half, quarter, half, full.
            let (m1, n1) = (half(m), half(n));
            let (m2, n2) = (half(m1), half(n1));
            let sizes = [(m, n), (m1, n1), (m2, n2), (m1, n1), (m, n)];
            let stages: u64 = (0..5)
                .map(|s| cfg.stage_depths[s] as u64 * parallel_layer(cfg, sizes[s].0, sizes[s].1, dims[s]))
                .sum();
            let pools = (m1 + n1) * dims[0] * dims[1] + (m2 + n2) * dims[1] * dims[2];
            let unpools = (m2 + n2) * dims[2] * dims[3] + (m1 + n1) * dims[3] * dims[4];
            stages + pools + unpools
        }
    };
    let final_projection = (m + n) * c * c + m * n * c;
    Flops { encoder, layers, final_projection }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn g(v: u64) -> f64 {
        v as f64 / 1e9
    }

    #[test]
    fn paper_table7_at_2048_keypoints() {
        // SPEC §10: ≈127.4, ≈105.9, ≈65.8 GMACs (≈126.3, ≈104.8, ≈64.7 without the score matrix).
        for (cfg, total, no_scores) in [
            (Config::superglue(), 127.4, 126.3),
            (Config::paraformer(), 105.9, 104.8),
            (Config::paraformer_u(), 65.8, 64.7),
        ] {
            let f = flops(&cfg, 2048, 2048);
            assert!((g(f.total()) - total).abs() < 0.05, "{:?}: {}", cfg.model, g(f.total()));
            let without = f.total() - 2048 * 2048 * 256;
            assert!((g(without) - no_scores).abs() < 0.05, "{:?}: {}", cfg.model, g(without));
        }
    }

    #[test]
    fn switches_add_the_products_they_need() {
        let base = Config { num_layers: 1, ..Config::paraformer() };
        let f = |sw: crate::ParallelSwitches| flops(&Config { parallel: sw, ..base.clone() }, 100, 80).layers;
        let on = f(Default::default());
        let c = 256u64;
        let no_share = crate::ParallelSwitches { share_attention_weights: false, ..Default::default() };
        assert_eq!(f(no_share) - on, 100 * 80 * c, "one more score product");
        let no_qkv = crate::ParallelSwitches { share_qkv: false, ..Default::default() };
        assert_eq!(f(no_qkv) - on, 2 * (100 + 80) * c * c, "cross q, k, v of both");
        assert_eq!(flops(&base, 0, 80), Flops::default());
    }
}
