//! Metrics as the paper and its peers report them.

use nalgebra::Matrix3;

use crate::error::{Error, Result};
use crate::geometry::homography::apply;
use crate::geometry::Point;

/// AUC thresholds must be positive and finite: a recall curve up to 0 or below has no area.
fn check_thresholds(mut thresholds: impl Iterator<Item = f64>) -> Result<()> {
    match thresholds.find(|t| !(t.is_finite() && *t > 0.0)) {
        Some(t) => Err(Error::input("thresholds", format!("{t}: expected positive finite values"))),
        None => Ok(()),
    }
}

/// Exact area under the recall-vs-error curve up to each threshold, divided by the
/// threshold (SuperGlue's `pose_auc`: trapezoids of the empirical recall curve).
/// `errors` may contain `f64::INFINITY` for failures; a threshold ≤ 0 or not finite is
/// an error.
pub fn auc(errors: &[f64], thresholds: &[f64]) -> Result<Vec<f64>> {
    check_thresholds(thresholds.iter().copied())?;
    let mut e: Vec<f64> = errors.iter().map(|v| if v.is_nan() { f64::INFINITY } else { *v }).collect();
    e.sort_by(f64::total_cmp);
    let n = e.len() as f64;
    Ok(thresholds
        .iter()
        .map(|&t| {
            if e.is_empty() {
                return 0.0;
            }
            // Curve points (0, 0), (e_i, (i+1)/n) for e_i < t, then (t, last recall).
            let (mut area, mut px, mut py) = (0.0, 0.0, 0.0);
            for (i, &x) in e.iter().enumerate() {
                if x >= t {
                    break;
                }
                let y = (i + 1) as f64 / n;
                area += (x - px) * (py + y) / 2.0;
                (px, py) = (x, y);
            }
            area += (t - px) * (py + py) / 2.0;
            area / t
        })
        .collect())
}

/// Approximate AUC (as LoFTR/SuperGlue's evaluation tables): the mean accuracy at
/// the integer thresholds `1..=t`; a threshold of 0 is an error.
pub fn auc_approx(errors: &[f64], thresholds: &[u32]) -> Result<Vec<f64>> {
    check_thresholds(thresholds.iter().map(|&t| f64::from(t)))?;
    let n = errors.len().max(1) as f64;
    Ok(thresholds
        .iter()
        .map(|&t| (1..=t).map(|k| errors.iter().filter(|&&e| e < k as f64).count() as f64 / n).sum::<f64>() / t as f64)
        .collect())
}

/// Mean distance of the four image corners mapped by the estimated and the true
/// homography (pixels); infinite if either maps a corner to infinity. `width` and
/// `height` must be positive and finite.
pub fn homography_corner_error(h_est: &Matrix3<f64>, h_gt: &Matrix3<f64>, width: f64, height: f64) -> Result<f64> {
    for (name, v) in [("width", width), ("height", height)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(Error::input(name, format!("{v}: expected a positive image size in pixels")));
        }
    }
    let corners = [[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]];
    Ok(corners
        .iter()
        .map(|c| match (apply(h_est, c), apply(h_gt, c)) {
            (Some(a), Some(b)) => (a[0] - b[0]).hypot(a[1] - b[1]),
            _ => f64::INFINITY,
        })
        .sum::<f64>()
        / 4.0)
}

/// Precision, recall and F1 of predicted matches against ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PrecisionRecall {
    /// True positives / predicted matches.
    pub precision: f64,
    /// True positives / ground-truth matches.
    pub recall: f64,
    /// Harmonic mean of precision and recall.
    pub f1: f64,
    /// Predicted matches that are true.
    pub true_positives: usize,
    /// Predicted matches (keypoints of image 0 not in IGNORED).
    pub predicted: usize,
    /// Ground-truth matches.
    pub positives: usize,
}

/// `pred0[i]`: predicted match of keypoint i (−1 none). `gt0[i]`: ground truth
/// (`j ≥ 0` positive, −1 unmatched, −2 ignored). Predictions on ignored keypoints
/// are left out of the precision, as in SuperGlue's evaluation.
pub fn precision_recall(pred0: &[i64], gt0: &[i64]) -> PrecisionRecall {
    let mut r = PrecisionRecall::default();
    for (&p, &g) in pred0.iter().zip(gt0) {
        if g >= 0 {
            r.positives += 1;
        }
        if p >= 0 && g != -2 {
            r.predicted += 1;
            if p == g {
                r.true_positives += 1;
            }
        }
    }
    let ratio = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
    r.precision = ratio(r.true_positives, r.predicted);
    r.recall = ratio(r.true_positives, r.positives);
    r.f1 = if r.precision + r.recall > 0.0 { 2.0 * r.precision * r.recall / (r.precision + r.recall) } else { 0.0 };
    r
}

