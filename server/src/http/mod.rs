//! The HTTP API (axum), versioned under `/v1`.
//!
//! One module per concern: [`sessions`] (lifecycle), [`frames`] (one image per request),
//! [`stream_ws`] (protobuf WebSocket), [`events_sse`] (JSON server-sent events), [`uploads`]
//! (whole datasets), [`downloads`] (results), [`map`] (snapshot, wire schema), [`maps`] (saved
//! maps), [`auth`]
//! (bearer tokens), [`error`] (the one error shape), [`openapi`] (the description served at
//! `/openapi.json`), [`docs`] (its page) and [`viewer`] (the live map viewer). Handlers only
//! translate between HTTP and the session manager; no SLAM logic lives here.

pub mod auth;
pub mod body;
pub mod cluster;
pub mod docs;
pub mod downloads;
pub mod error;
pub mod events_sse;
pub mod frames;
pub mod map;
pub mod maps;
pub mod openapi;
pub mod routing;
pub mod security;
pub mod serve;
pub mod sessions;
pub mod stream_remote;
pub mod stream_ws;
pub mod streams;
pub mod tls;
pub mod uploads;
pub mod viewer;
pub mod ws;

use std::sync::Arc;

use axum::extract::{DefaultBodyLimit, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Serialize;
use utoipa::ToSchema;

use crate::AppState;

/// Every route of the service, with its state. Buffered bodies (JSON, frames) are read whole,
/// in bounded size and time, before a handler runs ([`body`]); uploads are streamed and
/// bounded by `limits.max_upload_bytes` as they arrive.
pub fn router(state: Arc<AppState>) -> Router {
    let body_limit = usize::try_from(state.config.limits.max_frame_bytes).unwrap_or(usize::MAX);
    Router::new()
        .route(
            "/v1/sessions",
            post(sessions::create_session).get(sessions::list_sessions),
        )
        .route(
            "/v1/sessions/{id}",
            get(sessions::get_session).delete(sessions::delete_session),
        )
        .route("/v1/sessions/{id}/frames", post(frames::post_frame))
        .route("/v1/sessions/{id}/finish", post(sessions::finish_session))
        .route("/v1/sessions/{id}/stream", get(stream_ws::stream))
        .route("/v1/sessions/{id}/events", get(events_sse::events))
        .route("/v1/sessions/{id}/trajectory", get(downloads::trajectory))
        .route("/v1/sessions/{id}/keyframes", get(downloads::keyframes))
        .route(
            "/v1/sessions/{id}/pointcloud.ply",
            get(downloads::pointcloud_ply),
        )
        .route("/v1/sessions/{id}/mesh.ply", get(downloads::mesh_ply))
        .route(
            "/v1/sessions/{id}/recording.mcap",
            get(downloads::recording_mcap),
        )
        .route("/v1/sessions/{id}/mesh.glb", get(downloads::mesh_glb))
        .route("/v1/sessions/{id}/map", get(map::map_snapshot))
        .route("/v1/maps", post(maps::save_map).get(maps::list_maps))
        .route("/v1/maps/{id}", get(maps::get_map).delete(maps::delete_map))
        .route("/v1/proto", get(map::proto_files))
        .route("/v1/proto/{*path}", get(map::proto_file))
        .route("/v1/uploads", post(uploads::upload))
        .route("/v1/version", get(version))
        .route("/v1/cluster", get(cluster::cluster))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(openapi_json))
        .route("/docs", get(docs::page))
        .route("/docs/swagger-ui-bundle.js", get(docs::bundle))
        .route("/docs/swagger-ui.css", get(docs::css))
        .route("/docs/init.js", get(docs::init))
        .route("/", get(viewer::page))
        .route("/view/{id}", get(viewer::page))
        .route("/viewer/viewer.js", get(viewer::script))
        .route("/viewer/viewer.css", get(viewer::style))
        .route("/viewer/licenses.txt", get(viewer::licenses))
        .fallback(error::no_route)
        .method_not_allowed_fallback(error::wrong_method)
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            routing::to_owner,
        ))
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            body::buffer_body,
        ))
        .layer(axum::middleware::from_fn(security::headers))
        .with_state(state)
}

/// Liveness: `ok` while the service can do its work; 503 with the reason when a part of it
/// is broken (a GPU pool worker stopped, the store cannot be written, resident memory is over
/// `limits.memory_budget_mb`). A failed session is not a broken service.
#[utoipa::path(get, path = "/healthz", tag = "service",
    responses(
        (status = 200, description = "`ok`", body = String, content_type = "text/plain"),
        (status = 503, description = "What is broken", body = String, content_type = "text/plain"),
    ))]
pub async fn healthz(State(state): State<Arc<AppState>>) -> Response {
    let sessions = state.sessions.clone();
    match tokio::task::spawn_blocking(move || sessions.health()).await {
        Ok(Ok(())) => "ok".into_response(),
        Ok(Err(reason)) => (StatusCode::SERVICE_UNAVAILABLE, reason).into_response(),
        Err(e) => (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("the health check failed: {e}"),
        )
            .into_response(),
    }
}

/// Readiness: 200 while new sessions are accepted, 503 while shutting down.
#[utoipa::path(get, path = "/readyz", tag = "service",
    responses(
        (status = 200, description = "`ready`", body = String, content_type = "text/plain"),
        (status = 503, description = "Shutting down", body = String, content_type = "text/plain"),
    ))]
pub async fn readyz(State(state): State<Arc<AppState>>) -> Response {
    if state.sessions.is_accepting() {
        "ready".into_response()
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "shutting down").into_response()
    }
}

/// Prometheus metrics (OpenMetrics text).
#[utoipa::path(get, path = "/metrics", tag = "service",
    responses((status = 200, description = "Frames in / processed / dropped, per-stage latency histograms, sessions, queue depths, GPU jobs", body = String, content_type = "application/openmetrics-text")))]
pub async fn metrics(State(state): State<Arc<AppState>>) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        state.metrics.render(),
    )
        .into_response()
}

/// Name and version of the service.
#[derive(Debug, Serialize, ToSchema)]
pub struct Version {
    #[schema(example = "relfusiond")]
    pub name: &'static str,
    pub version: &'static str,
    /// The API version (the path prefix).
    #[schema(example = "v1")]
    pub api: &'static str,
}

/// Name and version of the service (no token needed).
#[utoipa::path(get, path = "/v1/version", tag = "service",
    responses((status = 200, description = "The service version", body = Version)))]
pub async fn version() -> Json<Version> {
    Json(Version {
        name: "relfusiond",
        version: env!("CARGO_PKG_VERSION"),
        api: "v1",
    })
}

/// This document.
#[utoipa::path(get, path = "/openapi.json", tag = "service",
    responses((status = 200, description = "The OpenAPI description of this API", content_type = "application/json", body = Object)))]
pub async fn openapi_json() -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        openapi::spec_json(),
    )
        .into_response()
}
