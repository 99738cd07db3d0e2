//! The WebSocket stream of a session another node of the cluster runs (see
//! [`crate::cluster::relay`]): the same protocol as [`super::stream_ws`], with frames handed
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

use super::stream_ws::{
    CLOSE_GRACE, Held, REPLY_QUEUE, binary, error_message, keep_alive, receive_loop, sized,
};
use super::streams::{KeepAliveClock, LastHeard};
use crate::cluster::Cluster;
use crate::cluster::relay::{Relay, Relayed, relayed};
use crate::{ApiError, AppState};

/// Starts the owner's relay, then upgrades.
pub(super) async fn open(
    state: &Arc<AppState>,
    node: String,
    id: String,
    authorization: Option<String>,
    upgrade: WebSocketUpgrade,
    held: Held,
) -> Result<Response, ApiError> {
    let cluster = state.cluster.clone();
    let relay = cluster
        .watch(
            &node,
            &id,
            authorization.clone(),
            state.config.limits.event_buffer,
            crate::cluster::relay::RelayFormat::Protobuf,
        )
        .await?;
    let stream = Stream {
        cluster,
        node,
        id,
        authorization,
    };
    Ok(sized(upgrade, state).on_upgrade(move |socket| serve(socket, stream, relay, held)))
}

/// Where this stream's session runs.
#[derive(Clone)]
struct Stream {
    cluster: Arc<Cluster>,
    node: String,
    id: String,
    authorization: Option<String>,
}

async fn serve(socket: WebSocket, stream: Stream, relay: Relay, held: Held) {
    let (sink, incoming) = socket.split();
    let (reply_tx, reply_rx) = mpsc::channel(REPLY_QUEUE);
    let heard = LastHeard::now();
    let keepalive = KeepAliveClock::new(heard.clone(), held.idle);
    let mut send_task = tokio::spawn(send_loop(sink, stream.clone(), relay, reply_rx, keepalive));
    let to = stream.clone();
    let mut receive_task = tokio::spawn(receive_loop(incoming, reply_tx, heard, move |data| {
        let to = to.clone();
        async move {
            let auth = to.authorization.clone();
            to.cluster.push(&to.node, &to.id, auth, data.to_vec()).await
        }
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
    tracing::debug!(session = %stream.id, node = %stream.node, "relayed websocket closed");
}

fn close(code: u16, reason: String) -> Message {
    Message::Close(Some(CloseFrame {
        code,
        reason: reason.into(),
    }))
}

async fn send_loop(
    mut sink: SplitSink<WebSocket, Message>,
    stream: Stream,
    relay: Relay,
    mut replies: mpsc::Receiver<ServerMessage>,
    mut keepalive: KeepAliveClock,
) {
    if relay.ended {
        let _ = sink
            .send(close(close_code::NORMAL, "session already finished".into()))
            .await;
        return;
    }
    let mut departures = stream.cluster.departures();
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
            sample = relay.subscriber.recv_async() => match sample.as_ref().map(relayed) {
                Ok(Relayed::Message(bytes)) => {
                    if sink.send(Message::Binary(bytes.into())).await.is_err() {
                        return;
                    }
                }
                Ok(Relayed::End) => {
                    while let Ok(message) = replies.try_recv() {
                        let _ = sink.send(binary(&message)).await;
                    }
                    let _ = sink.send(close(close_code::NORMAL, "session finished".into())).await;
                    return;
                }
                Err(_) => return,
            },
            left = departures.recv() => {
                if left.as_deref().is_ok_and(|n| *n == stream.node) {
                    let reason = format!(
                        "node {} running this session left the cluster: the session ended \
                         (results up to its last checkpoint are kept)",
                        stream.node
                    );
                    let message = error_message(ErrorCode::ResourceExhausted, reason.clone());
                    let _ = sink.send(binary(&message)).await;
                    let _ = sink.send(close(close_code::ERROR, "the session's node left".into())).await;
                    return;
                }
            }
        }
    }
}
