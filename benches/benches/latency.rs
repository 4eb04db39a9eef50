//! Criterion benchmarks (random weights made at bench time): end-to-end latency of the
//! three models at the paper's full widths (C = 256) at 512/1024/2048 keypoints; the
//! shipped configurations (C = 64 with 4 heads, and 2 heads) in fp32 and bf16; the parts
//! separately (one parallel layer, one serial layer, Sinkhorn, encoder); one C = 64
//! parallel layer through the fused narrow-head kernels against the general path; the
//! width-96 line's configuration (3 heads) in bf16 with and without AMX tiles, against fp32;
//! and XFeat at 640×480 with its direct convolutions against im2col + GEMM.
//!
//!     cargo bench -p paraformer-benches
//!     cargo bench -p paraformer-benches -- end_to_end/paraformer/2048   # one case
//!     cargo bench -p paraformer-benches -- shipped                      # shipped configs
//!     cargo bench -p paraformer-benches -- xfeat                        # XFeat, both paths
//!     cargo bench -p paraformer-benches -- amx                          # AMX tiles on and off

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use paraformer::kernels::{Ctx, Matrix, Precision};
use paraformer::layers::{ParallelLayer, SerialLayer};
use paraformer::sinkhorn::log_optimal_transport_inplace;
use paraformer::wave_pe::WavePe;
use paraformer::weights::random_var_builder;
use paraformer::{Config, Features, GrayImage, LayerKind, MatchOptions, Matcher, ParallelSwitches, XFeat};

const KEYPOINTS: [usize; 3] = [512, 1024, 2048];

fn random_matrix(rows: usize, cols: usize, seed: u64) -> Matrix {
    let f = Features::random(rows, cols, seed);
    Matrix { rows, cols, data: f.descriptors }
}

fn end_to_end(c: &mut Criterion) {
    let mut g = c.benchmark_group("end_to_end");
    g.sample_size(10);
    for name in ["superglue", "paraformer", "paraformer_u"] {
        let cfg = Config::preset(name).expect("preset");
        let matcher = Matcher::random(cfg.clone(), 0).expect("random weights");
        for k in KEYPOINTS {
            let (f0, f1) = (Features::random(k, 256, 1), Features::random(k, 256, 2));
            g.bench_with_input(BenchmarkId::new(name, k), &k, |b, _| {
                b.iter(|| matcher.match_pair_with(&f0, &f1, MatchOptions::default()).expect("runs"))
            });
        }
    }
    g.finish();
}

fn parts(c: &mut Criterion) {
    let mut g = c.benchmark_group("parts");
    g.sample_size(10);
    let vb = random_var_builder(3);
    let parallel = ParallelLayer::new(256, 4, ParallelSwitches::default(), vb.pp("p")).expect("layer");
    let serial = SerialLayer::new(256, 4, LayerKind::Cross, vb.pp("s")).expect("layer");
    let wave = WavePe::new(256, vb.pp("w")).expect("encoder");
    for k in KEYPOINTS {
        let (x, y) = (random_matrix(k, 256, 4), random_matrix(k, 256, 5));
        let ctx = Ctx::default();
        g.bench_with_input(BenchmarkId::new("parallel_layer", k), &k, |b, _| {
            b.iter(|| parallel.forward(&ctx, &x, &y, false).expect("runs"))
        });
        g.bench_with_input(BenchmarkId::new("serial_cross_layer", k), &k, |b, _| {
            b.iter(|| serial.forward(&ctx, &x, &y).expect("runs"))
        });
        let pos = Matrix { rows: k, cols: 3, data: Features::random(k, 3, 6).descriptors };
        g.bench_with_input(BenchmarkId::new("wave_pe_encoder", k), &k, |b, _| {
            b.iter(|| wave.forward(&ctx, x.clone(), &pos).expect("runs"))
        });
        let scores = random_matrix(k + 1, k + 1, 7);
        g.bench_with_input(BenchmarkId::new("sinkhorn_100", k), &k, |b, _| {
            b.iter(|| {
                let mut z = scores.clone();
                log_optimal_transport_inplace(&mut z, 1.0, 100);
                z
            })
        });
    }
    g.finish();
}

/// The shipped ParaFormer's shape: C = 64, 4 layers, `heads` heads, XFeat descriptors.
fn shipped_config(heads: usize) -> Config {
    let mut cfg = Config::paraformer();
    (cfg.descriptor_dim, cfg.dim, cfg.num_heads, cfg.num_layers, cfg.sinkhorn_iterations) = (64, 64, heads, 4, 50);
    cfg
}

