//! The evaluation harness behind `paraformer eval`: runs a matcher (learned or a
//! baseline) over a dataset with precomputed features and aggregates the metrics of
//! the paper's Tables 1–2.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::error::{Error, Result};
use crate::eval::baselines::{match_descriptors, Baseline};
use crate::eval::datasets::{HomographyPair, PosePair};
use crate::eval::{ground_truth, metrics};
use crate::features::Features;
use crate::geometry::epipolar::{find_relative_pose, rotation_error_deg, translation_error_deg};
use crate::geometry::homography::find_homography;
use crate::geometry::{Point, RansacConfig};
use crate::Matcher;

/// A matcher to evaluate: a descriptor baseline or learned weights.
pub enum MatcherSpec {
    /// A descriptor baseline, with its display name.
    Baseline(String, Baseline),
    /// A learned matcher, with its display name.
    Learned(String, Box<Matcher>),
}

impl MatcherSpec {
    /// `nn`, `mnn`, `ratio` (0.8) or `ratio:R`, a pretrained name
    /// ([`crate::matcher::PRETRAINED`]), or the path of a weights file.
    pub fn parse(spec: &str) -> Result<Self> {
        if let Some(b) = Baseline::parse(spec)? {
            let name = match b {
                Baseline::NearestNeighbour => "NN".into(),
                Baseline::MutualNearestNeighbour => "mutual NN".into(),
                Baseline::RatioTest { ratio } => format!("ratio test {ratio}"),
            };
            return Ok(Self::Baseline(name, b));
        }
        Ok(match spec {
            name if crate::matcher::PRETRAINED.iter().any(|p| p.0 == name) => {
                Self::Learned(name.to_string(), Box::new(Matcher::pretrained(name)?))
            }
            path if !Path::new(path).exists() => {
                let names: Vec<&str> = crate::matcher::PRETRAINED.iter().map(|p| p.0).collect();
                return Err(Error::input(
                    "matcher",
                    format!(
                        "`{path}` is not nn, mnn, ratio, ratio:R, a pretrained name ({}) or an existing weights file",
                        if names.is_empty() { "none shipped".to_string() } else { names.join(", ") }
                    ),
                ));
            }
            path => {
                let m = Matcher::from_file(path)?;
                let name = Path::new(path).file_stem().map_or(path.to_string(), |s| s.to_string_lossy().into_owned());
                Self::Learned(name, Box::new(m))
            }
        })
    }

    /// The display name (`mnn`, `paraformer-xfeat`, a weights file's stem).
    pub fn name(&self) -> &str {
        match self {
            Self::Baseline(n, _) | Self::Learned(n, _) => n,
        }
    }

    /// Runs a learned matcher's attention in `precision` (baselines have none).
    pub fn set_precision(&mut self, precision: crate::Precision) {
        if let Self::Learned(_, m) = self {
            m.set_precision(precision);
        }
    }

    /// `matches0` for a pair.
    pub fn matches(&self, f0: &Features, f1: &Features) -> Result<Vec<i64>> {
        match self {
            Self::Baseline(_, b) => Ok(match_descriptors(&f0.descriptors, &f1.descriptors, f0.descriptor_dim, *b)),
            Self::Learned(_, m) => Ok(m.match_pair(f0, f1)?.matches0),
        }
    }
}

fn lookup<'a>(features: &'a BTreeMap<String, Features>, name: &str) -> Result<&'a Features> {
    features.get(name).ok_or_else(|| Error::input("features", format!("no features for image `{name}`")))
}

fn points(f: &Features) -> Vec<Point> {
    f.keypoints.iter().map(|p| [p[0] as f64, p[1] as f64]).collect()
}

/// The matched keypoint coordinates `(points0, points1)` of `matches0` (−1 skipped).
pub fn correspondences(f0: &Features, f1: &Features, m0: &[i64]) -> (Vec<Point>, Vec<Point>) {
    m0.iter()
        .enumerate()
        .filter_map(|(i, &j)| usize::try_from(j).ok().map(|j| (i, j)))
        .map(|(i, j)| ([f0.keypoints[i][0] as f64, f0.keypoints[i][1] as f64], [f1.keypoints[j][0] as f64, f1.keypoints[j][1] as f64]))
        .unzip()
}

/// One row of the homography table.
#[derive(Debug, Clone, Serialize)]
pub struct HomographyRow {
    /// Matcher name.
    pub matcher: String,
    /// Pairs evaluated.
    pub pairs: usize,
    /// AUC of the corner error at 1, 3, 5, 10 px (percent).
    pub auc: [f64; 4],
    /// Match precision against the ground truth (percent).
    pub precision: f64,
    /// Match recall (percent).
    pub recall: f64,
    /// F1 of precision and recall (percent).
    pub f1: f64,
    /// Mean matching accuracy at 1..10 px (percent).
    pub mma: Vec<f64>,
    /// Matches per pair.
    pub mean_matches: f64,
}

