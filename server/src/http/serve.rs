//! The accept loop: HTTP/1.1 connections (with WebSocket upgrades) served by hyper with the
//! bounds a public server needs, which `axum::serve` does not set.
//!
//! - At most `http.max_connections` connections are open; the loop stops accepting while at
//!   the limit, so further clients wait in the kernel's backlog instead of costing memory. A
//!   connection upgraded to a WebSocket keeps its slot (the [`ConnectionSlot`] travels with
//!   the request into the socket's task) until the socket closes.
//! - A write that makes no progress for `http.write_timeout_s` fails ([`WriteDeadline`]),
//!   which ends the connection: a client that stops reading holds nothing for long, on plain
//!   responses, server-sent events and upgraded WebSockets alike.
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
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpListener;
use tokio::sync::{OwnedSemaphorePermit, Semaphore, watch};
use tokio::time::Sleep;
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
    let write_timeout = Duration::from_secs(limits.write_timeout_s);
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
        let slot = ConnectionSlot(Arc::new(slot));
        let held = slot.clone();
        let service = TowerToHyperService::new(router.clone().map_request(
            move |mut request: hyper::Request<Incoming>| {
                request.extensions_mut().insert(held.clone());
                request.map(Body::new)
            },
        ));
        let stream = WriteDeadline::new(stream, write_timeout);
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

/// A connection's place among `http.max_connections`, shared by its requests: a WebSocket
/// handler moves it into the socket's task, so an upgraded connection keeps counting.
#[derive(Clone, Debug)]
pub struct ConnectionSlot(#[allow(dead_code)] Arc<OwnedSemaphorePermit>);

/// An IO whose writes must make progress: a write (or flush, or shutdown) that stays blocked
/// for `timeout` fails with `TimedOut`.
#[derive(Debug)]
pub struct WriteDeadline<IO> {
    io: IO,
    timeout: Duration,
    /// Armed while a write is blocked.
    blocked: Option<Pin<Box<Sleep>>>,
}

impl<IO> WriteDeadline<IO> {
    pub fn new(io: IO, timeout: Duration) -> Self {
        Self {
            io,
            timeout,
            blocked: None,
        }
    }

    /// The outcome of one write attempt: progress disarms the clock, a blocked write arms it
    /// and fails once it has run out.
    fn watch<T>(
        &mut self,
        cx: &mut Context<'_>,
        poll: Poll<std::io::Result<T>>,
    ) -> Poll<std::io::Result<T>> {
        match poll {
            Poll::Ready(result) => {
                self.blocked = None;
                Poll::Ready(result)
            }
            Poll::Pending => {
                let timeout = self.timeout;
                let sleep = self
                    .blocked
                    .get_or_insert_with(|| Box::pin(tokio::time::sleep(timeout)));
                match sleep.as_mut().poll(cx) {
                    Poll::Ready(()) => Poll::Ready(Err(std::io::Error::new(
                        std::io::ErrorKind::TimedOut,
                        "the client did not read for http.write_timeout_s",
                    ))),
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }
}

impl<IO: AsyncRead + Unpin> AsyncRead for WriteDeadline<IO> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_read(cx, buf)
    }
}

impl<IO: AsyncWrite + Unpin> AsyncWrite for WriteDeadline<IO> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        let poll = Pin::new(&mut self.io).poll_write(cx, buf);
        self.watch(cx, poll)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let poll = Pin::new(&mut self.io).poll_write_vectored(cx, bufs);
        self.watch(cx, poll)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let poll = Pin::new(&mut self.io).poll_flush(cx);
        self.watch(cx, poll)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let poll = Pin::new(&mut self.io).poll_shutdown(cx);
        self.watch(cx, poll)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::AsyncWriteExt as _;

    #[tokio::test]
    async fn a_write_that_makes_no_progress_fails_after_the_deadline() {
        // A pipe of 64 bytes that nobody reads: the writer blocks once it is full.
        let (client, _server) = tokio::io::duplex(64);
        let mut io = WriteDeadline::new(client, Duration::from_millis(200));
        let started = std::time::Instant::now();
        let result = io.write_all(&[7u8; 4096]).await;
        let error = result.expect_err("the write is cut");
        assert_eq!(error.kind(), std::io::ErrorKind::TimedOut);
        assert!(started.elapsed() >= Duration::from_millis(200));
        assert!(started.elapsed() < Duration::from_secs(5));
    }

    #[tokio::test]
    async fn writes_that_progress_are_untouched() {
        let (client, mut server) = tokio::io::duplex(64);
        let mut io = WriteDeadline::new(client, Duration::from_millis(200));
        let reader = tokio::spawn(async move {
            let mut all = Vec::new();
            let mut buf = [0u8; 16];
            use tokio::io::AsyncReadExt as _;
            loop {
                tokio::time::sleep(Duration::from_millis(20)).await;
                match server.read(&mut buf).await {
                    Ok(0) | Err(_) => break,
                    Ok(n) => all.extend_from_slice(&buf[..n]),
                }
            }
            all.len()
        });
        // 1 KiB at 16 bytes per 20 ms takes > 1 s in all, far past the deadline, but every
        // write makes progress within it.
        io.write_all(&[1u8; 1024]).await.expect("slow but steady");
        io.shutdown().await.expect("shutdown");
        drop(io);
        assert_eq!(reader.await.expect("reader"), 1024);
    }
}
