//! Thin PyO3 layer over the `paraformer` core. The pure-Python package
//! (`python/paraformer`) validates numpy arrays and hands them over as little-endian
//! bytes; everything heavy runs here with the GIL released.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use paraformer::eval::baselines::{self, Baseline};
use paraformer::features::f32_from_le;
use paraformer::eval::{ground_truth, metrics};
use paraformer::geometry::{epipolar, homography, NoModel, RansacConfig, RansacResult};
use paraformer::nalgebra::Matrix3;
use paraformer::{Config, Error, Features, GrayImage, MatchOptions, MatchOutput, Matcher, Precision, Weights, XFeat, XFeatConfig};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::pybacked::PyBackedBytes;
use pyo3::types::{PyByteArray, PyBytes, PyDict};

create_exception!(paraformer, ParaformerError, PyException, "Base class of every paraformer error.");
create_exception!(
    paraformer,
    WeightsError,
    ParaformerError,
    "A weights file is not valid safetensors, has a bad config, or does not match its config."
);

/// `paraformer.ResourceError`: a `ParaformerError` and a `MemoryError` (two bases, so
/// it is built with `type(...)` when the module loads).
static RESOURCE_ERROR: pyo3::sync::PyOnceLock<Py<pyo3::types::PyType>> = pyo3::sync::PyOnceLock::new();

fn resource_error(msg: String) -> PyErr {
    Python::attach(|py| match RESOURCE_ERROR.get(py) {
        Some(t) => PyErr::from_type(t.bind(py).clone(), msg),
        None => pyo3::exceptions::PyMemoryError::new_err(msg),
    })
}

/// The Python argument name for a core argument name (`keypoints0` → `kpts0`).
fn python_name(arg: &str) -> String {
    for (core, py) in [("keypoints", "kpts"), ("descriptors", "desc"), ("image_size", "size")] {
        if let Some(rest) = arg.strip_prefix(core) {
            return format!("{py}{rest}");
        }
    }
    arg.to_string()
}

fn to_py_err(e: Error) -> PyErr {
    match e {
        Error::Io { ref source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        Error::Io { .. } => PyOSError::new_err(e.to_string()),
        Error::InvalidInput { argument, reason } => {
            PyValueError::new_err(format!("{}: {reason}", python_name(&argument)))
        }
        e @ Error::Resource { .. } => resource_error(e.to_string()),
        e if e.is_weights_error() => WeightsError::new_err(e.to_string()),
        e => ParaformerError::new_err(e.to_string()),
    }
}

/// One image as the Python layer passes it: `(kpts_f32le, desc_f32le, D, scores_f32le | None, w, h)`.
#[derive(FromPyObject)]
struct RawFeatures(PyBackedBytes, PyBackedBytes, usize, Option<PyBackedBytes>, f32, f32);

impl RawFeatures {
    fn to_features(&self, image: usize) -> PyResult<Features> {
        let RawFeatures(kpts, desc, d, scores, w, h) = self;
        if kpts.len() % 8 != 0 || desc.len() % 4 != 0 {
            return Err(PyValueError::new_err(format!("kpts{image}/desc{image}: buffers are not whole float32 rows")));
        }
        let keypoints = f32_from_le(kpts).chunks_exact(2).map(|c| [c[0], c[1]]).collect();
        Ok(Features::new(keypoints, scores.as_ref().map(|s| f32_from_le(s)), f32_from_le(desc), *d, (*w, *h)))
    }
}

/// Either a path or the bytes of a weights file.
#[derive(FromPyObject)]
enum WeightsArg {
    Bytes(PyBackedBytes),
    Path(PathBuf),
}

fn output_dict<'py>(py: Python<'py>, out: &MatchOutput) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("matches0", PyByteArray::new(py, &i64_bytes(&out.matches0)))?;
    d.set_item("matches1", PyByteArray::new(py, &i64_bytes(&out.matches1)))?;
    d.set_item("matching_scores0", PyByteArray::new(py, &f32_bytes(&out.matching_scores0)))?;
    d.set_item("matching_scores1", PyByteArray::new(py, &f32_bytes(&out.matching_scores1)))?;
    if let Some(la) = &out.log_assignment {
        d.set_item("log_assignment", (PyByteArray::new(py, &f32_bytes(&la.data)), la.rows, la.cols))?;
    }
    Ok(d)
}

/// The `precision` keyword: "fp32" or "bf16", else the error that names it.
fn precision_arg(precision: &str) -> PyResult<Precision> {
    Precision::parse(precision).map_err(to_py_err)
}

/// A loaded matcher (the Rust core); use `paraformer.Matcher`, which wraps it.
#[pyclass(frozen, name = "_Matcher", module = "paraformer._paraformer")]
struct PyMatcher {
    inner: Arc<Matcher>,
}

