//! Weights bytes → `Matcher`: any input is a named error or a matcher that matches a
//! small pair without panicking.
#![no_main]
use libfuzzer_sys::fuzz_target;
use paraformer::{Features, Matcher};

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = Matcher::from_bytes(data) {
        let d = m.config().descriptor_dim;
        if d <= 512 {
            let f0 = Features::new(vec![[10.0, 20.0], [30.0, 5.0]], None, vec![0.1; 2 * d], d, (64.0, 48.0));
            let f1 = Features::new(vec![[12.0, 21.0]], None, vec![0.2; d], d, (64.0, 48.0));
            let _ = m.match_pair(&f0, &f1);
        }
    }
});
