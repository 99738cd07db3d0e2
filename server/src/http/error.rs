//! Every failure of the HTTP API leaves as the same JSON shape, `{"error":{"code","message"}}`,
//! including the ones axum's own extractors detect (bad JSON, bad query, body too large), so a
//! client needs exactly one error parser.

use axum::extract::rejection::{BytesRejection, JsonRejection, QueryRejection};
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::request::Parts;
use axum::http::{StatusCode, Uri};
use axum::response::{IntoResponse, Response};

use serde::de::DeserializeOwned;

use crate::ApiError;

pub use relfusion_proto::http::{ErrorBody, ErrorDetail};

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = StatusCode::from_u16(self.status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
        if status == StatusCode::INTERNAL_SERVER_ERROR {
            tracing::error!(code = self.code, "request failed: {}", self.message);
        } else if status.is_server_error() {
            // At capacity or shutting down: expected under load, not a fault.
            tracing::warn!(code = self.code, "request refused: {}", self.message);
        } else {
            tracing::debug!(
                code = self.code,
                status = self.status,
                "request refused: {}",
                self.message
            );
        }
        let body = ErrorBody {
            error: ErrorDetail {
                code: self.code.to_string(),
                message: self.message,
            },
        };
        (status, axum::Json(body)).into_response()
    }
}

/// Maps one of axum's extractor rejections onto our error codes. axum reports undecodable JSON
/// as 422; the API promises 400 for every malformed argument, so 422 becomes 400.
fn from_rejection(status: StatusCode, text: String) -> ApiError {
    match status {
        StatusCode::PAYLOAD_TOO_LARGE => ApiError::payload_too_large(text),
        StatusCode::UNSUPPORTED_MEDIA_TYPE => ApiError::unsupported_media(text),
        s if s.is_server_error() => ApiError::internal(text),
        _ => ApiError::bad_request(text),
    }
}

impl From<JsonRejection> for ApiError {
    fn from(rejection: JsonRejection) -> Self {
        from_rejection(rejection.status(), rejection.body_text())
    }
}

impl From<QueryRejection> for ApiError {
    fn from(rejection: QueryRejection) -> Self {
        from_rejection(rejection.status(), rejection.body_text())
    }
}

impl From<BytesRejection> for ApiError {
    fn from(rejection: BytesRejection) -> Self {
        from_rejection(rejection.status(), rejection.body_text())
    }
}

/// `axum::Json` whose rejections are [`ApiError`]s.
#[derive(Debug)]
pub struct ApiJson<T>(pub T);

impl<T, S> FromRequest<S> for ApiJson<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let axum::Json(value) = axum::Json::<T>::from_request(req, state).await?;
        Ok(Self(value))
    }
}

/// `axum::extract::Query` whose rejections are [`ApiError`]s.
#[derive(Debug)]
pub struct ApiQuery<T>(pub T);

impl<T, S> FromRequestParts<S> for ApiQuery<T>
where
    T: DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        let axum::extract::Query(value) =
            axum::extract::Query::<T>::from_request_parts(parts, state).await?;
        Ok(Self(value))
    }
}

/// Unknown paths answer in the API's error shape too.
pub async fn no_route(uri: Uri) -> ApiError {
    ApiError::not_found(format!(
        "no route {}; the API is described at /openapi.json",
        uri.path()
    ))
}

/// A known path with a method it does not serve.
pub async fn wrong_method(uri: Uri) -> ApiError {
    ApiError {
        status: 405,
        code: "invalid_argument",
        message: format!(
            "{} does not take this method; see /openapi.json",
            uri.path()
        ),
    }
}
