//! The wgpu runtime and one runner per WGSL kernel of `relfusion-shaders`.
//!
//! - [`context`]: [`GpuContext`] (adapter choice with the lavapipe CPU fallback, pipeline
//!   cache, buffer upload/download) and its [`GpuConfig`].
//! - [`pyramid`]: [`PyramidKernel`], image pyramid + gradients for LSD-SLAM tracking; CPU twin
//!   in [`crate::image::pyramid`].
//! - [`timer`]: [`PassTimer`], kernel time from timestamp queries.
//! - The dense layer's runners live beside their CPU references in [`crate::dense`].
//!
//! Every runner is tested against its CPU twin on random inputs with a real adapter (lavapipe
//! on machines without a GPU); such tests fail, never skip, when no adapter exists.

pub mod context;
pub mod pyramid;
pub mod timer;

pub use context::{AdapterChoice, GpuConfig, GpuContext};
pub use pyramid::{GpuPyramid, PyramidKernel};
pub use timer::PassTimer;

/// The process-wide GPU context with the default [`GpuConfig`], opened on first use and shared
/// by every session (a wgpu device is thread-safe; one per process keeps the pipeline cache
/// and driver memory single). The error, if opening failed, is returned to every caller.
pub fn shared_context() -> crate::Result<std::sync::Arc<GpuContext>> {
    static SHARED: std::sync::OnceLock<std::result::Result<std::sync::Arc<GpuContext>, String>> =
        std::sync::OnceLock::new();
    SHARED
        .get_or_init(|| {
            GpuContext::new(&GpuConfig::default())
                .map(std::sync::Arc::new)
                .map_err(|e| e.to_string())
        })
        .clone()
        .map_err(crate::Error::Gpu)
}
