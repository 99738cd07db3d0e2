//! relfusion-slam: the DeepRelativeFusion pipeline as a library with no networking.
//!
//! Module map, lower layers first: a module uses only those above it (ARCHITECTURE.md has the
//! table of what each may use).
//! - [`error`]: the crate's `Error` and `Result`.
//! - [`background`]: one background-worker pattern (`Service`, `Worker`, `Link`) with the
//!   threads' priorities below the frame path.
//! - [`image`]: grayscale float images (from `relfusion-core`), pyramids and gradients (CPU
//!   references of the GPU kernels).
//! - [`geometry`]: Lie groups (`SO3`, `SE3`, `Sim3`) and the pinhole camera with distortion
//!   (re-exported from `relfusion-core`).
//! - [`frame`]: an undistorted frame with its pyramid, shared by every stage.
//! - [`npy`]: minimal NumPy `.npy` float32 reader/writer for depth maps and benchmarks.
//! - [`optim`]: the Levenberg–Marquardt schedule and loop, and the photometric residual model,
//!   shared by tracking and the back end.
//! - [`scale_shift`]: the robust eq. (3) scale/shift fit of one depth map to another.
//! - [`gpu`]: the wgpu contexts (one per adapter) and the pyramid kernel's runner.
//! - [`dataset`]: TUM RGB-D reader and trajectory files (from `relfusion-core`), the synthetic
//!   room renderer.
//! - [`mapping`]: the semi-dense inverse-depth filter of each keyframe, keyframe selection.
//! - [`tracking`]: coarse-to-fine SE(3) direct image alignment against the keyframe.
//! - [`graph`]: keyframe-to-keyframe Sim(3) constraints, the pose graph, the back end.
//! - [`dense`]: the dense layer (depth prior, filter, densification, two-view consistency).
//! - [`fusion`]: TSDF fusion of the dense keyframes (sparse blocks, GPU kernels), marching
//!   cubes, mesh deltas.
//! - [`export`]: PLY point clouds and meshes, glTF binary meshes, for people to open.
//! - [`map`]: saved maps (versioned format, atomic write, load) and localisation in them.
//! - [`pipeline`]: `Pipeline::push(frame) -> events` over all of the above.
//! - [`eval`]: ATE / RPE with Umeyama alignment, depth and mesh accuracy, diagnostics.
//!
//! Conventions used everywhere: poses are named by their frames (`world_from_camera`,
//! `T_w_c`); Lie-group tangents are perturbed on the right (`T · exp(δ)`); SE(3) tangents are
//! ordered (translation ρ, rotation φ), Sim(3) tangents (ρ, φ, σ) with scale `s = exp(σ)`.

pub mod background;
pub mod dataset;
pub mod dense;
pub mod error;
pub mod eval;
pub mod export;
pub mod frame;
pub mod frame_log;
pub mod fusion;
pub mod gpu;
pub mod graph;
pub mod image;
pub mod map;
pub mod mapping;
pub mod metric_scale;
pub mod npy;
pub mod odometry;
pub mod optim;
pub mod pipeline;
pub mod scale_shift;
pub mod spill;
pub mod tracking;
pub mod window;

pub use error::{Error, Result};
/// Lie groups and the camera model live in `relfusion-core`, shared with the client SDK.
pub use relfusion_core::geometry;
