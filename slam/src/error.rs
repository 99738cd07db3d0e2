//! The one error type of `relfusion-slam`.

use std::path::PathBuf;

/// Every failure the pipeline library can report. Each variant says what the user can fix.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An image file could not be decoded or encoded.
    #[error("image {path}: {source}")]
    Image {
        path: PathBuf,
        #[source]
        source: ::image::ImageError,
    },
    /// A dataset folder or file is malformed (missing file, bad line, no associations, ...).
    #[error("dataset: {0}")]
    Dataset(String),
    /// Camera intrinsics are invalid (non-positive focal length, NaN, zero size, ...).
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    /// An input has the wrong size or shape for the operation.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// An evaluation could not be computed (e.g. too few matched poses).
    #[error("evaluation: {0}")]
    Eval(String),
    /// No usable GPU adapter, or a GPU operation failed.
    #[error("gpu: {0}")]
    Gpu(String),
    /// The depth-prior runtime or model failed (missing runtime library, model file, shapes).
    #[error("depth prior: {0}")]
    Prior(String),
    /// A keyframe could not be spilled to, or read back from, the session's store.
    #[error("spill: {0}")]
    Spill(String),
    /// A configuration value is invalid.
    #[error("config: {0}")]
    Config(String),
    /// The SLAM back end was misused (unknown keyframe id, duplicate keyframe) or its thread
    /// has stopped.
    #[error("back end: {0}")]
    Backend(String),
    /// A keyframe has no pixel certain and near enough to integrate (`fusion` limits): it is
    /// left out of the mesh, which goes on without it.
    #[error("keyframe {0} has no depth to fuse")]
    NothingToFuse(usize),
    /// A saved map cannot be used: another format version, another camera, a missing or
    /// inconsistent part.
    #[error("map: {0}")]
    Map(String),
}

/// Shorthand used throughout the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// Wraps an I/O error with the path it concerns.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
}

/// The shared types' errors keep their variant: a bad camera stays `InvalidCamera`, a bad
/// dataset `Dataset`.
impl From<relfusion_core::Error> for Error {
    fn from(e: relfusion_core::Error) -> Self {
        use relfusion_core::Error as E;
        match e {
            E::Io { path, source } => Error::Io { path, source },
            E::Image { path, source } => Error::Image { path, source },
            E::Dataset(m) => Error::Dataset(m),
            E::InvalidCamera(m) => Error::InvalidCamera(m),
            E::Shape(m) => Error::Shape(m),
        }
    }
}
