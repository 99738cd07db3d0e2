//! relfusion-sdk: the client library of `relfusiond`, everything `relfusion stream`, `upload`,
//! `fetch` and `bench serve` do, as Rust functions. It builds without the pipeline (no wgpu, no
//! ONNX Runtime) and without test tools: the camera and dataset types come from
//! `relfusion-core`.
//!
//! - [`Client`] ([`api`]): one method per HTTP route (`/v1/sessions`, frames, downloads, ...);
//!   failures are [`ClientError`]s with the server's `{"error":{code,message}}` parsed.
//! - [`link`]: a live session as two channels (protobuf frames in, protobuf updates out)
//!   whatever the transport: WebSocket ([`ws`]) or Zenoh ([`zenoh_transport`]), chosen in
//!   [`transport`]; [`message`] builds what goes in.
//! - [`dataset_stream::stream_dataset`]: a TUM-layout sequence streamed like a camera.
//! - [`upload::upload_dataset`]: a dataset as a tar archive built on the fly.
//! - [`fetch::fetch`]: a session's results into a folder.

pub mod api;
pub mod dataset_stream;
pub mod error;
pub mod fetch;
pub mod link;
pub mod message;
pub mod tls;
pub mod transport;
pub mod upload;
pub mod ws;
pub mod zenoh_transport;

pub use api::{
    CameraJson, Client, CreateSession, FramePolicy, MapInfo, MapMode, MapStart, SessionInfo,
    SessionKind, SessionState, camera_json,
};
pub use dataset_stream::{Pace, StreamEvent, StreamOptions, StreamSummary, stream_dataset};
pub use error::ClientError;
pub use fetch::{Fetched, fetch};
pub use link::SessionLink;
pub use transport::{Transport, open_session};
pub use upload::{UploadOptions, upload_dataset};
