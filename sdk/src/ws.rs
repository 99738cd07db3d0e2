//! The WebSocket transport: `GET /v1/sessions/{id}/stream`, binary protobuf both ways.
//!
//! The socket is split into a writer task (frames channel → socket) and a reader task
//! (socket → updates channel), so a client that is busy sending still receives poses, and a
//! server that stops reading (a `wait` session with a full queue) blocks only the writer.

use futures_util::{SinkExt as _, StreamExt as _};
use relfusion_proto::Message as _;
use relfusion_proto::v1::{ClientMessage, ServerMessage};
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::client::IntoClientRequest as _;
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::{self, Message};

use crate::api::{Client, session_path};
use crate::error::ClientError;
use crate::link::{FRAME_CHANNEL, SessionLink, TaskGuard, UPDATE_CHANNEL};

/// Connects to the stream of the existing session `session_id`.
pub async fn connect(client: &Client, session_id: &str) -> Result<SessionLink, ClientError> {
    let mut url = client.url(&session_path(session_id, "stream"))?;
    let scheme = if url.scheme() == "https" { "wss" } else { "ws" };
    url.set_scheme(scheme).map_err(|()| ClientError::Url {
        url: url.to_string(),
        reason: "cannot switch to a WebSocket scheme".into(),
    })?;
    let mut request = url.as_str().into_client_request()?;
    if let Some(token) = client.token() {
        let value = HeaderValue::from_str(&format!("Bearer {token}"))
            .map_err(|e| ClientError::InvalidOption(format!("token: {e}")))?;
        request.headers_mut().insert("authorization", value);
    }
    // Nagle off: a pose update is small and latency is the point of a live stream.
    let connector = tokio_tungstenite::Connector::Rustls(client.tls());
    let (socket, _) = match tokio_tungstenite::connect_async_tls_with_config(
        request,
        None,
        true,
        Some(connector),
    )
    .await
    {
        Ok(ok) => ok,
        // The upgrade was refused with an HTTP answer: surface the server's JSON error.
        Err(tungstenite::Error::Http(resp)) => {
            let body = resp.body().clone().unwrap_or_default();
            return Err(ClientError::from_response(resp.status().as_u16(), &body));
        }
        Err(e) => return Err(e.into()),
    };
    let (mut sink, mut stream) = socket.split();
    let (frames_tx, mut frames_rx) = mpsc::channel::<ClientMessage>(FRAME_CHANNEL);
    let (updates_tx, updates_rx) = mpsc::channel(UPDATE_CHANNEL);

    let writer_errors = updates_tx.clone();
    let writer = tokio::spawn(async move {
        while let Some(msg) = frames_rx.recv().await {
            let bytes = msg.encode_to_vec();
            if let Err(e) = sink.send(Message::Binary(bytes.into())).await {
                let _ = writer_errors.send(Err(e.into())).await;
                return;
            }
        }
        // Every message is sent. The socket stays open: the server closes it once the session
        // has finished and the last updates are out.
    });
    let reader = tokio::spawn(async move {
        while let Some(item) = stream.next().await {
            let out = match item {
                Ok(Message::Binary(bytes)) => ServerMessage::decode(bytes)
                    .map_err(|e| ClientError::Protocol(format!("undecodable ServerMessage: {e}"))),
                Ok(Message::Text(text)) => Err(ClientError::Protocol(format!(
                    "unexpected text message on the stream: {}",
                    text.as_str().chars().take(300).collect::<String>()
                ))),
                Ok(Message::Close(_)) => break,
                Ok(_) => continue, // ping/pong: answered by tungstenite itself
                Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => {
                    break;
                }
                Err(e) => {
                    let _ = updates_tx.send(Err(e.into())).await;
                    break;
                }
            };
            if updates_tx.send(out).await.is_err() {
                break; // nobody listens any more
            }
        }
    });
    Ok(SessionLink {
        session_id: session_id.to_string(),
        info: None,
        frames: frames_tx,
        updates: updates_rx,
        tasks: TaskGuard(vec![writer, reader]),
    })
}
