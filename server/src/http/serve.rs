//! The accept loop: HTTP/1.1 connections (with WebSocket upgrades) served by hyper with the
//! bounds a public server needs, which `axum::serve` does not set.
//!
//! - At most `http.max_connections` connections are open; the loop stops accepting while at
//!   the limit, so further clients wait in the kernel's backlog instead of costing memory.
//! - A request's headers must arrive within `http.header_timeout_s` of the connection being
//!   ready for them (hyper's header-read timer), which also closes idle keep-alive
//!   connections: half-sent headers cannot hold a connection.
//! - Request bodies are bounded in size and time by [`super::body`].
//! - With TLS ([`super::tls`]) the handshake runs in the connection's task and must finish
//!   within the same header timeout.
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
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpListener;
use tokio::sync::{Semaphore, watch};
use tokio_rustls::TlsAcceptor;
use tower::ServiceExt as _;

use crate::config::HttpLimits;

/// Serves `router` on `listener` (over TLS with `tls`) until `shutdown` resolves, then waits
/// for open connections to finish their requests (the caller bounds that wait).
pub async fn serve(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
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
        let stop = stop_rx.clone();
        let closed = closed_tx.clone();
        let tls = tls.clone();
        tokio::spawn(async move {
            match tls {
                None => serve_connection(stream, service, header_timeout, stop).await,
                Some(acceptor) => {
                    match tokio::time::timeout(header_timeout, acceptor.accept(stream)).await {
                        Ok(Ok(stream)) => {
                            serve_connection(stream, service, header_timeout, stop).await;
                        }
                        Ok(Err(e)) => tracing::debug!(%peer, "TLS handshake failed: {e}"),
                        Err(_) => tracing::debug!(%peer, "TLS handshake timed out"),
                    }
                }
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

/// One HTTP/1.1 connection (with upgrades) until it ends or `stop` asks for a graceful close.
async fn serve_connection<IO, S>(
    io: IO,
    service: S,
    header_timeout: Duration,
    mut stop: watch::Receiver<()>,
) where
    IO: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    S: hyper::service::Service<hyper::Request<Incoming>, Response = axum::response::Response>
        + Send
        + 'static,
    S::Future: Send + 'static,
    S::Error: std::error::Error + Send + Sync + 'static,
{
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(header_timeout)
        .max_buf_size(64 * 1024);
    let conn = builder
        .serve_connection(TokioIo::new(io), service)
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
        tracing::debug!("connection ended: {e}");
    }
}
