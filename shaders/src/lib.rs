//! Every WGSL compute kernel of relfusion, one `.wgsl` file per kernel under `shaders/wgsl/`,
//! embedded as `&'static str` so that the library needs no files at run time.
//!
//! [`ALL`] lists every kernel; the naga validation test (`tests/validate.rs`) walks it, so a new
//! kernel is validated as soon as it is listed here.
//!
//! Conventions every kernel follows (so that the Rust runners in `relfusion_slam::gpu` stay
//! uniform):
//! - the entry point is `main`;
//! - binding 0 of group 0 is the kernel's parameter uniform, whose Rust mirror is a `#[repr(C)]`
//!   `bytemuck::Pod` struct with explicit padding and a size assert next to its runner;
//! - images are row-major `array<f32>` in 8-bit intensity units (0..255).
//!
//! WGSL has no `#include`. When several kernels need shared declarations, put them in
//! `wgsl/common.wgsl` and build the constant as
//! `concat!(include_str!("../wgsl/common.wgsl"), include_str!("../wgsl/foo.wgsl"))`; the
//! validation test then checks the concatenation, which is what the GPU compiles.

/// Entry point of every kernel (see the crate conventions).
pub const ENTRY_POINT: &str = "main";

/// 2×2 box downsampling of one pyramid level into the next (floor size).
pub const PYRAMID_DOWNSAMPLE: &str = include_str!("../wgsl/pyramid_downsample.wgsl");

/// Central-difference gradients `gx`, `gy` and `|∇I|` of one pyramid level (clamp-to-edge).
pub const IMAGE_GRADIENT: &str = include_str!("../wgsl/image_gradient.wgsl");

/// The semi-dense adaptive filter of DeepRelativeFusion (eqs. 4–8): one pixel per invocation,
/// filtered inverse depth and re-estimated variance over a (2r+1)² window.
pub const ADAPTIVE_FILTER: &str = include_str!("../wgsl/adaptive_filter.wgsl");

/// One Adam iteration of the densification (eqs. 10–13): analytic gradient of the energy at
/// each pixel from the previous iterate (ping-pong buffers), moment update, step.
pub const DENSIFY_ADAM: &str = include_str!("../wgsl/densify_adam.wgsl");

/// Forward warp of the previous keyframe's inverse depth into the new keyframe (eq. 14) with a
/// nearest-surface test (atomic max on the inverse depth's bits).
pub const TWO_VIEW_WARP: &str = include_str!("../wgsl/two_view_warp.wgsl");

/// TSDF integration / de-integration of one depth map: one invocation per voxel of the listed
/// blocks, projective signed distance, weighted running average.
pub const TSDF_INTEGRATE: &str = include_str!("../wgsl/tsdf_integrate.wgsl");

/// Marching cubes over voxel blocks: one invocation per cell of each meshing job, triangles
/// appended through an atomic counter (case table uploaded by the runner).
pub const MARCHING_CUBES: &str = include_str!("../wgsl/marching_cubes.wgsl");

/// Every kernel as `(name, source)`; names are unique and are the pipeline-cache keys.
pub const ALL: &[(&str, &str)] = &[
    ("pyramid_downsample", PYRAMID_DOWNSAMPLE),
    ("image_gradient", IMAGE_GRADIENT),
    ("adaptive_filter", ADAPTIVE_FILTER),
    ("densify_adam", DENSIFY_ADAM),
    ("two_view_warp", TWO_VIEW_WARP),
    ("tsdf_integrate", TSDF_INTEGRATE),
    ("marching_cubes", MARCHING_CUBES),
];