/// Evaluates `spec` on homography pairs; `progress(i, n)` after each pair.
pub fn eval_homography(
    pairs: &[HomographyPair],
    features: &BTreeMap<String, Features>,
    spec: &MatcherSpec,
    ransac: &RansacConfig,
    mut progress: impl FnMut(usize, usize),
) -> Result<HomographyRow> {
    let (mut errors, mut f1s, mut ps, mut rs, mut mmas, mut counts) = (vec![], vec![], vec![], vec![], vec![0.0; 10], 0usize);
    for (k, pair) in pairs.iter().enumerate() {
        let (f0, f1) = (lookup(features, &pair.name0)?, lookup(features, &pair.name1)?);
        let m0 = spec.matches(f0, f1)?;
        let gt = ground_truth::matches_from_homography(&pair.h, &points(f0), &points(f1), 3.0);
        let pr = metrics::precision_recall(&m0, &gt.matches0);
        ps.push(pr.precision);
        rs.push(pr.recall);
        f1s.push(pr.f1);
        for (acc, v) in mmas.iter_mut().zip(metrics::mma(&pair.h, &points(f0), &points(f1), &m0, 10)) {
            *acc += v;
        }
        let (x0, x1) = correspondences(f0, f1, &m0);
        counts += x0.len();
        let (w, h) = f0.image_size;
        errors.push(match find_homography(&x0, &x1, ransac) {
            Ok(r) => metrics::homography_corner_error(&r.model, &pair.h, w as f64, h as f64)?,
            Err(_) => f64::INFINITY,
        });
        progress(k + 1, pairs.len());
    }
    let n = pairs.len().max(1) as f64;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / n * 100.0;
    let auc = metrics::auc(&errors, &[1.0, 3.0, 5.0, 10.0])?;
    Ok(HomographyRow {
        matcher: spec.name().into(),
        pairs: pairs.len(),
        auc: [auc[0] * 100.0, auc[1] * 100.0, auc[2] * 100.0, auc[3] * 100.0],
        precision: mean(&ps),
        recall: mean(&rs),
        f1: mean(&f1s),
        mma: mmas.iter().map(|v| v / n * 100.0).collect(),
        mean_matches: counts as f64 / n,
    })
}

/// One row of the pose table.
#[derive(Debug, Clone, Serialize)]
pub struct PoseRow {
    /// Matcher name.
    pub matcher: String,
    /// Pairs evaluated.
    pub pairs: usize,
    /// Exact AUC of max(angle R, angle t) at 5, 10, 20° (percent).
    pub auc: [f64; 3],
    /// Approximate (histogram) AUC at 5, 10, 20° (percent).
    pub auc_approx: [f64; 3],
    /// Matches per pair.
    pub mean_matches: f64,
    /// Essential-matrix inliers per pair.
    pub mean_inliers: f64,
}

/// Evaluates `spec` on calibrated pairs.
pub fn eval_pose(
    pairs: &[PosePair],
    features: &BTreeMap<String, Features>,
    spec: &MatcherSpec,
    ransac: &RansacConfig,
    mut progress: impl FnMut(usize, usize),
) -> Result<PoseRow> {
    let (mut errors, mut matches, mut inliers) = (vec![], 0usize, 0usize);
    for (k, pair) in pairs.iter().enumerate() {
        let (f0, f1) = (lookup(features, &pair.name0)?, lookup(features, &pair.name1)?);
        let m0 = spec.matches(f0, f1)?;
        let (x0, x1) = correspondences(f0, f1, &m0);
        matches += x0.len();
        errors.push(match find_relative_pose(&x0, &x1, &pair.k0, &pair.k1, ransac) {
            Ok(p) => {
                inliers += p.num_inliers;
                rotation_error_deg(&p.rotation, &pair.rotation).max(translation_error_deg(&p.translation, &pair.translation))
            }
            Err(_) => f64::INFINITY,
        });
        progress(k + 1, pairs.len());
    }
    let n = pairs.len().max(1) as f64;
    let exact = metrics::auc(&errors, &[5.0, 10.0, 20.0])?;
    let approx = metrics::auc_approx(&errors, &[5, 10, 20])?;
    Ok(PoseRow {
        matcher: spec.name().into(),
        pairs: pairs.len(),
        auc: [exact[0] * 100.0, exact[1] * 100.0, exact[2] * 100.0],
        auc_approx: [approx[0] * 100.0, approx[1] * 100.0, approx[2] * 100.0],
        mean_matches: matches as f64 / n,
        mean_inliers: inliers as f64 / n,
    })
}
