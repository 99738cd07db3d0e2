//! The one error type of `relfusion-core`.

use std::path::PathBuf;

/// What reading a camera, an image or a dataset can fail with. Each variant says what the user
/// can fix; `relfusion-slam`'s error has the same variants and converts from this one.
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
