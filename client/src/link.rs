//! A live session seen through some transport: protobuf `ClientMessage`s go in, protobuf
//! `ServerMessage`s come out.
//!
//! Every transport (WebSocket in [`crate::ws`], Zenoh in `zenoh_transport`) is reduced to the
//! same [`SessionLink`]: two bounded channels pumped by background tasks. The code that streams
//! a dataset, the CLI and the benchmark are written once against it, so a transport only has to
//! open a session and move messages. The frame channel is small on purpose: when the server
//! stops reading (a `wait` session whose queue is full) the sender feels it at once.

use relfusion_proto::v1::{
    ClientMessage, EndOfStream, Frame, ImageEncoding, ServerMessage, client_message,
};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::api::{Client, CreateSession, SessionInfo};
use crate::error::ClientError;

/// Frames buffered between the producer and the transport's writer.
pub const FRAME_CHANNEL: usize = 2;
/// Server messages buffered between the transport's reader and the consumer.
pub const UPDATE_CHANNEL: usize = 1024;

/// How frames reach the server and updates come back.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum Transport {
    /// `POST /v1/sessions` to open, then the session's WebSocket (`/v1/sessions/{id}/stream`).
    #[default]
    Http,
    /// Zenoh: the session is created through `relfusion/sessions/create` and frames/poses
    /// travel on its key space; `endpoint` is the router or peer to connect to
    /// (`tcp/127.0.0.1:7447`).
    Zenoh { endpoint: String },
}

/// An open session on some transport.
///
/// To end a stream cleanly send [`end_of_stream`], drop `frames`, and read `updates` until it
/// closes (the server closes the stream once the session is finished and its last updates are
/// out). `updates` closes only after every `frames` sender is gone, so keep none around.
#[derive(Debug)]
pub struct SessionLink {
    /// The server's session id.
    pub session_id: String,
    /// The session as created, when the transport reports it (HTTP does).
    pub info: Option<SessionInfo>,
    /// Frames and the end-of-stream marker, in order.
    pub frames: mpsc::Sender<ClientMessage>,
    /// Everything the server sends, then `None` once the stream is over. A transport failure
    /// arrives as one `Err` before the end.
    pub updates: mpsc::Receiver<Result<ServerMessage, ClientError>>,
    /// The transport's background tasks, aborted when this is dropped.
    pub tasks: TaskGuard,
}

/// Background tasks that must not outlive their owner (aborted on drop).
#[derive(Debug, Default)]
pub struct TaskGuard(pub Vec<JoinHandle<()>>);

impl Drop for TaskGuard {
    fn drop(&mut self) {
        for task in &self.0 {
            task.abort();
        }
    }
}

/// Creates a session as `req` says and connects to it over `transport`.
pub async fn open_session(
    client: &Client,
    transport: &Transport,
    req: &CreateSession,
) -> Result<SessionLink, ClientError> {
    match transport {
        Transport::Http => {
            let info = client.create_session(req).await?;
            let mut link = crate::ws::connect(client, &info.id).await?;
            link.info = Some(info);
            Ok(link)
        }
        Transport::Zenoh { endpoint } => open_zenoh(client, endpoint, req).await,
    }
}

/// The Zenoh transport ([`crate::zenoh_transport`]) as the client's user and token.
async fn open_zenoh(
    client: &Client,
    endpoint: &str,
    req: &CreateSession,
) -> Result<SessionLink, ClientError> {
    crate::zenoh_transport::open(endpoint, &client.zenoh_identity(), req).await
}

/// Image formats the server accepts, told apart by their magic bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    Jpeg,
    Png,
    Unknown,
}

/// The encoding of `bytes` from its first bytes (what the server does too: file names and
/// extensions are not trusted).
pub fn sniff_encoding(bytes: &[u8]) -> Encoding {
    if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
        Encoding::Jpeg
    } else if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Encoding::Png
    } else {
        Encoding::Unknown
    }
}

/// A protobuf `Frame` message for an encoded image.
pub fn frame_message(frame_id: u64, timestamp: f64, image: Vec<u8>) -> ClientMessage {
    let encoding = match sniff_encoding(&image) {
        Encoding::Jpeg => ImageEncoding::Jpeg,
        Encoding::Png => ImageEncoding::Png,
        Encoding::Unknown => ImageEncoding::Unspecified,
    };
    ClientMessage {
        message: Some(client_message::Message::Frame(Frame {
            frame_id,
            timestamp,
            image,
            encoding: encoding as i32,
            camera: None,
        })),
    }
}

/// The protobuf end-of-stream marker.
pub fn end_of_stream() -> ClientMessage {
    ClientMessage {
        message: Some(client_message::Message::EndOfStream(EndOfStream {})),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encodings_are_sniffed_from_magic_bytes() {
        assert_eq!(sniff_encoding(&[0xff, 0xd8, 0xff, 0xe0]), Encoding::Jpeg);
        assert_eq!(sniff_encoding(b"\x89PNG\r\n\x1a\n...."), Encoding::Png);
        assert_eq!(sniff_encoding(b"GIF89a"), Encoding::Unknown);
        assert_eq!(sniff_encoding(b""), Encoding::Unknown);
        let m = frame_message(7, 1.5, b"\x89PNG\r\n\x1a\nxx".to_vec());
        let Some(client_message::Message::Frame(f)) = m.message else {
            panic!("a frame message")
        };
        assert_eq!((f.frame_id, f.timestamp), (7, 1.5));
        assert_eq!(f.encoding, ImageEncoding::Png as i32);
    }
}
