//! The one error type of the server library.

/// Failures of the service itself (not of a request: those become HTTP errors).
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("config {path}: {message}")]
    Config { path: String, message: String },
    #[error("serving HTTP: {0}")]
    Serve(#[source] std::io::Error),
}
