//! Direct SE(3) tracking of new frames against the current keyframe (LSD-SLAM, Engel et al.
//! ECCV 2014 §3.3; the "SE3Tracker" of tum-vision/lsd_slam).
//!
//! A frame is aligned to the keyframe by minimising the variance-normalised photometric error
//! of the keyframe's semi-dense points, `E(ξ) = Σ ρ_huber(r_p² / σ_rp²)` with
//! `r_p = I_kf(p) − I_frame(π(T(ξ)·p))` (eqs. (12)–(14)), coarse-to-fine over the image
//! pyramid with Levenberg–Marquardt on the 6×6 normal equations.
//!
//! - [`reference`]: the keyframe side, its depth pyramid and per-level point clouds;
//! - [`warp`]: the inner loops (warp, residuals, weights, Jacobians, normal equations);
//! - [`se3_tracker`]: the LM schedule, loss detection and relocalisation;
//! - [`config`]: [`TrackingConfig`] with LSD-SLAM's defaults.

pub mod config;
pub mod reference;
pub mod se3_tracker;
pub mod warp;

pub use config::TrackingConfig;
pub use reference::{ReferenceLevel, TrackingReference};
pub use se3_tracker::{SE3Tracker, TrackingResult};
pub use warp::intensity_jacobian_right;

#[cfg(test)]
mod tests;
