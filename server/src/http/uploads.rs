//! `POST /v1/uploads`: a whole TUM-layout dataset as one `.tar` or `.zip` stream.
//!
//! Admission comes first: before a byte of the body is read, the upload reserves its place
//! in the upload queue and in its owner's quotas ([`crate::session::admission`]), so that
//! uploads racing for the last place cannot both be written. The body is then streamed to a
//! temporary file inside the data directory (never held in memory, counted against
//! `limits.max_upload_bytes` as it arrives, aborted when no byte arrives for
//! `http.body_timeout_s` or when it falls behind `http.min_upload_kib_per_s` on average after
//! its first `body_timeout_s` — so its whole deadline grows with its size, and a trickle
//! cannot hold an upload place for ever), and handed to the session manager, which extracts it safely,
//! stores it durably and only then returns: the 201 is the promise that the upload survives a
//! crash. Processing follows on the worker pool; progress is in `GET /v1/sessions/{id}`.
//! In a cluster with a shared store, it follows on the node placement chose
//! ([`crate::locator::Locator::store_upload`]).

use std::sync::Arc;

use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, header};
use axum::response::Response;
use futures_util::StreamExt;
use serde::Deserialize;
use tokio::io::AsyncWriteExt;
use utoipa::IntoParams;

use super::auth::Auth;
use super::body::Binary;
use super::error::{ApiQuery, ErrorBody};
use super::sessions::created;
use relfusion_proto::http::CreatedSession;
use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::pipeline::Config as SlamConfig;

use crate::session::admission::UploadTicket;
use crate::session::overrides::upload_config;
use crate::session::types::checked_camera;
use crate::session::{ArchiveKind, NewUpload};
use crate::{ApiError, AppState};

/// Query parameters of an upload. Intrinsics are all-or-nothing; without them the camera comes
/// from the dataset's `calibration.txt`, else from a TUM / 7-Scenes preset recognised by the
/// folder name.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct UploadParams {
    /// `tar` or `zip`; omitted: from the Content-Type, else sniffed from the first bytes.
    pub format: Option<String>,
    pub fx: Option<f64>,
    pub fy: Option<f64>,
    pub cx: Option<f64>,
    pub cy: Option<f64>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Partial pipeline configuration as a JSON object (URL-encoded): only the user settings
    /// anyone may set (README, "Configuration"); any other key is refused by name.
    pub config: Option<String>,
}

impl UploadParams {
    fn camera(&self) -> Result<Option<PinholeCamera>, ApiError> {
        match (self.fx, self.fy, self.cx, self.cy, self.width, self.height) {
            (None, None, None, None, None, None) => Ok(None),
            (Some(fx), Some(fy), Some(cx), Some(cy), Some(width), Some(height)) => {
                checked_camera([fx, fy, cx, cy], width, height, None).map(Some)
            }
            _ => Err(ApiError::bad_request(
                "give all of fx, fy, cx, cy, width, height, or none of them",
            )),
        }
    }

    /// The upload's pipeline configuration: the `config` overrides over the upload defaults.
    fn config(&self) -> Result<SlamConfig, ApiError> {
        let overrides = match &self.config {
            None => serde_json::Value::Null,
            Some(text) => match serde_json::from_str(text) {
                Ok(value @ serde_json::Value::Object(_)) => value,
                Ok(_) => return Err(ApiError::bad_request("config must be a JSON object")),
                Err(e) => return Err(ApiError::bad_request(format!("config is not JSON: {e}"))),
            },
        };
        upload_config(&overrides)
    }
}

/// The archive format a Content-Type names, if any.
fn kind_from_content_type(content_type: &str) -> Option<ArchiveKind> {
    match content_type.to_ascii_lowercase().as_str() {
        "application/x-tar" => Some(ArchiveKind::Tar),
        "application/zip" | "application/x-zip-compressed" => Some(ArchiveKind::Zip),
        _ => None,
    }
}

