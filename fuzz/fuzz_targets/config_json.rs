//! Config JSON → `Config`: a named error or a config that validates; small valid configs
//! also build a random-weight matcher and match a pair.
#![no_main]
use libfuzzer_sys::fuzz_target;
use paraformer::{Config, Features, Matcher};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(cfg) = Config::from_json(text) else { return };
    if cfg.validate().is_err() {
        return;
    }
    let widths = [cfg.descriptor_dim, cfg.dim].into_iter().chain(cfg.stage_dims.iter().copied());
    let small = widths.into_iter().all(|w| w <= 64)
        && cfg.num_layers <= 4
        && cfg.layer_names.len() <= 8
        && cfg.stage_depths.iter().all(|&d| d <= 2)
        && cfg.sinkhorn_iterations <= 100;
    if small {
        let d = cfg.descriptor_dim;
        if let Ok(m) = Matcher::random(cfg, 0) {
            let f0 = Features::new(vec![[1.0, 2.0], [3.0, 4.0], [5.0, 1.0]], None, vec![0.3; 3 * d], d, (8.0, 8.0));
            let f1 = Features::new(vec![[2.0, 2.0], [4.0, 1.0]], None, vec![0.1; 2 * d], d, (8.0, 8.0));
            let _ = m.match_pair(&f0, &f1);
        }
    }
});
