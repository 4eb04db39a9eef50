//! Evaluation: metrics (pose and homography AUC, precision/recall/F1, MMA),
//! ground-truth matches from a homography, and descriptor-matching baselines.

pub mod baselines;
pub mod datasets;
pub mod draw;
pub mod ground_truth;
pub mod harness;
pub mod metrics;
pub mod synthetic;
