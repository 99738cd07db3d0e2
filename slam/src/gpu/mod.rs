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

pub use context::{AdapterChoice, GpuConfig, GpuContext, gpu_adapter_count};
pub use pyramid::{GpuPyramid, PyramidKernel};
pub use timer::PassTimer;

/// The process-wide GPU context on the first preferred adapter ([`context_for`]`(0)`): what a
/// single-session process (the CLI) uses.
pub fn shared_context() -> crate::Result<std::sync::Arc<GpuContext>> {
    context_for(0)
}

/// The process-wide context of the `index`-th preferred adapter (see
/// [`GpuContext::on_adapter`]) with the default [`GpuConfig`], opened on first use and shared
/// by every session placed on that adapter (a wgpu device is thread-safe; one per adapter
/// keeps the pipeline cache and driver memory single). The error, if opening failed, is
/// returned to every caller.
pub fn context_for(index: usize) -> crate::Result<std::sync::Arc<GpuContext>> {
    type Opened = std::result::Result<std::sync::Arc<GpuContext>, String>;
    static CONTEXTS: std::sync::Mutex<Vec<(usize, Opened)>> = std::sync::Mutex::new(Vec::new());
    let mut contexts = CONTEXTS.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, opened)) = contexts.iter().find(|(i, _)| *i == index) {
        return opened.clone().map_err(crate::Error::Gpu);
    }
    let opened = GpuContext::on_adapter(&GpuConfig::default(), index)
        .map(std::sync::Arc::new)
        .map_err(|e| e.to_string());
    contexts.push((index, opened.clone()));
    opened.map_err(crate::Error::Gpu)
}
