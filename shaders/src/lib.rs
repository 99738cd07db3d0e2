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

/// Every kernel as `(name, source)`; names are unique and are the pipeline-cache keys.
pub const ALL: &[(&str, &str)] = &[
    ("pyramid_downsample", PYRAMID_DOWNSAMPLE),
    ("image_gradient", IMAGE_GRADIENT),
];
