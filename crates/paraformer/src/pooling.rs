//! ParaFormer-U pooling and unpooling (SPEC §7, paper §"ParaFormer-U"): keep the top
//! half of the keypoints by an importance score, gate them, and scatter them back.

use candle_core::{Module, Result, Tensor, D};
use candle_nn::{Linear, VarBuilder};

use crate::config::Pooling;

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
    pub from_len: usize,
}

/// One pooling step, prefix `pools.{p}`: `proj` and, for gPool, `score`.
#[derive(Debug, Clone)]
pub struct Pool {
    proj: Linear,
    score: Option<Tensor>,
    kind: Pooling,
    seed: u64,
    index: usize,
}

impl Pool {
    pub fn new(c_in: usize, c_out: usize, kind: Pooling, seed: u64, index: usize, vb: VarBuilder) -> Result<Self> {
        let score = match kind {
            Pooling::Gpool => Some(vb.get(c_in, "score")?),
            _ => None,
        };
        Ok(Self { proj: candle_nn::linear(c_in, c_out, vb.pp("proj"))?, score, kind, seed, index })
    }

    /// Pools `x` `[K, C_s]` of image `image` (0 = X, 1 = Y) to `[ceil(K/2), C_{s+1}]`.
    /// `self_probs` `[H, K, K]` are the last self-attention probabilities of the stage
    /// (needed by attentional pooling only).
    pub fn forward(&self, x: &Tensor, self_probs: Option<&Tensor>, image: usize) -> Result<(Tensor, PoolIndex)> {
        let n = x.dim(0)?;
        let k = n.div_ceil(2);
        let (rows, gate) = match self.kind {
            Pooling::Attentional => {
                let probs = self_probs.ok_or_else(|| {
                    candle_core::Error::Msg("attentional pooling needs a stage with at least one layer".into())
                })?;
                // s_j = mean over heads of the column sums of A.
                let s: Vec<f32> = probs.sum(1)?.mean(0)?.to_vec1()?;
                let rows = top_k(&s, k);
                let gate = rows.iter().map(|&r| sigmoid(s[r])).collect::<Vec<_>>();
                (rows, Some(gate))
            }
            Pooling::Gpool => {
                let w = self.score.as_ref().ok_or_else(|| candle_core::Error::Msg("gPool score missing".into()))?;
                let w = (w / w.sqr()?.sum_all()?.sqrt()?.to_scalar::<f32>()? as f64)?;
                let s: Vec<f32> = x.broadcast_mul(&w)?.sum(D::Minus1)?.to_vec1()?;
                let rows = top_k(&s, k);
                let gate = rows.iter().map(|&r| sigmoid(s[r])).collect::<Vec<_>>();
                (rows, Some(gate))
            }
            Pooling::Random => {
                let seed = 4u64.wrapping_mul(self.seed).wrapping_add(2 * self.index as u64 + image as u64);
                (random_indices(n, k, seed), None)
            }
        };
        let ids = Tensor::from_vec(rows.iter().map(|&r| r as u32).collect::<Vec<_>>(), rows.len(), x.device())?;
        let mut out = self.proj.forward(&x.index_select(&ids, 0)?)?;
        if let Some(gate) = gate {
            out = out.broadcast_mul(&Tensor::from_vec(gate, (rows.len(), 1), x.device())?)?;
        }
        Ok((out, PoolIndex { rows, from_len: n }))
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
    pub fn new(c_in: usize, c_out: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { proj: candle_nn::linear(c_in, c_out, vb.pp("proj"))? })
    }

    pub fn forward(&self, x: &Tensor, index: &PoolIndex, skip: &Tensor) -> Result<Tensor> {
        let u = self.proj.forward(x)?;
        let ids = Tensor::from_vec(index.rows.iter().map(|&r| r as u32).collect::<Vec<_>>(), index.rows.len(), x.device())?;
        let zeros = skip.zeros_like()?;
        zeros.index_add(&ids, &u, 0)? + skip
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