/// The archive format from its first bytes: zip local header / end record, or the ustar magic.
fn sniff(head: &[u8]) -> Option<ArchiveKind> {
    if head.starts_with(b"PK\x03\x04") || head.starts_with(b"PK\x05\x06") {
        Some(ArchiveKind::Zip)
    } else if head.len() >= 262 && &head[257..262] == b"ustar" {
        Some(ArchiveKind::Tar)
    } else {
        None
    }
}

/// When an upload must have arrived: no gap over `http.body_timeout_s`, and on average at
/// least `http.min_upload_kib_per_s` after a first `body_timeout_s`.
struct UploadDeadline {
    start: std::time::Instant,
    idle: std::time::Duration,
    min_bytes_per_s: f64,
}

impl UploadDeadline {
    fn new(http: &crate::config::HttpLimits) -> Self {
        Self {
            start: std::time::Instant::now(),
            idle: std::time::Duration::from_secs(http.body_timeout_s),
            min_bytes_per_s: http.min_upload_kib_per_s as f64 * 1024.0,
        }
    }

    /// How long the next chunk may take after `received` bytes; 408 when the upload is
    /// already behind its minimum rate.
    fn wait(&self, received: u64) -> Result<std::time::Duration, ApiError> {
        let allowed =
            self.idle + std::time::Duration::from_secs_f64(received as f64 / self.min_bytes_per_s);
        let elapsed = self.start.elapsed();
        if elapsed >= allowed {
            return Err(ApiError::request_timeout(format!(
                "the upload arrived too slowly: {received} bytes in {} s, below \
                 http.min_upload_kib_per_s = {} after the first http.body_timeout_s",
                elapsed.as_secs(),
                self.min_bytes_per_s / 1024.0
            )));
        }
        Ok(self.idle.min(allowed - elapsed))
    }
}

fn too_large(limit: u64) -> ApiError {
    ApiError::payload_too_large(format!(
        "upload larger than limits.max_upload_bytes = {limit} bytes"
    ))
}

fn disk_error(e: std::io::Error) -> ApiError {
    ApiError::internal(format!("storing the upload failed: {e}"))
}

/// Uploads a TUM-layout dataset (`rgb.txt` + `rgb/`, optional `groundtruth.txt` and
/// `calibration.txt`, at the archive root or one folder down) to be processed as a session.
#[utoipa::path(
    post, path = "/v1/uploads", tag = "uploads",
    params(UploadParams),
    request_body(content = Binary, content_type = "application/x-tar",
        description = "The archive (tar or zip), streamed"),
    responses(
        (status = 201, description = "Stored durably; processing is queued", body = CreatedSession),
        (status = 400, description = "Unknown format, truncated or invalid archive, unsafe paths (../, absolute, links), not a TUM layout, no camera", body = ErrorBody),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 408, description = "No byte arrived for http.body_timeout_s, or the upload fell below http.min_upload_kib_per_s on average", body = ErrorBody),
        (status = 413, description = "Larger than limits.max_upload_bytes, more entries than limits.max_upload_entries, or extracting to more than the limits allow", body = ErrorBody),
        (status = 429, description = "The token's quotas (uploads in flight, sessions, bytes stored) are used up", body = ErrorBody),
        (status = 503, description = "The upload queue is full (limits.max_queued_uploads)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn upload(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    ApiQuery(params): ApiQuery<UploadParams>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let limit = state.config.limits.max_upload_bytes;
    // Refuse a declared oversize before reading anything.
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit) {
        return Err(too_large(limit));
    }
    let camera = params.camera()?;
    let config = params.config()?;
    // Reserved before the body is read; given back on every error path (dropped).
    let ticket = state.sessions.reserve_upload(&owner, declared)?;
    let mut kind = match &params.format {
        Some(name) => Some(name.parse::<ArchiveKind>()?),
        None => headers
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| kind_from_content_type(v.split(';').next().unwrap_or_default().trim())),
    };

    let (temp, received, head) = receive(&state, body).await?;
    if received == 0 {
        return Err(ApiError::bad_request(
            "empty upload: send a .tar or .zip of a TUM-layout dataset",
        ));
    }
    if kind.is_none() {
        kind = sniff(&head);
    }
    let kind = kind.ok_or_else(|| {
        ApiError::bad_request(
            "unknown archive format: pass ?format=tar or ?format=zip (or a tar/zip Content-Type)",
        )
    })?;
    let upload = NewUpload {
        archive: temp.path(),
        kind,
        camera,
        config,
    };
    store(&state, ticket, upload, received).await
}

