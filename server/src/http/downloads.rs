//! Results of a session: trajectory and keyframes (TUM text), point cloud and mesh files.
//! They are the current state while a session runs and the final one once it has finished
//! (finished sessions are read back from the store, so they survive restarts).

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};

use super::auth::Auth;
use super::body::Binary;
use super::error::ErrorBody;
use crate::session::Session;
use crate::session::outputs::Stored;
use crate::{ApiError, AppState};
use relfusion_proto::http::SessionInfo;

const TEXT: &str = "text/plain; charset=utf-8";
const BINARY: &str = "application/octet-stream";
const GLB: &str = "model/gltf-binary";
const MCAP: &str = "application/x-mcap";

/// Bytes per read of a streamed download.
const CHUNK: usize = 1 << 20;

/// Runs `produce` on a blocking thread: results may be read from disk or be large to build.
async fn produce<T: Send + 'static>(
    session: Arc<Session>,
    produce: impl FnOnce(&Session) -> T + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(move || produce(&session))
        .await
        .map_err(|e| ApiError::internal(format!("building the result failed: {e}")))
}

fn file(content_type: &'static str, name: String, body: impl IntoResponse) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type.to_string()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{name}\""),
            ),
        ],
        body,
    )
        .into_response()
}

/// The 404 of a session without a mesh, saying why from its figures.
fn no_mesh(id: &str, info: &SessionInfo) -> ApiError {
    let why = if info.dense_mode == "off" {
        "its dense layer is off (pipeline.dense.enabled = false), so it fuses nothing".to_string()
    } else {
        let source = if info.dense_mode == "no_model" {
            "without a depth model, from the semi-dense keyframe depth"
        } else {
            "with the depth model"
        };
        format!(
            "nothing fused yet: {} keyframes, {} of them densified ({source}); the mesh \
             appears once a densified keyframe is fused",
            info.keyframes, info.keyframes_densified
        )
    };
    ApiError::not_found(format!(
        "no mesh: session {id}: {why}; the trajectory, keyframes and point cloud are available"
    ))
}

/// Camera trajectory, one TUM line per tracked frame: `timestamp tx ty tz qx qy qz qw`.
#[utoipa::path(
    get, path = "/v1/sessions/{id}/trajectory", tag = "results",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "TUM trajectory (world_from_camera)", body = String, content_type = "text/plain"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn trajectory(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    let text = produce(session, Session::trajectory_tum)
        .await?
        .map_err(ApiError::internal)?;
    Ok(file(TEXT, format!("{id}-trajectory.txt"), text))
}

/// Keyframe poses after pose-graph optimisation, TUM lines.
#[utoipa::path(
    get, path = "/v1/sessions/{id}/keyframes", tag = "results",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "TUM keyframe trajectory", body = String, content_type = "text/plain"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn keyframes(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    let text = produce(session, Session::keyframes_tum).await?;
    Ok(file(TEXT, format!("{id}-keyframes.txt"), text))
}

/// Semi-dense point cloud of the keyframes' depth maps (binary PLY).
#[utoipa::path(
    get, path = "/v1/sessions/{id}/pointcloud.ply", tag = "results",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "PLY point cloud", body = Binary, content_type = "application/octet-stream"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn pointcloud_ply(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    let bytes = produce(session, Session::pointcloud_ply).await?;
    Ok(file(BINARY, format!("{id}-pointcloud.ply"), bytes))
}

/// The fused surface as PLY (404 until the session has a mesh).
#[utoipa::path(
    get, path = "/v1/sessions/{id}/mesh.ply", tag = "results",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "PLY mesh", body = Binary, content_type = "application/octet-stream"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session, or no mesh yet", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn mesh_ply(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    let bytes = produce(session.clone(), Session::mesh_ply)
        .await?
        .ok_or_else(|| no_mesh(&id, &session.info()))?;
    Ok(file(BINARY, format!("{id}-mesh.ply"), bytes))
}

/// The fused surface as binary glTF (404 until the session has a mesh).
#[utoipa::path(
    get, path = "/v1/sessions/{id}/mesh.glb", tag = "results",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "glTF binary mesh", body = Binary, content_type = "model/gltf-binary"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session, or no mesh yet", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn mesh_glb(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    let bytes = produce(session.clone(), Session::mesh_glb)
        .await?
        .ok_or_else(|| no_mesh(&id, &session.info()))?;
    Ok(file(GLB, format!("{id}-mesh.glb"), bytes))
}

/// The session's recording as MCAP with the Foxglove schemas (issue 38): every tracked pose and
/// its transform, the keyframes' trajectory and dense points, the mesh block by block, as
/// `relfusion stream --mcap` records them (without the camera images, which the service does not
/// keep). Stored when the session ends; at most `limits.max_recording_mb`.
#[utoipa::path(
    get, path = "/v1/sessions/{id}/recording.mcap", tag = "results",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "MCAP recording", body = Binary, content_type = "application/x-mcap"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session, the session still runs, or it has no recording (limits.max_recording_mb = 0)", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn recording_mcap(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    let stored = produce(session.clone(), Session::recording)
        .await?
        .map_err(|e| ApiError::internal(format!("reading the recording: {e}")))?;
    let name = format!("{id}-recording.mcap");
    match stored {
        Some(Stored::Bytes(bytes)) => Ok(file(MCAP, name, bytes)),
        Some(Stored::File(path)) => {
            let f = tokio::fs::File::open(&path)
                .await
                .map_err(|e| ApiError::internal(format!("opening the recording: {e}")))?;
            let chunks = futures_util::stream::unfold(f, |mut f| async move {
                use tokio::io::AsyncReadExt as _;
                let mut buf = vec![0u8; CHUNK];
                match f.read(&mut buf).await {
                    Ok(0) => None,
                    Ok(n) => {
                        buf.truncate(n);
                        Some((Ok::<_, std::io::Error>(bytes::Bytes::from(buf)), f))
                    }
                    Err(e) => Some((Err(e), f)),
                }
            });
            Ok(file(MCAP, name, axum::body::Body::from_stream(chunks)))
        }
        None if session.state().is_terminal() => Err(ApiError::not_found(format!(
            "no recording: session {id} was not recorded (limits.max_recording_mb = 0 when it \
             ran, or it failed before its results were stored)"
        ))),
        None => Err(ApiError::not_found(format!(
            "no recording yet: session {id} is {:?}; its recording is stored when it ends",
            session.state()
        ))),
    }
}
