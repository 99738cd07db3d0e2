//! Cluster routing of HTTP requests (see [`crate::cluster`]): a request for a session this node
//! does not hold goes to the node that does; a new live session goes to the node placement
//! picks. Everything else, and every request already forwarded once, is served here.
//!
//! Runs after [`super::body`], so a forwarded body is already read whole and bounded. The
//! WebSocket stream is relayed by its handler ([`super::stream_remote`]); the SSE stream of a
//! session on another node is refused with the node's name (use the WebSocket through any
//! node, or the events of the node itself).

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use crate::cluster::forward::{FORWARDED, session_path};
use crate::{ApiError, AppState};

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
        if rest == "stream" || state.sessions.holds(id) {
            return next.run(request).await;
        }
        let id = id.to_string();
        let events = rest == "events";
        if let Some(node) = cluster.owner_of(&id).await {
            if events {
                return ApiError {
                    status: 409,
                    code: "conflict",
                    message: format!(
                        "session {id} runs on node {node}: its server-sent events are served \
                         there; through any node, use the WebSocket stream"
                    ),
                }
                .into_response();
            }
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
