//! What can go wrong talking to `relfusiond`, as one error type.
//!
//! The server answers every failed request with `{"error":{"code","message"}}`; that body is
//! parsed into [`ClientError::Api`] so callers can branch on the stable `code` (and the HTTP
//! status) instead of on message text. Everything else (connection, WebSocket, local files,
//! the dataset) keeps its own variant with the underlying error as its source.

use std::path::PathBuf;

/// A failed client operation.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server refused the request (any non-2xx answer).
    #[error("server answered {status} {code}: {message}")]
    Api {
        /// HTTP status (400, 401, 404, 409, 413, 503, ...).
        status: u16,
        /// The server's stable error code (`invalid_argument`, `not_found`, ...), or
        /// `http_<status>` when the body was not the server's JSON error.
        code: String,
        /// Human-readable reason, as the server wrote it.
        message: String,
    },
    /// The server URL given to [`crate::Client::new`] is unusable.
    #[error("invalid server URL `{url}`: {reason}")]
    Url { url: String, reason: String },
    /// Connecting, sending or receiving over HTTP failed. (Messages do not repeat their
    /// source: error reporters such as anyhow print the chain.)
    #[error("HTTP request failed")]
    Http(#[from] reqwest::Error),
    /// The WebSocket stream failed.
    #[error("WebSocket stream failed")]
    WebSocket(#[from] Box<tokio_tungstenite::tungstenite::Error>),
    /// A local file could not be read or written.
    #[error("{}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The local dataset is unusable (missing rgb.txt, unreadable calibration, ...).
    #[error(transparent)]
    Dataset(#[from] relfusion_core::Error),
    /// The server said something this client does not understand (bad protobuf, unexpected
    /// JSON shape, a stream that ended early).
    #[error("protocol: {0}")]
    Protocol(String),
    /// A transport other than HTTP (Zenoh) failed or is unavailable.
    #[error("transport: {0}")]
    Transport(String),
    /// The caller's options are inconsistent (e.g. a non-positive frame rate).
    #[error("invalid option: {0}")]
    InvalidOption(String),
}

impl ClientError {
    /// HTTP status of an [`ClientError::Api`] error.
    pub fn status(&self) -> Option<u16> {
        match self {
            Self::Api { status, .. } => Some(*status),
            _ => None,
        }
    }

    /// The server's error code of an [`ClientError::Api`] error.
    pub fn code(&self) -> Option<&str> {
        match self {
            Self::Api { code, .. } => Some(code),
            _ => None,
        }
    }

    /// The message with its whole chain of causes, `: `-separated (for one-line reports).
    pub fn report(&self) -> String {
        let mut out = self.to_string();
        let mut source = std::error::Error::source(self);
        while let Some(e) = source {
            out.push_str(": ");
            out.push_str(&e.to_string());
            source = e.source();
        }
        out
    }

    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            source,
        }
    }

    /// The error of a non-2xx answer with body `body`: the server's JSON error when the body
    /// is one, else the body text itself (a proxy's HTML page, say), shortened.
    pub fn from_response(status: u16, body: &[u8]) -> Self {
        match serde_json::from_slice::<relfusion_proto::http::ErrorBody>(body) {
            Ok(e) => Self::Api {
                status,
                code: e.error.code,
                message: e.error.message,
            },
            Err(_) => {
                let text = String::from_utf8_lossy(body);
                let text = text.trim();
                const MAX: usize = 300;
                let message = match text.char_indices().nth(MAX) {
                    Some((cut, _)) => format!("{}…", &text[..cut]),
                    None => text.to_string(),
                };
                Self::Api {
                    status,
                    code: format!("http_{status}"),
                    message,
                }
            }
        }
    }
}

impl From<tokio_tungstenite::tungstenite::Error> for ClientError {
    fn from(e: tokio_tungstenite::tungstenite::Error) -> Self {
        Self::WebSocket(Box::new(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_servers_json_error() {
        let body = br#"{"error":{"code":"invalid_argument","message":"fx must be > 0"}}"#;
        let e = ClientError::from_response(400, body);
        assert_eq!(e.status(), Some(400));
        assert_eq!(e.code(), Some("invalid_argument"));
        assert_eq!(
            e.to_string(),
            "server answered 400 invalid_argument: fx must be > 0"
        );
    }

    #[test]
    fn keeps_a_non_json_body_as_the_message() {
        let e = ClientError::from_response(502, b"<html>Bad Gateway</html>");
        assert_eq!(e.code(), Some("http_502"));
        assert!(e.to_string().contains("Bad Gateway"), "{e}");
        let long = vec![b'x'; 5000];
        let e = ClientError::from_response(500, &long);
        assert!(e.to_string().len() < 400, "long bodies are shortened");
    }

    #[test]
    fn reports_carry_the_cause_chain() {
        let e = ClientError::io(
            "/x/y.png",
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        );
        assert_eq!(e.report(), "/x/y.png: no such file");
    }
}