#[pymethods]
impl PyMatcher {
    /// Loads a weights file whose metadata holds the config.
    ///
    /// Args:
    ///     path: path of a safetensors weights file.
    /// Returns:
    ///     The matcher.
    #[staticmethod]
    #[pyo3(signature = (path, /, precision = "fp32"))]
    fn from_file(py: Python<'_>, path: PathBuf, precision: &str) -> PyResult<Self> {
        let p = precision_arg(precision)?;
        let m = py.detach(|| Matcher::from_file(&path)).map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(m.with_precision(p)) })
    }

    /// Loads trained weights shipped inside the package, by name.
    ///
    /// Args:
    ///     name: one of `pretrained_names()`, e.g. "paraformer-xfeat".
    /// Returns:
    ///     The matcher.
    #[staticmethod]
    #[pyo3(signature = (name, /, precision = "fp32"))]
    fn pretrained(py: Python<'_>, name: &str, precision: &str) -> PyResult<Self> {
        let p = precision_arg(precision)?;
        let m = py.detach(|| Matcher::pretrained(name)).map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(m.with_precision(p)) })
    }

    /// Loads weights from bytes whose metadata holds the config.
    ///
    /// Args:
    ///     data: the bytes of a safetensors weights file.
    /// Returns:
    ///     The matcher.
    #[staticmethod]
    #[pyo3(signature = (data, /, precision = "fp32"))]
    fn from_bytes(py: Python<'_>, data: PyBackedBytes, precision: &str) -> PyResult<Self> {
        let p = precision_arg(precision)?;
        let m = py.detach(|| Matcher::from_bytes(&data)).map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(m.with_precision(p)) })
    }

    /// Builds a matcher from an explicit config and a weights file or its bytes.
    ///
    /// Args:
    ///     config_json: the config as JSON (SPEC §9 fields; absent ones take defaults).
    ///     weights: a path (str or os.PathLike) or the bytes of a safetensors file.
    /// Returns:
    ///     The matcher.
    #[staticmethod]
    #[pyo3(signature = (config_json, weights, /, precision = "fp32"))]
    fn with_config(py: Python<'_>, config_json: &str, weights: WeightsArg, precision: &str) -> PyResult<Self> {
        let p = precision_arg(precision)?;
        let config = Config::from_json(config_json).map_err(|e| PyValueError::new_err(format!("config: {e}")))?;
        let m = py
            .detach(|| {
                let w = match &weights {
                    WeightsArg::Bytes(b) => Weights::from_bytes(b)?,
                    WeightsArg::Path(p) => Weights::from_file(p)?,
                };
                Matcher::new(config, &w)
            })
            .map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(m.with_precision(p)) })
    }

    /// The attention precision asked for, and what runs on this CPU.
    ///
    /// Returns:
    ///     `(asked, effective)`, each "fp32" or "bf16".
    #[getter]
    fn precision(&self) -> (&'static str, &'static str) {
        let p = self.inner.precision();
        (p.name(), p.effective().name())
    }

    /// The config as JSON, every field written out.
    ///
    /// Returns:
    ///     A JSON object string.
    #[getter]
    fn config_json(&self) -> String {
        self.inner.config().to_json_used()
    }

    /// Matches one pair.
    ///
    /// Args:
    ///     features0: image 0 as `(kpts_f32le, desc_f32le, D, scores_f32le | None, w, h)`.
    ///     features1: image 1, same layout.
    ///     return_log_assignment: also return the `[M+1, N+1]` log assignment.
    /// Returns:
    ///     A dict of little-endian byte arrays: `matches0/1` (int64), `matching_scores0/1`
    ///     (float32) and, when asked, `log_assignment` as `(bytes, rows, cols)`.
    #[pyo3(signature = (features0, features1, return_log_assignment = false))]
    fn match_pair<'py>(
        &self,
        py: Python<'py>,
        features0: RawFeatures,
        features1: RawFeatures,
        return_log_assignment: bool,
    ) -> PyResult<Bound<'py, PyDict>> {
        let (f0, f1) = (features0.to_features(0)?, features1.to_features(1)?);
        let opts = MatchOptions { return_log_assignment, ..Default::default() };
        let out = py.detach(|| self.inner.match_pair_with(&f0, &f1, opts)).map_err(to_py_err)?;
        output_dict(py, &out)
    }

    /// Matches one pair and reports where the time went.
    ///
    /// Args:
    ///     features0: image 0, as for `match_pair`.
    ///     features1: image 1, as for `match_pair`.
    /// Returns:
    ///     A dict of seconds per part (`encoder`, `layers`, `final_projection`, `sinkhorn`,
    ///     `extraction`, `total`) and `macs`, the multiply-accumulates performed.
    #[pyo3(signature = (features0, features1))]
    fn profile<'py>(&self, py: Python<'py>, features0: RawFeatures, features1: RawFeatures) -> PyResult<Bound<'py, PyDict>> {
        let (f0, f1) = (features0.to_features(0)?, features1.to_features(1)?);
        let (_, p) = py.detach(|| self.inner.profile(&f0, &f1, MatchOptions::default())).map_err(to_py_err)?;
        let d = PyDict::new(py);
        for (k, v) in [
            ("encoder", p.encoder),
            ("layers", p.layers),
            ("final_projection", p.final_projection),
            ("sinkhorn", p.sinkhorn),
            ("extraction", p.extraction),
            ("total", p.total()),
        ] {
            d.set_item(k, v)?;
        }
        d.set_item("macs", p.macs)?;
        Ok(d)
    }

    /// Bytes a match of `m` × `n` keypoints needs at its peak (checked against the limit).
    ///
    /// Args:
    ///     m: keypoints of image 0.
    ///     n: keypoints of image 1.
    /// Returns:
    ///     The estimate in bytes.
    #[pyo3(signature = (m, n))]
    fn memory_needed(&self, m: usize, n: usize) -> u64 {
        self.inner.memory_needed(m, n)
    }

    /// Matches many pairs in parallel on `num_threads` threads (default: all cores).
    ///
    /// Args:
    ///     pairs: a list of `(features0, features1)` in the layout of `match_pair`.
    ///     return_log_assignment: also return each log assignment.
    ///     num_threads: worker threads; `None` for the number of cores.
    /// Returns:
    ///     A list of dicts as `match_pair` returns, in the order of `pairs`.
    #[pyo3(signature = (pairs, return_log_assignment = false, num_threads = None))]
    fn match_many<'py>(
        &self,
        py: Python<'py>,
        pairs: Vec<(RawFeatures, RawFeatures)>,
        return_log_assignment: bool,
        num_threads: Option<usize>,
    ) -> PyResult<Vec<Bound<'py, PyDict>>> {
        let feats = pairs
            .iter()
            .enumerate()
            .map(|(i, (a, b))| {
                let wrap = |e: PyErr| PyValueError::new_err(format!("pair {i}: {}", e.value(py)));
                Ok((a.to_features(0).map_err(wrap)?, b.to_features(1).map_err(wrap)?))
            })
            .collect::<PyResult<Vec<_>>>()?;
        let opts = MatchOptions { return_log_assignment, ..Default::default() };
        let threads = num_threads
            .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1))
            .clamp(1, feats.len().max(1));
        // Pairs run side by side only as far as their memory fits the limit together.
        let limit = paraformer::memory::memory_limit();
        let largest = feats
            .iter()
            .map(|(a, b)| paraformer::memory::match_bytes(self.inner.config(), a.len(), b.len(), 1))
            .max()
            .unwrap_or(0);
        let threads = threads.min(usize::try_from(limit / largest.max(1)).unwrap_or(usize::MAX).max(1));
        let cancel = std::sync::atomic::AtomicBool::new(false);
        let mut interrupt: Option<PyErr> = None;
        let results = py.detach(|| {
            let next = AtomicUsize::new(0);
            let mut slots: Vec<Option<paraformer::Result<MatchOutput>>> = (0..feats.len()).map(|_| None).collect();
            std::thread::scope(|s| {
                let workers: Vec<_> = (0..threads)
                    .map(|_| {
                        s.spawn(|| {
                            let mut done = Vec::new();
                            while !cancel.load(Ordering::Relaxed) {
                                let i = next.fetch_add(1, Ordering::Relaxed);
                                let Some((f0, f1)) = feats.get(i) else { break };
                                done.push((i, self.inner.match_pair_with(f0, f1, opts)));
                            }
                            done
                        })
                    })
                    .collect();
                // The calling thread watches for Ctrl-C (Python handles signals on it) while
                // the workers run; on a signal they stop after their current pair.
                while !workers.iter().all(|w| w.is_finished()) {
                    std::thread::sleep(std::time::Duration::from_millis(20));
                    if let Err(e) = Python::attach(|py| py.check_signals()) {
                        cancel.store(true, Ordering::Relaxed);
                        interrupt = Some(e);
                        break;
                    }
                }
                for w in workers {
                    // A worker only panics on a bug; its pairs are then reported as errors below.
                    if let Ok(done) = w.join() {
                        for (i, r) in done {
                            slots[i] = Some(r);
                        }
                    }
                }
            });
            slots
        });
        if let Some(e) = interrupt {
            return Err(e);
        }
        results
            .into_iter()
            .enumerate()
            .map(|(i, r)| match r {
                Some(Ok(out)) => output_dict(py, &out),
                Some(Err(e)) => {
                    let resource = matches!(e, Error::Resource { .. });
                    let err = to_py_err(e);
                    let msg = format!("pair {i}: {}", err.value(py));
                    Err(match () {
                        _ if resource => resource_error(msg),
                        _ if err.is_instance_of::<PyValueError>(py) => PyValueError::new_err(msg),
                        _ => ParaformerError::new_err(msg),
                    })
                }
                None => Err(ParaformerError::new_err(format!("pair {i}: worker thread failed"))),
            })
            .collect()
    }
}

