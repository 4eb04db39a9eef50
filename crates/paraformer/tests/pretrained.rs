//! The shipped, trained matchers: they load by name, carry their full config, and match
//! the sample pair (XFeat features) well enough to recover its known homography.

use paraformer::geometry::homography::{apply, find_homography};
use paraformer::geometry::RansacConfig;
use paraformer::nalgebra::Matrix3;
use paraformer::{GrayImage, Matcher, XFeat};

fn sample(name: &str) -> String {
    format!("{}/../../assets/sample/{name}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn shipped_matchers_load_by_name_and_recover_the_sample_homography() {
    let names: Vec<&str> = paraformer::matcher::PRETRAINED.iter().map(|p| p.0).collect();
    assert_eq!(names, ["paraformer-xfeat", "paraformer-u-xfeat"]);
    let xf = XFeat::pretrained().expect("XFeat");
    let f0 = xf.detect_and_compute(&GrayImage::open(sample("coffee_0.jpg")).expect("image"), Some(512)).expect("features");
    let f1 = xf.detect_and_compute(&GrayImage::open(sample("coffee_1.jpg")).expect("image"), Some(512)).expect("features");
    let truth: Vec<f64> = std::fs::read_to_string(sample("H_0to1.txt"))
        .expect("H")
        .split_whitespace()
        .map(|t| t.parse().expect("number"))
        .collect();
    let truth = Matrix3::from_row_slice(&truth);
    for name in names {
        let m = Matcher::pretrained(name).expect("embedded weights load");
        assert_eq!(m.config().descriptor_dim, 64, "{name}");
        let out = m.match_pair(&f0, &f1).expect("match");
        let pt = |p: [f32; 2]| [p[0] as f64, p[1] as f64];
        let (x0, x1): (Vec<_>, Vec<_>) = out.pairs().into_iter().map(|(i, j)| (pt(f0.keypoints[i]), pt(f1.keypoints[j]))).unzip();
        assert!(x0.len() >= 100, "{name}: only {} matches", x0.len());
        let fit = find_homography(&x0, &x1, &RansacConfig::default()).expect("a homography");
        let inliers = fit.inliers.iter().filter(|&&b| b).count();
        assert!(inliers as f64 >= 0.5 * x0.len() as f64, "{name}: {inliers} inliers of {}", x0.len());
        for c in [[0.0, 0.0], [600.0, 0.0], [600.0, 400.0], [0.0, 400.0]] {
            let (a, b) = (apply(&truth, &c).expect("finite"), apply(&fit.model, &c).expect("finite"));
            assert!((a[0] - b[0]).hypot(a[1] - b[1]) < 3.0, "{name}: corner {c:?} off by more than 3 px");
        }
    }
    assert!(Matcher::pretrained("nope").is_err());
}

/// bf16 attention (where the CPU has AVX-512 BF16) keeps ≥ 99% of the fp32 matches of the
/// shipped matchers on the sample pair at 2048 keypoints; elsewhere it is fp32 exactly.
#[test]
fn bf16_keeps_the_fp32_matches_on_the_sample_pair() {
    use paraformer::Precision;
    let xf = XFeat::pretrained().expect("XFeat");
    let f0 = xf.detect_and_compute(&GrayImage::open(sample("coffee_0.jpg")).expect("image"), Some(2048)).expect("features");
    let f1 = xf.detect_and_compute(&GrayImage::open(sample("coffee_1.jpg")).expect("image"), Some(2048)).expect("features");
    for (name, _) in paraformer::matcher::PRETRAINED {
        let fp32 = Matcher::pretrained(name).expect("weights");
        assert_eq!(fp32.precision(), Precision::Fp32, "fp32 is the default");
        let bf16 = fp32.clone().with_precision(Precision::Bf16);
        let (a, b) = (fp32.match_pair(&f0, &f1).expect("fp32"), bf16.match_pair(&f0, &f1).expect("bf16"));
        if Precision::Bf16.effective() == Precision::Fp32 {
            eprintln!("no AVX-512 BF16 here: bf16 runs as fp32");
            assert_eq!(a, b, "{name}");
            continue;
        }
        let same = a.matches0.iter().zip(&b.matches0).filter(|(x, y)| x == y).count();
        let frac = same as f64 / a.matches0.len() as f64;
        assert!(frac >= 0.99, "{name}: {same} of {} keypoints keep their match", a.matches0.len());
    }
}

#[test]
fn precision_names_parse_and_bad_ones_are_named() {
    use paraformer::Precision;
    assert_eq!(Precision::parse("fp32").expect("fp32"), Precision::Fp32);
    assert_eq!(Precision::parse("bf16").expect("bf16"), Precision::Bf16);
    let e = Precision::parse("fp16").expect_err("unknown").to_string();
    assert!(e.contains("precision") && e.contains("fp16"), "{e}");
}
