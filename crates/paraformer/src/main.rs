//! The `paraformer` command line.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use paraformer::{read_pair_file, MatchOptions, Matcher, Weights};

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
