//! Parity with the SPEC test vectors of an independent implementation
//! (`tests/data/spec_vectors`, copied from `../shared/spec_vectors`).
//! Pass: identical matches, `log_assignment` and matching scores within 1e-4 absolute.

mod common;

use std::collections::HashMap;

use common::{check_case, data_dir, load_case};
use paraformer::Matcher;

const TOL: f32 = 1e-4;

#[derive(serde::Deserialize)]
struct IndexEntry {
    case: String,
    weights: String,
    #[serde(rename = "M")]
    m: usize,
    #[serde(rename = "N")]
    n: usize,
    valid_matches: usize,
}

#[test]
fn every_spec_vector_matches() {
    let dir = data_dir().join("spec_vectors");
    let index: Vec<IndexEntry> =
        serde_json::from_slice(&common::read(&dir.join("index.json"))).expect("index.json parses");
    assert_eq!(index.len(), 30, "expected 10 configurations × 3 cases");
    let mut matchers: HashMap<String, Matcher> = HashMap::new();
    for e in &index {
        let matcher = matchers
            .entry(e.weights.clone())
            .or_insert_with(|| Matcher::from_file(dir.join(&e.weights)).unwrap_or_else(|err| panic!("{}: {err}", e.weights)));
        let case = load_case(&dir.join(&e.case));
        assert_eq!(case.weights, e.weights);
        assert_eq!((case.f0.len(), case.f1.len()), (e.m, e.n), "{}", e.case);
        assert_eq!(case.matches0.iter().filter(|&&j| j >= 0).count(), e.valid_matches, "{}", e.case);
        let d = check_case(matcher, &case, TOL, &e.case);
        println!("{:<55} M={:<3} N={:<3} max|Δ log_assignment| = {d:.2e}", e.case, e.m, e.n);
    }
}

/// The golden fixtures of our PyTorch reference (`training/make_fixtures.py`): 100
/// Sinkhorn iterations, widths 8–24, `input_proj` on every model, a U-Net stage of
/// depth 0, all switches off at once, and an f16 weights file.
#[test]
fn every_golden_fixture_matches() {
    let dir = data_dir().join("golden");
    let index: Vec<IndexEntry> =
        serde_json::from_slice(&common::read(&dir.join("index.json"))).expect("index.json parses");
    assert!(index.len() >= 40, "golden index has {} cases", index.len());
    for e in &index {
        let matcher = Matcher::from_file(dir.join(&e.weights)).unwrap_or_else(|err| panic!("{}: {err}", e.weights));
        let case = load_case(&dir.join(&e.case));
        assert_eq!((case.f0.len(), case.f1.len()), (e.m, e.n), "{}", e.case);
        assert_eq!(case.matches0.iter().filter(|&&j| j >= 0).count(), e.valid_matches, "{}", e.case);
        let d = check_case(&matcher, &case, TOL, &e.case);
        println!("{:<55} M={:<3} N={:<3} max|Δ log_assignment| = {d:.2e}", e.case, e.m, e.n);
    }
}
