//! The `paraformer` command line.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use paraformer::{flops, read_pair_file, Config, Features, MatchOptions, Matcher, Weights};

fn rayon_threads() -> usize {
    paraformer::kernels::Ctx::default().threads
}

#[derive(Parser)]
#[command(name = "paraformer", version, about = "Sparse feature matching with ParaFormer, ParaFormer-U and SuperGlue")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Match one pair of stored features (a pair file, as in tests/data) and print the matches.
    Demo {
        /// Weights file (safetensors with `paraformer.config` metadata).
        #[arg(long, default_value = "tests/data/spec_vectors/paraformer.weights.safetensors")]
        weights: PathBuf,
        /// Pair file: keypoints0/1, scores0/1, descriptors0/1, image_size0/1.
        #[arg(long, default_value = "tests/data/spec_vectors/paraformer.case0.safetensors")]
        pair: PathBuf,
    },
    /// Print the config and tensor names of a weights file, after a strict check.
    Inspect {
        weights: PathBuf,
    },
    /// Multiply-accumulates per model and keypoint count (SPEC §10, the paper's Table 7).
    Flops {
        /// Keypoints per image.
        #[arg(long, value_delimiter = ',', default_values_t = vec![512, 1024, 2048])]
        keypoints: Vec<usize>,
        /// Write the table as CSV (keypoints and GMACs per model) to this file.
        #[arg(long)]
        csv: Option<PathBuf>,
    },
    /// Time matching at the paper's widths with random weights, part by part.
    Bench {
        /// superglue, paraformer or paraformer_u (repeatable; default all three).
        #[arg(long, value_delimiter = ',', default_values_t = vec!["superglue".to_string(), "paraformer".to_string(), "paraformer_u".to_string()])]
        model: Vec<String>,
        /// Keypoints per image.
        #[arg(long, value_delimiter = ',', default_values_t = vec![512, 1024, 2048])]
        keypoints: Vec<usize>,
        /// Timed repetitions (the best is reported) after one warm-up run.
        #[arg(long, default_value_t = 3)]
        repeat: usize,
    },
}

const MODELS: [&str; 3] = ["superglue", "paraformer", "paraformer_u"];

/// Random features with the given descriptor width.
fn random_features(k: usize, d: usize, seed: u64) -> Features {
    let mut state = seed;
    let mut next = || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    };
    let kpts = (0..k).map(|_| [next() * 640.0, next() * 480.0]).collect();
    let scores = (0..k).map(|_| next()).collect();
    let desc = (0..k * d).map(|_| next() - 0.5).collect();
    Features::new(kpts, Some(scores), desc, d, (640.0, 480.0))
}

fn run(cli: Cli) -> paraformer::Result<()> {
    match cli.command {
        Command::Demo { weights, pair } => {
            let matcher = Matcher::from_file(&weights)?;
            let (f0, f1) = read_pair_file(&pair)?;
            let start = std::time::Instant::now();
            let out = matcher.match_pair_with(&f0, &f1, MatchOptions::default())?;
            let elapsed = start.elapsed();
            let cfg = matcher.config();
            println!("model {:?} (C = {}), {} × {} keypoints", cfg.model, cfg.model_dim(), f0.len(), f1.len());
            println!("{} matches in {:.2} ms:", out.pairs().len(), elapsed.as_secs_f64() * 1e3);
            for (i, j) in out.pairs() {
                let (p, q) = (f0.keypoints[i], f1.keypoints[j]);
                println!(
                    "  {i:>4} ({:7.1}, {:7.1})  ->  {j:>4} ({:7.1}, {:7.1})  score {:.3}",
                    p[0], p[1], q[0], q[1], out.matching_scores0[i]
                );
            }
        }
        Command::Flops { keypoints, csv } => {
            println!("{:>10} {:>12} {:>12} {:>14}   (GMACs: encoder + layers + final projection)", "keypoints", "SuperGlue", "ParaFormer", "ParaFormer-U");
            let mut rows = String::from("keypoints,superglue,paraformer,paraformer_u\n");
            for &k in &keypoints {
                let g: Vec<f64> = MODELS.iter().map(|m| Config::preset(m).map(|c| flops(&c, k, k).total() as f64 / 1e9)).collect::<paraformer::Result<_>>()?;
                println!("{k:>10} {:>12.2} {:>12.2} {:>14.2}", g[0], g[1], g[2]);
                rows.push_str(&format!("{k},{},{},{}\n", g[0], g[1], g[2]));
            }
            println!("paper (2048): SuperGlue 125.85, ParaFormer 104.22, ParaFormer-U 61.67");
            if let Some(path) = csv {
                std::fs::write(&path, rows).map_err(|source| paraformer::Error::Io { path: path.clone(), source })?;
            }
        }
        Command::Bench { model, keypoints, repeat } => {
            println!("simd: {}, threads: {}", paraformer::kernels::simd_name(), rayon_threads());
            println!("{:<13} {:>6} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>11}", "model", "kp", "total ms", "encoder", "layers", "final", "sinkhorn", "extract", "GFLOP/s net");
            for name in &model {
                let cfg = Config::preset(name)?;
                let matcher = Matcher::random(cfg.clone(), 0)?;
                for &k in &keypoints {
                    let (f0, f1) = (random_features(k, cfg.descriptor_dim, 1), random_features(k, cfg.descriptor_dim, 2));
                    matcher.profile(&f0, &f1, MatchOptions::default())?;
                    let mut best: Option<paraformer::Profile> = None;
                    for _ in 0..repeat.max(1) {
                        let (_, p) = matcher.profile(&f0, &f1, MatchOptions::default())?;
                        if best.is_none_or(|b| p.total() < b.total()) {
                            best = Some(p);
                        }
                    }
                    let p = best.unwrap_or_default();
                    let ms = |s: f64| s * 1e3;
                    println!(
                        "{name:<13} {k:>6} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>11.1}",
                        ms(p.total()), ms(p.encoder), ms(p.layers), ms(p.final_projection), ms(p.sinkhorn), ms(p.extraction),
                        2.0 * p.macs as f64 / p.network() / 1e9
                    );
                }
            }
        }
        Command::Inspect { weights } => {
            let w = Weights::from_file(&weights)?;
            let matcher = Matcher::from_weights(&w)?;
            println!("{}", matcher.config().to_json());
            println!("{} tensors, all present with the expected shapes", w.names().count());
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
