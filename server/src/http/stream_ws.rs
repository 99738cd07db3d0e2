//! `GET /v1/sessions/{id}/stream`: the session as a WebSocket, protobuf both ways.
//!
//! The client sends binary `ClientMessage`s (`Frame`, `EndOfStream`; `config` is ignored: the
//! session exists already); the server sends binary `ServerMessage`s (`PoseUpdate`,
//! `KeyframeUpdate`, `MeshUpdate`, `Error`). A bad message (undecodable, corrupt image, wrong
//! size, ...) is answered with an `Error` and the socket stays open: one bad frame must not
//! cost a live stream. After `EndOfStream` the server keeps sending updates until the session
//! has finished its map, then closes the socket normally.
//!
//! Receiving and sending run as two tasks so that a frame waiting for queue room (the `wait`
//! policy) never holds back the updates of earlier frames. The socket counts against its
//! owner's and its session's stream caps and keeps its connection slot until it closes; it
//! is pinged and closed when its peer falls silent ([`super::streams`]).

use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade, close_code};
use axum::extract::{Extension, Path, State};
use axum::http::{HeaderMap, Uri};
use axum::response::Response;
use futures_util::stream::{SplitSink, SplitStream};
use futures_util::{SinkExt, StreamExt};
use relfusion_proto::Message as _;
use relfusion_proto::v1::{self, ErrorCode, ServerMessage, server_message};
use tokio::sync::broadcast::{self, error::RecvError};
use tokio::sync::mpsc;

use super::auth::Auth;
use super::error::ErrorBody;
use super::serve::ConnectionSlot;
use super::streams::{KeepAlive, KeepAliveClock, LastHeard, StreamSlot, open_stream};
use crate::cluster::forward::FORWARDED;
use crate::session::{Session, SessionEvent};
use crate::{ApiError, AppState};

/// Room for protobuf framing around the largest allowed image.
const MESSAGE_OVERHEAD: usize = 64 * 1024;

/// How long a closed-by-us socket waits for the client's close reply before it is dropped.
pub(super) const CLOSE_GRACE: Duration = Duration::from_secs(5);

/// Error replies queued between the receiving and the sending task (bounded: a client that
/// floods bad messages waits for its errors to be written).
pub(super) const REPLY_QUEUE: usize = 16;

