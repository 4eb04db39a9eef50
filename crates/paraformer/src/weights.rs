//! Strict safetensors loading (SPEC §9): the config from the `paraformer.config`
//! metadata, and a check of the file against exactly the tensors the config needs.
//!
//! Models are built through a candle `VarBuilder` whose backend (`CheckedBackend`)
//! records every problem instead of failing at the first one, so a single load
//! reports every missing, unexpected, mis-shaped or wrongly typed tensor.

use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use std::sync::Mutex;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::VarBuilder;
use safetensors::{Dtype, SafeTensors};

use crate::config::{Config, CONFIG_METADATA_KEY};
use crate::error::{Error, Result, TensorProblem};

/// One tensor of a file, kept as raw little-endian bytes until it is asked for.
#[derive(Debug, Clone)]
struct RawTensor {
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

impl RawTensor {
    fn is_float(&self) -> bool {
        matches!(self.dtype, Dtype::F32 | Dtype::F16 | Dtype::BF16)
    }

    /// The values upcast to f32 (caller has checked `is_float`).
    fn to_f32(&self) -> Vec<f32> {
        match self.dtype {
            Dtype::F16 => self
                .data
                .chunks_exact(2)
                .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            Dtype::BF16 => self
                .data
                .chunks_exact(2)
                .map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            _ => crate::features::f32_from_le(&self.data),
        }
    }
}

/// The tensors (and optional config) of a safetensors weights file.
#[derive(Debug, Clone)]
pub struct Weights {
    tensors: BTreeMap<String, RawTensor>,
    config: Option<Config>,
}

impl Weights {
    /// Reads a weights file. A missing or unreadable file is [`Error::Io`].
    pub fn from_file(path: impl AsRef<Path>) -> Result<Weights> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| Error::Io { path: path.to_path_buf(), source })?;
        // Name the file in format and config errors.
        Weights::from_bytes(&bytes).map_err(|e| match e {
            Error::WeightsFormat(m) => Error::WeightsFormat(format!("{}: {m}", path.display())),
            Error::Config(m) => Error::Config(format!("{}: {m}", path.display())),
            e => e,
        })
    }

    /// Parses safetensors bytes. Truncated or corrupted data is [`Error::WeightsFormat`];
    /// a present but invalid config is [`Error::Config`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Weights> {
        let (_, metadata) =
            SafeTensors::read_metadata(bytes).map_err(|e| Error::WeightsFormat(e.to_string()))?;
        let st = SafeTensors::deserialize(bytes).map_err(|e| Error::WeightsFormat(e.to_string()))?;
        let config = match metadata.metadata().as_ref().and_then(|m| m.get(CONFIG_METADATA_KEY)) {
            Some(json) => Some(
                Config::from_json(json)
                    .map_err(|e| Error::Config(format!("metadata `{CONFIG_METADATA_KEY}`: {e}")))?,
            ),
            None => None,
        };
        let tensors = st
            .tensors()
            .into_iter()
            .map(|(name, view)| {
                let raw = RawTensor { dtype: view.dtype(), shape: view.shape().to_vec(), data: view.data().to_vec() };
                (name, raw)
            })
            .collect();
        Ok(Weights { tensors, config })
    }

    /// The config stored in the file's metadata, if any.
    pub fn config(&self) -> Option<&Config> {
        self.config.as_ref()
    }

    /// Names of all tensors in the file, sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.tensors.keys().map(String::as_str)
    }

    /// Builds a model from these weights, failing with every tensor problem at once.
    pub(crate) fn build<T>(&self, build: impl FnOnce(VarBuilder) -> candle_core::Result<T>) -> Result<T> {
        let backend = CheckedBackend { weights: self, requested: Mutex::default(), problems: Mutex::default() };
        let vb = VarBuilder::from_backend(Box::new(backend.clone_ref()), DType::F32, Device::Cpu);
        let model = build(vb)?;
        let requested = backend.requested.into_inner().unwrap_or_else(|e| e.into_inner());
        let mut problems = backend.problems.into_inner().unwrap_or_else(|e| e.into_inner());
        for (name, t) in &self.tensors {
            if requested.contains(name) {
                continue;
            }
            // BatchNorm's step counter is ignored by readers (SPEC §2).
            if let Some(prefix) = name.strip_suffix(".num_batches_tracked") {
                if requested.contains(&format!("{prefix}.running_mean")) {
                    continue;
                }
            }
            problems.push(TensorProblem::Unexpected { name: name.clone(), shape: t.shape.clone() });
        }
        if problems.is_empty() {
            Ok(model)
        } else {
            Err(Error::WeightsMismatch(problems))
        }
    }
}

