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
    /// Memory limit for matching and extraction, in bytes or with a unit (`8G`, `512M`);
    /// default: 90% of the memory available. A call needing more fails with an error.
    #[arg(long, global = true, value_parser = parse_bytes)]
    memory_limit: Option<u64>,
    /// Arithmetic of the learned matchers' attention: fp32 (default) or bf16 (bf16
    /// operands, fp32 sums; needs AVX-512 BF16, elsewhere runs as fp32).
    #[arg(long, global = true, default_value = "fp32", value_parser = parse_precision)]
    precision: paraformer::Precision,
    #[command(subcommand)]
    command: Command,
}

fn parse_precision(s: &str) -> Result<paraformer::Precision, String> {
    paraformer::Precision::parse(s).map_err(|e| e.to_string())
}

/// `8G`, `512M`, `64K` or plain bytes; at least one byte (beyond `u64` it saturates).
fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let (num, mult) = match t.char_indices().last() {
        Some((i, c)) if c.is_ascii_alphabetic() => {
            let m = match c.to_ascii_uppercase() {
                'K' => 1u64 << 10,
                'M' => 1 << 20,
                'G' => 1 << 30,
                'T' => 1 << 40,
                _ => return Err(format!("expected a size such as 8G or 512M (units K, M, G, T), got {s:?}")),
            };
            (&t[..i], m)
        }
        _ => (t, 1),
    };
    let v: f64 = num.trim().parse().map_err(|_| format!("expected a size such as 8G or 512M, got {s:?}"))?;
    // Below one byte (`0.5`) the limit would round to 0 and refuse every call.
    if !v.is_finite() || v * (mult as f64) < 1.0 {
        return Err(format!("expected a positive size of at least one byte, got {s:?}"));
    }
    Ok((v * mult as f64) as u64)
}

