//! The OpenAPI description of the HTTP API, generated from the handlers' annotations (utoipa),
//! served at `/openapi.json` and pinned by a snapshot test (`server/tests/openapi.rs`) so that
//! every change of the API is a visible diff.

use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use super::error::{ErrorBody, ErrorDetail};
use super::{Version, downloads, events_sse, frames, sessions, stream_ws, uploads};
use crate::session::{CameraJson, CreateSession, FramePolicy, SessionInfo};
use relfusion_proto::http::{CreatedSession, FrameAccepted, SessionList};

/// The relfusiond HTTP API.
#[derive(Debug, OpenApi)]
#[openapi(
    info(
        title = "relfusiond",
        description = "DeepRelativeFusion dense monocular SLAM as a service. Every /v1 route \
            except /v1/version needs `Authorization: Bearer <token>` when the server has tokens \
            configured (WebSocket and SSE clients may pass `?access_token=` instead); errors are \
            `{\"error\":{\"code\",\"message\"}}`. The WebSocket and Zenoh payloads are the \
            protobuf messages of package relfusion.v1."
    ),
    paths(
        sessions::create_session,
        sessions::list_sessions,
        sessions::get_session,
        sessions::delete_session,
        sessions::finish_session,
        frames::post_frame,
        stream_ws::stream,
        events_sse::events,
        uploads::upload,
        downloads::trajectory,
        downloads::keyframes,
        downloads::pointcloud_ply,
        downloads::mesh_ply,
        downloads::recording_mcap,
        downloads::mesh_glb,
        super::map::map_snapshot,
        super::map::proto_files,
        super::map::proto_file,
        super::maps::save_map,
        super::maps::list_maps,
        super::maps::get_map,
        super::maps::delete_map,
        super::healthz,
        super::readyz,
        super::metrics,
        super::version,
        super::cluster::cluster,
        super::openapi_json,
    ),
    components(schemas(
        CreateSession,
        CameraJson,
        FramePolicy,
        SessionInfo,
        CreatedSession,
        SessionList,
        FrameAccepted,
        ErrorBody,
        ErrorDetail,
        Version,
        super::cluster::ClusterView,
        super::cluster::ClusterNode,
        super::body::Binary,
        super::events_sse::SseEvent,
        super::map::ProtoFiles,
        relfusion_proto::http::MapStart,
        relfusion_proto::http::Ros2Session,
        relfusion_proto::http::MapMode,
        relfusion_proto::http::SaveMap,
        relfusion_proto::http::MapInfo,
        relfusion_proto::http::MapList,
    )),
    modifiers(&BearerAuth),
    tags(
        (name = "sessions", description = "Live and uploaded sessions"),
        (name = "frames", description = "Sending frames over plain HTTP"),
        (name = "streams", description = "WebSocket (protobuf) and server-sent events (JSON)"),
        (name = "uploads", description = "Whole datasets as tar or zip"),
        (name = "results", description = "Trajectory, keyframes, point cloud, mesh"),
        (name = "maps", description = "Saved maps that outlive sessions; sessions localise in them"),
        (name = "service", description = "Health, readiness, metrics, version, this document"),
    )
)]
pub struct ApiDoc;

/// Declares the `bearer` security scheme the protected routes refer to.
#[derive(Debug)]
struct BearerAuth;

impl Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(
                HttpBuilder::new()
                    .scheme(HttpAuthScheme::Bearer)
                    .description(Some(
                        "A token from the server's auth.tokens (only when tokens are configured)",
                    ))
                    .build(),
            ),
        );
    }
}

/// The document as pretty JSON (what `/openapi.json` serves and the snapshot holds).
pub fn spec_json() -> String {
    ApiDoc::openapi()
        .to_pretty_json()
        .unwrap_or_else(|e| format!("{{\"error\":\"openapi: {e}\"}}"))
}
