//! Routing of HTTP requests to where their session is ([`crate::locator`]): a request for a
//! session this node does not hold goes to the node that does (also `POST /v1/maps`, which names its session in
//! the body); a new live session goes to the node placement picks. Everything else, and every
//! request already forwarded once, is served here.
//!
//! Runs after [`super::body`], so a forwarded body is already read whole and bounded. The
//! streams are relayed by their handlers: the WebSocket by [`super::stream_remote`], the
//! server-sent events by [`super::events_sse`].

use std::sync::Arc;

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use relfusion_proto::http::SaveMap;

use crate::locator::Hop;
use crate::session::types::valid_session_id;
use crate::{ApiError, AppState};

/// The middleware (see the module docs).
pub async fn to_owner(
    State(state): State<Arc<AppState>>,
    request: Request,
    next: Next,
) -> Response {
    let locator = &state.locator;
    if !locator.joined() || Hop::of(request.headers()) == Hop::FromNode {
        return next.run(request).await;
    }
    let path = request.uri().path();
    if let Some((id, rest)) = session_path(path) {
        // The streams are relayed by their handlers.
        if rest == "stream" || rest == "events" {
            return next.run(request).await;
        }
        let id = id.to_string();
        if let Some(remote) = locator.elsewhere(&id).await {
            return remote.forward(request).await;
        }
    } else if request.method() == Method::POST
        && path == "/v1/sessions"
        && let Some(node) = locator.place()
    {
        tracing::debug!(node = %node.name(), "placing a new session on another node");
        return node.forward(request).await;
    } else if request.method() == Method::POST && path == "/v1/maps" {
        return save_map_where_it_ran(&state, request, next).await;
    }
    next.run(request).await
}

/// Which session a path names, and the rest of the path (`/v1/sessions/<id>/<rest>`).
fn session_path(path: &str) -> Option<(&str, &str)> {
    let rest = path.strip_prefix("/v1/sessions/")?;
    let (id, tail) = rest.split_once('/').unwrap_or((rest, ""));
    (!id.is_empty()).then_some((id, tail))
}

/// `POST /v1/maps` names its session in the body: the map is saved by the node that holds the
/// session (into the shared store, where every node finds it).
async fn save_map_where_it_ran(state: &AppState, request: Request, next: Next) -> Response {
    let (parts, body) = request.into_parts();
    // Read whole and bounded by `super::body` already: this only takes the buffered bytes.
    let bytes = match axum::body::to_bytes(body, usize::MAX).await {
        Ok(bytes) => bytes,
        Err(e) => return ApiError::bad_request(format!("reading the body: {e}")).into_response(),
    };
    let session = serde_json::from_slice::<SaveMap>(&bytes)
        .ok()
        .map(|save| save.session)
        .filter(|id| valid_session_id(id));
    let request = Request::from_parts(parts, Body::from(bytes));
    if let Some(id) = session
        && let Some(remote) = state.locator.elsewhere(&id).await
    {
        return remote.forward(request).await;
    }
    next.run(request).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn session_paths_are_recognised() {
        assert_eq!(session_path("/v1/sessions/s-1"), Some(("s-1", "")));
        assert_eq!(
            session_path("/v1/sessions/s-1/frames"),
            Some(("s-1", "frames"))
        );
        assert_eq!(session_path("/v1/sessions"), None);
        assert_eq!(session_path("/v1/sessions/"), None);
        assert_eq!(session_path("/v1/maps/m-1"), None);
    }
}