/// The request body, streamed into a temporary file inside the data directory (deleted when
/// dropped) under the size limit and the upload deadlines; the file, its size and its first
/// 512 bytes (to recognise the format).
async fn receive(
    state: &AppState,
    body: Body,
) -> Result<(tempfile::NamedTempFile, u64, Vec<u8>), ApiError> {
    let limit = state.config.limits.max_upload_bytes;
    // The manager's temp folder is inside the data directory and emptied at every start, so
    // a crash mid-upload leaves nothing behind for long.
    let tmp_dir = state.sessions.temp_dir();
    tokio::fs::create_dir_all(tmp_dir)
        .await
        .map_err(disk_error)?;
    // Deleted when dropped: on every error path below, and after the manager has copied it.
    let temp = tempfile::Builder::new()
        .prefix("upload-")
        .suffix(".part")
        .tempfile_in(tmp_dir)
        .map_err(disk_error)?;
    let mut file = tokio::fs::File::from_std(temp.reopen().map_err(disk_error)?);
    let mut head = Vec::with_capacity(512);
    let mut received: u64 = 0;
    let mut chunks = body.into_data_stream();
    let deadline = UploadDeadline::new(&state.config.http);
    loop {
        let wait = deadline.wait(received)?;
        let Ok(next) = tokio::time::timeout(wait, chunks.next()).await else {
            deadline.wait(received)?;
            return Err(ApiError::request_timeout(format!(
                "no byte of the upload arrived for {} s (http.body_timeout_s) after {received} \
                 bytes",
                wait.as_secs()
            )));
        };
        let Some(chunk) = next else {
            break;
        };
        let chunk = chunk.map_err(|e| {
            ApiError::bad_request(format!(
                "the upload was interrupted after {received} bytes: {e}"
            ))
        })?;
        received += chunk.len() as u64;
        if received > limit {
            return Err(too_large(limit));
        }
        if head.len() < 512 {
            let take = (512 - head.len()).min(chunk.len());
            head.extend_from_slice(&chunk[..take]);
        }
        file.write_all(&chunk).await.map_err(disk_error)?;
    }
    file.flush().await.map_err(disk_error)?;
    drop(file);
    Ok((temp, received, head))
}

/// Stores an upload as a session, here or on the node placement chose
/// ([`crate::locator::Locator::store_upload`]).
async fn store(
    state: &AppState,
    ticket: UploadTicket,
    upload: NewUpload<'_>,
    received: u64,
) -> Result<Response, ApiError> {
    let info = state.locator.store_upload(ticket, upload).await?;
    tracing::info!(session = %info.id, bytes = received, node = ?info.node, "upload stored");
    Ok(created(info))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn archives_are_recognised_by_their_magic() {
        assert!(matches!(sniff(b"PK\x03\x04rest"), Some(ArchiveKind::Zip)));
        let mut tar = vec![0u8; 512];
        tar[257..263].copy_from_slice(b"ustar\0");
        assert!(matches!(sniff(&tar), Some(ArchiveKind::Tar)));
        assert!(sniff(b"\x89PNG").is_none());
    }

    #[test]
    fn intrinsics_are_all_or_nothing() {
        let params = |fx: Option<f64>, width: Option<u32>| UploadParams {
            format: None,
            fx,
            fy: fx,
            cx: fx,
            cy: fx,
            width,
            height: width,
            config: None,
        };
        assert!(matches!(params(None, None).camera(), Ok(None)));
        assert!(matches!(
            params(Some(500.0), Some(320)).camera(),
            Ok(Some(_))
        ));
        assert_eq!(
            params(Some(500.0), None)
                .camera()
                .map_err(|e| e.status)
                .err(),
            Some(400)
        );
    }
}
