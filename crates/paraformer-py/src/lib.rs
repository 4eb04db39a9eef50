//! Thin PyO3 layer over the `paraformer` core. The pure-Python package
//! (`python/paraformer`) validates numpy arrays and hands them over as little-endian
//! bytes; everything heavy runs here with the GIL released.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use paraformer::{Config, Error, Features, MatchOptions, MatchOutput, Matcher, Weights};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::pybacked::PyBackedBytes;
use pyo3::types::{PyByteArray, PyDict};

create_exception!(paraformer, ParaformerError, PyException, "Base class of every paraformer error.");
create_exception!(
    paraformer,
    WeightsError,
    ParaformerError,
    "A weights file is not valid safetensors, has a bad config, or does not match its config."
);

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
        e if e.is_weights_error() => WeightsError::new_err(e.to_string()),
        e => ParaformerError::new_err(e.to_string()),
    }
}

fn f32s(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
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
        let keypoints = f32s(kpts).chunks_exact(2).map(|c| [c[0], c[1]]).collect();
        Ok(Features::new(keypoints, scores.as_ref().map(|s| f32s(s)), f32s(desc), *d, (*w, *h)))
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
    let bytes_i64 = |v: &[i64]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let bytes_f32 = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    d.set_item("matches0", PyByteArray::new(py, &bytes_i64(&out.matches0)))?;
    d.set_item("matches1", PyByteArray::new(py, &bytes_i64(&out.matches1)))?;
    d.set_item("matching_scores0", PyByteArray::new(py, &bytes_f32(&out.matching_scores0)))?;
    d.set_item("matching_scores1", PyByteArray::new(py, &bytes_f32(&out.matching_scores1)))?;
    if let Some(la) = &out.log_assignment {
        d.set_item("log_assignment", (PyByteArray::new(py, &bytes_f32(&la.data)), la.rows, la.cols))?;
    }
    Ok(d)
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
    #[pyo3(signature = (path, /))]
    fn from_file(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let m = py.detach(|| Matcher::from_file(&path)).map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(m) })
    }

    /// Loads weights from bytes whose metadata holds the config.
    ///
    /// Args:
    ///     data: the bytes of a safetensors weights file.
    /// Returns:
    ///     The matcher.
    #[staticmethod]
    #[pyo3(signature = (data, /))]
    fn from_bytes(py: Python<'_>, data: PyBackedBytes) -> PyResult<Self> {
        let m = py.detach(|| Matcher::from_bytes(&data)).map_err(to_py_err)?;
        Ok(Self { inner: Arc::new(m) })
    }

    /// Builds a matcher from an explicit config and a weights file or its bytes.
    ///
    /// Args:
    ///     config_json: the config as JSON (SPEC §9 fields; absent ones take defaults).
    ///     weights: a path (str or os.PathLike) or the bytes of a safetensors file.
    /// Returns:
    ///     The matcher.
    #[staticmethod]
    #[pyo3(signature = (config_json, weights, /))]
    fn with_config(py: Python<'_>, config_json: &str, weights: WeightsArg) -> PyResult<Self> {
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
        Ok(Self { inner: Arc::new(m) })
    }

    /// The config as JSON, every field written out.
    ///
    /// Returns:
    ///     A JSON object string.
    #[getter]
    fn config_json(&self) -> String {
        self.inner.config().to_json()
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
        let opts = MatchOptions { return_log_assignment };
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
        let opts = MatchOptions { return_log_assignment };
        let threads = num_threads
            .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1))
            .clamp(1, feats.len().max(1));
        let results = py.detach(|| {
            let next = AtomicUsize::new(0);
            let mut slots: Vec<Option<paraformer::Result<MatchOutput>>> = (0..feats.len()).map(|_| None).collect();
            std::thread::scope(|s| {
                let workers: Vec<_> = (0..threads)
                    .map(|_| {
                        s.spawn(|| {
                            let mut done = Vec::new();
                            loop {
                                let i = next.fetch_add(1, Ordering::Relaxed);
                                let Some((f0, f1)) = feats.get(i) else { break };
                                done.push((i, self.inner.match_pair_with(f0, f1, opts)));
                            }
                            done
                        })
                    })
                    .collect();
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
        results
            .into_iter()
            .enumerate()
            .map(|(i, r)| match r {
                Some(Ok(out)) => output_dict(py, &out),
                Some(Err(e)) => {
                    let err = to_py_err(e);
                    let msg = format!("pair {i}: {}", err.value(py));
                    Err(match () {
                        _ if err.is_instance_of::<PyValueError>(py) => PyValueError::new_err(msg),
                        _ => ParaformerError::new_err(msg),
                    })
                }
                None => Err(ParaformerError::new_err(format!("pair {i}: worker thread failed"))),
            })
            .collect()
    }
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

/// The native core of the `paraformer` package.
#[pymodule]
fn _paraformer(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyMatcher>()?;
    m.add_function(wrap_pyfunction!(flops, m)?)?;
    m.add("ParaformerError", m.py().get_type::<ParaformerError>())?;
    m.add("WeightsError", m.py().get_type::<WeightsError>())?;
    m.add("__version__", paraformer::VERSION)?;
    Ok(())
}
