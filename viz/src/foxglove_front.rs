//! The front door of the live Foxglove view: the Foxglove SDK's server accepts only the
//! WebSocket subprotocol `foxglove.sdk.v1`, while the protocol's published name, which
//! Lichtblick, Foxglove Studio before 2025 and other viewers offer alone, is
//! `foxglove.websocket.v1` (the same messages: `serverInfo`, `advertise`, `subscribe`,
//! binary message data). This front accepts either, connects to the SDK's server on a
//! loopback port with `foxglove.sdk.v1`, and relays the frames both ways unchanged.
//!
//! It runs on a thread of its own (a current-thread tokio runtime) until dropped. A client is
//! refused (HTTP 400, no upgrade) when it offers neither subprotocol.

use std::net::SocketAddr;

use futures_util::{SinkExt as _, StreamExt as _};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::oneshot;
use tokio_tungstenite::tungstenite::client::IntoClientRequest as _;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode, header};

/// The subprotocol the SDK's server speaks.
pub const SDK: &str = "foxglove.sdk.v1";
/// The protocol's published name.
pub const WEBSOCKET_V1: &str = "foxglove.websocket.v1";

/// A running front; dropping it stops accepting (open relays end with their server).
#[derive(Debug)]
pub struct FoxgloveFront {
    addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// The subprotocol to answer a client that offers `offered` (comma-separated), if any.
pub fn choose(offered: &str) -> Option<&'static str> {
    let offered: Vec<&str> = offered.split(',').map(str::trim).collect();
    [SDK, WEBSOCKET_V1]
        .into_iter()
        .find(|p| offered.contains(p))
}

impl FoxgloveFront {
    /// Listens on `bind` and relays every client to the SDK's server at
    /// `127.0.0.1:upstream_port`.
    pub fn start(bind: SocketAddr, upstream_port: u16) -> std::io::Result<Self> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let listener = runtime.block_on(TcpListener::bind(bind))?;
        let addr = listener.local_addr()?;
        let (stop, mut stopped) = oneshot::channel();
        let thread = std::thread::Builder::new()
            .name("foxglove-front".into())
            .spawn(move || {
                runtime.block_on(async move {
                    loop {
                        tokio::select! {
                            accepted = listener.accept() => {
                                if let Ok((stream, _)) = accepted {
                                    tokio::spawn(relay(stream, upstream_port));
                                }
                            }
                            _ = &mut stopped => break,
                        }
                    }
                });
            })?;
        Ok(FoxgloveFront {
            addr,
            stop: Some(stop),
            thread: Some(thread),
        })
    }

    /// Where viewers connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for FoxgloveFront {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// One viewer: the handshake with the subprotocol it offered, the SDK's server behind.
// The handshake callback's error type is tungstenite's HTTP response.
#[allow(clippy::result_large_err)]
async fn relay(stream: TcpStream, upstream_port: u16) {
    let answer = |request: &Request, mut response: Response| {
        let offered = request
            .headers()
            .get(header::SEC_WEBSOCKET_PROTOCOL)
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default();
        match choose(offered) {
            Some(protocol) => {
                response.headers_mut().insert(
                    header::SEC_WEBSOCKET_PROTOCOL,
                    HeaderValue::from_static(protocol),
                );
                Ok(response)
            }
            None => {
                let mut refused = ErrorResponse::new(Some(format!(
                    "offer the WebSocket subprotocol {SDK} or {WEBSOCKET_V1}"
                )));
                *refused.status_mut() = StatusCode::BAD_REQUEST;
                Err(refused)
            }
        }
    };
    let Ok(viewer) = tokio_tungstenite::accept_hdr_async(stream, answer).await else {
        return;
    };
    let Ok(mut request) = format!("ws://127.0.0.1:{upstream_port}").into_client_request() else {
        return;
    };
    request.headers_mut().insert(
        header::SEC_WEBSOCKET_PROTOCOL,
        HeaderValue::from_static(SDK),
    );
    let Ok((server, _)) = tokio_tungstenite::connect_async(request).await else {
        return;
    };
    let (mut to_viewer, mut from_viewer) = viewer.split();
    let (mut to_server, mut from_server) = server.split();
    let down = async {
        while let Some(Ok(message)) = from_server.next().await {
            if to_viewer.send(message).await.is_err() {
                break;
            }
        }
        let _ = to_viewer.close().await;
    };
    let up = async {
        while let Some(Ok(message)) = from_viewer.next().await {
            if to_server.send(message).await.is_err() {
                break;
            }
        }
        let _ = to_server.close().await;
    };
    tokio::select! {
        () = down => {}
        () = up => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn either_name_of_the_protocol_is_accepted() {
        assert_eq!(choose("foxglove.websocket.v1"), Some(WEBSOCKET_V1));
        assert_eq!(choose("foxglove.sdk.v1, foxglove.websocket.v1"), Some(SDK));
        assert_eq!(choose("x, foxglove.websocket.v1 "), Some(WEBSOCKET_V1));
        assert_eq!(choose("graphql-ws"), None);
        assert_eq!(choose(""), None);
    }
}
