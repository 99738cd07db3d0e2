//! The one error type of the server library.

/// Failures of the service itself (not of a request: those become HTTP errors).
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("config {path}: {message}")]
    Config { path: String, message: String },
    #[error("serving HTTP: {0}")]
    Serve(#[source] std::io::Error),
    #[error("data directory: {0}")]
    Store(#[from] crate::storage::StoreError),
    #[error("depth model {path}: {message}")]
    Model { path: String, message: String },
    #[error("starting the service: {0}")]
    Startup(String),
}
