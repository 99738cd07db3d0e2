//! Cluster routing of HTTP requests (see [`crate::cluster`]): a request for a session this node
//! does not hold goes to the node that does; a new live session goes to the node placement
//! picks. Everything else, and every request already forwarded once, is served here.
//!
//! Runs after [`super::body`], so a forwarded body is already read whole and bounded. The
//! streams are relayed by their handlers: the WebSocket by [`super::stream_remote`], the
//! server-sent events by [`super::events_sse`].

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::Response;

use crate::AppState;
use crate::cluster::forward::{FORWARDED, session_path};

/// The middleware (see the module docs).
pub async fn to_owner(
    State(state): State<Arc<AppState>>,
    request: Request,
    next: Next,
) -> Response {
    let cluster = &state.cluster;
    if cluster.zenoh().is_none() || request.headers().contains_key(FORWARDED) {
        return next.run(request).await;
    }
    let path = request.uri().path();
    if let Some((id, rest)) = session_path(path) {
        // The streams are relayed by their handlers.
        if rest == "stream" || rest == "events" || state.sessions.holds(id) {
            return next.run(request).await;
        }
        let id = id.to_string();
        if let Some(node) = cluster.owner_of(&id).await {
            return cluster.forward(&node, request).await;
        }
    } else if request.method() == Method::POST
        && path == "/v1/sessions"
        && let Some(node) = cluster.place()
    {
        tracing::debug!(node = %node, "placing a new session on another node");
        return cluster.forward(&node, request).await;
    }
    next.run(request).await
}