/// Mean matching accuracy at `1..=max_px`: the fraction of predicted matches whose
/// transfer error under the true homography is below each threshold.
pub fn mma(h_gt: &Matrix3<f64>, kpts0: &[Point], kpts1: &[Point], matches0: &[i64], max_px: u32) -> Vec<f64> {
    let errs: Vec<f64> = matches0
        .iter()
        .enumerate()
        .filter_map(|(i, &j)| {
            let j = usize::try_from(j).ok()?;
            let q = apply(h_gt, kpts0.get(i)?)?;
            let p = kpts1.get(j)?;
            Some((q[0] - p[0]).hypot(q[1] - p[1]))
        })
        .collect();
    let n = errs.len().max(1) as f64;
    (1..=max_px).map(|t| errs.iter().filter(|&&e| e <= t as f64).count() as f64 / n).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auc_matches_superglue_pose_auc() {
        // Values worked by hand with SuperGlue's formula.
        let e = [1.0, 3.0, 7.0, f64::INFINITY];
        let a = auc(&e, &[5.0, 10.0, 20.0]).unwrap();
        // t=5: trapezoids (0,0)-(1,.25)-(3,.5)-(5,.5) → (.125 + .75 + 1.0)/5
        assert!((a[0] - 1.875 / 5.0).abs() < 1e-12, "{a:?}");
        // t=10: .125 + .75 + (3→7, .5→.75) 2.5 + (7→10 at .75) 2.25 → 5.625/10
        assert!((a[1] - 0.5625).abs() < 1e-12, "{a:?}");
        // t=20: .125 + .75 + 2.5 + (7→20 at .75) 9.75 → 13.125/20
        assert!((a[2] - 13.125 / 20.0).abs() < 1e-12, "{a:?}");
        assert_eq!(auc(&[], &[5.0]).unwrap(), vec![0.0]);
        assert_eq!(auc(&[0.0; 3], &[5.0]).unwrap(), vec![1.0]);
    }

    #[test]
    fn thresholds_and_sizes_that_have_no_area_are_named() {
        for t in [0.0, -5.0, f64::NAN, f64::INFINITY] {
            let e = auc(&[1.0, 2.0], &[5.0, t]).expect_err("bad threshold").to_string();
            assert!(e.contains("thresholds") && e.contains("positive finite"), "{e}");
        }
        assert!(auc_approx(&[1.0], &[0, 5]).expect_err("zero").to_string().contains("thresholds"));
        let id = Matrix3::identity();
        for (w, h, name) in [(0.0, 480.0, "width"), (640.0, -1.0, "height"), (640.0, f64::INFINITY, "height")] {
            let e = homography_corner_error(&id, &id, w, h).expect_err(name).to_string();
            assert!(e.contains(name), "{e}");
        }
    }

    #[test]
    fn approximate_auc_and_precision_recall() {
        let a = auc_approx(&[0.5, 1.5, 100.0], &[2]).unwrap();
        assert!((a[0] - (1.0 / 3.0 + 2.0 / 3.0) / 2.0).abs() < 1e-12);
        let pr = precision_recall(&[1, 2, -1, 5, 0], &[1, 3, 4, -2, -1]);
        assert_eq!((pr.true_positives, pr.predicted, pr.positives), (1, 3, 3));
        assert!((pr.precision - 1.0 / 3.0).abs() < 1e-12 && (pr.recall - 1.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn corner_error_and_mma() {
        let id = Matrix3::identity();
        let shift = Matrix3::new(1.0, 0.0, 3.0, 0.0, 1.0, 4.0, 0.0, 0.0, 1.0);
        assert!((homography_corner_error(&shift, &id, 640.0, 480.0).unwrap() - 5.0).abs() < 1e-12);
        let k0 = [[0.0, 0.0], [10.0, 10.0]];
        let k1 = [[3.0, 4.0], [14.0, 12.0]];
        let m = mma(&shift, &k0, &k1, &[0, 1], 3);
        // First match exact, second off by (1, −2), i.e. √5 ≈ 2.24 px.
        assert_eq!(m, vec![0.5, 0.5, 1.0]);
    }
}
