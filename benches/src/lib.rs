//! Criterion benchmarks of the paraformer engine: see `benches/latency.rs`. Inputs come
//! from `paraformer::Features::random`.
