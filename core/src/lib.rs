//! relfusion-core: the types every relfusion crate shares, with no GPU and no network, so that
//! the client SDK can use them without building the pipeline.
//!
//! - [`error`]: the crate's `Error` and `Result`.
//! - [`geometry`]: Lie groups (`SO3`, `SE3`, `Sim3`) and the pinhole camera with distortion.
//! - [`image`]: grayscale float images.
//! - [`dataset`]: the TUM RGB-D folder layout (reader, calibration, trajectory files).

pub mod dataset;
pub mod error;
pub mod geometry;
pub mod image;

pub use error::{Error, Result};
