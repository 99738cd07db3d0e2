//! Direct SE(3) tracking of new frames against the current keyframe (LSD-SLAM, Engel et al.
//! ECCV 2014 §3.3; the "SE3Tracker" of tum-vision/lsd_slam).
//!
//! A frame is aligned to the keyframe by minimising the variance-normalised photometric error
//! of the keyframe's semi-dense points, `E(ξ) = Σ ρ_huber(r_p² / σ_rp²)` with
//! `r_p = I_kf(p) − I_frame(π(T(ξ)·p))` (eqs. (12)–(14)), coarse-to-fine over the image
//! pyramid with Levenberg–Marquardt on the 6×6 normal equations.
//!
//! - [`reference`](mod@reference): the keyframe side, its depth pyramid and per-level point clouds;
//! - [`warp`]: the inner loops (warp, residuals, weights, Jacobians, normal equations);
//! - [`se3_tracker`]: the LM schedule, loss detection and relocalisation;
//! - [`config`]: [`TrackingConfig`] with LSD-SLAM's defaults.
//!
//! Internally the increments are applied on the left, `T ← exp(δ)·T` (LSD-SLAM's form: the
//! Jacobian then depends only on the warped point); the reported information matrix is
//! converted to the crate's right-perturbation convention.
//!
//! Performance (640×480, 2-core EPYC VM, test profile): ~2.8 ms per `track` for a keyframe
//! with 44k semi-dense points (17k at level 1, where tracking stops by default), ~7.5 ms when
//! tracking down to level 0. Inner loops are `f32` over struct-of-arrays buffers reused
//! across calls; the weighting pass is written lane-wise and vectorises. Tracking stays on
//! one thread: the pipeline's second core runs the depth-map filter concurrently (as
//! LSD-SLAM's mapping thread), and one evaluation at level 1 takes only ~0.3 ms, so the
//! ~40 per-evaluation thread hand-offs would eat most of a 2-way split.

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

#[cfg(test)]
mod real_tests;
