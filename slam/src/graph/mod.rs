//! The back end of LSD-SLAM (Engel et al., ECCV 2014, §3.4–3.5): keyframe-to-keyframe Sim(3)
//! constraints, their search and verification, and the Sim(3) pose graph. DeepRelativeFusion
//! (Loo et al., IROS 2021) keeps this back end unchanged and only feeds it better depth.
//!
//! - [`sim3_tracker`]: direct Sim(3) alignment of two keyframes with photometric *and* depth
//!   residuals ([`Sim3Tracker`]);
//! - [`points`]: per-level inverse-depth pyramids and reference point clouds of a keyframe;
//! - [`search`]: candidate keyframes (pose proximity, appearance thumbnail) and the staged
//!   reciprocal consistency test;
//! - [`pose_graph`]: the graph and its sparse Levenberg–Marquardt ([`PoseGraph`]), solved by the
//!   block Cholesky of [`cholesky`] (live passes over a whole large graph by the conjugate
//!   gradients of [`conjugate_gradients`]); `scope`: which vertices a live (bounded)
//!   optimisation moves;
//! - [`backend`]: [`Backend`], the keyframe store, constraint search and optimisation;
//! - [`resident`]: which keyframes the back end holds in full (the others compact);
//! - [`link`]: [`BackendLink`], the back end in step or on its own thread.
//!
//! Naming: a constraint's transform is `to_from_from` (maps `from`-keyframe coordinates to
//! `to`-keyframe coordinates); vertices are `world_from_keyframe`. Perturbations are on the
//! right, tangents (ρ, φ, σ), as everywhere in the crate.

pub mod backend;
pub mod cholesky;
pub mod config;
pub mod conjugate_gradients;
pub mod link;
pub mod points;
pub mod pose_graph;
pub mod resident;
mod scope;
pub mod search;
pub mod sim3_tracker;

/// Keyframes are identified by the pipeline's keyframe counter.
pub type KeyframeId = usize;

pub use backend::{Backend, Budget, NewKeyframe, ParentEdge, ProcessReport};
pub use config::BackendConfig;
pub use link::{BackendCommand, BackendLink};
pub use pose_graph::{Constraint, OptimizeReport, PoseGraph, ScalePrior};
pub use search::{
    CompactKeyframe, Keyframe, KeyframeData, KeyframeMaps, ReciprocalCheck, Thumbnail,
    reciprocal_consistency, reciprocal_test,
};
pub use sim3_tracker::{Sim3TrackResult, Sim3Tracker};

#[cfg(test)]
mod tests;