fn f64s(bytes: &[u8]) -> Vec<f64> {
    bytes.chunks_exact(8).map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])).collect()
}

fn points(bytes: &[u8]) -> Vec<[f64; 2]> {
    f64s(bytes).chunks_exact(2).map(|c| [c[0], c[1]]).collect()
}

fn mat3(v: &[f64]) -> PyResult<Matrix3<f64>> {
    if v.len() != 9 {
        return Err(PyValueError::new_err(format!("expected a 3×3 matrix (9 values), got {}", v.len())));
    }
    Ok(Matrix3::from_row_slice(v))
}

fn rows(m: &Matrix3<f64>) -> Vec<f64> {
    m.transpose().as_slice().to_vec()
}

/// A RANSAC result for Python: `(model row-major | None, inliers, reason | None)`.
type Fit = (Option<Vec<f64>>, Vec<bool>, Option<String>);

type Robust = fn(&[[f64; 2]], &[[f64; 2]], &RansacConfig) -> Result<RansacResult<Matrix3<f64>>, NoModel>;

/// RANSAC parameters from Python, checked: a ValueError names the one that cannot work
/// (Python ints of any sign arrive here, so the integer ranges are checked too).
fn ransac_config(threshold: f64, confidence: f64, max_iterations: i128, seed: i128) -> PyResult<RansacConfig> {
    let max_iterations = usize::try_from(max_iterations).map_err(|_| PyValueError::new_err(format!("max_iterations: {max_iterations}: expected at least 1")))?;
    let seed = u64::try_from(seed).map_err(|_| PyValueError::new_err(format!("seed: {seed}: expected an int in [0, 2**64)")))?;
    let cfg = RansacConfig { threshold, confidence, max_iterations, seed, ..Default::default() };
    cfg.validate().map_err(to_py_err)?;
    Ok(cfg)
}

