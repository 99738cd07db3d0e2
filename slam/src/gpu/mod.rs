//! The wgpu runtime and one runner per WGSL kernel of `relfusion-shaders`.
//!
//! - [`context`]: [`GpuContext`] (adapter choice with the lavapipe CPU fallback, pipeline
//!   cache, buffer upload/download) and its [`GpuConfig`].
//! - [`pyramid`]: [`PyramidKernel`], image pyramid + gradients for LSD-SLAM tracking; CPU twin
//!   in [`crate::image::pyramid`].
//!
//! Every runner is tested against its CPU twin on random inputs with a real adapter (lavapipe
//! on machines without a GPU); such tests fail, never skip, when no adapter exists.

pub mod context;
pub mod pyramid;

pub use context::{AdapterChoice, GpuConfig, GpuContext};
pub use pyramid::{GpuPyramid, PyramidKernel};
