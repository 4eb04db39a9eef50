//! Pair-file bytes (the features file of `paraformer eval`/`demo`) → features: a named
//! error or two feature sets that validate without panicking.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok((f0, f1)) = paraformer::read_pair_bytes(data) {
        let _ = f0.validate(f0.descriptor_dim, 0);
        let _ = f1.validate(f1.descriptor_dim, 1);
    }
});
