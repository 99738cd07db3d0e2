//! relfusion-slam: the DeepRelativeFusion pipeline as a library with no networking.
//!
//! Module map (see ARCHITECTURE.md):
//! - [`geometry`]: Lie groups (`SO3`, `SE3`, `Sim3`) and the pinhole camera with distortion.
//! - [`image`]: grayscale float images, pyramids and gradients (CPU references of the GPU kernels).
//! - [`dataset`]: TUM RGB-D reader, trajectory files, the synthetic room renderer.
//! - [`eval`]: ATE / RPE with Umeyama alignment, percentage of correct depth.
//! - [`gpu`]: the wgpu context and one runner per WGSL kernel.
//! - [`dense`]: the dense layer (depth prior runtime, scale/shift alignment, ...).
//! - [`background`]: the dense and fusion threads at the lowest priority, so tracking runs first.
//! - [`frame`]: an undistorted frame with its pyramid, shared by every stage.
//! - [`fusion`]: TSDF fusion of the dense keyframes (sparse blocks, GPU kernels), marching
//!   cubes, mesh deltas.
//! - [`tracking`]: coarse-to-fine SE(3) direct image alignment against the keyframe.
//! - [`mapping`]: the semi-dense inverse-depth filter of each keyframe, keyframe selection.
//! - [`graph`]: keyframe-to-keyframe Sim(3) constraints and the pose graph.
//! - [`export`]: PLY point clouds and meshes, glTF binary meshes, for people to open.
//! - [`pipeline`]: `Pipeline::push(frame) -> events` over tracking, mapping and the back end.
//! - [`npy`]: minimal NumPy `.npy` float32 reader/writer for depth maps and benchmarks.
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
pub mod fusion;
pub mod geometry;
pub mod gpu;
pub mod graph;
pub mod image;
pub mod mapping;
pub mod npy;
pub mod pipeline;
pub mod tracking;

pub use error::{Error, Result};
