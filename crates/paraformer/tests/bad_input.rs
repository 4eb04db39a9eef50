//! Every bad-input class of the loader and of `match_pair` gives a named error, never
//! a panic: truncated, corrupted, non-safetensors and mismatched weights files, bad
//! configs; zero and one keypoint, NaN/Inf, wrong shapes and widths.

mod common;

use std::collections::HashMap;

use common::{data_dir, entries, load_case, read, serialize, Entry};
use paraformer::{Config, Error, Features, MatchOptions, Matcher, TensorProblem, Weights};
use safetensors::Dtype;

fn weights_bytes() -> Vec<u8> {
    read(&data_dir().join("golden/paraformer.weights.safetensors"))
}

fn case() -> common::Case {
    load_case(&data_dir().join("golden/paraformer.case0.safetensors"))
}

fn matcher() -> Matcher {
    Matcher::from_bytes(&weights_bytes()).expect("golden weights load")
}

/// Rewrites the golden weights with `edit` applied to its tensors and metadata.
fn edited(edit: impl FnOnce(&mut Vec<Entry>, &mut HashMap<String, String>)) -> Vec<u8> {
    let (mut ents, mut meta) = entries(&weights_bytes());
    edit(&mut ents, &mut meta);
    serialize(&ents, &meta)
}

fn mismatch_problems(bytes: &[u8]) -> Vec<TensorProblem> {
    match Matcher::from_bytes(bytes) {
        Err(Error::WeightsMismatch(p)) => p,
        other => panic!("expected WeightsMismatch, got {other:?}"),
    }
}

// ---- weights files -------------------------------------------------------------

#[test]
fn truncated_file_is_a_format_error() {
    let bytes = weights_bytes();
    for cut in [0, 4, 8, 100, bytes.len() / 2, bytes.len() - 1] {
        let err = Matcher::from_bytes(&bytes[..cut]).expect_err("truncated file must fail");
        assert!(matches!(err, Error::WeightsFormat(_)), "cut at {cut}: {err}");
        assert!(err.is_weights_error());
    }
}

