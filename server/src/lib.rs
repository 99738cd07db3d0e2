//! relfusiond: the relfusion service.
//!
//! Sessions ([`session::SessionManager`]) run one `slam::Pipeline` each on their own thread,
//! share the GPU through [`gpu_pool::GpuPool`], keep uploads and results in the store
//! ([`storage`]) and report through [`metrics`]. `fn app(state) -> Router` is the HTTP API
//! (testable without a socket); [`run`] serves it until shutdown, then shuts the sessions down
//! gracefully.

pub mod api_error;
pub mod auth;
pub mod cluster;
pub mod config;
pub mod convert;
pub mod error;
pub mod folders;
pub mod gpu_pool;
pub mod http;
pub mod locator;
pub mod maps;
pub mod memory;
pub mod metrics;
pub mod ros2_api;
pub mod ros2_names;
pub mod session;
pub mod storage;
pub mod zenoh_api;

use std::future::Future;
use std::sync::Arc;

pub use api_error::ApiError;
pub use config::Config;
pub use error::ServerError;

/// State shared by every request handler.
#[derive(Debug)]
pub struct AppState {
    pub config: Config,
    pub sessions: Arc<session::SessionManager>,
    pub metrics: Arc<metrics::Metrics>,
    /// Request bodies buffered at once ([`http::body`]).
    pub body_budget: http::body::BodyBudget,
    /// Where sessions are: here or on another node of the cluster (inert without Zenoh).
    pub locator: Arc<locator::Locator>,
    /// WebSocket and SSE streams open, per owner and per session ([`http::streams`]).
    pub streams: Arc<http::streams::StreamCounts>,
}

impl AppState {
    /// Opens the session manager (store, model, GPU pool, recovery) for `config`.
    pub fn open(config: Config) -> Result<Self, ServerError> {
        let metrics = Arc::new(metrics::Metrics::new());
        let sessions = session::SessionManager::open(&config, metrics.clone())?;
        Ok(Self {
            locator: Arc::new(locator::Locator::new(cluster::Cluster::new(
                sessions.clone(),
            ))),
            body_budget: http::body::BodyBudget::new(
                config.limits.max_buffered_body_mb,
                config
                    .quotas
                    .buffered_body_mb(config.limits.max_buffered_body_mb, config.auth.enabled()),
            ),
            config,
            sessions,
            metrics,
            streams: Arc::default(),
        })
    }
}

/// The HTTP application: every route, no socket (tests call it with `oneshot`).
pub fn app(state: Arc<AppState>) -> axum::Router {
    http::router(state)
}

/// The Zenoh side of a running server.
enum ZenohSide {
    Up(zenoh_api::ZenohHandle),
    /// Still waiting for its router.
    Joining(tokio::task::JoinHandle<Result<zenoh_api::ZenohHandle, ServerError>>),
}

/// Serves `app` on `listener` until `shutdown` resolves; then stops accepting connections,
/// shuts the sessions down gracefully (live sessions finish their queued frames and persist
/// their results, uploads stop and re-run on restart) and gives open requests (event streams
/// end with their sessions) `limits.shutdown_grace_s` to complete.
///
/// Boxed in and out so that the caller compiles none of it: a generic or `async fn` here would be
/// compiled again, with the HTTP and Zenoh stack below it, in every crate that calls it
/// (`relfusiond`'s binary, issue 36).
pub fn run(
    listener: tokio::net::TcpListener,
    tls: Option<tokio_rustls::TlsAcceptor>,
    state: Arc<AppState>,
    shutdown: BoxFuture<()>,
) -> BoxFuture<Result<(), ServerError>> {
    Box::pin(serve_until(listener, tls, state, shutdown))
}

/// A future that a binary awaits without compiling its body (see [`run`]).
pub type BoxFuture<T> = std::pin::Pin<Box<dyn Future<Output = T> + Send + 'static>>;

async fn serve_until(
    listener: tokio::net::TcpListener,
    tls: Option<tokio_rustls::TlsAcceptor>,
    state: Arc<AppState>,
    shutdown: BoxFuture<()>,
) -> Result<(), ServerError> {
    // Zenoh (when enabled) serves the same sessions; it closes after them so that their last
    // updates still go out. A client of a router joins in the background (the router may come
    // up after relfusiond); a peer is up before HTTP is, or relfusiond does not start.
    let zenoh = match (
        state.config.zenoh.enabled,
        state.config.zenoh.mode == "client",
    ) {
        (false, _) => None,
        (true, false) => Some(ZenohSide::Up(
            zenoh_api::start(&state.config, state.locator.clone()).await?,
        )),
        (true, true) => {
            zenoh_api::check(&state.config, &state.sessions)?;
            let (config, locator) = (state.config.clone(), state.locator.clone());
            Some(ZenohSide::Joining(tokio::spawn(async move {
                zenoh_api::start(&config, locator).await
            })))
        }
    };
    let janitor = state.sessions.spawn_janitor();
    let trimmer = memory::spawn_trimmer(std::time::Duration::from_secs(
        state.config.limits.memory_trim_interval_s,
    ));
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let router = app(state.clone());
    state.locator.serve_forwarded_with(router.clone());
    let limits = state.config.http.clone();
    let mut server = tokio::spawn(async move {
        http::serve::serve(listener, tls, router, &limits, async move {
            let _ = stop_rx.await;
        })
        .await;
    });
    shutdown.await;
    tracing::info!("shutting down: no new connections; finishing sessions");
    let _ = stop_tx.send(());
    janitor.abort();
    if let Some(trimmer) = trimmer {
        trimmer.abort();
    }
    state.sessions.shutdown().await;
    match zenoh {
        Some(ZenohSide::Up(zenoh)) => zenoh.close().await,
        Some(ZenohSide::Joining(task)) if task.is_finished() => match task.await {
            Ok(Ok(zenoh)) => zenoh.close().await,
            Ok(Err(e)) => tracing::warn!("Zenoh did not start: {e}"),
            Err(e) => tracing::warn!("Zenoh's start stopped: {e}"),
        },
        Some(ZenohSide::Joining(task)) => task.abort(),
        None => {}
    }
    let grace = std::time::Duration::from_secs(state.config.limits.shutdown_grace_s);
    if tokio::time::timeout(grace, &mut server).await.is_err() {
        tracing::warn!("open connections did not close within {grace:?}; closing them");
        server.abort();
    }
    Ok(())
}