/// Runs a robust estimator on two point buffers with the GIL released.
fn robust_fit(py: Python<'_>, points0: &[u8], points1: &[u8], cfg: RansacConfig, estimate: Robust) -> Fit {
    py.detach(|| {
        let (x0, x1) = (points(points0), points(points1));
        match estimate(&x0, &x1, &cfg) {
            Ok(r) => (Some(rows(&r.model)), r.inliers, None),
            Err(e) => (None, vec![false; x0.len()], Some(e.to_string())),
        }
    })
}

/// Robust homography (normalised DLT in RANSAC with local optimisation).
///
/// Args:
///     points0: `[N, 2]` float64 little-endian bytes (image 0).
///     points1: `[N, 2]` float64 little-endian bytes (image 1).
///     threshold: inlier transfer error in pixels.
///     confidence: RANSAC confidence.
///     max_iterations: upper bound on hypotheses.
///     seed: sampler seed.
/// Returns:
///     `(H row-major or None, inlier mask, reason or None)`.
#[pyfunction]
#[pyo3(signature = (points0, points1, threshold = 3.0, confidence = 0.999, max_iterations = 10000, seed = 0))]
fn find_homography(
    py: Python<'_>,
    points0: PyBackedBytes,
    points1: PyBackedBytes,
    threshold: f64,
    confidence: f64,
    max_iterations: i128,
    seed: i128,
) -> PyResult<Fit> {
    let cfg = ransac_config(threshold, confidence, max_iterations, seed)?;
    Ok(robust_fit(py, &points0, &points1, cfg, homography::find_homography))
}

/// Robust fundamental matrix (normalised 8-point in RANSAC, Sampson distance).
///
/// Args:
///     points0: `[N, 2]` float64 little-endian bytes (image 0).
///     points1: `[N, 2]` float64 little-endian bytes (image 1).
///     threshold: inlier Sampson distance in pixels.
///     confidence: RANSAC confidence.
///     max_iterations: upper bound on hypotheses.
///     seed: sampler seed.
/// Returns:
///     `(F row-major or None, inlier mask, reason or None)`.
#[pyfunction]
#[pyo3(signature = (points0, points1, threshold = 1.0, confidence = 0.999, max_iterations = 10000, seed = 0))]
fn find_fundamental(
    py: Python<'_>,
    points0: PyBackedBytes,
    points1: PyBackedBytes,
    threshold: f64,
    confidence: f64,
    max_iterations: i128,
    seed: i128,
) -> PyResult<Fit> {
    let cfg = ransac_config(threshold, confidence, max_iterations, seed)?;
    Ok(robust_fit(py, &points0, &points1, cfg, epipolar::find_fundamental))
}

/// Robust relative pose: essential matrix (8-point + manifold projection) in RANSAC,
/// then cheirality.
///
/// Args:
///     points0: `[N, 2]` float64 little-endian bytes (pixels, image 0).
///     points1: `[N, 2]` float64 little-endian bytes (pixels, image 1).
///     k0: intrinsics of camera 0, 9 values row-major.
///     k1: intrinsics of camera 1, 9 values row-major.
///     threshold: inlier Sampson distance in pixels.
///     confidence: RANSAC confidence.
///     max_iterations: upper bound on hypotheses.
///     seed: sampler seed.
/// Returns:
///     `((R, t, E) or None, inlier mask, reason or None)`, R and E row-major.
#[pyfunction]
#[pyo3(signature = (points0, points1, k0, k1, threshold = 1.0, confidence = 0.999, max_iterations = 10000, seed = 0))]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn find_relative_pose(
    py: Python<'_>,
    points0: PyBackedBytes,
    points1: PyBackedBytes,
    k0: Vec<f64>,
    k1: Vec<f64>,
    threshold: f64,
    confidence: f64,
    max_iterations: i128,
    seed: i128,
) -> PyResult<(Option<(Vec<f64>, Vec<f64>, Vec<f64>)>, Vec<bool>, Option<String>)> {
    let (k0, k1) = (mat3(&k0)?, mat3(&k1)?);
    let cfg = ransac_config(threshold, confidence, max_iterations, seed)?;
    Ok(py.detach(|| {
        let (x0, x1) = (points(&points0), points(&points1));
        match epipolar::find_relative_pose(&x0, &x1, &k0, &k1, &cfg) {
            Ok(p) => (Some((rows(&p.rotation), p.translation.as_slice().to_vec(), rows(&p.essential))), p.inliers, None),
            Err(e) => (None, vec![false; x0.len()], Some(e.to_string())),
        }
    }))
}

/// Exact AUC of the recall-vs-error curve (SuperGlue's `pose_auc`).
///
/// Args:
///     errors: per-pair errors (inf for failures).
///     thresholds: AUC thresholds.
/// Returns:
///     One AUC per threshold.
#[pyfunction]
#[pyo3(signature = (errors, thresholds))]
fn pose_auc(errors: Vec<f64>, thresholds: Vec<f64>) -> PyResult<Vec<f64>> {
    metrics::auc(&errors, &thresholds).map_err(to_py_err)
}

/// Approximate (histogram) AUC: mean accuracy at the integer thresholds 1..=t.
///
/// Args:
///     errors: per-pair errors.
///     thresholds: integer thresholds.
/// Returns:
///     One value per threshold.
#[pyfunction]
#[pyo3(signature = (errors, thresholds))]
fn pose_auc_approx(errors: Vec<f64>, thresholds: Vec<i64>) -> PyResult<Vec<f64>> {
    let thresholds = thresholds
        .iter()
        .map(|&t| u32::try_from(t).map_err(|_| PyValueError::new_err(format!("thresholds: {t}: expected positive integers below 2^32"))))
        .collect::<PyResult<Vec<u32>>>()?;
    metrics::auc_approx(&errors, &thresholds).map_err(to_py_err)
}

