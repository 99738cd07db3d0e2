//! The accept loop: HTTP/1.1 connections (with WebSocket upgrades) served by hyper with the
//! bounds a public server needs, which `axum::serve` does not set.
//!
//! - At most `http.max_connections` connections are open; the loop stops accepting while at
//!   the limit, so further clients wait in the kernel's backlog instead of costing memory.
//! - A request's headers must arrive within `http.header_timeout_s` of the connection being
//!   ready for them (hyper's header-read timer), which also closes idle keep-alive
//!   connections: half-sent headers cannot hold a connection.
//! - Request bodies are bounded in size and time by [`super::body`].
//!
//! On shutdown the listener closes, every connection finishes its request in flight and
//! closes (hyper's graceful shutdown), and the loop returns once they have.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio::sync::{Semaphore, watch};
use tower::ServiceExt as _;

use crate::config::HttpLimits;

/// Serves `router` on `listener` until `shutdown` resolves, then waits for open connections to
/// finish their requests (the caller bounds that wait).
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: &HttpLimits,
    shutdown: impl Future<Output = ()>,
) {
    let slots = Arc::new(Semaphore::new(limits.max_connections));
    let header_timeout = Duration::from_secs(limits.header_timeout_s);
    // Dropped at shutdown: every connection task starts its graceful close.
    let (stop_tx, stop_rx) = watch::channel(());
    let (closed_tx, mut closed_rx) = watch::channel(());
    tokio::pin!(shutdown);
    loop {
        let slot = tokio::select! {
            slot = slots.clone().acquire_owned() => match slot {
                Ok(slot) => slot,
                Err(_) => break,
            },
            () = &mut shutdown => break,
        };
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of file descriptors and the like: wait instead of spinning.
                    tracing::warn!("accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let service = TowerToHyperService::new(
            router
                .clone()
                .map_request(|request: hyper::Request<Incoming>| request.map(Body::new)),
        );
        let mut stop = stop_rx.clone();
        let closed = closed_tx.clone();
        tokio::spawn(async move {
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(header_timeout)
                .max_buf_size(64 * 1024);
            let conn = builder
                .serve_connection(TokioIo::new(stream), service)
                .with_upgrades();
            tokio::pin!(conn);
            let result = tokio::select! {
                result = conn.as_mut() => result,
                _ = stop.changed() => {
                    conn.as_mut().graceful_shutdown();
                    conn.as_mut().await
                }
            };
            if let Err(e) = result {
                tracing::debug!(%peer, "connection ended: {e}");
            }
            drop(slot);
            drop(closed);
        });
    }
    drop(listener);
    drop(stop_tx);
    drop(closed_tx);
    // Resolves once every connection task has dropped its sender.
    let _ = closed_rx.changed().await;
}
