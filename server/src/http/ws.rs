//! The WebSocket plumbing both session streams share: local ([`super::stream_ws`]) and relayed
//! from another node ([`super::stream_remote`]): message limits, what an open socket holds,
//! keep-alive, the receiving loop and the encoding of replies.

use std::time::Duration;

use axum::body::Bytes;
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade, close_code};
use futures_util::stream::{SplitSink, SplitStream};
use futures_util::{SinkExt, StreamExt};
use relfusion_proto::Message as _;
use relfusion_proto::v1::{self, ErrorCode, ServerMessage, server_message};
use tokio::sync::mpsc;

use super::serve::ConnectionSlot;
use super::streams::{KeepAlive, KeepAliveClock, LastHeard, StreamSlot};
use crate::{ApiError, AppState};

/// Room for protobuf framing around the largest allowed image.
const MESSAGE_OVERHEAD: usize = 64 * 1024;

/// How long a closed-by-us socket waits for the client's close reply before it is dropped.
pub(super) const CLOSE_GRACE: Duration = Duration::from_secs(5);

/// Error replies queued between the receiving and the sending task (bounded: a client that
/// floods bad messages waits for its errors to be written).
pub(super) const REPLY_QUEUE: usize = 16;

/// What an open stream holds until it closes: its connection slot, its place under the
/// stream caps, and its idle timeout.
#[derive(Debug)]
pub(super) struct Held {
    _connection: Option<ConnectionSlot>,
    _stream: StreamSlot,
    pub idle: Duration,
}

impl Held {
    pub(super) fn new(
        connection: Option<ConnectionSlot>,
        stream: StreamSlot,
        idle: Duration,
    ) -> Self {
        Self {
            _connection: connection,
            _stream: stream,
            idle,
        }
    }
}

/// The upgrade, or the 400 that says this endpoint is a WebSocket.
pub(super) fn checked_upgrade(
    upgrade: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
    id: &str,
) -> Result<WebSocketUpgrade, ApiError> {
    upgrade.map_err(|rejection| ApiError {
        status: rejection.status().as_u16(),
        code: "invalid_argument",
        message: format!(
            "{}: this endpoint is a WebSocket (ws://.../v1/sessions/{id}/stream)",
            rejection.body_text()
        ),
    })
}

/// The upgrade with the message limits: the largest allowed image and its framing.
pub(super) fn sized(upgrade: WebSocketUpgrade, state: &AppState) -> WebSocketUpgrade {
    let limit = usize::try_from(state.config.limits.max_frame_bytes)
        .unwrap_or(usize::MAX)
        .saturating_add(MESSAGE_OVERHEAD);
    upgrade.max_message_size(limit).max_frame_size(limit)
}

/// An `Error` message for the client.
pub(super) fn error_message(code: ErrorCode, message: impl Into<String>) -> ServerMessage {
    ServerMessage {
        message: Some(server_message::Message::Error(v1::Error {
            code: code as i32,
            message: message.into(),
        })),
    }
}

/// A message as a binary WebSocket frame.
pub(super) fn binary(message: &ServerMessage) -> Message {
    Message::Binary(Bytes::from(message.encode_to_vec()))
}

/// Acts on a keep-alive tick: a ping, or the close of a silent peer. Whether the socket
/// stays open.
pub(super) async fn keep_alive(
    sink: &mut SplitSink<WebSocket, Message>,
    tick: KeepAlive,
    clock: &KeepAliveClock,
) -> bool {
    match tick {
        KeepAlive::Ping => sink.send(Message::Ping(Bytes::new())).await.is_ok(),
        KeepAlive::Expired => {
            let reason = format!(
                "no message or pong for {} s (http.stream_idle_timeout_s)",
                clock.idle().as_secs()
            );
            let _ = sink
                .send(Message::Close(Some(CloseFrame {
                    code: close_code::POLICY,
                    reason: reason.into(),
                })))
                .await;
            false
        }
    }
}

/// Reads client messages until the client closes, hands each binary one to `handle`; every
/// failure becomes an `Error` reply; every message (pongs too) counts as `heard`. Shared by
/// local and relayed streams.
pub(super) async fn receive_loop<F, Fut>(
    mut stream: SplitStream<WebSocket>,
    replies: mpsc::Sender<ServerMessage>,
    heard: LastHeard,
    mut handle: F,
) where
    F: FnMut(Bytes) -> Fut,
    Fut: std::future::Future<Output = Result<(), ApiError>>,
{
    while let Some(Ok(message)) = stream.next().await {
        heard.heard();
        let outcome = match message {
            Message::Binary(data) => handle(data).await,
            Message::Text(_) => Err(ApiError::bad_request(
                "text messages are not understood: send binary protobuf relfusion.v1.ClientMessage",
            )),
            Message::Close(_) => break,
            // Pings are answered by the WebSocket layer itself.
            Message::Ping(_) | Message::Pong(_) => Ok(()),
        };
        if let Err(error) = outcome
            && replies
                .send(error_message(error.proto_code(), error.message))
                .await
                .is_err()
        {
            break;
        }
    }
}
