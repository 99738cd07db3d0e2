//! Semi-dense mapping: per-keyframe inverse-depth filtering (LSD-SLAM §3, Engel et al. ICCV 2013).
//!
//! - [`DepthFilter`] (`filter`): the keyframe's hypotheses; `observe` (epipolar stereo, `stereo`,
//!   and Kalman fusion), `regularize` (`regularize`: smoothing, outlier removal, hole filling),
//!   `propagate_to` (`propagate`: forward warp to the next keyframe), `normalize_scale`.
//! - [`DepthMap`] (`depth_map`): the published snapshot tracking and the dense layer read.
//! - [`keyframe_score`] / [`needs_new_keyframe`] (`keyframe`): when to start a new keyframe.
//! - [`MappingConfig`] (`config`): every constant, with LSD-SLAM's defaults.
//!
//! Typical use (LSD-SLAM's mapping thread): for each tracked frame `observe` then `regularize`;
//! when a new keyframe is selected, `propagate_to` it, `normalize_scale` and give the returned
//! factor to the new keyframe's Sim(3) pose.

mod bands;
#[cfg(test)]
mod bench_tests;
pub mod config;
pub mod depth_map;
pub mod filter;
#[cfg(test)]
mod filter_tests;
mod hypothesis;
pub mod keyframe;
mod prior_fill;
mod propagate;
#[cfg(test)]
mod real_tests;
mod regularize;
mod stereo;
#[cfg(test)]
pub(crate) mod test_scene;

pub use config::MappingConfig;
pub use depth_map::{CompactDepth, DepthMap, InverseDepth};
pub use filter::{DepthFilter, ObserveStats};
pub use keyframe::{keyframe_score, keyframe_threshold, needs_new_keyframe};
pub use prior_fill::{PriorFill, PriorFillParams};
