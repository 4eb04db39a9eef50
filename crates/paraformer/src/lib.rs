//! # paraformer
//!
//! Sparse feature matching with learned attention matchers on the CPU: ParaFormer
//! (parallel attention + Wave-PE), ParaFormer-U (its U-Net variant) and the SuperGlue
//! baseline, all ending in SuperGlue's optimal matching layer. The numerical contract
//! is `SPEC.md`; weights are safetensors files with the config in their metadata.
//!
//! ```no_run
//! use paraformer::{Features, Matcher};
//! let matcher = Matcher::from_file("paraformer.safetensors")?;
//! let d = matcher.config().descriptor_dim;
//! let f0 = Features::new(vec![[10.0, 20.0]], None, vec![0.1; d], d, (640.0, 480.0));
//! let f1 = Features::new(vec![[12.0, 21.0]], None, vec![0.1; d], d, (640.0, 480.0));
//! let out = matcher.match_pair(&f0, &f1)?;
//! println!("{:?}", out.pairs());
//! # Ok::<(), paraformer::Error>(())
//! ```

pub mod attention;
pub mod config;
pub mod error;
pub mod eval;
pub mod features;
pub mod flops;
pub mod geometry;
pub mod kernels;
pub mod layers;
pub mod matcher;
pub mod memory;
pub mod mlp;
pub mod pooling;
pub mod sinkhorn;
pub mod wave_pe;
pub mod weights;
pub mod xfeat;

/// Re-exported so that users of the geometry API name the same matrix types.
pub use nalgebra;
pub use config::{Config, LayerKind, ModelKind, ParallelSwitches, Pooling, PositionalEncoding};
pub use error::{Error, Result, TensorProblem};
pub use features::{read_pair_bytes, read_pair_file, Features};
pub use flops::{flops, Flops};
pub use matcher::{MatchOptions, MatchOutput, Matcher, Profile};
pub use sinkhorn::Matrix;
pub use weights::Weights;
pub use xfeat::{GrayImage, XFeat, XFeatConfig};

/// The crate version.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