/// A `VarBuilder` backend over [`Weights`] that records problems and hands out
/// zeros in place of bad tensors, so that the build runs to the end.
struct CheckedBackend<'a> {
    weights: &'a Weights,
    requested: Mutex<HashSet<String>>,
    problems: Mutex<Vec<TensorProblem>>,
}

/// Shares the recording state between the boxed backend and the caller.
struct SharedBackend<'a>(&'a CheckedBackend<'a>);

impl<'a> CheckedBackend<'a> {
    fn clone_ref(&'a self) -> SharedBackend<'a> {
        SharedBackend(self)
    }

    fn fetch(&self, shape: &Shape, name: &str) -> candle_core::Result<Tensor> {
        let expected = shape.dims().to_vec();
        if let Ok(mut r) = self.requested.lock() {
            r.insert(name.to_string());
        }
        let problem = match self.weights.tensors.get(name) {
            None => Some(TensorProblem::Missing { name: name.into(), expected_shape: expected.clone() }),
            Some(t) if !t.is_float() => {
                Some(TensorProblem::WrongDtype { name: name.into(), found: format!("{:?}", t.dtype) })
            }
            // A scalar may be stored as `[]` or `[1]` (SPEC §8, `bin_score`).
            Some(t) if t.shape != expected && !(expected.is_empty() && t.shape == [1]) => {
                Some(TensorProblem::WrongShape {
                    name: name.into(),
                    expected_shape: expected.clone(),
                    found_shape: t.shape.clone(),
                })
            }
            Some(t) => {
                let values = t.to_f32();
                match values.iter().position(|v| !v.is_finite()) {
                    None => return Tensor::from_vec(values, shape.clone(), &Device::Cpu),
                    Some(index) => Some(TensorProblem::NonFinite { name: name.into(), index, value: values[index].to_string() }),
                }
            }
        };
        if let (Some(p), Ok(mut ps)) = (problem, self.problems.lock()) {
            ps.push(p);
        }
        Tensor::zeros(shape.clone(), DType::F32, &Device::Cpu)
    }
}

impl candle_nn::var_builder::SimpleBackend for SharedBackend<'_> {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _h: candle_nn::Init,
        _dtype: DType,
        _dev: &Device,
    ) -> candle_core::Result<Tensor> {
        self.0.fetch(&s, name)
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        let shape = self.0.weights.tensors.get(name).map(|t| t.shape.clone()).unwrap_or_default();
        self.0.fetch(&Shape::from(shape), name)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.0.weights.tensors.contains_key(name)
    }
}

/// A `VarBuilder` backend that invents deterministic random weights of the requested
/// shapes: Linear weights `U(±sqrt(3/fan_in))`, small biases, positive running
/// variances, norm weights near 1. For benchmarks and tests at any width.
struct RandomBackend {
    seed: u64,
}

impl candle_nn::var_builder::SimpleBackend for RandomBackend {
    fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        // One stream per tensor name, so values do not depend on the build order.
        let mut state = name.bytes().fold(self.seed ^ 0xCBF2_9CE4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x100_0000_01B3));
        let mut uniform = || {
            let mut rng = crate::pooling::SplitMix64::new(state);
            state = rng.next_u64();
            (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        };
        let dims = s.dims().to_vec();
        let n = s.elem_count();
        let values: Vec<f32> = if name.ends_with("running_var") {
            (0..n).map(|_| 1.0 + 0.5 * uniform()).collect()
        } else if dims.len() == 2 {
            let bound = (3.0 / dims[1] as f32).sqrt();
            (0..n).map(|_| bound * uniform()).collect()
        } else if name.ends_with("weight") {
            (0..n).map(|_| 1.0 + 0.1 * uniform()).collect()
        } else {
            (0..n).map(|_| 0.1 * uniform()).collect()
        };
        Tensor::from_vec(values, s, &Device::Cpu)
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        Err(candle_core::Error::Msg(format!("random weights need a shape for `{name}`")))
    }

    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

/// A `VarBuilder` that hands out deterministic random weights of any requested shape,
/// for building single layers or whole models in benchmarks and tests.
pub fn random_var_builder(seed: u64) -> VarBuilder<'static> {
    VarBuilder::from_backend(Box::new(RandomBackend { seed }), DType::F32, Device::Cpu)
}