/// Mean distance of the image corners under the estimated and the true homography.
///
/// Args:
///     h_est: estimated homography, 9 values row-major.
///     h_gt: true homography, 9 values row-major.
///     width: image 0 width.
///     height: image 0 height.
/// Returns:
///     The corner error in pixels.
#[pyfunction]
#[pyo3(signature = (h_est, h_gt, width, height))]
fn homography_corner_error(h_est: Vec<f64>, h_gt: Vec<f64>, width: f64, height: f64) -> PyResult<f64> {
    metrics::homography_corner_error(&mat3(&h_est)?, &mat3(&h_gt)?, width, height).map_err(to_py_err)
}

/// Ground-truth matches from a homography (mutual nearest under the symmetric
/// transfer distance and below `threshold`; −1 unmatched, −2 ignored).
///
/// Args:
///     h: homography image 0 → image 1, 9 values row-major.
///     kpts0: `[M, 2]` float64 little-endian bytes.
///     kpts1: `[N, 2]` float64 little-endian bytes.
///     threshold: pixels.
/// Returns:
///     `(matches0, matches1)` as lists of int.
#[pyfunction]
#[pyo3(signature = (h, kpts0, kpts1, threshold = 3.0))]
fn gt_matches_from_homography(h: Vec<f64>, kpts0: PyBackedBytes, kpts1: PyBackedBytes, threshold: f64) -> PyResult<(Vec<i64>, Vec<i64>)> {
    let gt = ground_truth::matches_from_homography(&mat3(&h)?, &points(&kpts0), &points(&kpts1), threshold);
    Ok((gt.matches0, gt.matches1))
}

/// Descriptor-matching baselines.
///
/// Args:
///     desc0: `[M, D]` float32 little-endian bytes.
///     desc1: `[N, D]` float32 little-endian bytes.
///     dim: D.
///     method: "nn", "mnn" or "ratio".
///     ratio: Lowe's ratio for "ratio", in (0, 1].
/// Returns:
///     matches0 as a list of int (−1 = unmatched).
#[pyfunction]
#[pyo3(signature = (desc0, desc1, dim, method = "mnn", ratio = 0.8))]
fn match_baseline(desc0: PyBackedBytes, desc1: PyBackedBytes, dim: usize, method: &str, ratio: f32) -> PyResult<Vec<i64>> {
    let m = Baseline::from_method(method, ratio).map_err(to_py_err)?;
    Ok(baselines::match_descriptors(&f32_from_le(&desc0), &f32_from_le(&desc1), dim, m))
}

/// A baseline matcher's name parsed and checked: `nn`, `mnn`, `ratio` or `ratio:R`.
///
/// Args:
///     spec: the name.
/// Returns:
///     `(method, ratio)` for `match_baseline` (ratio 0.8 where the method has none), or
///     None when `spec` names no baseline.
#[pyfunction]
#[pyo3(signature = (spec))]
fn parse_baseline(spec: &str) -> PyResult<Option<(&'static str, f32)>> {
    Ok(Baseline::parse(spec).map_err(to_py_err)?.map(|b| (b.name(), b.ratio())))
}

/// Names accepted by `_Matcher.pretrained`.
///
/// Returns:
///     The list of shipped weight names.
#[pyfunction]
#[pyo3(signature = ())]
fn pretrained_names() -> Vec<&'static str> {
    paraformer::matcher::PRETRAINED.iter().map(|p| p.0).collect()
}

/// The embedded XFeat network, loaded once on first use.
/// `subpixel`: the instance that refines keypoints (`XFeatConfig::subpixel`); both
/// instances share the one network (`XFeat` clones share their weights).
fn xfeat(subpixel: bool) -> PyResult<&'static XFeat> {
    static PLAIN: std::sync::OnceLock<XFeat> = std::sync::OnceLock::new();
    static SUBPIXEL: std::sync::OnceLock<XFeat> = std::sync::OnceLock::new();
    let plain = match PLAIN.get() {
        Some(x) => x,
        None => {
            let x = XFeat::pretrained().map_err(to_py_err)?;
            PLAIN.get_or_init(|| x)
        }
    };
    if !subpixel {
        return Ok(plain);
    }
    Ok(SUBPIXEL.get_or_init(|| {
        let config = XFeatConfig { subpixel: true, ..plain.config().clone() };
        plain.clone().with_config(config)
    }))
}

/// XFeat output as `(kpts_f32le, scores_f32le, desc_f32le, width, height)`.
type Extracted = (Vec<u8>, Vec<u8>, Vec<u8>, f32, f32);

fn extracted(f: Features) -> Extracted {
    let kpts: Vec<f32> = f.keypoints.iter().flatten().copied().collect();
    (f32_bytes(&kpts), f32_bytes(&f.scores), f32_bytes(&f.descriptors), f.image_size.0, f.image_size.1)
}

