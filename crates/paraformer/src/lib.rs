//! # paraformer
//!
//! Sparse feature matching with learned attention matchers on the CPU: ParaFormer
//! (parallel attention + Wave-PE), ParaFormer-U (its U-Net variant) and the SuperGlue
//! baseline, all ending in SuperGlue's optimal matching layer. The numerical contract
//! is `SPEC.md`; weights are safetensors files with the config in their metadata.
//!
//! From two images to a homography with the shipped models (XFeat keypoints, the trained
//! ParaFormer, RANSAC), on the sample pair that comes with the repository:
//!
//! ```
//! use paraformer::geometry::{homography::find_homography, RansacConfig};
//! use paraformer::{GrayImage, Matcher, XFeat};
//!
//! let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/sample");
//! let xfeat = XFeat::pretrained()?; // weights embedded in the crate
//! let f0 = xfeat.detect_and_compute(&GrayImage::open(format!("{dir}/coffee_0.jpg"))?, Some(1024))?;
//! let f1 = xfeat.detect_and_compute(&GrayImage::open(format!("{dir}/coffee_1.jpg"))?, Some(1024))?;
//!
//! let matcher = Matcher::pretrained("paraformer-xfeat")?;
//! let out = matcher.match_pair(&f0, &f1)?; // matches0[i] = j, or −1
//! let point = |p: [f32; 2]| [p[0] as f64, p[1] as f64];
//! let (x0, x1): (Vec<_>, Vec<_>) =
//!     out.pairs().into_iter().map(|(i, j)| (point(f0.keypoints[i]), point(f1.keypoints[j]))).unzip();
//!
//! let fit = find_homography(&x0, &x1, &RansacConfig::default())?;
//! assert!(fit.num_inliers > 100, "{} inliers of {} matches", fit.num_inliers, x0.len());
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! Modules: [`matcher`] (load and run), [`xfeat`] (keypoints from images), [`geometry`]
//! (RANSAC estimators), [`eval`] (ground truth, metrics, datasets), [`config`],
//! [`weights`] (the strict loader), [`memory`] (the memory guard), [`error`], and with the
//! feature `mimalloc` the process allocator of the command and the Python module (`allocator`).

#![warn(missing_docs)]

#[cfg(feature = "mimalloc")]
pub mod allocator;
pub mod amx;
#[doc(hidden)]
pub mod attention;
#[doc(hidden)]
pub mod attention_fused;
#[doc(hidden)]
pub mod attention_fused_avx2;
pub mod attention_grad;
pub mod config;
#[doc(hidden)]
pub mod conv_direct;
pub mod error;
pub mod eval;
pub mod features;
pub mod flops;
pub mod geometry;
#[doc(hidden)]
pub mod gemm_bf16;
#[doc(hidden)]
pub mod kernels;
#[doc(hidden)]
pub mod layers;
pub mod matcher;
pub mod memory;
#[doc(hidden)]
pub mod mlp;
#[doc(hidden)]
pub mod pooling;
pub mod sinkhorn;
#[doc(hidden)]
pub mod wave_pe;
pub mod weights;
pub mod xfeat;

/// Re-exported so that users of the geometry API name the same matrix types.
pub use nalgebra;
pub use config::{Config, LayerKind, ModelKind, ParallelSwitches, Pooling, PositionalEncoding};
pub use error::{Error, Result, TensorProblem};
pub use features::{read_pair_bytes, read_pair_file, Features};
pub use flops::{flops, Flops};
pub use kernels::Precision;
pub use matcher::{MatchOptions, MatchOutput, Matcher, Profile};
pub use sinkhorn::Matrix;
pub use weights::Weights;
pub use xfeat::{GrayImage, XFeat, XFeatConfig};

/// The crate version.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