/// Opens the session's protobuf WebSocket.
#[utoipa::path(
    get, path = "/v1/sessions/{id}/stream", tag = "streams",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 101, description = "WebSocket: binary protobuf relfusion.v1.ClientMessage in, relfusion.v1.ServerMessage out"),
        (status = 400, description = "Not a WebSocket upgrade request", body = ErrorBody),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
        (status = 429, description = "The session has limits.max_streams_per_session streams open, or the token quotas.max_streams", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn stream(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
    headers: HeaderMap,
    uri: Uri,
    connection: Option<Extension<ConnectionSlot>>,
    upgrade: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Result<Response, ApiError> {
    // Counted only once the session is found: a cap must not tell whether another tenant's
    // session exists.
    let hold = |state: &Arc<AppState>| -> Result<Held, ApiError> {
        Ok(Held {
            _connection: connection.map(|Extension(slot)| slot),
            _stream: open_stream(state, &owner, &id)?,
            idle: Duration::from_secs(state.config.http.stream_idle_timeout_s),
        })
    };
    let session = match state.sessions.get(&id, &owner) {
        Ok(session) => session,
        // Not here: another node of the cluster may run it (its owner checks the token).
        Err(e) if e.status == 404 && !headers.contains_key(FORWARDED) => {
            let Some(node) = state.cluster.owner_of(&id).await else {
                return Err(e);
            };
            let upgrade = checked_upgrade(upgrade, &id)?;
            let held = hold(&state)?;
            let authorization = super::auth::relayed_authorization(&headers, &uri);
            return super::stream_remote::open(&state, node, id, authorization, upgrade, held)
                .await;
        }
        Err(e) => return Err(e),
    };
    let upgrade = checked_upgrade(upgrade, &id)?;
    let held = hold(&state)?;
    // Subscribe before the 101 goes out: a client that fetches the map snapshot once the socket
    // is open (a viewer joining late) then sees every later update, with no gap.
    let events = session.subscribe();
    Ok(sized(upgrade, &state).on_upgrade(move |socket| serve(socket, session, events, held)))
}

/// What an open stream holds until it closes: its connection slot, its place under the
/// stream caps, and its idle timeout.
#[derive(Debug)]
pub(super) struct Held {
    _connection: Option<ConnectionSlot>,
    _stream: StreamSlot,
    pub idle: Duration,
}

/// The upgrade, or the 400 that says this endpoint is a WebSocket.
fn checked_upgrade(
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

async fn serve(
    socket: WebSocket,
    session: Arc<Session>,
    events: broadcast::Receiver<SessionEvent>,
    held: Held,
) {
    let already_ended = session.info().state.is_terminal();
    let (sink, stream) = socket.split();
    let (reply_tx, reply_rx) = mpsc::channel(REPLY_QUEUE);
    let heard = LastHeard::now();
    let mut send_task = tokio::spawn(send_loop(
        sink,
        events,
        reply_rx,
        session.id().to_string(),
        already_ended,
        KeepAliveClock::new(heard.clone(), held.idle),
    ));
    let receiving = session.clone();
    let mut receive_task = tokio::spawn(receive_loop(stream, reply_tx, heard, move |data| {
        let session = receiving.clone();
        async move { session.apply_encoded(&data).await }
    }));
    tokio::select! {
        _ = &mut send_task => {
            // We closed (session finished): give the client a moment to answer the close.
            if tokio::time::timeout(CLOSE_GRACE, &mut receive_task).await.is_err() {
                receive_task.abort();
            }
        }
        _ = &mut receive_task => send_task.abort(),
    }
    drop(held);
    tracing::debug!(session = session.id(), "websocket closed");
}

pub(super) fn error_message(code: ErrorCode, message: impl Into<String>) -> ServerMessage {
    ServerMessage {
        message: Some(server_message::Message::Error(v1::Error {
            code: code as i32,
            message: message.into(),
        })),
    }
}

pub(super) fn binary(message: &ServerMessage) -> Message {
    Message::Binary(Bytes::from(message.encode_to_vec()))
}

/// Forwards session updates and error replies to the client; closes after the session's end.
async fn send_loop(
    mut sink: SplitSink<WebSocket, Message>,
    mut events: broadcast::Receiver<SessionEvent>,
    mut replies: mpsc::Receiver<ServerMessage>,
    session_id: String,
    already_ended: bool,
    mut keepalive: KeepAliveClock,
) {
    let close = |reason: &'static str| {
        Message::Close(Some(CloseFrame {
            code: close_code::NORMAL,
            reason: reason.into(),
        }))
    };
    if already_ended {
        let _ = sink.send(close("session already finished")).await;
        return;
    }
    let mut replies_open = true;
    loop {
        tokio::select! {
            tick = keepalive.tick() => {
                if !keep_alive(&mut sink, tick, &keepalive).await {
                    return;
                }
            }
            reply = replies.recv(), if replies_open => match reply {
                Some(message) => {
                    if sink.send(binary(&message)).await.is_err() {
                        return;
                    }
                }
                None => replies_open = false,
            },
            event = events.recv() => match event {
                Ok(event) => {
                    for message in event.to_proto(&session_id) {
                        if sink.send(binary(&message)).await.is_err() {
                            return;
                        }
                    }
                    if event.is_last() {
                        // Error replies already queued still go out before the close.
                        while let Ok(message) = replies.try_recv() {
                            let _ = sink.send(binary(&message)).await;
                        }
                        let _ = sink.send(close("session finished")).await;
                        return;
                    }
                }
                Err(RecvError::Lagged(skipped)) => {
                    let message = error_message(
                        ErrorCode::ResourceExhausted,
                        format!("{skipped} updates skipped: this client reads too slowly; the trajectory endpoint has them all"),
                    );
                    if sink.send(binary(&message)).await.is_err() {
                        return;
                    }
                }
                Err(RecvError::Closed) => {
                    let _ = sink.send(close("session closed")).await;
                    return;
                }
            },
        }
    }
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
