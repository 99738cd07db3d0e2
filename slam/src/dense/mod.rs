//! The dense layer of DeepRelativeFusion (§III-B..D): the CNN depth prior and its scale/shift
//! correction onto the semi-dense map.
//!
//! - [`prior`]: the [`DepthPrior`] trait and its ONNX Runtime implementation
//!   ([`OnnxDepthPrior`]), which turns a keyframe's RGB image into a relative inverse-depth
//!   map `D_CNN` (§III-B).
//! - [`model_config`]: how a model is fed and read ([`ModelConfig`]), and the table of models
//!   recognised without a config.
//! - [`align`]: eq. (2)–(3), the closed-form scale and shift that map `D_CNN` onto a target
//!   inverse depth (semi-dense map or ground truth).

pub mod align;
pub mod model_config;
pub mod prior;

pub use align::{
    ScaleShift, aligned_depth, fit_scale_shift, fit_scale_shift_unconstrained, inverse_depth_target,
};
pub use model_config::{Layout, ModelConfig, OutputKind, Recognition, ResizeMode};
pub use prior::{DepthPrior, InverseDepth, OnnxDepthPrior, init_runtime, runtime_library_path};
