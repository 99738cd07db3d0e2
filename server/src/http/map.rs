//! Joining a session mid-way and the wire schema (issue 23, items 2 and 3).
//!
//! - `GET /v1/sessions/{id}/map`: the session's current `MapSnapshot` (the same message the
//!   Zenoh queryable answers), protobuf by default, JSON with `Accept: application/json`. A
//!   client that connects late takes it, then applies the `MeshUpdate`s whose revision is
//!   above the snapshot's `mesh_revision`: no gap, no duplicate.
//! - `GET /v1/proto` and `GET /v1/proto/{path}`: the `.proto` sources the binary was built from
//!   ([`relfusion_proto::PROTO_FILES`]), so other languages can generate clients. Public, like
//!   `/openapi.json`.

use std::sync::Arc;

use axum::Json;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, header};
use axum::response::{IntoResponse, Response};
use relfusion_proto::v1::{MapSnapshot, MeshBlock, StampedPose};
use serde::Serialize;
use serde_json::{Value, json};

use super::auth::Auth;
use super::body::Binary;
use super::error::ErrorBody;
use crate::{ApiError, AppState};

const PROTOBUF: &str = "application/x-protobuf";

/// The `.proto` files this server speaks.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct ProtoFiles {
    /// Paths relative to the proto root, in dependency order; each is served at
    /// `/v1/proto/{path}`.
    #[schema(example = json!(["relfusion/v1/geometry.proto"]))]
    pub files: Vec<&'static str>,
}

/// The wire schema's files (no token needed).
#[utoipa::path(get, path = "/v1/proto", tag = "service",
    responses((status = 200, description = "The .proto files", body = ProtoFiles)))]
pub async fn proto_files() -> Json<ProtoFiles> {
    Json(ProtoFiles {
        files: relfusion_proto::PROTO_FILES
            .iter()
            .map(|(p, _)| *p)
            .collect(),
    })
}

/// One `.proto` source (no token needed).
#[utoipa::path(get, path = "/v1/proto/{path}", tag = "service",
    params(("path" = String, Path, description = "A path listed by /v1/proto")),
    responses(
        (status = 200, description = "The .proto source", body = String, content_type = "text/plain"),
        (status = 404, description = "Not one of the listed files", body = ErrorBody),
    ))]
pub async fn proto_file(Path(path): Path<String>) -> Result<Response, ApiError> {
    let (_, text) = relfusion_proto::PROTO_FILES
        .iter()
        .find(|(p, _)| *p == path)
        .ok_or_else(|| {
            ApiError::not_found(format!("no proto file {path:?}; GET /v1/proto lists them"))
        })?;
    Ok(([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], *text).into_response())
}

/// The session's whole current map: trajectory, keyframes and every mesh block, with the mesh
/// revision it is at.
#[utoipa::path(
    get, path = "/v1/sessions/{id}/map", tag = "results",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "relfusion.v1.MapSnapshot (protobuf); JSON with Accept: application/json (geometry as number arrays)", body = Binary, content_type = "application/x-protobuf"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn map_snapshot(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    let wants_json = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.contains("application/json"));
    let built = |e| ApiError::internal(format!("building the map failed: {e}"));
    Ok(if wants_json {
        let snapshot =
            tokio::task::spawn_blocking(move || crate::session::snapshot::snapshot(&session))
                .await
                .map_err(built)??;
        Json(snapshot_json(&snapshot)).into_response()
    } else {
        let bytes =
            tokio::task::spawn_blocking(move || crate::session::snapshot::snapshot_bytes(&session))
                .await
                .map_err(built)??;
        ([(header::CONTENT_TYPE, PROTOBUF)], bytes).into_response()
    })
}

fn pose_json(pose: &StampedPose) -> Value {
    let p = pose.world_from_camera.unwrap_or_default();
    let t = p.translation.unwrap_or_default();
    let q = p.rotation.unwrap_or_default();
    json!({
        "timestamp": pose.timestamp,
        "t": [t.x, t.y, t.z],
        "q": [q.x, q.y, q.z, q.w],
        "scale": p.scale,
    })
}

/// Packed little-endian `float32`s as numbers.
fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

fn block_json(block: &MeshBlock) -> Value {
    let index = block.index.unwrap_or_default();
    json!({
        "index": [index.x, index.y, index.z],
        "vertices": floats(&block.vertices),
        "colors": block.colors,
        "normals": floats(&block.normals),
        "indices": block.indices,
    })
}

/// The snapshot as JSON: the message's fields by their proto names, poses as `t`/`q`/`scale`
/// (as the SSE events), packed geometry as plain number arrays.
pub fn snapshot_json(s: &MapSnapshot) -> Value {
    json!({
        "session_id": s.session_id,
        "state": s.state,
        "frames_processed": s.frames_processed,
        "frames_received": s.frames_received,
        "frames_dropped": s.frames_dropped,
        "mesh_revision": s.mesh_revision,
        "block_size": s.block_size,
        "trajectory": s.trajectory.iter().map(pose_json).collect::<Vec<_>>(),
        "keyframes": s.keyframes.iter().map(pose_json).collect::<Vec<_>>(),
        "mesh_blocks": s.mesh_blocks.iter().map(block_json).collect::<Vec<_>>(),
    })
}
