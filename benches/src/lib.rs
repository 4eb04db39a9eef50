//! Shared inputs of the benchmarks: random features at any keypoint count.

use paraformer::Features;

/// `k` random keypoints in a 640×480 image with `d`-wide descriptors (SplitMix64 stream).
pub fn random_features(k: usize, d: usize, seed: u64) -> Features {
    let mut rng = paraformer::pooling::SplitMix64::new(seed);
    let mut next = move || (rng.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
    let kpts = (0..k).map(|_| [next() * 640.0, next() * 480.0]).collect();
    let scores = (0..k).map(|_| next()).collect();
    let desc = (0..k * d).map(|_| next() - 0.5).collect();
    Features::new(kpts, Some(scores), desc, d, (640.0, 480.0))
}
