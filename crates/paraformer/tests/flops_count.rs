//! The FLOPs counter (SPEC §10) against an independent count: the multiply-accumulates
//! of every matrix product the engine actually performs, recorded by its GEMM wrapper.

use paraformer::{flops, Config, Features, MatchOptions, Matcher, ParallelSwitches, Pooling};

fn features(k: usize, d: usize, seed: u32) -> Features {
    let kp = (0..k).map(|i| [(i as f32 * 37.0 + seed as f32) % 640.0, (i as f32 * 91.0) % 480.0]).collect();
    let desc = (0..k * d).map(|i| (((i as u32).wrapping_mul(2654435761).wrapping_add(seed) >> 8) as f32 / 16777216.0) - 0.5).collect();
    Features::new(kp, None, desc, d, (640.0, 480.0))
}

fn check(cfg: Config, m: usize, n: usize) {
    let label = format!("{:?} {:?} {:?} M={m} N={n}", cfg.model, cfg.parallel, cfg.pooling);
    let matcher = Matcher::random(cfg.clone(), 1).expect("random weights");
    let d = cfg.descriptor_dim;
    let (_, profile) = matcher.profile(&features(m, d, 1), &features(n, d, 2), MatchOptions::default()).expect("runs");
    assert_eq!(profile.macs, flops(&cfg, m, n).total(), "{label}");
}

#[test]
fn counted_macs_equal_the_formula_for_every_model_and_switch() {
    let small = |model: &str| Config { descriptor_dim: 24, dim: 16, num_layers: 2, ..Config::preset(model).expect("preset") };
    let sg = Config { layer_names: Config::superglue().layer_names[..4].to_vec(), ..small("superglue") };
    for (m, n) in [(33, 20), (7, 41), (1, 1)] {
        check(sg.clone(), m, n);
        for sw in [
            ParallelSwitches::default(),
            ParallelSwitches { share_qkv: false, ..Default::default() },
            ParallelSwitches { share_merge: false, ..Default::default() },
            ParallelSwitches { share_attention_weights: false, ..Default::default() },
            ParallelSwitches { share_qkv: false, share_merge: false, share_attention_weights: false },
        ] {
            check(Config { parallel: sw, ..small("paraformer") }, m, n);
        }
        for pooling in [Pooling::Attentional, Pooling::Gpool, Pooling::Random] {
            let u = Config { stage_dims: vec![16, 24, 8, 24, 16], descriptor_dim: 16, pooling, ..Config::paraformer_u() };
            check(u, m, n);
        }
    }
}