/// XFeat keypoints and descriptors of an image given as pixels.
///
/// Args:
///     pixels: `[H, W, C]` values 0–255 as bytes: float32 little-endian, or uint8.
///     height: H.
///     width: W.
///     channels: C (1 grey, 2 grey + alpha, 3 RGB, 4 RGBA).
///     top_k: keep at most this many keypoints (best score first).
///     dtype: `"f32"` or `"u8"`, the element type of `pixels`.
///     subpixel: refine keypoints to sub-pixel precision (a Gaussian fit of the heatmap
///         peak); whole pixels, as the original, when false.
/// Returns:
///     `(kpts, scores, desc, width, height)`: float32 little-endian bytes `[K, 2]`, `[K]`,
///     `[K, 64]` and the image size.
#[pyfunction]
#[pyo3(signature = (pixels, height, width, channels, top_k, dtype = "f32", subpixel = false))]
#[allow(clippy::too_many_arguments)]
fn extract(
    py: Python<'_>,
    pixels: PyBackedBytes,
    height: usize,
    width: usize,
    channels: usize,
    top_k: usize,
    dtype: &str,
    subpixel: bool,
) -> PyResult<Extracted> {
    let xf = xfeat(subpixel)?;
    let u8_pixels = match dtype {
        "f32" => false,
        "u8" => true,
        other => return Err(PyValueError::new_err(format!("dtype: expected \"f32\" or \"u8\", got {other:?}"))),
    };
    py.detach(|| {
        let values: Vec<f32> = if u8_pixels { pixels.iter().map(|&b| b as f32).collect() } else { f32_from_le(&pixels) };
        let img = GrayImage::from_channels(width, height, channels, &values)?;
        xf.detect_and_compute(&img, Some(top_k))
    })
    .map(extracted)
    .map_err(to_py_err)
}

/// Checks, before an array's pixels are copied for `extract`, that XFeat on it fits the
/// memory limit together with those copies (its bytes and their float32 values).
///
/// Args:
///     height: H.
///     width: W.
///     channels: C.
///     item_bytes: bytes per value of the copy (1 for uint8, 4 for float32).
/// Raises:
///     ResourceError: naming the bytes needed and the limit.
#[pyfunction]
#[pyo3(signature = (height, width, channels, item_bytes))]
fn check_extract_memory(height: usize, width: usize, channels: usize, item_bytes: usize) -> PyResult<()> {
    let values = (height as u64).saturating_mul(width as u64).saturating_mul(channels as u64);
    let copies = values.saturating_mul(item_bytes as u64 + 4);
    let needed = paraformer::memory::xfeat_bytes(width, height).saturating_add(copies);
    paraformer::memory::check(format!("XFeat on a {width}×{height} image"), needed, paraformer::memory::memory_limit()).map_err(to_py_err)
}

/// XFeat keypoints and descriptors of an image file (PNG, JPEG, PNM, BMP, TIFF, WebP).
///
/// Args:
///     path: the image file.
///     top_k: keep at most this many keypoints (best score first).
///     subpixel: refine keypoints to sub-pixel precision, as for `extract`.
/// Returns:
///     `(kpts, scores, desc, width, height)` as for `extract`.
#[pyfunction]
#[pyo3(signature = (path, top_k, subpixel = false))]
fn extract_file(py: Python<'_>, path: PathBuf, top_k: usize, subpixel: bool) -> PyResult<Extracted> {
    let xf = xfeat(subpixel)?;
    py.detach(|| xf.detect_and_compute_file(&path, Some(top_k))).map(extracted).map_err(to_py_err)
}

/// Sets the process-wide memory limit of matching and extraction.
///
/// Args:
///     bytes: the limit in bytes (a positive int), or None for the default (90% of the
///         available memory).
/// Raises:
///     ValueError: for 0, a negative number, a bool or anything but an int.
#[pyfunction]
#[pyo3(signature = (bytes,))]
fn set_memory_limit(bytes: Option<&Bound<'_, PyAny>>) -> PyResult<()> {
    let limit = match bytes {
        None => None,
        // A limit of 0 would refuse every call; a bool is an int to Python but not a size.
        Some(b) => match (b.is_instance_of::<pyo3::types::PyBool>(), b.extract::<u64>()) {
            (false, Ok(n)) if n > 0 => Some(n),
            _ => return Err(PyValueError::new_err(format!("bytes: expected a positive int or None, got {}", b.repr()?))),
        },
    };
    paraformer::memory::set_memory_limit(limit);
    Ok(())
}

/// The memory limit in force, in bytes.
///
/// Returns:
///     The limit set, else 90% of the memory available now.
#[pyfunction]
#[pyo3(signature = ())]
fn memory_limit() -> u64 {
    paraformer::memory::memory_limit()
}

/// Decodes an image file to grey values as XFeat sees it (colour averaged over R, G, B).
///
/// Args:
///     path: the image file (PNG, JPEG, PNM, BMP, TIFF, WebP).
/// Returns:
///     `(grey float32 little-endian bytes, width, height)`, values in 0–255.
#[pyfunction]
#[pyo3(signature = (path,))]
fn load_image(py: Python<'_>, path: PathBuf) -> PyResult<(Vec<u8>, usize, usize)> {
    py.detach(|| GrayImage::open(&path))
        .map(|img| (f32_bytes(&img.data), img.width, img.height))
        .map_err(to_py_err)
}

/// Multiply-accumulates of one forward pass (SPEC §10).
///
/// Args:
///     config_json: the config as JSON.
///     m: keypoints of image 0.
///     n: keypoints of image 1.
/// Returns:
///     `(encoder, layers, final_projection)` MAC counts.
#[pyfunction]
#[pyo3(signature = (config_json, m, n))]
fn flops(config_json: &str, m: usize, n: usize) -> PyResult<(u64, u64, u64)> {
    let config = Config::from_json(config_json).map_err(|e| PyValueError::new_err(format!("config: {e}")))?;
    let f = paraformer::flops(&config, m, n);
    Ok((f.encoder, f.layers, f.final_projection))
}