#[test]
fn corrupted_header_is_a_format_error() {
    let mut bytes = weights_bytes();
    for b in bytes[8..40].iter_mut() {
        *b = b'#';
    }
    let err = Matcher::from_bytes(&bytes).expect_err("corrupted header must fail");
    assert!(matches!(err, Error::WeightsFormat(_)), "{err}");
    // A header length far beyond the file.
    let mut bytes = weights_bytes();
    bytes[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    assert!(matches!(Matcher::from_bytes(&bytes), Err(Error::WeightsFormat(_))));
}

#[test]
fn non_safetensors_input_is_a_format_error() {
    for junk in [&b""[..], b"PK\x03\x04 this is a zip", b"{\"model\": \"paraformer\"}", &[0xffu8; 64][..]] {
        let err = Matcher::from_bytes(junk).expect_err("junk must fail");
        assert!(matches!(err, Error::WeightsFormat(_)), "{err}");
    }
}

#[test]
fn missing_file_is_an_io_error_naming_the_path() {
    let err = Matcher::from_file("/nonexistent/dir/weights.safetensors").expect_err("missing file");
    match &err {
        Error::Io { source, .. } => assert_eq!(source.kind(), std::io::ErrorKind::NotFound),
        other => panic!("expected Io, got {other:?}"),
    }
    assert!(err.to_string().contains("/nonexistent/dir/weights.safetensors"), "{err}");
}

#[test]
fn missing_config_metadata() {
    let bytes = edited(|_, meta| {
        meta.clear();
    });
    assert!(matches!(Matcher::from_bytes(&bytes), Err(Error::MissingConfig)));
    // With an explicit config the same tensors load.
    let w = Weights::from_bytes(&bytes).expect("tensors parse");
    let cfg = Weights::from_bytes(&weights_bytes()).expect("ok").config().cloned().expect("config");
    Matcher::new(cfg, &w).expect("explicit config");
}

#[test]
fn invalid_config_json_unknown_field_and_bad_values() {
    let cases = [
        ("{not json", "metadata"),
        (r#"{"model": "paraformer", "dim": 16, "descriptor_dim": 16, "num_layers": 3, "colour": 1}"#, "colour"),
        (r#"{"model": "transformer"}"#, "transformer"),
        (r#"{"model": "paraformer", "dim": 18, "num_heads": 4}"#, "num_heads"),
        (r#"{"model": "paraformer", "parallel": {"share_everything": true}}"#, "share_everything"),
        (r#"{"model": "paraformer_u", "stage_dims": [16, 24, 8]}"#, "stage_dims"),
    ];
    for (json, needle) in cases {
        let bytes = edited(|_, meta| {
            meta.insert("paraformer.config".into(), json.into());
        });
        let err = Matcher::from_bytes(&bytes).expect_err(json);
        assert!(matches!(err, Error::Config(_)), "{json}: {err}");
        assert!(err.to_string().contains(needle), "{json}: `{err}` should mention {needle}");
    }
}

#[test]
fn missing_tensor_is_named() {
    let bytes = edited(|ents, _| ents.retain(|e| e.name != "layers.1.attn.merge.weight"));
    let problems = mismatch_problems(&bytes);
    assert_eq!(
        problems,
        vec![TensorProblem::Missing { name: "layers.1.attn.merge.weight".into(), expected_shape: vec![16, 16] }]
    );
}

#[test]
fn unexpected_tensor_is_named() {
    let bytes = edited(|ents, _| {
        ents.push(Entry { name: "layers.7.extra".into(), dtype: Dtype::F32, shape: vec![2], data: vec![0; 8] })
    });
    let problems = mismatch_problems(&bytes);
    assert_eq!(problems, vec![TensorProblem::Unexpected { name: "layers.7.extra".into(), shape: vec![2] }]);
}

#[test]
fn wrong_shape_is_named() {
    let bytes = edited(|ents, _| {
        let e = ents.iter_mut().find(|e| e.name == "final_proj.weight").expect("present");
        e.shape = vec![8, 32];
    });
    let err = Matcher::from_bytes(&bytes).expect_err("wrong shape");
    assert!(err.to_string().contains("final_proj.weight"), "{err}");
    assert_eq!(
        mismatch_problems(&bytes),
        vec![TensorProblem::WrongShape { name: "final_proj.weight".into(), expected_shape: vec![16, 16], found_shape: vec![8, 32] }]
    );
}

#[test]
fn wrong_dtype_is_named() {
    let bytes = edited(|ents, _| {
        let e = ents.iter_mut().find(|e| e.name == "bin_score").expect("present");
        e.dtype = Dtype::I32;
    });
    assert_eq!(mismatch_problems(&bytes), vec![TensorProblem::WrongDtype { name: "bin_score".into(), found: "I32".into() }]);
}

#[test]
fn every_problem_is_reported_at_once() {
    let bytes = edited(|ents, _| {
        ents.retain(|e| e.name != "wave_pe.phase.0.bias" && e.name != "layers.2.fuse.3.weight");
        let e = ents.iter_mut().find(|e| e.name == "layers.0.fuse.1.weight").expect("present");
        e.shape = vec![8, 4];
        ents.push(Entry { name: "kenc.encoder.0.weight".into(), dtype: Dtype::F32, shape: vec![32, 3], data: vec![0; 384] });
        let e = ents.iter_mut().find(|e| e.name == "layers.1.attn.proj.2.bias").expect("present");
        e.dtype = Dtype::I32;
    });
    let problems = mismatch_problems(&bytes);
    let mut names: Vec<&str> = problems.iter().map(|p| p.name()).collect();
    names.sort();
    assert_eq!(
        names,
        [
            "kenc.encoder.0.weight",
            "layers.0.fuse.1.weight",
            "layers.1.attn.proj.2.bias",
            "layers.2.fuse.3.weight",
            "wave_pe.phase.0.bias"
        ]
    );
    let msg = Matcher::from_bytes(&bytes).expect_err("mismatch").to_string();
    assert!(msg.contains("5 problems"), "{msg}");
}

#[test]
fn weights_for_another_config_are_rejected() {
    // SuperGlue tensors under a ParaFormer config: every difference is listed.
    let sg = read(&data_dir().join("golden/superglue.weights.safetensors"));
    let w = Weights::from_bytes(&sg).expect("parses");
    let cfg = Config { descriptor_dim: 16, dim: 16, num_layers: 3, ..Config::paraformer() };
    match Matcher::new(cfg, &w) {
        Err(Error::WeightsMismatch(p)) => {
            assert!(p.iter().any(|p| matches!(p, TensorProblem::Missing { name, .. } if name == "wave_pe.amplitude.0.weight")));
            assert!(p.iter().any(|p| matches!(p, TensorProblem::Unexpected { name, .. } if name == "gnn.layers.0.attn.merge.weight")));
        }
        other => panic!("expected mismatch, got {other:?}"),
    }
}

#[test]
fn scalar_bin_score_may_be_shape_one_and_batch_counters_are_ignored() {
    let bytes = edited(|ents, _| {
        let e = ents.iter_mut().find(|e| e.name == "bin_score").expect("present");
        e.shape = vec![1];
        ents.push(Entry {
            name: "wave_pe.phase.1.num_batches_tracked".into(),
            dtype: Dtype::I64,
            shape: vec![],
            data: 7i64.to_le_bytes().to_vec(),
        });
    });
    let c = case();
    let a = Matcher::from_bytes(&bytes).expect("loads").match_pair(&c.f0, &c.f1).expect("runs");
    let b = matcher().match_pair(&c.f0, &c.f1).expect("runs");
    assert_eq!(a, b);
}

#[test]
fn bf16_weights_are_upcast() {
    let bytes = edited(|ents, _| {
        for e in ents.iter_mut() {
            e.data = common::f32s(e).iter().flat_map(|&v| half::bf16::from_f32(v).to_le_bytes()).collect();
            e.dtype = Dtype::BF16;
        }
    });
    let c = case();
    let out = Matcher::from_bytes(&bytes).expect("bf16 loads").match_pair(&c.f0, &c.f1).expect("runs");
    // bf16 keeps 8 mantissa bits: most matches survive the rounding of the weights.
    let same = out.matches0.iter().zip(&c.matches0).filter(|(a, b)| a == b).count();
    assert!(same * 10 >= c.matches0.len() * 8, "only {same}/{} matches agree after bf16 rounding", c.matches0.len());
}

// ---- match_pair inputs -----------------------------------------------------------

fn expect_input_error(r: paraformer::Result<paraformer::MatchOutput>, argument: &str, needle: &str) {
    match r {
        Err(Error::InvalidInput { argument: a, reason }) => {
            assert_eq!(a, argument, "reason: {reason}");
            assert!(reason.contains(needle), "`{reason}` should contain `{needle}`");
        }
        other => panic!("expected InvalidInput({argument}), got {other:?}"),
    }
}

#[test]
fn zero_keypoints_on_either_side_gives_all_unmatched() {
    let m = matcher();
    let c = case();
    let empty = Features::new(vec![], None, vec![], 16, (640.0, 480.0));
    for (a, b) in [(&empty, &c.f1), (&c.f0, &empty), (&empty, &empty)] {
        let out = m.match_pair_with(a, b, MatchOptions { return_log_assignment: true, ..Default::default() }).expect("K = 0 is valid");
        assert_eq!(out.matches0, vec![-1; a.len()]);
        assert_eq!(out.matches1, vec![-1; b.len()]);
        assert!(out.matching_scores0.iter().chain(&out.matching_scores1).all(|&s| s == 0.0));
        let la = out.log_assignment.expect("asked for");
        assert_eq!((la.rows, la.cols), (a.len() + 1, b.len() + 1));
    }
}

#[test]
fn one_keypoint_each_side() {
    let m = matcher();
    let c = case();
    let one = |f: &Features| Features::new(vec![f.keypoints[0]], Some(vec![f.scores[0]]), f.descriptors[..16].to_vec(), 16, f.image_size);
    let out = m.match_pair(&one(&c.f0), &one(&c.f1)).expect("K = 1 runs");
    assert_eq!(out.matches0.len(), 1);
    assert_eq!(out.matches1.len(), 1);
    assert!(out.matching_scores0[0].is_finite() && (0.0..=1.0).contains(&out.matching_scores0[0]));
}

#[test]
fn nan_and_inf_are_rejected_by_name() {
    let m = matcher();
    let c = case();
    let mut f = c.f0.clone();
    f.keypoints[3][1] = f32::NAN;
    expect_input_error(m.match_pair(&f, &c.f1), "keypoints0", "row 3");
    let mut f = c.f1.clone();
    f.descriptors[16 * 5 + 2] = f32::INFINITY;
    expect_input_error(m.match_pair(&c.f0, &f), "descriptors1", "row 5");
    let mut f = c.f1.clone();
    f.scores[0] = f32::NEG_INFINITY;
    expect_input_error(m.match_pair(&c.f0, &f), "scores1", "entry 0");
    let mut f = c.f0.clone();
    f.image_size = (f32::NAN, 480.0);
    expect_input_error(m.match_pair(&f, &c.f1), "image_size0", "positive finite");
}

#[test]
fn keypoints_far_outside_the_image_are_rejected_by_name() {
    let m = matcher();
    let c = case();
    let (w, h) = c.f0.image_size;
    // A swapped (height, width): keypoints near the right border land past the claimed width.
    let mut f = c.f0.clone();
    f.keypoints[2] = [w - 1.0, 10.0];
    f.image_size = (h, w);
    expect_input_error(m.match_pair(&f, &c.f1), "keypoints0", "row 2");
    // Far outside on each side, as normalised or another image's coordinates would be.
    let margin = paraformer::features::KEYPOINT_MARGIN * w.max(h) + 1.0;
    for p in [[-margin - 1.0, 5.0], [5.0, -margin - 1.0], [w + margin + 1.0, 5.0], [5.0, h + margin + 1.0], [1e30, 1e30]] {
        let mut f = c.f1.clone();
        f.image_size = (w, h);
        f.keypoints[0] = p;
        expect_input_error(m.match_pair(&c.f0, &f), "keypoints1", "lies outside the");
    }
    // On the borders and a little beyond (border conventions) is accepted.
    let mut f = c.f1.clone();
    f.image_size = (w, h);
    f.keypoints[0] = [0.0, 0.0];
    f.keypoints[1] = [w, h];
    f.keypoints[2] = [-0.5 * margin, h + 0.5 * margin];
    m.match_pair(&c.f0, &f).expect("keypoints on and just past the border");
}

#[test]
fn wrong_shapes_and_widths_are_rejected_by_name() {
    let m = matcher();
    let c = case();
    // Descriptor width of another extractor.
    let k = c.f0.len();
    let f = Features::new(c.f0.keypoints.clone(), None, vec![0.0; k * 32], 32, c.f0.image_size);
    expect_input_error(m.match_pair(&f, &c.f1), "descriptors0", &format!("expected shape [{k}, 16]"));
    // Descriptor rows do not match the keypoints.
    let mut f = c.f1.clone();
    f.descriptors.truncate(f.descriptors.len() - 16);
    expect_input_error(m.match_pair(&c.f0, &f), "descriptors1", "values");
    // Scores of another length.
    let mut f = c.f0.clone();
    f.scores.pop();
    expect_input_error(m.match_pair(&f, &c.f1), "scores0", &format!("expected shape [{k}]"));
    // Empty or negative image.
    let mut f = c.f1.clone();
    f.image_size = (0.0, 10.0);
    expect_input_error(m.match_pair(&c.f0, &f), "image_size1", "positive");
}

#[test]
fn log_assignment_only_when_asked_and_outputs_are_consistent() {
    let m = matcher();
    let c = case();
    let out = m.match_pair(&c.f0, &c.f1).expect("runs");
    assert!(out.log_assignment.is_none());
    for (i, &j) in out.matches0.iter().enumerate() {
        if j >= 0 {
            assert_eq!(out.matches1[j as usize], i as i64, "matches must be mutual");
        }
    }
}

#[test]
fn matcher_is_send_sync_and_threads_agree() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<Matcher>();
    let m = matcher();
    let c = case();
    let reference = m.match_pair(&c.f0, &c.f1).expect("runs");
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..4)
            .map(|_| s.spawn(|| (0..5).map(|_| m.match_pair(&c.f0, &c.f1).expect("runs")).collect::<Vec<_>>()))
            .collect();
        for h in handles {
            for out in h.join().expect("thread") {
                assert_eq!(out, reference);
            }
        }
    });
}

// ---- XFeat: images and weights ---------------------------------------------------

#[test]
fn xfeat_rejects_bad_images_with_named_errors() {
    use paraformer::{GrayImage, XFeat};
    let xf = XFeat::pretrained().expect("embedded weights");
    let msg = |e: paraformer::Error| e.to_string();
    assert!(msg(GrayImage::new(40, 40, vec![0.0; 10]).expect_err("short")).contains("40×40"));
    assert!(msg(GrayImage::from_channels(40, 40, 5, &[0.0; 8000]).expect_err("channels")).contains("5 channels"));
    assert!(msg(GrayImage::from_channels(40, 40, 3, &[0.0; 100]).expect_err("short rgb")).contains("40×40×3"));
    // A size whose value count overflows is an error, not a wrapped count that might match.
    let e = msg(GrayImage::from_channels(usize::MAX / 2 + 1, 2, 1, &[]).expect_err("overflow"));
    assert!(e.contains("more than memory can hold"), "{e}");
    let mut nan = GrayImage::new(64, 64, vec![10.0; 64 * 64]).expect("image");
    nan.data[70] = f32::NAN;
    assert!(msg(xf.detect_and_compute(&nan, None).expect_err("NaN")).contains("non-finite pixel value at index 70"));
    let tiny = GrayImage::new(31, 200, vec![0.0; 31 * 200]).expect("image");
    assert!(msg(xf.detect_and_compute(&tiny, None).expect_err("tiny")).contains("at least 32×32"));
    // A flat image has no keypoints: an empty, well-formed result.
    let flat = GrayImage::new(64, 64, vec![100.0; 64 * 64]).expect("image");
    let f = xf.detect_and_compute(&flat, None).expect("flat image");
    assert_eq!((f.len(), f.descriptors.len(), f.descriptor_dim), (f.scores.len(), 64 * f.len(), 64));
    assert!(GrayImage::from_encoded(b"not an image").is_err());
    let missing = GrayImage::open("/no/such/image.png").expect_err("missing");
    assert!(matches!(missing, paraformer::Error::Io { .. }), "{missing}");
}

#[test]
fn xfeat_weights_truncated_or_mismatched_are_errors() {
    use paraformer::xfeat::XFEAT_WEIGHTS;
    use paraformer::XFeat;
    for cut in [0, 7, 100, XFEAT_WEIGHTS.len() / 2, XFEAT_WEIGHTS.len() - 1] {
        let err = XFeat::from_bytes(&XFEAT_WEIGHTS[..cut]).expect_err("truncated");
        assert!(matches!(err, paraformer::Error::WeightsFormat(_)), "cut {cut}: {err}");
    }
    // ParaFormer weights are not XFeat weights: every XFeat tensor is reported missing.
    let other = std::fs::read(common::data_dir().join("spec_vectors/paraformer.weights.safetensors")).expect("fixture");
    let err = XFeat::from_bytes(&other).expect_err("mismatched").to_string();
    assert!(err.contains("block1.0.layer.0.weight") && err.contains("missing"), "{err}");
    assert!(err.contains("unexpected"), "{err}");
}

// ---- hostile weights, absurd configs, memory limits ----------------------------

#[test]
fn non_finite_weights_are_named() {
    for (bits, shown) in [(f32::NAN.to_le_bytes(), "NaN"), (f32::INFINITY.to_le_bytes(), "inf")] {
        let bytes = edited(|ents, _| {
            let e = ents.iter_mut().find(|e| e.name == "final_proj.weight").expect("present");
            e.data[12..16].copy_from_slice(&bits);
        });
        let err = Matcher::from_bytes(&bytes).expect_err("non-finite weight");
        assert!(err.is_weights_error(), "{err}");
        assert_eq!(
            mismatch_problems(&bytes),
            vec![TensorProblem::NonFinite { name: "final_proj.weight".into(), index: 3, value: shown.into() }]
        );
    }
}

#[test]
fn absurd_config_values_are_refused_before_allocating() {
    for (field, value, needle) in [
        ("dim", "1000000000", "dim = 1000000000"),
        ("num_layers", "1000000", "num_layers = 1000000"),
        ("sinkhorn_iterations", "1000000000", "sinkhorn_iterations = 1000000000"),
        ("descriptor_dim", "1000000000", "descriptor_dim = 1000000000"),
    ] {
        let json = format!(r#"{{"model": "paraformer", "{field}": {value}}}"#);
        let err = paraformer::Config::from_json(&json).and_then(|c| c.validate()).expect_err(field);
        assert!(matches!(err, Error::Config(_)) && err.to_string().contains(needle), "{err}");
    }
    let zero_stage = r#"{"model": "paraformer_u", "stage_dims": [64, 0, 64, 0, 64]}"#;
    let err = paraformer::Config::from_json(zero_stage).and_then(|c| c.validate()).expect_err("zero-width stage");
    assert!(err.to_string().contains("stage_dims[1] = 0"), "{err}");
    let huge_stage = r#"{"model": "paraformer_u", "stage_depths": [1, 1, 1000000, 1, 1]}"#;
    let err = paraformer::Config::from_json(huge_stage).and_then(|c| c.validate()).expect_err("deep stage");
    assert!(err.to_string().contains("stage_depths[2]"), "{err}");
}

#[test]
fn a_match_beyond_the_memory_limit_is_an_error_not_an_abort() {
    let m = matcher();
    let c = case();
    let opts = MatchOptions { memory_limit: Some(1000), ..Default::default() };
    match m.match_pair_with(&c.f0, &c.f1, opts) {
        Err(Error::Resource { needed, limit, .. }) => assert!(needed > limit && limit == 1000),
        other => panic!("expected Resource, got {other:?}"),
    }
    // 60,000 × 60,000 keypoints: ~29 GB of couplings, refused under a 4 GB limit.
    let d = m.config().descriptor_dim;
    let n = 60_000;
    let kpts: Vec<[f32; 2]> = (0..n).map(|i| [(i % 640) as f32, (i / 640) as f32]).collect();
    let f = paraformer::Features::new(kpts, None, vec![0.1; n * d], d, (640.0, 480.0));
    let opts = MatchOptions { memory_limit: Some(4_000_000_000), ..Default::default() };
    let err = m.match_pair_with(&f, &f, opts).expect_err("too large");
    assert!(matches!(err, Error::Resource { .. }) && err.to_string().contains("60000 × 60000"), "{err}");
}

#[test]
fn debug_form_of_errors_is_the_message() {
    let err = Matcher::pretrained("nope").expect_err("unknown name");
    assert_eq!(format!("{err:?}"), err.to_string());
    assert!(err.to_string().contains("paraformer-xfeat"), "{err}");
}
