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

use axum::extract::ws::rejection::WebSocketUpgradeRejection;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade, close_code};
use axum::extract::{Extension, Path, State};
use axum::http::{HeaderMap, Uri};
use axum::response::Response;
use futures_util::stream::SplitSink;
use futures_util::{SinkExt, StreamExt};
use relfusion_proto::v1::{ErrorCode, ServerMessage};
use tokio::sync::broadcast::{self, error::RecvError};
use tokio::sync::mpsc;

use super::auth::Auth;
use super::error::ErrorBody;
use super::serve::ConnectionSlot;
use super::streams::{KeepAliveClock, LastHeard, open_stream};
use super::ws::{
    CLOSE_GRACE, Held, REPLY_QUEUE, binary, checked_upgrade, error_message, keep_alive,
    receive_loop, sized,
};
use crate::locator::{Hop, Located};
use crate::session::{Session, SessionEvent};
use crate::{ApiError, AppState};

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
        Ok(Held::new(
            connection.map(|Extension(slot)| slot),
            open_stream(state, &owner, &id)?,
            Duration::from_secs(state.config.http.stream_idle_timeout_s),
        ))
    };
    let session = match state.locator.locate(&id, &owner, Hop::of(&headers)).await? {
        Located::Here(session) => session,
        // Its node checks the token.
        Located::Elsewhere(remote) => {
            let upgrade = checked_upgrade(upgrade, &id)?;
            let held = hold(&state)?;
            let authorization = super::auth::relayed_authorization(&headers, &uri);
            return super::stream_remote::open(&state, remote, authorization, upgrade, held).await;
        }
    };
    let upgrade = checked_upgrade(upgrade, &id)?;
    let held = hold(&state)?;
    // Subscribe before the 101 goes out: a client that fetches the map snapshot once the socket
    // is open (a viewer joining late) then sees every later update, with no gap.
    let events = session.subscribe();
    Ok(sized(upgrade, &state).on_upgrade(move |socket| serve(socket, session, events, held)))
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
