//! A live session seen through some transport: protobuf `ClientMessage`s go in, protobuf
//! `ServerMessage`s come out.
//!
//! Every transport (WebSocket in [`crate::ws`], Zenoh in [`crate::zenoh_transport`]; chosen in
//! [`crate::transport`]) is reduced to the
//! same [`SessionLink`]: two bounded channels pumped by background tasks. The code that streams
//! a dataset, the CLI and the benchmark are written once against it, so a transport only has to
//! open a session and move messages. The frame channel is small on purpose: when the server
//! stops reading (a `wait` session whose queue is full) the sender feels it at once.

use relfusion_proto::v1::{ClientMessage, ServerMessage};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::api::SessionInfo;
use crate::error::ClientError;

/// Frames buffered between the producer and the transport's writer.
pub const FRAME_CHANNEL: usize = 2;
/// Server messages buffered between the transport's reader and the consumer.
pub const UPDATE_CHANNEL: usize = 1024;

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
