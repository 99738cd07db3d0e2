//! Saved maps (issue 24): keep a finished session's map, list, describe, delete. A session
//! starts from one with `"map": {"id": …, "mode": "localize"}` in its create request (HTTP) or
//! `map_id` in its `SessionConfig` (Zenoh). A token sees only its own maps.

use std::sync::Arc;

use axum::Json;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use relfusion_proto::http::{MapInfo, MapList, SaveMap};

use super::auth::Auth;
use super::error::{ApiJson, ErrorBody};
use crate::session::SessionState;
use crate::{ApiError, AppState};

/// Keeps the map of a finished session as a saved map of the caller.
#[utoipa::path(
    post, path = "/v1/maps", tag = "maps",
    request_body = SaveMap,
    responses(
        (status = 201, description = "Saved", body = MapInfo),
        (status = 400, description = "A name too long or with control characters", body = ErrorBody),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 409, description = "The session has not finished, or made no map", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
        (status = 429, description = "The token keeps quotas.max_maps maps already", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn save_map(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    ApiJson(request): ApiJson<SaveMap>,
) -> Result<(StatusCode, Json<MapInfo>), ApiError> {
    let session = state.sessions.get(&request.session, &owner)?;
    if session.state() != SessionState::Finished {
        return Err(ApiError::conflict(format!(
            "session {} is {:?}: only a finished session's map can be kept",
            request.session,
            session.state()
        )));
    }
    let sessions = state.sessions.clone();
    let info = tokio::task::spawn_blocking(move || {
        sessions.maps().save(&owner, &request.session, request.name)
    })
    .await
    .map_err(|e| ApiError::internal(format!("saving the map: {e}")))??;
    Ok((StatusCode::CREATED, Json(info)))
}

/// The caller's saved maps, oldest first.
#[utoipa::path(
    get, path = "/v1/maps", tag = "maps",
    responses(
        (status = 200, description = "The caller's maps", body = MapList),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn list_maps(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
) -> Result<Json<MapList>, ApiError> {
    Ok(Json(MapList {
        maps: state.sessions.maps().list(&owner)?,
    }))
}

/// One saved map.
#[utoipa::path(
    get, path = "/v1/maps/{id}", tag = "maps",
    params(("id" = String, Path, description = "Map id")),
    responses(
        (status = 200, description = "The map", body = MapInfo),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such map", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn get_map(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Json<MapInfo>, ApiError> {
    Ok(Json(state.sessions.maps().get(&id, &owner)?))
}

/// Deletes a saved map (sessions already localising in it keep their loaded copy).
#[utoipa::path(
    delete, path = "/v1/maps/{id}", tag = "maps",
    params(("id" = String, Path, description = "Map id")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such map", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn delete_map(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    state.sessions.maps().delete(&id, &owner)?;
    Ok(StatusCode::NO_CONTENT)
}