fn shipped(c: &mut Criterion) {
    let mut g = c.benchmark_group("shipped");
    g.sample_size(10);
    for heads in [4, 2] {
        let base = Matcher::random(shipped_config(heads), 0).expect("random weights");
        for k in [512, 2048] {
            let (f0, f1) = (Features::random(k, 64, 1), Features::random(k, 64, 2));
            for p in [Precision::Fp32, Precision::Bf16] {
                let m = base.clone().with_precision(p);
                g.bench_with_input(BenchmarkId::new(format!("c64_h{heads}_{}", p.name()), k), &k, |b, _| {
                    b.iter(|| m.match_pair_with(&f0, &f1, MatchOptions::default()).expect("runs"))
                });
            }
        }
    }
    // One parallel layer at 2048 keypoints (C = 64 with head widths 16 and 32, and the
    // paper's C = 256 with 64): fused kernels (fp32, bf16) and the general path.
    let vb = random_var_builder(3);
    for (c, heads) in [(64, 4), (64, 2), (256, 4)] {
        let (x, y) = (random_matrix(2048, c, 4), random_matrix(2048, c, 5));
        let layer = ParallelLayer::new(c, heads, ParallelSwitches::default(), vb.pp(format!("l{c}_{heads}"))).expect("layer");
        let mut general = Ctx::default();
        general.fused = false;
        for (name, ctx) in [("general", general), ("fused_fp32", Ctx::default()), ("fused_bf16", Ctx::with_precision(Precision::Bf16))] {
            g.bench_function(format!("layer_c{c}_h{heads}/{name}"), |b| b.iter(|| layer.forward(&ctx, &x, &y, false).expect("runs")));
        }
    }
    g.finish();
}

/// XFeat on the sample image stretched to 640×480 (nearest pixel), 4096 keypoints.
fn xfeat(c: &mut Criterion) {
    let mut g = c.benchmark_group("xfeat_640x480");
    g.sample_size(20);
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/sample/coffee_0.jpg");
    let src = GrayImage::open(path).expect("sample image");
    let (w, h) = (640, 480);
    let data = (0..w * h).map(|i| src.data[(i / w) * src.height / h * src.width + (i % w) * src.width / w]).collect();
    let img = GrayImage::new(w, h, data).expect("image");
    let direct = XFeat::pretrained().expect("weights");
    let general = XFeat::pretrained().expect("weights").without_direct_convolutions();
    for (name, xf) in [("direct", &direct), ("im2col_gemm", &general)] {
        g.bench_function(name, |b| b.iter(|| xf.detect_and_compute(&img, Some(4096)).expect("runs")));
    }
    g.finish();
}

/// The width-96 configuration (3 heads of 32, 4 layers, 25 Sinkhorn iterations) at 2048
/// keypoints: fp32, bf16 on AVX-512 BF16 and bf16 on AMX tiles, end to end and one layer.
/// Where the CPU lacks AMX the last two are the same kernels.
fn amx(c: &mut Criterion) {
    let mut g = c.benchmark_group("amx");
    g.sample_size(10);
    let mut cfg = shipped_config(3);
    (cfg.dim, cfg.sinkhorn_iterations) = (96, 25);
    let base = Matcher::random(cfg, 0).expect("random weights");
    let (f0, f1) = (Features::random(2048, 64, 1), Features::random(2048, 64, 2));
    let layer = ParallelLayer::new(96, 3, ParallelSwitches::default(), random_var_builder(3).pp("l")).expect("layer");
    let (x, y) = (random_matrix(2048, 96, 4), random_matrix(2048, 96, 5));
    eprintln!("AMX tiles supported here: {}", paraformer::amx::supported());
    for (name, p, tiles) in [("fp32", Precision::Fp32, false), ("bf16_avx512", Precision::Bf16, false), ("bf16_amx", Precision::Bf16, true)] {
        let m = base.clone().with_precision(p);
        let ctx = Ctx::with_precision(p);
        g.bench_function(format!("w96_h3_2048/{name}"), |b| {
            paraformer::amx::set_enabled(tiles);
            b.iter(|| m.match_pair_with(&f0, &f1, MatchOptions::default()).expect("runs"))
        });
        g.bench_function(format!("layer_c96_h3_2048/{name}"), |b| {
            paraformer::amx::set_enabled(tiles);
            b.iter(|| layer.forward(&ctx, &x, &y, false).expect("runs"))
        });
    }
    paraformer::amx::set_enabled(true);
    g.finish();
}

criterion_group!(benches, end_to_end, shipped, parts, xfeat, amx);
criterion_main!(benches);
