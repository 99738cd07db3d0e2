//! The dense layer of DeepRelativeFusion (§III-B..E): the CNN depth prior and its scale/shift
//! correction onto the semi-dense map, the adaptive filter, densification and the two-view
//! consistency that refines the pose graph.
//!
//! - [`prior`]: the [`DepthPrior`] trait and its ONNX Runtime implementation
//!   ([`OnnxDepthPrior`]), which turns a keyframe's RGB image into a relative inverse-depth
//!   map `D_CNN` (§III-B).
//! - [`model_config`]: how a model is fed and read ([`ModelConfig`]), and the table of models
//!   recognised without a config.
//! - [`align`]: eq. (2)–(3), the closed-form scale and shift that map `D_CNN` onto a target
//!   inverse depth (semi-dense map or ground truth).
//! - [`config`]: every parameter, the paper's values as defaults.
//! - [`resample`]: keyframe image, semi-dense map and prior at the working resolution.
//! - [`filter`] / [`gpu_filter`]: the adaptive filter (eqs. 4–9), CPU reference and kernel.
//! - [`densify`] / [`gpu_densify`]: the energy (eqs. 10–13), its analytic gradient and Adam,
//!   CPU reference and kernel.
//! - [`two_view`] / [`gpu_warp`]: two-view consistency and pose-uncertainty propagation
//!   (eqs. 14–16).
//! - [`support`]: the variance a densified pixel gains with its distance to the semi-dense
//!   depth that supports it.
//! - [`layer`]: the per-keyframe orchestration and its worker thread.
//! - [`store`]: the on-disk layout of densified keyframes (`OUT/keyframes/`).

pub mod config;
pub mod densify;
pub mod filter;
pub mod gpu_densify;
pub mod gpu_filter;
pub mod gpu_warp;
pub mod keyframe;
pub mod layer;
pub mod model_config;
pub mod prior;
pub mod resample;
pub mod store;
pub mod support;
pub mod two_view;

pub use crate::scale_shift::{
    ScaleShift, aligned_depth, fit_scale_shift, fit_scale_shift_robust,
    fit_scale_shift_unconstrained, inverse_depth_target,
};
pub use config::{
    AlignParams, DenseCompute, DenseConfig, DensifyParams, EnergyTerms, FilterParams, TwoViewParams,
};
pub use keyframe::{DenseKeyframe, DenseMode, DenseStages, DenseTimings};
pub use model_config::{Layout, ModelConfig, OutputKind, Recognition, ResizeMode};
pub use prior::{
    DepthPrior, InverseDepth, LoadOptions, OnnxDepthPrior, init_runtime, runtime_library_path,
};