/// Little-endian 16-bit values of `bytes`: borrowed where they are aligned, else copied.
fn u16s(bytes: &[u8]) -> std::borrow::Cow<'_, [u16]> {
    #[cfg(target_endian = "little")]
    {
        // SAFETY: every bit pattern is a valid u16; `align_to` splits off what is unaligned.
        let (head, mid, tail) = unsafe { bytes.align_to::<u16>() };
        if head.is_empty() && tail.is_empty() {
            return std::borrow::Cow::Borrowed(mid);
        }
    }
    std::borrow::Cow::Owned(bytes.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect())
}

/// `v` as little-endian bytes: borrowed on little-endian machines.
fn u16_bytes(v: &[u16]) -> std::borrow::Cow<'_, [u8]> {
    #[cfg(target_endian = "little")]
    {
        // SAFETY: u8 has no alignment or validity requirement, so the middle is all of `v`.
        let (head, mid, tail) = unsafe { v.align_to::<u8>() };
        if head.is_empty() && tail.is_empty() {
            return std::borrow::Cow::Borrowed(mid);
        }
    }
    std::borrow::Cow::Owned(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}

/// `v` as little-endian bytes.
fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// `v` as little-endian bytes.
fn i64_bytes(v: &[i64]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Softmax attention of bf16 operands with the rows' log-sum-exp, for training (the
/// forward that `attention_backward_bf16` pairs with; AVX-512 BF16 CPUs only).
///
/// Args:
///     q: `[bh, n, d]` bfloat16 bits as little-endian uint16 bytes (queries).
///     k: `[bh, m, d]` bfloat16 bits (keys).
///     v: `[bh, m, d]` bfloat16 bits (values).
///     bh: independent heads (batch × heads).
///     n: query rows.
///     m: key rows (at least 1 when there are queries).
///     d: head width, 16, 32 or 64.
///     scale: the factor of the scores, usually `1/√d`.
/// Returns:
///     `(o, lse)`: `softmax(scale·q·kᵀ)·v` as bfloat16 bits `[bh, n, d]`, and
///     `log Σ_j exp(scale·q_i·k_j)` as float32 little-endian bytes `[bh, n]`.
#[pyfunction]
#[pyo3(signature = (q, k, v, bh, n, m, d, scale))]
#[allow(clippy::too_many_arguments)]
fn attention_forward_bf16<'py>(
    py: Python<'py>,
    q: PyBackedBytes,
    k: PyBackedBytes,
    v: PyBackedBytes,
    bh: usize,
    n: usize,
    m: usize,
    d: usize,
    scale: f32,
) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>)> {
    for (name, b) in [("q", &q), ("k", &k), ("v", &v)] {
        if b.len() % 2 != 0 {
            return Err(PyValueError::new_err(format!("{name}: {} bytes, not a whole number of 2-byte values", b.len())));
        }
    }
    let (o, lse) = py
        .detach(|| paraformer::attention_grad::attention_forward_bf16(&u16s(&q), &u16s(&k), &u16s(&v), bh, n, m, d, scale))
        .map_err(to_py_err)?;
    Ok((PyBytes::new(py, &u16_bytes(&o)), PyBytes::new(py, &f32_bytes(&lse))))
}

/// Gradients of softmax attention from bf16 operands, for training (the flash-attention
/// backward with bf16 products and fp32 accumulation; AVX-512 BF16 CPUs only).
///
/// Args:
///     q: `[bh, n, d]` bfloat16 bits as little-endian uint16 bytes (queries).
///     k: `[bh, m, d]` bfloat16 bits (keys).
///     v: `[bh, m, d]` bfloat16 bits (values).
///     o: `[bh, n, d]` bfloat16 bits (the forward's output).
///     d_o: `[bh, n, d]` bfloat16 bits (the gradient of the output).
///     lse: `[bh, n]` float32 little-endian bytes: log Σ_j exp(scale·q_i·k_j) per row.
///     bh: independent heads (batch × heads).
///     n: query rows.
///     m: key rows.
///     d: head width, 16, 32 or 64.
///     scale: the factor of the scores, usually `1/√d`.
/// Returns:
///     `(dq, dk, dv)`: bfloat16 bits as little-endian uint16 bytes, in the layouts of `q`,
///     `k`, `v`.
#[pyfunction]
#[pyo3(signature = (q, k, v, o, d_o, lse, bh, n, m, d, scale))]
#[allow(clippy::too_many_arguments)]
fn attention_backward_bf16<'py>(
    py: Python<'py>,
    q: PyBackedBytes,
    k: PyBackedBytes,
    v: PyBackedBytes,
    o: PyBackedBytes,
    d_o: PyBackedBytes,
    lse: PyBackedBytes,
    bh: usize,
    n: usize,
    m: usize,
    d: usize,
    scale: f32,
) -> PyResult<(Bound<'py, PyBytes>, Bound<'py, PyBytes>, Bound<'py, PyBytes>)> {
    for (name, b, width) in [("q", &q, 2), ("k", &k, 2), ("v", &v, 2), ("o", &o, 2), ("d_o", &d_o, 2), ("lse", &lse, 4)] {
        if b.len() % width != 0 {
            return Err(PyValueError::new_err(format!("{name}: {} bytes, not a whole number of {width}-byte values", b.len())));
        }
    }
    let (dq, dk, dv) = py
        .detach(|| {
            let lse = f32_from_le(&lse);
            paraformer::attention_grad::attention_backward_bf16(&u16s(&q), &u16s(&k), &u16s(&v), &u16s(&o), &u16s(&d_o), &lse, bh, n, m, d, scale)
        })
        .map_err(to_py_err)?;
    Ok((PyBytes::new(py, &u16_bytes(&dq)), PyBytes::new(py, &u16_bytes(&dk)), PyBytes::new(py, &u16_bytes(&dv))))
}

