//! Helpers shared by the integration tests: fixture paths, reading expected outputs,
//! and rewriting safetensors files to build bad inputs.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::PathBuf;

use paraformer::{read_pair_bytes, Features, MatchOptions, Matcher};
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};

/// The repository's `tests/data` folder.
pub fn data_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data")
}

pub fn read(path: &PathBuf) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("cannot read fixture {}: {e}", path.display()))
}

/// One tensor of a safetensors file, owned.
#[derive(Clone, Debug)]
pub struct Entry {
    pub name: String,
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

/// All tensors and the metadata of a safetensors file.
pub fn entries(bytes: &[u8]) -> (Vec<Entry>, HashMap<String, String>) {
    let st = SafeTensors::deserialize(bytes).expect("fixture is valid safetensors");
    let (_, meta) = SafeTensors::read_metadata(bytes).expect("fixture metadata");
    let mut out: Vec<Entry> = st
        .tensors()
        .into_iter()
        .map(|(name, v)| Entry { name, dtype: v.dtype(), shape: v.shape().to_vec(), data: v.data().to_vec() })
        .collect();
    out.sort_by(|a, b| a.name.cmp(&b.name));
    (out, meta.metadata().clone().unwrap_or_default())
}

/// Serialises tensors and metadata back into safetensors bytes.
pub fn serialize(entries: &[Entry], meta: &HashMap<String, String>) -> Vec<u8> {
    let views: Vec<(String, TensorView)> = entries
        .iter()
        .map(|e| (e.name.clone(), TensorView::new(e.dtype, e.shape.clone(), &e.data).expect("consistent tensor")))
        .collect();
    let meta = if meta.is_empty() { None } else { Some(meta.clone()) };
    safetensors::tensor::serialize(views, meta).expect("serialize")
}

pub fn f32s(e: &Entry) -> Vec<f32> {
    paraformer::features::f32_from_le(&e.data)
}

pub fn i64s(e: &Entry) -> Vec<i64> {
    e.data.chunks_exact(8).map(|b| i64::from_le_bytes(b.try_into().expect("8 bytes"))).collect()
}

/// A pair with its expected outputs.
pub struct Case {
    pub f0: Features,
    pub f1: Features,
    pub weights: String,
    pub log_assignment: Vec<f32>,
    pub la_shape: Vec<usize>,
    pub matches0: Vec<i64>,
    pub matches1: Vec<i64>,
    pub scores0: Vec<f32>,
    pub scores1: Vec<f32>,
}

pub fn load_case(path: &PathBuf) -> Case {
    let bytes = read(path);
    let (f0, f1) = read_pair_bytes(&bytes).expect("pair inputs");
    let (ents, meta) = entries(&bytes);
    let get = |n: &str| ents.iter().find(|e| e.name == n).unwrap_or_else(|| panic!("{n} missing")).clone();
    let la = get("log_assignment");
    Case {
        f0,
        f1,
        weights: meta.get("weights").cloned().expect("`weights` metadata"),
        log_assignment: f32s(&la),
        la_shape: la.shape.clone(),
        matches0: i64s(&get("matches0")),
        matches1: i64s(&get("matches1")),
        scores0: f32s(&get("matching_scores0")),
        scores1: f32s(&get("matching_scores1")),
    }
}

pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Runs `matcher` on a case and checks it: identical matches, `log_assignment` and
/// matching scores within `tol` absolute. Returns the max abs diff of `log_assignment`.
pub fn check_case(matcher: &Matcher, case: &Case, tol: f32, label: &str) -> f32 {
    let out = matcher
        .match_pair_with(&case.f0, &case.f1, MatchOptions { return_log_assignment: true, ..Default::default() })
        .unwrap_or_else(|e| panic!("{label}: {e}"));
    let la = out.log_assignment.expect("asked for log_assignment");
    assert_eq!(vec![la.rows, la.cols], case.la_shape, "{label}: log_assignment shape");
    let d = max_abs_diff(&la.data, &case.log_assignment);
    assert!(d <= tol, "{label}: log_assignment max abs diff {d} > {tol}");
    assert_eq!(out.matches0, case.matches0, "{label}: matches0");
    assert_eq!(out.matches1, case.matches1, "{label}: matches1");
    let ds = max_abs_diff(&out.matching_scores0, &case.scores0).max(max_abs_diff(&out.matching_scores1, &case.scores1));
    assert!(ds <= tol, "{label}: matching scores max abs diff {ds} > {tol}");
    d
}
