//! The error of one request: an HTTP status, a stable machine-readable code and a message that
//! says what to fix. The HTTP layer renders it as `{"error":{"code","message"}}`; Zenoh replies
//! carry the same code and message in the protobuf `Error`.

/// A request failed; the server itself is fine.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{code} ({status}): {message}")]
pub struct ApiError {
    /// HTTP status code.
    pub status: u16,
    /// Stable code for programs (`invalid_argument`, `not_found`, ...).
    pub code: &'static str,
    /// For people: what was wrong and what to do.
    pub message: String,
}

impl ApiError {
    /// An error of any status (prefer the named constructors).
    pub fn new(status: u16, code: &'static str, message: impl Into<String>) -> Self {
        Self {
            status,
            code,
            message: message.into(),
        }
    }

    /// 400: malformed input (bad image, bad intrinsics, unknown config key, ...).
    pub fn bad_request(message: impl Into<String>) -> Self {
        Self::new(400, "invalid_argument", message)
    }

    /// 401: no or unknown bearer token.
    pub fn unauthorized(message: impl Into<String>) -> Self {
        Self::new(401, "unauthorized", message)
    }

    /// 403: the token is known but may not do this.
    pub fn forbidden(message: impl Into<String>) -> Self {
        Self::new(403, "forbidden", message)
    }

    /// 404: no such session (or it belongs to another token), no such result.
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(404, "not_found", message)
    }

    /// 408: the request did not arrive in time (`http.body_timeout_s`).
    pub fn request_timeout(message: impl Into<String>) -> Self {
        Self::new(408, "request_timeout", message)
    }

    /// 410: the session existed but its data expired (`retention.finished_ttl_s`).
    pub fn gone(message: impl Into<String>) -> Self {
        Self::new(410, "gone", message)
    }

    /// 429: the caller's quota (`[quotas]`) is used up; others are not affected.
    pub fn quota(message: impl Into<String>) -> Self {
        Self::new(429, "quota_exceeded", message)
    }

    /// 409: the request does not fit the resource's state (frames after end of stream, ...).
    pub fn conflict(message: impl Into<String>) -> Self {
        Self::new(409, "conflict", message)
    }

    /// 413: a body over the configured limit.
    pub fn payload_too_large(message: impl Into<String>) -> Self {
        Self::new(413, "payload_too_large", message)
    }

    /// 415: a body in a format the endpoint does not take.
    pub fn unsupported_media(message: impl Into<String>) -> Self {
        Self::new(415, "unsupported_media_type", message)
    }

    /// 503: at capacity (sessions, queues) or shutting down; retry later.
    pub fn unavailable(message: impl Into<String>) -> Self {
        Self::new(503, "resource_exhausted", message)
    }

    /// 500: the server failed; the message says where.
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(500, "internal", message)
    }

    /// The protobuf error code for the same failure (Zenoh replies, WebSocket errors).
    /// The stable code `code` names (an error that crossed the cluster as text); unknown
    /// codes read as `internal`.
    pub fn known_code(code: &str) -> &'static str {
        const CODES: [&str; 13] = [
            "conflict",
            "forbidden",
            "gone",
            "internal",
            "invalid_argument",
            "not_found",
            "payload_too_large",
            "quota_exceeded",
            "request_timeout",
            "resource_exhausted",
            "unauthorized",
            "unsupported_media_type",
            "unavailable",
        ];
        CODES.into_iter().find(|c| *c == code).unwrap_or("internal")
    }

    pub fn proto_code(&self) -> relfusion_proto::v1::ErrorCode {
        use relfusion_proto::v1::ErrorCode;
        match self.status {
            401 => ErrorCode::Unauthenticated,
            404 | 410 => ErrorCode::NotFound,
            429 | 503 => ErrorCode::ResourceExhausted,
            500..=599 => ErrorCode::Internal,
            _ => ErrorCode::InvalidArgument,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_map_to_statuses_and_proto() {
        assert_eq!(ApiError::bad_request("x").status, 400);
        assert_eq!(ApiError::unavailable("x").code, "resource_exhausted");
        assert_eq!(
            ApiError::not_found("x").proto_code(),
            relfusion_proto::v1::ErrorCode::NotFound
        );
        assert_eq!(
            ApiError::unauthorized("x").proto_code(),
            relfusion_proto::v1::ErrorCode::Unauthenticated
        );
        assert_eq!(
            ApiError::payload_too_large("x").proto_code(),
            relfusion_proto::v1::ErrorCode::InvalidArgument
        );
    }
}
