//! Session lifecycle: create, list, inspect, finish, delete.

use relfusion_proto::http::{CreatedSession, SessionList};
use std::sync::Arc;

use axum::Json;
use axum::extract::{Path, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::auth::Auth;
use super::error::{ApiJson, ErrorBody};
use crate::locator::Hop;
use crate::session::{CreateSession, SessionInfo, SessionRequest};
use crate::{ApiError, AppState};

/// `201 Created` with a `Location` header pointing at the session.
pub(super) fn created(info: SessionInfo) -> Response {
    let location = format!("/v1/sessions/{}", info.id);
    let mut response = (
        StatusCode::CREATED,
        Json(CreatedSession {
            id: info.id.clone(),
            session: info,
        }),
    )
        .into_response();
    if let Ok(value) = HeaderValue::from_str(&location) {
        response.headers_mut().insert(header::LOCATION, value);
    }
    response
}

/// Opens a live session: frames then arrive over `/frames`, `/stream` (WebSocket) or Zenoh.
#[utoipa::path(
    post, path = "/v1/sessions", tag = "sessions",
    request_body = CreateSession,
    responses(
        (status = 201, description = "Session created", body = CreatedSession),
        (status = 400, description = "Invalid camera, config or model; a camera too large for limits.max_image_pixels or the session's memory share", body = ErrorBody),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 408, description = "The body did not arrive within http.body_timeout_s", body = ErrorBody),
        (status = 413, description = "Body larger than limits.max_frame_bytes", body = ErrorBody),
        (status = 415, description = "Not a JSON body", body = ErrorBody),
        (status = 429, description = "The token's quota (quotas.max_active_sessions, max_stored_sessions, max_stored_gb) is used up", body = ErrorBody),
        (status = 503, description = "At capacity (limits.max_sessions), or too many request bodies arriving", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn create_session(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    ApiJson(mut request): ApiJson<CreateSession>,
) -> Result<Response, ApiError> {
    let mut ros2 = crate::ros2_api::prepare(
        &state.sessions,
        request.ros2.as_ref(),
        request.camera.is_some(),
        owner.tenant(),
    )
    .await?;
    if let Some(camera) = ros2.as_mut().and_then(|r| r.camera.take()) {
        request.camera = Some(camera);
    }
    let session = state
        .sessions
        .create(SessionRequest::from_http(request)?, &owner)?;
    if let Some(ros2) = ros2 {
        ros2.attach(&state.sessions, session.clone()).await?;
    }
    Ok(created(session.info()))
}

/// Lists the caller's sessions (live, uploads, finished) on every node of the cluster.
#[utoipa::path(
    get, path = "/v1/sessions", tag = "sessions",
    responses(
        (status = 200, description = "The caller's sessions", body = SessionList),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn list_sessions(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    headers: axum::http::HeaderMap,
) -> Json<SessionList> {
    let mut sessions = state.sessions.list(&owner);
    // Asked directly (not by another node): the other nodes' sessions of the caller too.
    if Hop::of(&headers) == Hop::FromClient {
        let authorization = headers
            .get(axum::http::header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok());
        for body in state.locator.gather("/v1/sessions", authorization).await {
            if let Ok(list) = serde_json::from_slice::<SessionList>(&body) {
                sessions.extend(list.sessions);
            }
        }
        sessions.sort_by(|a, b| (a.created_unix, &a.id).cmp(&(b.created_unix, &b.id)));
        sessions.dedup_by(|a, b| a.id == b.id);
    }
    Json(SessionList { sessions })
}

/// State and progress of one session.
#[utoipa::path(
    get, path = "/v1/sessions/{id}", tag = "sessions",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "The session", body = SessionInfo),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn get_session(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Json<SessionInfo>, ApiError> {
    Ok(Json(state.sessions.get(&id, &owner)?.info()))
}

/// Stops a session and removes its data and results.
#[utoipa::path(
    delete, path = "/v1/sessions/{id}", tag = "sessions",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn delete_session(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    state.sessions.delete(&id, &owner)?;
    Ok(StatusCode::NO_CONTENT)
}

/// End of stream: the session processes its queued frames, finishes the map and persists the
/// results; `/events` and `/stream` report `finished` when done.
#[utoipa::path(
    post, path = "/v1/sessions/{id}/finish", tag = "sessions",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 202, description = "Finishing; the body is the session as of now", body = SessionInfo),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn finish_session(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<(StatusCode, Json<SessionInfo>), ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    session.end_of_stream();
    Ok((StatusCode::ACCEPTED, Json(session.info())))
}
