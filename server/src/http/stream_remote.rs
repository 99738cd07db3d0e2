//! The WebSocket stream of a session another node of the cluster runs
//! ([`crate::locator::Remote`]): the same protocol as [`super::stream_ws`], with frames handed
//! to the owner one at a time (the next read only once the owner took the last: the `wait`
//! policy pushes back through both nodes) and the owner's updates relayed back.
//!
//! When the owner leaves the cluster, the client gets an `Error` (UNAVAILABLE-like
//! `RESOURCE_EXHAUSTED` code, with the reason) and a close with code 1011.

use std::sync::Arc;

use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade, close_code};
use axum::response::Response;
use futures_util::stream::SplitSink;
use futures_util::{SinkExt, StreamExt};
use relfusion_proto::v1::{ErrorCode, ServerMessage};
use tokio::sync::mpsc;

use super::streams::{KeepAliveClock, LastHeard};
use super::ws::{
    CLOSE_GRACE, Held, REPLY_QUEUE, binary, error_message, keep_alive, receive_loop, sized,
};
use crate::locator::{Feed, RelayFormat, Remote, Update};
use crate::{ApiError, AppState};

/// Starts following the session on its node, then upgrades.
pub(super) async fn open(
    state: &Arc<AppState>,
    remote: Remote,
    authorization: Option<String>,
    upgrade: WebSocketUpgrade,
    held: Held,
) -> Result<Response, ApiError> {
    let limit = state.config.limits.event_buffer;
    let feed = remote
        .follow(authorization.clone(), limit, RelayFormat::Protobuf)
        .await?;
    Ok(sized(upgrade, state)
        .on_upgrade(move |socket| serve(socket, remote, authorization, feed, held)))
}

async fn serve(
    socket: WebSocket,
    remote: Remote,
    authorization: Option<String>,
    feed: Feed,
    held: Held,
) {
    let (sink, incoming) = socket.split();
    let (reply_tx, reply_rx) = mpsc::channel(REPLY_QUEUE);
    let heard = LastHeard::now();
    let keepalive = KeepAliveClock::new(heard.clone(), held.idle);
    let mut send_task = tokio::spawn(send_loop(sink, feed, reply_rx, keepalive));
    let to = remote.clone();
    let mut receive_task = tokio::spawn(receive_loop(incoming, reply_tx, heard, move |data| {
        let (to, authorization) = (to.clone(), authorization.clone());
        async move { to.push(authorization, data.to_vec()).await }
    }));
    tokio::select! {
        _ = &mut send_task => {
            if tokio::time::timeout(CLOSE_GRACE, &mut receive_task).await.is_err() {
                receive_task.abort();
            }
        }
        _ = &mut receive_task => send_task.abort(),
    }
    drop(held);
    tracing::debug!(session = %remote.id(), node = %remote.node(), "relayed websocket closed");
}

fn close(code: u16, reason: String) -> Message {
    Message::Close(Some(CloseFrame {
        code,
        reason: reason.into(),
    }))
}

async fn send_loop(
    mut sink: SplitSink<WebSocket, Message>,
    mut feed: Feed,
    mut replies: mpsc::Receiver<ServerMessage>,
    mut keepalive: KeepAliveClock,
) {
    if feed.already_ended() {
        let _ = sink
            .send(close(close_code::NORMAL, "session already finished".into()))
            .await;
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
            update = feed.next() => match update {
                Update::Message(bytes) => {
                    if sink.send(Message::Binary(bytes.into())).await.is_err() {
                        return;
                    }
                }
                Update::End => {
                    while let Ok(message) = replies.try_recv() {
                        let _ = sink.send(binary(&message)).await;
                    }
                    let _ = sink.send(close(close_code::NORMAL, "session finished".into())).await;
                    return;
                }
                Update::NodeLeft(reason) => {
                    let message = error_message(ErrorCode::ResourceExhausted, reason);
                    let _ = sink.send(binary(&message)).await;
                    let _ = sink.send(close(close_code::ERROR, "the session's node left".into())).await;
                    return;
                }
                Update::Lost => return,
            },
        }
    }
}
