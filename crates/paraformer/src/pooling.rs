//! ParaFormer-U pooling and unpooling (SPEC §7, paper §"ParaFormer-U"): keep the top
//! half of the keypoints by an importance score, gate them, and scatter them back.

use candle_core::Result as CResult;
use candle_nn::VarBuilder;

use crate::config::{Config, Pooling};
use crate::error::Result;
use crate::kernels::{Ctx, Matrix};
use crate::mlp::{read, Linear};

/// SplitMix64, the generator of random pooling.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
}

/// The first `k` entries of a partial Fisher–Yates shuffle of `0..n`.
pub fn random_indices(n: usize, k: usize, seed: u64) -> Vec<usize> {
    let mut rng = SplitMix64::new(seed);
    let mut a: Vec<usize> = (0..n).collect();
    for t in 0..k.min(n) {
        let j = t + (rng.next_u64() % (n - t) as u64) as usize;
        a.swap(t, j);
    }
    a.truncate(k);
    a
}

/// Indices of the `k` largest scores, descending, ties broken by lower index.
pub fn top_k(scores: &[f32], k: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..scores.len()).collect();
    idx.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    idx.truncate(k);
    idx
}

/// Which rows a pool kept, in order; unpooling scatters back to them.
#[derive(Debug, Clone)]
pub struct PoolIndex {
    pub rows: Vec<usize>,
}

/// One pooling step, prefix `pools.{p}`: `proj` and, for gPool, `score`.
#[derive(Debug, Clone)]
pub struct Pool {
    proj: Linear,
    score: Option<Vec<f32>>,
    kind: Pooling,
    seed: u64,
    index: usize,
    heads: usize,
}

impl Pool {
    pub fn new(c_in: usize, c_out: usize, cfg: &Config, index: usize, vb: VarBuilder) -> CResult<Self> {
        let score = match cfg.pooling {
            Pooling::Gpool => Some(read(&vb, &[c_in], "score")?),
            _ => None,
        };
        Ok(Self { proj: Linear::new(c_in, c_out, vb.pp("proj"))?, score, kind: cfg.pooling, seed: cfg.pooling_seed, index, heads: cfg.num_heads })
    }

    /// Whether this pool needs the stage's self-attention column sums.
    pub fn needs_col_sums(&self) -> bool {
        self.kind == Pooling::Attentional
    }

    /// Pools `x` `[K, C_s]` of image `image` (0 = X, 1 = Y) to `[ceil(K/2), C_{s+1}]`.
    /// `col_sums` `[K]` are `Σ_h Σ_i A[h, i, j]` of the stage's last self-attention
    /// (needed by attentional pooling only).
    pub fn forward(&self, ctx: &Ctx, x: &Matrix, col_sums: Option<&[f32]>, image: usize) -> Result<(Matrix, PoolIndex)> {
        let n = x.rows;
        let k = n.div_ceil(2);
        let (rows, gate) = match self.kind {
            Pooling::Attentional => {
                let cs = col_sums.ok_or_else(|| {
                    crate::Error::Config("attentional pooling needs a stage with at least one layer".into())
                })?;
                // s_j = mean over heads of the column sums of A.
                let s: Vec<f32> = cs.iter().map(|v| v / self.heads as f32).collect();
                let rows = top_k(&s, k);
                let gate = rows.iter().map(|&r| sigmoid(s[r])).collect::<Vec<_>>();
                (rows, Some(gate))
            }
            Pooling::Gpool => {
                let w = self.score.as_deref().unwrap_or_default();
                let norm = w.iter().map(|v| v * v).sum::<f32>().sqrt();
                let s: Vec<f32> = x.data.chunks_exact(x.cols.max(1)).map(|r| r.iter().zip(w).map(|(a, b)| a * b).sum::<f32>() / norm).collect();
                let rows = top_k(&s, k);
                let gate = rows.iter().map(|&r| sigmoid(s[r])).collect::<Vec<_>>();
                (rows, Some(gate))
            }
            Pooling::Random => {
                let seed = 4u64.wrapping_mul(self.seed).wrapping_add(2 * self.index as u64 + image as u64);
                (random_indices(n, k, seed), None)
            }
        };
        let mut picked = Matrix::zeros(rows.len(), x.cols);
        for (dst, &r) in picked.data.chunks_exact_mut(x.cols.max(1)).zip(&rows) {
            dst.copy_from_slice(x.row(r));
        }
        let mut out = self.proj.forward(ctx, picked.view())?;
        if let Some(gate) = gate {
            for (row, g) in out.data.chunks_exact_mut(out.cols.max(1)).zip(gate) {
                for v in row {
                    *v *= g;
                }
            }
        }
        Ok((out, PoolIndex { rows }))
    }
}

fn sigmoid(v: f32) -> f32 {
    1.0 / (1.0 + (-v).exp())
}

/// One unpooling step, prefix `unpools.{q}`: project, scatter into zeros, add the skip.
#[derive(Debug, Clone)]
pub struct Unpool {
    proj: Linear,
}

impl Unpool {
    pub fn new(c_in: usize, c_out: usize, vb: VarBuilder) -> CResult<Self> {
        Ok(Self { proj: Linear::new(c_in, c_out, vb.pp("proj"))? })
    }

    pub fn forward(&self, ctx: &Ctx, x: &Matrix, index: &PoolIndex, skip: &Matrix) -> Result<Matrix> {
        let u = self.proj.forward(ctx, x.view())?;
        let mut out = skip.clone();
        let c = out.cols;
        for (i, &r) in index.rows.iter().enumerate() {
            for (o, v) in out.data[r * c..(r + 1) * c].iter_mut().zip(u.row(i)) {
                *o += v;
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix64_reference_values() {
        // First outputs of SplitMix64 from state 0 (Vigna's reference implementation).
        let mut r = SplitMix64::new(0);
        assert_eq!(r.next_u64(), 0xE220_A839_7B1D_CDAF);
        assert_eq!(r.next_u64(), 0x6E78_9E6A_A1B9_65F4);
    }

    #[test]
    fn random_indices_are_a_prefix_of_a_permutation() {
        let idx = random_indices(11, 6, 42);
        assert_eq!(idx.len(), 6);
        let mut sorted = idx.clone();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), 6);
        assert!(idx.iter().all(|&i| i < 11));
        assert_eq!(random_indices(11, 6, 42), idx, "deterministic");
        assert_ne!(random_indices(11, 6, 43), idx, "seed matters");
    }

    #[test]
    fn top_k_is_descending_with_ties_to_lower_index() {
        assert_eq!(top_k(&[0.5, 2.0, 0.5, 2.0, 1.0], 3), vec![1, 3, 4]);
        assert_eq!(top_k(&[1.0, 1.0, 1.0], 2), vec![0, 1]);
    }
}