#[derive(Subcommand)]
enum Command {
    /// Match one pair of stored features (a pair file, as in tests/data) and print the matches.
    Demo {
        /// Weights file (safetensors with `paraformer.config` metadata); default: the SPEC
        /// test-vector model built into the binary.
        #[arg(long)]
        weights: Option<PathBuf>,
        /// Pair file: keypoints0/1, scores0/1, descriptors0/1, image_size0/1; default: the
        /// SPEC test-vector pair built into the binary.
        #[arg(long)]
        pair: Option<PathBuf>,
    },
    /// Print the config and tensor names of a weights file, after a strict check.
    Inspect {
        /// A shipped matcher name (paraformer-xfeat, paraformer-u-xfeat) or a weights file.
        weights: String,
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
    /// Evaluate matchers on a dataset with precomputed features.
    Eval {
        #[command(subcommand)]
        task: EvalTask,
    },
    /// Write seeded synthetic homography pairs (PNG + homographies.txt) from a folder of photos.
    Synth {
        /// Folder of photos to warp.
        #[arg(long)]
        photos: PathBuf,
        /// Output folder (PNG pairs and homographies.txt).
        #[arg(long)]
        out: PathBuf,
        /// Pairs to write.
        #[arg(long, default_value_t = 200)]
        count: usize,
        /// Seed of the warps (the pairs are a pure function of it).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// 0 (identity) to 1 (corner shifts 25%, rotation ±45°, scale 0.7–1.3).
        #[arg(long, default_value_t = 0.5)]
        difficulty: f64,
    },
    /// Match two images end to end: XFeat keypoints and descriptors, a matcher, a robust
    /// geometric model; prints counts, the model and a timing breakdown.
    Match {
        /// First image (PNG, JPEG, PNM, BMP, TIFF, WebP).
        image0: PathBuf,
        /// Second image.
        image1: PathBuf,
        /// paraformer-xfeat (default), paraformer-u-xfeat, nn, mnn, ratio, ratio:R, or a
        /// weights file.
        #[arg(long, conflicts_with = "weights")]
        matcher: Option<String>,
        /// A weights file (safetensors with `paraformer.config` metadata) instead of --matcher.
        #[arg(long)]
        weights: Option<PathBuf>,
        /// Keypoints kept per image (best XFeat scores first).
        #[arg(long, default_value_t = 2048)]
        max_keypoints: usize,
        /// Model fitted by RANSAC: homography or fundamental.
        #[arg(long, default_value = "homography")]
        geometry: String,
        /// RANSAC threshold in pixels.
        #[arg(long, default_value_t = 3.0)]
        threshold: f64,
        /// Write the side-by-side picture (inliers green, outliers red) to this PNG.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write keypoint counts, matches, inliers, the model and timings as JSON (compact).
        #[arg(long)]
        json: Option<PathBuf>,
        /// Indent the --json output.
        #[arg(long, requires = "json")]
        pretty: bool,
        /// 1: match image1 as given; 4: also turned by 90, 180 and 270° (XFeat's descriptors
        /// are upright), keeping the turn with the most inliers.
        #[arg(long, default_value_t = 1)]
        rotations: usize,
    },
    /// Draw the matches of one pair side by side (inliers green, outliers red) into a PNG.
    Draw {
        /// First image.
        image0: PathBuf,
        /// Second image.
        image1: PathBuf,
        /// Features file holding both images (by file name).
        #[arg(long)]
        features: PathBuf,
        /// paraformer-xfeat, paraformer-u-xfeat, nn, mnn, ratio, ratio:R, or a weights file.
        #[arg(long, default_value = "mnn")]
        matcher: String,
        /// Model that decides inliers: homography or fundamental.
        #[arg(long, default_value = "homography")]
        geometry: String,
        /// RANSAC threshold in pixels.
        #[arg(long, default_value_t = 3.0)]
        threshold: f64,
        #[arg(long, default_value = "matches.png")]
        out: PathBuf,
    },
    /// Time matching with random weights, part by part, in --precision.
    Bench {
        /// superglue, paraformer, paraformer_u (the paper's widths), a shipped matcher's
        /// name (its config), or a config JSON file (repeatable; default the three presets).
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

/// What both evaluations take besides their data.
#[derive(clap::Args)]
struct EvalArgs {
    /// Features file (safetensors: `{image}::keypoints|scores|descriptors|image_size`).
    #[arg(long)]
    features: PathBuf,
    /// Comma-separated: paraformer-xfeat, paraformer-u-xfeat, nn, mnn, ratio, ratio:R, or weights files.
    #[arg(long, value_delimiter = ',', default_values_t = vec!["nn".to_string(), "mnn".to_string(), "ratio".to_string()])]
    matcher: Vec<String>,
    /// Write the results as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Subcommand)]
enum EvalTask {
    /// Homography estimation: corner-error AUC@1/3/5/10 px, precision/recall/F1, MMA.
    Homography {
        /// An HPatches-style folder (img1..N + H1toNp / H_1_N) or a homographies.txt list.
        #[arg(long)]
        data: PathBuf,
        #[command(flatten)]
        common: EvalArgs,
        /// RANSAC inlier threshold in pixels.
        #[arg(long, default_value_t = 3.0)]
        threshold: f64,
    },
    /// Relative pose: AUC@5/10/20° of max(angle R, angle t), exact and approximate.
    Pose {
        /// A Strecha-format scene folder, or a pairs_with_gt.txt file (images beside it in images/).
        #[arg(long)]
        data: PathBuf,
        #[command(flatten)]
        common: EvalArgs,
        /// RANSAC inlier threshold (Sampson distance, pixels).
        #[arg(long, default_value_t = 1.0)]
        threshold: f64,
        /// Strecha: pair images at most this far apart in the sequence.
        #[arg(long, default_value_t = 2)]
        max_gap: usize,
    },
}

/// The config `bench --model` names: a preset, a shipped matcher or a JSON file.
fn bench_config(name: &str) -> paraformer::Result<Config> {
    if let Some(p) = paraformer::matcher::PRETRAINED.iter().find(|p| p.0 == name) {
        return Ok(Matcher::from_bytes(p.1)?.config().clone());
    }
    if name.ends_with(".json") {
        let text = std::fs::read_to_string(name).map_err(|e| input_error("--model", format!("cannot read `{name}`: {e}")))?;
        return Config::from_json(&text);
    }
    Config::preset(name)
}

const MODELS: [&str; 3] = ["superglue", "paraformer", "paraformer_u"];

/// The `--precision` of this run, applied to every learned matcher the CLI builds.
static PRECISION: std::sync::OnceLock<paraformer::Precision> = std::sync::OnceLock::new();

fn precision() -> paraformer::Precision {
    PRECISION.get().copied().unwrap_or_default()
}

/// A matcher by name or file, in this run's precision.
fn matcher_spec(name: &str) -> paraformer::Result<paraformer::eval::harness::MatcherSpec> {
    let mut spec = paraformer::eval::harness::MatcherSpec::parse(name)?;
    spec.set_precision(precision());
    Ok(spec)
}

fn run(cli: Cli) -> paraformer::Result<()> {
    let _ = PRECISION.set(cli.precision);
    if cli.memory_limit.is_some() {
        paraformer::memory::set_memory_limit(cli.memory_limit);
    }
    match cli.command {
        Command::Demo { weights, pair } => {
            // Built in, so that `paraformer demo` runs from any folder.
            const DEMO_WEIGHTS: &[u8] = include_bytes!("../demo/paraformer.weights.safetensors");
            const DEMO_PAIR: &[u8] = include_bytes!("../demo/paraformer.case0.safetensors");
            let matcher = match &weights {
                Some(w) => Matcher::from_file(w)?,
                None => Matcher::from_bytes(DEMO_WEIGHTS)?,
            }
            .with_precision(precision());
            let (f0, f1) = match &pair {
                Some(p) => read_pair_file(p)?,
                None => paraformer::read_pair_bytes(DEMO_PAIR)?,
            };
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
                std::fs::write(&path, rows).map_err(|source| paraformer::Error::Write { path: path.clone(), source })?;
            }
        }
        Command::Bench { model, keypoints, repeat } => {
            if keypoints.contains(&0) {
                return Err(input_error("--keypoints", "must be at least 1"));
            }
            if repeat == 0 {
                return Err(input_error("--repeat", "must be at least 1"));
            }
            println!("simd: {}, threads: {}, allocator: {}", paraformer::kernels::simd_name(), rayon_threads(), paraformer::allocator::name());
            println!("{:<13} {:>6} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>11}", "model", "kp", "total ms", "encoder", "layers", "final", "sinkhorn", "extract", "GFLOP/s net");
            let tiles = if precision().effective() == paraformer::Precision::Bf16 && paraformer::amx::active() { ", on AMX tiles" } else { "" };
            println!("precision: {} (runs as {}{tiles})", precision().name(), precision().effective().name());
            for name in &model {
                let cfg = bench_config(name)?;
                let matcher = Matcher::random(cfg.clone(), 0)?.with_precision(precision());
                for &k in &keypoints {
                    // The limit first: the random features alone can exceed the memory.
                    let needed = paraformer::memory::match_bytes(&cfg, k, k, rayon_threads());
                    paraformer::memory::check(format!("a match of {k} × {k} keypoints"), needed, paraformer::memory::memory_limit())?;
                    let (f0, f1) = (Features::random(k, cfg.descriptor_dim, 1), Features::random(k, cfg.descriptor_dim, 2));
                    matcher.profile(&f0, &f1, MatchOptions::default())?;
                    let mut best: Option<paraformer::Profile> = None;
                    for _ in 0..repeat {
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
        Command::Eval { task } => eval(task)?,
        Command::Synth { photos, out, count, seed, difficulty } => {
            let cfg = paraformer::eval::synthetic::SyntheticConfig { count, seed, difficulty };
            let pairs = paraformer::eval::synthetic::generate(&photos, &out, &cfg)?;
            println!("wrote {} pairs and {}", pairs.len(), out.join("homographies.txt").display());
        }
        Command::Draw { image0, image1, features, matcher, geometry, threshold, out } => {
            let feats = paraformer::eval::datasets::read_features(&features)?;
            let name = |p: &PathBuf| p.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            let get = |n: String| feats.get(&n).ok_or_else(|| paraformer::Error::InvalidInput { argument: "features".into(), reason: format!("no features for `{n}`") });
            let (f0, f1) = (get(name(&image0))?, get(name(&image1))?);
            let cfg = ransac_config(threshold)?;
            let spec = matcher_spec(&matcher)?;
            let m0 = spec.matches(f0, f1)?;
            let (x0, x1) = paraformer::eval::harness::correspondences(f0, f1, &m0);
            let fit = fit_model(&geometry, &x0, &x1, &cfg)?;
            draw(&image0, &image1, &x0, &x1, &fit.inliers, &out)?;
            println!("{} × {} keypoints, {} matches ({}), {} inliers ({geometry}); model:{}", f0.len(), f1.len(), x0.len(), spec.name(), fit.count(), fit.text);
            println!("wrote {}", out.display());
        }
        Command::Match { image0, image1, matcher, weights, max_keypoints, geometry, threshold, out, json, pretty, rotations } => {
            match_images(MatchArgs { image0, image1, matcher, weights, max_keypoints, geometry, threshold, out, json, pretty, rotations })?
        }
        Command::Inspect { weights } => {
            // One way to name a matcher everywhere: a shipped name, else a file.
            let w = match paraformer::matcher::PRETRAINED.iter().find(|p| p.0 == weights) {
                Some((_, bytes)) => Weights::from_bytes(bytes)?,
                None => Weights::from_file(&weights)?,
            };
            let matcher = Matcher::from_weights(&w)?;
            println!("{}", matcher.config().to_json_used());
            println!("{} tensors, all present with the expected shapes", w.names().count());
        }
    }
    Ok(())
}

/// XFeat's errors about "image" name the file instead.
fn name_image<T>(r: paraformer::Result<T>, path: &std::path::Path) -> paraformer::Result<T> {
    r.map_err(|e| match e {
        paraformer::Error::InvalidInput { argument, reason } if argument == "image" => {
            paraformer::Error::InvalidInput { argument: path.display().to_string(), reason }
        }
        e => e,
    })
}

fn input_error(argument: impl Into<String>, reason: impl ToString) -> paraformer::Error {
    paraformer::Error::InvalidInput { argument: argument.into(), reason: reason.to_string() }
}

/// A robust fit: the inlier mask and the model as text and JSON (`None` when RANSAC
/// found no model, which is reported, not an error).
struct Fit {
    inliers: Vec<bool>,
    text: String,
    model: Option<Vec<Vec<f64>>>,
}

impl Fit {
    fn count(&self) -> usize {
        self.inliers.iter().filter(|&&b| b).count()
    }
}

/// One turn of image1 tried by `match --rotations`: its features, matches, correspondences
/// (image1's points in its own frame) and geometric fit.
struct Turn {
    quarters: usize,
    f1: paraformer::Features,
    m0: Vec<i64>,
    x0: Vec<[f64; 2]>,
    x1: Vec<[f64; 2]>,
    fit: Fit,
}

/// RANSAC at `--threshold` pixels, checked (a threshold of 0 or less finds no inliers).
fn ransac_config(threshold: f64) -> paraformer::Result<paraformer::geometry::RansacConfig> {
    let cfg = paraformer::geometry::RansacConfig { threshold, ..Default::default() };
    cfg.validate().map_err(|e| match e {
        paraformer::Error::InvalidInput { reason, .. } => input_error("--threshold", reason),
        other => other,
    })?;
    Ok(cfg)
}

fn fit_model(geometry: &str, x0: &[[f64; 2]], x1: &[[f64; 2]], cfg: &paraformer::geometry::RansacConfig) -> paraformer::Result<Fit> {
    use paraformer::geometry::{epipolar, homography};
    let rows = |m: &paraformer::nalgebra::Matrix3<f64>| (0..3).map(|r| (0..3).map(|c| m[(r, c)]).collect()).collect();
    let text = |m: &Vec<Vec<f64>>, sci: bool| {
        let row = |r: &Vec<f64>| r.iter().map(|v| if sci { format!("{v:.4e}") } else { format!("{v:.4}") }).collect::<Vec<_>>().join(", ");
        format!(" [{}]", m.iter().map(row).collect::<Vec<_>>().join("; "))
    };
    let fit = match geometry {
        "homography" => homography::find_homography(x0, x1, cfg).map(|r| {
            let m: Vec<Vec<f64>> = rows(&(r.model / r.model[(2, 2)]));
            (r.inliers, text(&m, false), m)
        }),
        "fundamental" => epipolar::find_fundamental(x0, x1, cfg).map(|r| {
            let m: Vec<Vec<f64>> = rows(&r.model);
            (r.inliers, text(&m, true), m)
        }),
        other => return Err(input_error("geometry", format!("expected homography or fundamental, got {other}"))),
    };
    Ok(match fit {
        Ok((inliers, text, model)) => Fit { inliers, text, model: Some(model) },
        Err(e) => Fit { inliers: vec![false; x0.len()], text: format!(" no model: {e}"), model: None },
    })
}

fn draw(image0: &PathBuf, image1: &PathBuf, x0: &[[f64; 2]], x1: &[[f64; 2]], inliers: &[bool], out: &PathBuf) -> paraformer::Result<()> {
    let load = |p: &PathBuf| image::open(p).map(|i| i.to_rgb8()).map_err(|e| input_error(p.display().to_string(), e));
    let lines: Vec<_> = x0.iter().zip(x1).zip(inliers).map(|((a, b), &i)| (*a, *b, i)).collect();
    let canvas = paraformer::eval::draw::draw_matches(&load(image0)?, &load(image1)?, &lines);
    canvas.save(out).map_err(|e| paraformer::Error::Write { path: out.clone(), source: std::io::Error::other(e) })
}

struct MatchArgs {
    image0: PathBuf,
    image1: PathBuf,
    matcher: Option<String>,
    weights: Option<PathBuf>,
    max_keypoints: usize,
    geometry: String,
    threshold: f64,
    out: Option<PathBuf>,
    json: Option<PathBuf>,
    pretty: bool,
    rotations: usize,
}

/// The default matcher of `paraformer match`: the shipped ParaFormer when present.
fn default_matcher() -> String {
    let shipped = paraformer::matcher::PRETRAINED.iter().find(|p| p.0 == "paraformer-xfeat");
    shipped.map_or("mnn", |p| p.0).to_string()
}

fn match_images(a: MatchArgs) -> paraformer::Result<()> {
    use paraformer::eval::harness::MatcherSpec;
    use paraformer::{GrayImage, XFeat};
    use std::time::Instant;
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    if a.max_keypoints == 0 {
        return Err(input_error("--max-keypoints", "must be at least 1"));
    }
    // Checked before the images are read, not after the matching.
    let ransac = ransac_config(a.threshold)?;
    if a.rotations != 1 && a.rotations != 4 {
        return Err(input_error("--rotations", format!("must be 1 or 4, got {}", a.rotations)));
    }
    let total = Instant::now();
    let t = Instant::now();
    let spec = match (&a.weights, &a.matcher) {
        (Some(w), _) => {
            let name = w.file_stem().map_or("weights".into(), |s| s.to_string_lossy().into_owned());
            MatcherSpec::Learned(name, Box::new(paraformer::Matcher::from_file(w)?.with_precision(precision())))
        }
        (None, Some(m)) => matcher_spec(m)?,
        (None, None) => matcher_spec(&default_matcher())?,
    };
    let xfeat = XFeat::pretrained()?;
    let t_load = ms(t);
    let t = Instant::now();
    let (img0, img1) = (GrayImage::open(&a.image0)?, GrayImage::open(&a.image1)?);
    let t_decode = ms(t);
    let t = Instant::now();
    let f0 = name_image(xfeat.detect_and_compute(&img0, Some(a.max_keypoints)), &a.image0)?;
    let t_extract0 = ms(t);
    // Image1 as given, and with --rotations 4 also turned by 90, 180, 270°: the turn with
    // the most inliers is kept, its points mapped back into image1's own frame.
    let (mut t_extract1, mut t_match, mut t_geometry) = (0.0, 0.0, 0.0);
    let mut best: Option<Turn> = None;
    for quarters in 0..a.rotations {
        let t = Instant::now();
        let f1 = name_image(xfeat.detect_and_compute(&img1.rotate90(quarters), Some(a.max_keypoints)), &a.image1)?;
        t_extract1 += ms(t);
        let t = Instant::now();
        let m0 = spec.matches(&f0, &f1)?;
        t_match += ms(t);
        let (x0, x1) = paraformer::eval::harness::correspondences(&f0, &f1, &m0);
        let x1 = img1.unrotate_points(&x1, quarters);
        let t = Instant::now();
        let fit = fit_model(&a.geometry, &x0, &x1, &ransac)?;
        t_geometry += ms(t);
        if best.as_ref().is_none_or(|b| fit.count() > b.fit.count()) {
            best = Some(Turn { quarters, f1, m0, x0, x1, fit });
        }
    }
    let Some(Turn { quarters, f1, m0, x0, x1, fit }) = best else {
        return Err(input_error("--rotations", "must be 1 or 4"));
    };
    let t = Instant::now();
    if let Some(out) = &a.out {
        draw(&a.image0, &a.image1, &x0, &x1, &fit.inliers, out)?;
    }
    let t_draw = ms(t);
    let inliers = fit.count();
    println!("image0   {} ({}×{}): {} keypoints", a.image0.display(), img0.width, img0.height, f0.len());
    println!("image1   {} ({}×{}): {} keypoints", a.image1.display(), img1.width, img1.height, f1.len());
    println!("matcher  {}: {} matches", spec.name(), x0.len());
    if a.rotations > 1 {
        println!("rotation image1 turned {}° counter-clockwise matched best", 90 * quarters);
    }
    let share = if x0.is_empty() { 0.0 } else { 100.0 * inliers as f64 / x0.len() as f64 };
    println!("{:<8} {inliers} inliers ({share:.1}%) at {} px; model:{}", a.geometry, a.threshold, fit.text);
    println!(
        "time     load {t_load:.1} ms, decode {t_decode:.1} ms, extract {t_extract0:.1} + {t_extract1:.1} ms, match {t_match:.1} ms, geometry {t_geometry:.1} ms, draw {t_draw:.1} ms, total {:.1} ms ({} threads)",
        ms(total),
        rayon_threads()
    );
    if let Some(out) = &a.out {
        println!("wrote {}", out.display());
    }
    if let Some(path) = &a.json {
        let value = serde_json::json!({
            "image0": a.image0, "image1": a.image1,
            "keypoints0": f0.len(), "keypoints1": f1.len(),
            "matcher": spec.name(),
            "matches": m0.iter().enumerate().filter(|(_, &j)| j >= 0).map(|(i, &j)| [i as i64, j]).collect::<Vec<_>>(),
            "points0": x0, "points1": x1,
            "inliers": fit.inliers,
            "num_inliers": inliers,
            "geometry": a.geometry,
            "model": fit.model,
            "rotation": 90 * quarters,
            "timings_ms": {"load": t_load, "decode": t_decode, "extract0": t_extract0, "extract1": t_extract1, "match": t_match, "geometry": t_geometry, "draw": t_draw, "total": ms(total)},
        });
        let text = if a.pretty { serde_json::to_string_pretty(&value) } else { serde_json::to_string(&value) }
            .map_err(|e| input_error("--json", e))?;
        std::fs::write(path, text).map_err(|source| paraformer::Error::Write { path: path.clone(), source })?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// A textual progress bar on stderr.
fn progress(label: &str) -> impl FnMut(usize, usize) + '_ {
    move |i, n| {
        let width = 30;
        let filled = (i * width).checked_div(n).unwrap_or(width);
        eprint!("\r{label:<16} [{}{}] {i}/{n}", "#".repeat(filled), ".".repeat(width - filled));
        if i == n {
            eprintln!();
        }
    }
}

fn eval(task: EvalTask) -> paraformer::Result<()> {
    use paraformer::eval::{datasets, harness};
    let write_json = |path: &Option<PathBuf>, value: serde_json::Value| -> paraformer::Result<()> {
        if let Some(p) = path {
            let text = serde_json::to_string_pretty(&value).unwrap_or_default();
            std::fs::write(p, text).map_err(|source| paraformer::Error::Write { path: p.clone(), source })?;
            println!("wrote {}", p.display());
        }
        Ok(())
    };
    match task {
        EvalTask::Homography { data, common: EvalArgs { features, matcher, json }, threshold } => {
            let pairs = if data.is_file() { datasets::read_homography_list(&data)? } else { datasets::read_hpatches_folder(&data)? };
            let feats = datasets::read_features(&features)?;
            let cfg = ransac_config(threshold)?;
            let mut rows = Vec::new();
            for m in &matcher {
                let spec = matcher_spec(m)?;
                rows.push(harness::eval_homography(&pairs, &feats, &spec, &cfg, progress(spec.name()))?);
            }
            println!("{} pairs from {}", pairs.len(), data.display());
            println!("{:<18} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8}", "matcher", "AUC@1", "AUC@3", "AUC@5", "AUC@10", "P", "R", "F1", "MMA@3", "matches");
            for r in &rows {
                println!(
                    "{:<18} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>8.1}",
                    r.matcher, r.auc[0], r.auc[1], r.auc[2], r.auc[3], r.precision, r.recall, r.f1, r.mma[2], r.mean_matches
                );
            }
            write_json(&json, serde_json::json!({ "task": "homography", "data": data, "features": features, "rows": rows }))?;
        }
        EvalTask::Pose { data, common: EvalArgs { features, matcher, json }, threshold, max_gap } => {
            let pairs = if data.is_file() {
                let dir = data.parent().map(|p| p.join("images")).unwrap_or_default();
                datasets::read_pairs_with_gt(&data, &dir)?
            } else {
                datasets::read_strecha(&data, max_gap)?
            };
            let feats = datasets::read_features(&features)?;
            let cfg = ransac_config(threshold)?;
            let mut rows = Vec::new();
            for m in &matcher {
                let spec = matcher_spec(m)?;
                rows.push(harness::eval_pose(&pairs, &feats, &spec, &cfg, progress(spec.name()))?);
            }
            println!("{} pairs from {}", pairs.len(), data.display());
            println!("{:<18} {:>7} {:>7} {:>7} {:>9} {:>9} {:>9} {:>8} {:>8}", "matcher", "AUC@5", "AUC@10", "AUC@20", "~AUC@5", "~AUC@10", "~AUC@20", "matches", "inliers");
            for r in &rows {
                println!(
                    "{:<18} {:>7.2} {:>7.2} {:>7.2} {:>9.2} {:>9.2} {:>9.2} {:>8.1} {:>8.1}",
                    r.matcher, r.auc[0], r.auc[1], r.auc[2], r.auc_approx[0], r.auc_approx[1], r.auc_approx[2], r.mean_matches, r.mean_inliers
                );
            }
            write_json(&json, serde_json::json!({ "task": "pose", "data": data, "features": features, "rows": rows }))?;
        }
    }
    Ok(())
}

// mimalloc unless PARAFORMER_ALLOCATOR=system (paraformer::allocator; README, Performance).
#[global_allocator]
static GLOBAL: paraformer::allocator::ProcessAllocator = paraformer::allocator::ProcessAllocator;

fn main() -> ExitCode {
    // Output into a closed pipe (`paraformer bench | head`) ends the process quietly, as other
    // command-line tools do, instead of a panic in `println!` (Rust ignores SIGPIPE).
    #[cfg(unix)]
    // SAFETY: restores the default disposition before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    if let Err(e) = paraformer::allocator::check_env().and_then(|_| paraformer::amx::check_env()).and_then(|_| paraformer::kernels::check_env()) {
        eprintln!("error: {e}");
        return ExitCode::FAILURE;
    }
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
