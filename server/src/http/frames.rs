//! `POST /v1/sessions/{id}/frames`: one encoded image per request, for clients that cannot
//! hold a WebSocket open (scripts, curl). The image is decoded and checked against the session
//! camera before the 202, so a bad frame is refused here and never reaches the pipeline.

use relfusion_proto::http::FrameAccepted;
use std::sync::Arc;

use axum::Json;
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use serde::Deserialize;
use utoipa::IntoParams;

use super::auth::Auth;
use super::body::Binary;
use super::error::{ApiQuery, ErrorBody};
use crate::session::FrameData;
use crate::{ApiError, AppState};

/// Query parameters of a frame upload.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct FrameParams {
    /// Capture time in seconds (any epoch; e.g. the TUM stamp). Written to the trajectory.
    pub timestamp: f64,
    /// Client frame id, strictly increasing within the session; omitted: the server numbers
    /// frames 0, 1, 2, ...
    pub frame_id: Option<u64>,
}

/// Content types a frame may be sent as (the format itself is sniffed from the bytes).
const IMAGE_TYPES: [&str; 3] = ["image/jpeg", "image/png", "application/octet-stream"];

/// Sends one JPEG or PNG frame to a live session.
#[utoipa::path(
    post, path = "/v1/sessions/{id}/frames", tag = "frames",
    params(("id" = String, Path, description = "Session id"), FrameParams),
    request_body(content = Binary, content_type = "image/jpeg",
        description = "One JPEG or PNG image of the session camera's size (image/png and application/octet-stream are accepted too)"),
    responses(
        (status = 202, description = "Queued for the pipeline", body = FrameAccepted),
        (status = 400, description = "Corrupt image, size not matching the camera, bad timestamp or frame id", body = ErrorBody),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
        (status = 409, description = "The session's stream has ended", body = ErrorBody),
        (status = 408, description = "The image did not arrive within http.body_timeout_s", body = ErrorBody),
        (status = 413, description = "Larger than limits.max_frame_bytes", body = ErrorBody),
        (status = 415, description = "Not an image content type", body = ErrorBody),
        (status = 429, description = "This token has its share of the request-body budget in flight (quotas.max_buffered_body_mb); retry", body = ErrorBody),
        (status = 503, description = "Too many request bodies arriving at once (limits.max_buffered_body_mb); retry", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn post_frame(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
    ApiQuery(params): ApiQuery<FrameParams>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<(StatusCode, Json<FrameAccepted>), ApiError> {
    // The session first: an unknown or foreign session is a 404 whatever the body holds.
    let session = state.sessions.get(&id, &owner)?;
    if let Some(content_type) = headers.get(header::CONTENT_TYPE) {
        let essence = content_type
            .to_str()
            .unwrap_or_default()
            .split(';')
            .next()
            .unwrap_or_default()
            .trim()
            .to_ascii_lowercase();
        if !IMAGE_TYPES.contains(&essence.as_str()) {
            return Err(ApiError::unsupported_media(format!(
                "a frame is one JPEG or PNG image sent as {}; got Content-Type {essence:?}",
                IMAGE_TYPES.join(", ")
            )));
        }
    }
    let bytes = body.map_err(|rejection| {
        let error = ApiError::from(rejection);
        if error.status == 413 {
            ApiError::payload_too_large(format!(
                "frame larger than limits.max_frame_bytes = {} bytes",
                state.config.limits.max_frame_bytes
            ))
        } else {
            error
        }
    })?;
    if !params.timestamp.is_finite() {
        return Err(ApiError::bad_request(format!(
            "timestamp must be a finite number of seconds, got {}",
            params.timestamp
        )));
    }
    if bytes.is_empty() {
        return Err(ApiError::bad_request(
            "empty body: send one JPEG or PNG image",
        ));
    }
    let frame_index = session
        .push_frame(FrameData {
            frame_id: params.frame_id,
            timestamp: params.timestamp,
            bytes,
        })
        .await?;
    Ok((StatusCode::ACCEPTED, Json(FrameAccepted { frame_index })))
}
