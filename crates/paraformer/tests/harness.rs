//! The evaluation harness end to end on a small synthetic dataset made in the test:
//! keypoints of image 1 are those of image 0 moved by a known homography (plus
//! unrelated ones), descriptors are shared (with noise) for the true correspondences.

use std::collections::BTreeMap;

use paraformer::eval::datasets::HomographyPair;
use paraformer::eval::harness::{eval_homography, MatcherSpec};
use paraformer::geometry::homography::apply;
use paraformer::geometry::RansacConfig;
use paraformer::nalgebra::Matrix3;
use paraformer::pooling::SplitMix64;
use paraformer::Features;

#[test]
fn homography_harness_ranks_baselines_and_scores_a_clean_set_highly() {
    let mut rng = SplitMix64::new(3);
    let mut u = move || (rng.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
    let mut features = BTreeMap::new();
    let mut pairs = Vec::new();
    for p in 0..6 {
        let h = Matrix3::new(1.0 + 0.02 * p as f64, 0.05, 12.0, -0.03, 0.97, 8.0, 1e-4, 0.0, 1.0);
        let (n, d) = (150, 16);
        let k0: Vec<[f32; 2]> = (0..n).map(|_| [u() * 600.0 + 20.0, u() * 440.0 + 20.0]).collect();
        let d0: Vec<f32> = (0..n * d).map(|_| u() - 0.5).collect();
        let mut k1 = Vec::new();
        let mut d1 = Vec::new();
        for i in 0..n {
            if i < 100 {
                let q = apply(&h, &[k0[i][0] as f64, k0[i][1] as f64]).expect("finite");
                k1.push([q[0] as f32, q[1] as f32]);
                d1.extend(d0[i * d..(i + 1) * d].iter().map(|v| v + 0.02 * (u() - 0.5)));
            } else {
                k1.push([u() * 640.0, u() * 480.0]);
                d1.extend((0..d).map(|_| u() - 0.5));
            }
        }
        let (a, b) = (format!("{p}_0"), format!("{p}_1"));
        features.insert(a.clone(), Features::new(k0, None, d0, d, (640.0, 480.0)));
        features.insert(b.clone(), Features::new(k1, None, d1, d, (640.0, 480.0)));
        pairs.push(HomographyPair { name0: a, name1: b, image0: Default::default(), image1: Default::default(), h });
    }
    let cfg = RansacConfig::default();
    let mut calls = 0;
    let mnn = eval_homography(&pairs, &features, &MatcherSpec::parse("mnn").expect("spec"), &cfg, |_, _| calls += 1).expect("runs");
    let nn = eval_homography(&pairs, &features, &MatcherSpec::parse("nn").expect("spec"), &cfg, |_, _| {}).expect("runs");
    assert_eq!(calls, 6);
    assert!(mnn.auc[0] > 90.0, "{mnn:?}");
    // Mutual NN also pairs some unrelated keypoints with each other: those count as false.
    assert!(mnn.precision > 85.0 && mnn.recall > 95.0, "{mnn:?}");
    assert!(nn.precision < mnn.precision, "NN keeps the 50 unrelated keypoints: {nn:?}");
    assert!(MatcherSpec::parse("ratio:0.7").is_ok());
    assert!(MatcherSpec::parse("/no/such/weights.safetensors").is_err());
    // A missing image name is a named error.
    features.remove("0_1");
    let err = eval_homography(&pairs, &features, &MatcherSpec::parse("mnn").expect("spec"), &cfg, |_, _| {}).expect_err("missing");
    assert!(err.to_string().contains("0_1"), "{err}");
}
