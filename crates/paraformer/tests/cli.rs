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
