//! The one error type of the crate.

use std::fmt;
use std::path::PathBuf;

/// Everything that can go wrong when loading weights or matching. Its `Debug` form is
/// the message itself, so that `?` in a program's `main` prints a readable line.
#[derive(thiserror::Error)]
pub enum Error {
    /// A file (weights, image, dataset) could not be read from disk.
    #[error("cannot read {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What the operating system said (not found, permission denied, …).
        #[source]
        source: std::io::Error,
    },
    /// A file (an output picture, a JSON report) could not be written.
    #[error("cannot write {}: {source}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// What the operating system or the encoder said.
        #[source]
        source: std::io::Error,
    },
    /// The bytes are not a valid safetensors file (truncated, corrupted, other format).
    #[error("not a valid safetensors weights file: {0}")]
    WeightsFormat(String),
    /// The file has no `paraformer.config` metadata and no config was given.
    #[error("weights file has no `paraformer.config` metadata; pass a config explicitly")]
    MissingConfig,
    /// The config JSON or a config value is invalid.
    #[error("invalid config: {0}")]
    Config(String),
    /// The tensors in the file do not match the config (every problem is listed).
    #[error("weights do not match the config ({} problem{}):\n{}", .0.len(), if .0.len() == 1 { "" } else { "s" }, ProblemList(.0))]
    WeightsMismatch(Vec<TensorProblem>),
    /// A bad argument to `match_pair`, XFeat or the geometry (shape, width, NaN/Inf,
    /// image size, an undecodable image, an unknown pretrained name).
    #[error("invalid input `{argument}`: {reason}")]
    InvalidInput {
        /// The argument, as named in the API (`keypoints0`, `descriptors1`, `image`, a path).
        argument: String,
        /// What is wrong with it and what was expected.
        reason: String,
    },
    /// A call would need more memory than the limit allows (see [`crate::memory`]); nothing
    /// was allocated.
    #[error("{what} needs {} of memory, more than the limit of {} (fewer keypoints, a smaller image, or a higher limit: paraformer::memory::set_memory_limit, paraformer.set_memory_limit, --memory-limit)", crate::memory::human(*.needed), crate::memory::human(*.limit))]
    Resource {
        /// The call that was refused (`a match of 60000 × 60000 keypoints`).
        what: String,
        /// Bytes it would need.
        needed: u64,
        /// The limit in force, in bytes.
        limit: u64,
    },
    /// An internal tensor operation failed (a bug: please report it).
    #[error("tensor operation failed: {0}")]
    Tensor(#[from] candle_core::Error),
}

impl fmt::Debug for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(self, f)
    }
}

impl Error {
    pub(crate) fn input(argument: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::InvalidInput { argument: argument.into(), reason: reason.into() }
    }

    /// True for errors about the weights file or its config (as opposed to match inputs).
    pub fn is_weights_error(&self) -> bool {
        matches!(
            self,
            Error::WeightsFormat(_) | Error::MissingConfig | Error::Config(_) | Error::WeightsMismatch(_)
        )
    }
}

/// One way in which a tensor of a weights file differs from what the config needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TensorProblem {
    /// The config needs a tensor the file does not have.
    Missing {
        /// Tensor name.
        name: String,
        /// The shape the config needs.
        expected_shape: Vec<usize>,
    },
    /// The file has a tensor the config does not use.
    Unexpected {
        /// Tensor name.
        name: String,
        /// Its shape in the file.
        shape: Vec<usize>,
    },
    /// The tensor's shape differs from what the config needs.
    WrongShape {
        /// Tensor name.
        name: String,
        /// The shape the config needs.
        expected_shape: Vec<usize>,
        /// The shape in the file.
        found_shape: Vec<usize>,
    },
    /// The tensor is not a float tensor (F32, F16 or BF16).
    WrongDtype {
        /// Tensor name.
        name: String,
        /// Its dtype in the file.
        found: String,
    },
    /// The tensor holds a NaN or an infinity.
    NonFinite {
        /// Tensor name.
        name: String,
        /// Flat index of the first non-finite value.
        index: usize,
        /// That value (`NaN`, `inf`, `-inf`).
        value: String,
    },
}

impl TensorProblem {
    /// The tensor name the problem is about.
    pub fn name(&self) -> &str {
        match self {
            TensorProblem::Missing { name, .. }
            | TensorProblem::Unexpected { name, .. }
            | TensorProblem::WrongShape { name, .. }
            | TensorProblem::WrongDtype { name, .. }
            | TensorProblem::NonFinite { name, .. } => name,
        }
    }
}

impl fmt::Display for TensorProblem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TensorProblem::Missing { name, expected_shape } => {
                write!(f, "missing tensor `{name}` (expected shape {expected_shape:?})")
            }
            TensorProblem::Unexpected { name, shape } => {
                write!(f, "unexpected tensor `{name}` (shape {shape:?}) is not used by this config")
            }
            TensorProblem::WrongShape { name, expected_shape, found_shape } => write!(
                f,
                "tensor `{name}` has shape {found_shape:?}, expected {expected_shape:?}"
            ),
            TensorProblem::WrongDtype { name, found } => {
                write!(f, "tensor `{name}` has dtype {found}, expected F32, F16 or BF16")
            }
            TensorProblem::NonFinite { name, index, value } => {
                write!(f, "tensor `{name}` holds {value} at flat index {index}; weights must be finite")
            }
        }
    }
}

struct ProblemList<'a>(&'a [TensorProblem]);

impl fmt::Display for ProblemList<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, p) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "  - {p}")?;
        }
        Ok(())
    }
}

/// The crate's result type.
pub type Result<T> = std::result::Result<T, Error>;
