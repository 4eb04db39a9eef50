//! The `paraformer` command line: outputs, and one clear error line with a non-zero
//! exit code on bad input.

use std::process::Command;

fn run(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_paraformer")).args(args).output().expect("binary runs");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
}

fn data(rel: &str) -> String {
    format!("{}/../../tests/data/{rel}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn flops_prints_the_table_7_column() {
    let (ok, out, _) = run(&["flops", "--keypoints", "2048"]);
    assert!(ok);
    assert!(out.contains("127.41") && out.contains("105.90") && out.contains("65.77"), "{out}");
}

#[test]
fn demo_and_inspect_on_fixtures() {
    let (ok, out, err) = run(&[
        "demo",
        "--weights",
        &data("spec_vectors/paraformer.weights.safetensors"),
        "--pair",
        &data("spec_vectors/paraformer.case0.safetensors"),
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("20 matches"), "{out}");
    let (ok, out, _) = run(&["inspect", &data("golden/paraformer_u.weights.safetensors")]);
    assert!(ok);
    assert!(out.contains("\"model\":\"paraformer_u\""), "{out}");
}

#[test]
fn errors_are_one_line_with_a_non_zero_exit() {
    for args in [
        vec!["inspect", "/no/such/file.safetensors"],
        vec!["inspect", env!("CARGO_MANIFEST_DIR")],
        vec!["demo", "--weights", &data("spec_vectors/index.json")],
        vec!["eval", "homography", "--data", "/no/such/dir", "--features", "/no/such/f.safetensors"],
    ] {
        let (ok, _, err) = run(&args);
        assert!(!ok, "{args:?} should fail");
        assert_eq!(err.trim().lines().count(), 1, "{args:?}: {err}");
        assert!(err.starts_with("error: "), "{err}");
    }
}

fn sample(name: &str) -> String {
    format!("{}/../../assets/sample/{name}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn match_on_the_sample_pair_recovers_its_homography() {
    let dir = std::env::temp_dir().join(format!("paraformer-cli-match-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp dir");
    let (png, json) = (dir.join("m.png"), dir.join("m.json"));
    let (ok, out, err) = run(&[
        "match",
        &sample("coffee_0.jpg"),
        &sample("coffee_1.jpg"),
        "--matcher",
        "mnn",
        "--max-keypoints",
        "512",
        "--out",
        png.to_str().expect("utf-8 path"),
        "--json",
        json.to_str().expect("utf-8 path"),
    ]);
    assert!(ok, "{err}");
    for needle in ["512 keypoints", "mutual NN", "inliers", "extract", "wrote"] {
        assert!(out.contains(needle), "missing {needle:?} in {out}");
    }
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).expect("json written")).expect("valid json");
    assert_eq!(v["keypoints0"], 512);
    // The estimated homography maps the image centre within 2 px of the true one.
    let truth: Vec<f64> = std::fs::read_to_string(sample("H_0to1.txt"))
        .expect("H")
        .split_whitespace()
        .map(|t| t.parse().expect("number"))
        .collect();
    let est: Vec<f64> = v["model"].as_array().expect("model").iter().flat_map(|r| r.as_array().expect("row").iter().map(|x| x.as_f64().expect("f64"))).collect();
    let apply = |h: &[f64], x: f64, y: f64| {
        let w = h[6] * x + h[7] * y + h[8];
        ((h[0] * x + h[1] * y + h[2]) / w, (h[3] * x + h[4] * y + h[5]) / w)
    };
    let (a, b) = (apply(&truth, 300.0, 200.0), apply(&est, 300.0, 200.0));
    assert!((a.0 - b.0).hypot(a.1 - b.1) < 2.0, "{a:?} vs {b:?}");
    assert!(v["num_inliers"].as_u64().expect("count") > 100);
    assert!(image::open(&png).is_ok());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn match_errors_are_one_line() {
    let readme = format!("{}/../../README.md", env!("CARGO_MANIFEST_DIR"));
    let (s0, s1) = (sample("coffee_0.jpg"), sample("coffee_1.jpg"));
    for (args, needle) in [
        (vec!["match", s0.as_str(), "/no/such.jpg"], "/no/such.jpg"),
        (vec!["match", s0.as_str(), readme.as_str()], "unreadable image"),
        (vec!["match", s0.as_str(), s1.as_str(), "--weights", readme.as_str()], "safetensors"),
        (vec!["match", s0.as_str(), s1.as_str(), "--matcher", "nonsense"], "not nn, mnn"),
        (vec!["match", s0.as_str(), s1.as_str(), "--geometry", "affine"], "geometry"),
        (vec!["match", s0.as_str(), s1.as_str(), "--max-keypoints", "0"], "max-keypoints"),
        (vec!["match", s0.as_str(), s1.as_str(), "--matcher", "ratio:-1"], "(0, 1]"),
        (vec!["match", s0.as_str(), s1.as_str(), "--matcher", "ratio:NaN"], "(0, 1]"),
        (vec!["match", s0.as_str(), s1.as_str(), "--matcher", "ratio:x"], "ratio:x"),
        (vec!["match", s0.as_str(), s1.as_str(), "--threshold", "0"], "--threshold"),
        (vec!["match", s0.as_str(), s1.as_str(), "--threshold", "NaN"], "--threshold"),
        (vec!["bench", "--model", "paraformer-xfeat", "--keypoints", "0"], "--keypoints"),
        (vec!["bench", "--model", "paraformer-xfeat", "--keypoints", "64", "--repeat", "0"], "--repeat"),
    ] {
        let (ok, out, err) = run(&args);
        assert!(!ok, "{args:?} succeeded: {out}");
        assert_eq!(err.trim().lines().count(), 1, "{args:?}: {err}");
        assert!(err.starts_with("error: ") && err.contains(needle), "{args:?}: {err}");
    }
}

#[test]
fn memory_limit_refuses_with_a_one_line_error() {
    let (ok, _, err) = run(&["--memory-limit", "1M", "match", &sample("coffee_0.jpg"), &sample("coffee_1.jpg")]);
    assert!(!ok && err.contains("needs") && err.contains("limit of 1.0 MB") && err.trim().lines().count() == 1, "{err}");
    // bench checks the limit before it makes its random features (which alone would not fit).
    let (ok, _, err) = run(&["bench", "--model", "paraformer-xfeat", "--keypoints", "100000000", "--repeat", "1"]);
    assert!(!ok && err.contains("100000000 × 100000000 keypoints needs") && err.trim().lines().count() == 1, "{err}");
    let (ok, _, err) = run(&["bench", "--model", "paraformer-xfeat", "--keypoints", &usize::MAX.to_string(), "--repeat", "1"]);
    assert!(!ok && err.contains("needs"), "{err}");
    let (ok, _, err) = run(&["--memory-limit", "lots", "flops"]);
    assert!(!ok && err.contains("8G"), "{err}");
    for below_a_byte in ["0", "0.5", "1e-12G"] {
        let (ok, _, err) = run(&["--memory-limit", below_a_byte, "flops"]);
        assert!(!ok && err.contains("at least one byte"), "{below_a_byte}: {err}");
    }
}

#[test]
fn rotations_4_recovers_a_pair_turned_by_180_degrees() {
    let dir = std::env::temp_dir().join(format!("paraformer-rot-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let turned = dir.join("coffee_1_turned.png");
    let img = image::open(sample("coffee_1.jpg")).expect("sample decodes").rotate180();
    img.save(&turned).expect("writes");
    let json = dir.join("m.json");
    let (ok, out, err) = run(&["match", &sample("coffee_0.jpg"), turned.to_str().unwrap(), "--rotations", "4", "--max-keypoints", "1024",
                                "--json", json.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(out.contains("turned 180°"), "{out}");
    let text = std::fs::read_to_string(&json).expect("json written");
    assert_eq!(text.lines().count(), 1, "compact JSON is one line");
    let v: serde_json::Value = serde_json::from_str(&text).expect("valid JSON");
    assert_eq!(v["rotation"], 180);
    assert!(v["num_inliers"].as_u64().unwrap_or(0) > 100, "{v}");
    let (ok, _, err) = run(&["match", &sample("coffee_0.jpg"), &sample("coffee_1.jpg"), "--rotations", "3"]);
    assert!(!ok && err.contains("--rotations") && err.contains("1 or 4"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn demo_runs_from_any_folder() {
    let dir = std::env::temp_dir();
    let out = Command::new(env!("CARGO_BIN_EXE_paraformer")).arg("demo").current_dir(&dir).output().expect("runs");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("matches in"), "{text}");
}

#[test]
fn matchers_are_named_alike_and_errors_name_the_file() {
    let (ok, out, err) = run(&["inspect", "paraformer-xfeat"]);
    assert!(ok, "{err}");
    assert!(out.contains("\"model\":\"paraformer\"") && !out.contains("layer_names") && !out.contains("stage_dims"), "{out}");
    let (ok, out, _) = run(&["inspect", "paraformer-u-xfeat"]);
    assert!(ok && out.contains("stage_dims") && !out.contains("\"num_layers\""), "{out}");
    let missing_dir = std::env::temp_dir().join("paraformer-no-such-dir").join("m.png");
    let (ok, _, err) = run(&["match", &sample("coffee_0.jpg"), &sample("coffee_1.jpg"), "--max-keypoints", "256",
                              "--out", missing_dir.to_str().unwrap()]);
    assert!(!ok && err.contains("cannot write") && err.contains("m.png"), "{err}");
    let (ok, _, err) = run(&["match", &sample("coffee_0.jpg"), &sample("coffee_1.jpg"), "--weights", &sample("coffee_0.jpg")]);
    assert!(!ok && err.contains("coffee_0.jpg") && err.contains("safetensors"), "{err}");
    let tiny = std::env::temp_dir().join(format!("paraformer-tiny-{}.png", std::process::id()));
    image::GrayImage::new(16, 16).save(&tiny).expect("writes");
    let (ok, _, err) = run(&["match", tiny.to_str().unwrap(), &sample("coffee_1.jpg")]);
    assert!(!ok && err.contains(tiny.to_str().unwrap()) && err.contains("32×32"), "{err}");
    let _ = std::fs::remove_file(&tiny);
}

#[test]
fn every_subcommand_and_argument_has_help() {
    let commands: [&[&str]; 10] = [&[], &["demo"], &["inspect"], &["flops"], &["eval", "homography"], &["eval", "pose"],
                                   &["synth"], &["match"], &["draw"], &["bench"]];
    for cmd in commands {
        let mut args: Vec<&str> = cmd.to_vec();
        args.push("--help");
        let (ok, out, err) = run(&args);
        assert!(ok, "{args:?}: {err}");
        let mut section = false;
        for line in out.lines() {
            if line.ends_with(':') && !line.starts_with(' ') {
                section = matches!(line, "Arguments:" | "Options:" | "Commands:");
                continue;
            }
            if section && !line.trim().is_empty() && line.starts_with("  ") && !line.starts_with("          ") {
                // "  <NAME>  text" / "  --flag <V>  text": something after the name column
                let described = line.trim().split_once("  ").is_some_and(|(_, t)| !t.trim().is_empty());
                assert!(described, "{args:?}: no help for `{}`", line.trim());
            }
        }
    }
}

#[test]
fn precision_bf16_matches_the_sample_pair_and_bad_values_are_named() {
    let (ok, out, err) = run(&["match", &sample("coffee_0.jpg"), &sample("coffee_1.jpg"), "--precision", "bf16"]);
    assert!(ok, "{err}");
    assert!(out.contains("inliers"), "{out}");
    let (ok, out, _) = run(&["bench", "--model", "paraformer-xfeat", "--keypoints", "256", "--repeat", "1", "--precision", "bf16"]);
    assert!(ok && out.contains("precision: bf16"), "{out}");
    let (ok, _, err) = run(&["match", &sample("coffee_0.jpg"), &sample("coffee_1.jpg"), "--precision", "fp16"]);
    assert!(!ok && err.contains("--precision") && err.contains("fp16"), "{err}");
}

/// `PARAFORMER_ALLOCATOR` selects mimalloc (the default) or the system allocator, and the
/// bench header names the one in use; any other value is refused by name.
#[test]
fn allocator_is_chosen_by_the_environment_and_reported() {
    let bench = |value: Option<&str>| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_paraformer"));
        cmd.args(["bench", "--model", "superglue", "--keypoints", "16", "--repeat", "1"]).env_remove("PARAFORMER_ALLOCATOR");
        if let Some(v) = value {
            cmd.env("PARAFORMER_ALLOCATOR", v);
        }
        let out = cmd.output().expect("binary runs");
        (out.status.success(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    for (value, name) in [(None, "mimalloc"), (Some("mimalloc"), "mimalloc"), (Some("system"), "system")] {
        let (ok, out, err) = bench(value);
        assert!(ok, "{value:?}: {err}");
        assert!(out.contains(&format!("allocator: {name}")), "{value:?}: {out}");
    }
    let (ok, _, err) = bench(Some("jemalloc"));
    assert!(!ok);
    assert!(err.contains("PARAFORMER_ALLOCATOR") && err.contains("\"jemalloc\"") && err.contains("expected"), "{err}");
}

/// Output into a pipe the reader closed early ends the process without a panic message.
#[cfg(unix)]
#[test]
fn closed_stdout_pipe_ends_quietly() {
    use std::io::{BufRead, BufReader};
    use std::process::Stdio;
    let mut child = Command::new(env!("CARGO_BIN_EXE_paraformer"))
        .args(["bench", "--model", "paraformer-xfeat", "--keypoints", "64", "--keypoints", "128", "--keypoints", "256", "--repeat", "1"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("binary runs");
    let mut first = String::new();
    BufReader::new(child.stdout.take().expect("stdout")).read_line(&mut first).expect("first line");
    // The reader is gone: the next lines go into a closed pipe.
    let out = child.wait_with_output().expect("binary ends");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(first.starts_with("simd:"), "{first}");
    assert!(!err.contains("panicked") && !err.contains("Broken pipe"), "{err}");
}

/// `PARAFORMER_SIMD` caps the level of the project's kernels (the bench header names the level
/// that runs, never one above the CPU's); any value but a level's name is refused by name.
#[test]
fn simd_cap_is_read_from_the_environment_and_a_bad_value_is_named() {
    let bench = |value: &str| {
        let out = Command::new(env!("CARGO_BIN_EXE_paraformer"))
            .args(["bench", "--model", "paraformer-xfeat", "--keypoints", "64", "--repeat", "1"])
            .env("PARAFORMER_SIMD", value)
            .output()
            .expect("binary runs");
        (out.status.success(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let widest = paraformer::kernels::simd_name();
    let (ok, out, err) = bench("avx512");
    assert!(ok && out.contains(&format!("simd: {widest},")), "{out}{err}");
    let (ok, out, err) = bench("avx2");
    let capped = if widest == "baseline" { "baseline" } else { "avx2" };
    assert!(ok && out.contains(&format!("simd: {capped},")), "{out}{err}");
    let (ok, out, err) = bench("baseline");
    assert!(ok && out.contains("simd: baseline,"), "{out}{err}");
    let (ok, _, err) = bench("sse9");
    assert!(!ok && err.contains("PARAFORMER_SIMD") && err.contains("\"sse9\"") && err.contains("expected"), "{err}");
}

/// `PARAFORMER_AMX=0` keeps bf16 off the AMX tiles (the bench header says whether they run);
/// any value but 0, 1, on, off, true or false is refused by name.
#[test]
fn amx_switch_is_read_from_the_environment_and_a_bad_value_is_named() {
    let bench = |value: &str| {
        let out = Command::new(env!("CARGO_BIN_EXE_paraformer"))
            .args(["bench", "--model", "paraformer-xfeat", "--keypoints", "64", "--repeat", "1", "--precision", "bf16"])
            .env("PARAFORMER_AMX", value)
            .output()
            .expect("binary runs");
        (out.status.success(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
    };
    let (ok, out, err) = bench("0");
    assert!(ok && out.contains("precision: bf16") && !out.contains("AMX"), "{out}{err}");
    let (ok, out, err) = bench("1");
    assert!(ok, "{err}");
    // On tiles exactly where the library says they are supported (bf16 needs AVX-512 BF16).
    let expect = paraformer::amx::supported() && paraformer::Precision::Bf16.effective() == paraformer::Precision::Bf16;
    assert_eq!(out.contains("on AMX tiles"), expect, "{out}");
    let (ok, _, err) = bench("maybe");
    assert!(!ok && err.contains("PARAFORMER_AMX") && err.contains("\"maybe\"") && err.contains("expected"), "{err}");
}