/// The SIMD level of the module's own kernels: "avx512", "avx2" or "baseline", what the CPU
/// has, or lower where `PARAFORMER_SIMD` (read at the first call) caps it.
///
/// Returns:
///     The level's name.
#[pyfunction]
#[pyo3(signature = ())]
fn simd() -> &'static str {
    paraformer::kernels::simd_name()
}

/// The allocator of the module's native code: "mimalloc" (the default) or "system"
/// (`PARAFORMER_ALLOCATOR=system` in the environment before the import).
///
/// Returns:
///     The allocator's name.
#[pyfunction]
#[pyo3(signature = ())]
fn allocator() -> &'static str {
    paraformer::allocator::name()
}

/// Whether this CPU runs `attention_forward_bf16` and `attention_backward_bf16` (AVX-512
/// F, BW and BF16).
///
/// Returns:
///     True where the instructions are present.
#[pyfunction]
#[pyo3(signature = ())]
fn attention_bf16_available() -> bool {
    paraformer::attention_grad::available()
}

/// Whether bf16 matchers run their attention products and Linear layers on AMX tiles
/// (Intel AMX-BF16, Sapphire Rapids and later; Linux grants the tile state per process).
///
/// Returns:
///     True where the CPU has the tiles, the OS granted them and they are not turned off
///     (`set_amx(False)` or `PARAFORMER_AMX=0`).
#[pyfunction]
#[pyo3(signature = ())]
fn amx() -> bool {
    paraformer::amx::active()
}

/// Turns the AMX tiles of bf16 matchers on or off for the whole process (off: the AVX-512
/// BF16 kernels; for side-by-side timing). Where the CPU lacks AMX, on stays off.
///
/// Args:
///     enabled: whether to use the tiles where the CPU has them.
#[pyfunction]
#[pyo3(signature = (enabled))]
fn set_amx(enabled: bool) {
    paraformer::amx::set_enabled(enabled)
}

// mimalloc unless PARAFORMER_ALLOCATOR=system (paraformer::allocator): only the module's own
// Rust allocations use it (benches/allocator_compare.py).
#[global_allocator]
static GLOBAL: paraformer::allocator::ProcessAllocator = paraformer::allocator::ProcessAllocator;

/// The native core of the `paraformer` package.
#[pymodule]
fn _paraformer(m: &Bound<'_, PyModule>) -> PyResult<()> {
    paraformer::allocator::check_env().map_err(to_py_err)?;
    paraformer::amx::check_env().map_err(to_py_err)?;
    paraformer::kernels::check_env().map_err(to_py_err)?;
    m.add_class::<PyMatcher>()?;
    m.add_function(wrap_pyfunction!(flops, m)?)?;
    for f in [
        wrap_pyfunction!(find_homography, m)?,
        wrap_pyfunction!(find_fundamental, m)?,
        wrap_pyfunction!(find_relative_pose, m)?,
        wrap_pyfunction!(pose_auc, m)?,
        wrap_pyfunction!(pose_auc_approx, m)?,
        wrap_pyfunction!(homography_corner_error, m)?,
        wrap_pyfunction!(gt_matches_from_homography, m)?,
        wrap_pyfunction!(match_baseline, m)?,
        wrap_pyfunction!(parse_baseline, m)?,
        wrap_pyfunction!(pretrained_names, m)?,
        wrap_pyfunction!(extract, m)?,
        wrap_pyfunction!(extract_file, m)?,
        wrap_pyfunction!(check_extract_memory, m)?,
        wrap_pyfunction!(load_image, m)?,
        wrap_pyfunction!(set_memory_limit, m)?,
        wrap_pyfunction!(memory_limit, m)?,
        wrap_pyfunction!(attention_forward_bf16, m)?,
        wrap_pyfunction!(attention_backward_bf16, m)?,
        wrap_pyfunction!(attention_bf16_available, m)?,
        wrap_pyfunction!(allocator, m)?,
        wrap_pyfunction!(simd, m)?,
        wrap_pyfunction!(amx, m)?,
        wrap_pyfunction!(set_amx, m)?,
    ] {
        m.add_function(f)?;
    }
    m.add("ParaformerError", m.py().get_type::<ParaformerError>())?;
    let py = m.py();
    let bases = (py.get_type::<ParaformerError>(), py.get_type::<pyo3::exceptions::PyMemoryError>());
    let attrs = PyDict::new(py);
    attrs.set_item("__doc__", "A call would need more memory than the limit allows; nothing was allocated.")?;
    attrs.set_item("__module__", "paraformer")?;
    let t = py.get_type::<pyo3::types::PyType>().call1(("ResourceError", bases, attrs))?.cast_into::<pyo3::types::PyType>()?;
    m.add("ResourceError", t.clone())?;
    let _ = RESOURCE_ERROR.set(py, t.unbind());
    m.add("WeightsError", m.py().get_type::<WeightsError>())?;
    m.add("__version__", paraformer::VERSION)?;
    m.add("BASELINE_NAMES", Baseline::NAMES.to_vec())?;
    Ok(())
}
