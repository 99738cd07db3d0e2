//! relfusiond: the relfusion service.
//!
//! At this stage it serves health and version only; sessions, the GPU worker pool, uploads and
//! Zenoh arrive with the service issue. The shape is already the final one: a typed [`Config`],
//! `fn app(state) -> Router` (testable without a socket) and `run(listener, shutdown)`.

pub mod api_error;
pub mod config;
pub mod error;

use std::future::Future;
use std::sync::Arc;

use axum::{Json, Router, routing::get};
use serde_json::json;

pub use api_error::ApiError;
pub use config::Config;
pub use error::ServerError;

/// State shared by every request handler.
#[derive(Debug)]
pub struct AppState {
    pub config: Config,
}

/// The HTTP application: every route, no socket (tests call it with `oneshot`).
pub fn app(state: Arc<AppState>) -> Router {
    Router::new()
        .route("/healthz", get(|| async { "ok" }))
        .route("/readyz", get(|| async { "ready" }))
        .route("/v1/version", get(version))
        .with_state(state)
}

async fn version() -> Json<serde_json::Value> {
    Json(json!({ "name": "relfusiond", "version": env!("CARGO_PKG_VERSION"), "api": "v1" }))
}

/// Serves `app` on `listener` until `shutdown` resolves, then drains in-flight requests.
pub async fn run(
    listener: tokio::net::TcpListener,
    state: Arc<AppState>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    axum::serve(listener, app(state))
        .with_graceful_shutdown(shutdown)
        .await
        .map_err(ServerError::Serve)
}
