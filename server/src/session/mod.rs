//! Sessions: one `slam::Pipeline` each, fed by a bounded frame queue (live) or an uploaded
//! dataset, on its own thread; events broadcast to subscribers; results in the store.
//!
//! - [`types`]: the JSON of sessions (create request, info, camera, policy) and the typed
//!   request it parses into.
//! - [`handle`]: [`Session`], the shared handle request handlers use.
//! - [`lifecycle`]: a session's status, its transitions and its one stop signal.
//! - [`input`]: frames into a live session: checked, decoded, queued.
//! - [`manager`]: [`SessionManager`]: sessions, uploads, recovery, retention, health.
//! - [`admission`]: slots, the upload queue, per-owner quotas, upload tickets.
//! - [`track`]: what a session has produced (poses, keyframes, mesh) and its result files.
//! - [`overrides`]: the per-session pipeline config (JSON merged over defaults).
//! - [`worker`]: the per-session pipeline thread.
//! - [`queue`]: the bounded frame queue (drop-oldest or wait).
//! - [`events`]: [`SessionEvent`] and its protobuf form.
//! - [`upload`]: safe archive extraction.
//! - [`persist`]: what is stored, under which keys.
//! - [`recording`]: the session's recording for Foxglove (`recording.mcap`).
//! - [`prior`]: the shared depth model, run on the GPU pool.
//! - [`decode`]: JPEG/PNG frame decoding and checks.

pub mod admission;
mod checkpoint;
pub mod decode;
mod engine;
pub mod events;
pub mod handle;
pub mod input;
pub(crate) mod lifecycle;
pub mod manager;
mod mesh_state;
pub mod outputs;
pub mod overrides;
pub mod persist;
mod pointcloud;
pub mod prior;
pub mod queue;
pub mod recording;
pub mod snapshot;
mod spill;
pub mod track;
pub mod types;
pub mod upload;
mod worker;

pub use events::{SessionEvent, mesh_block};
pub use handle::Session;
pub use manager::{NewUpload, SessionManager};
pub use overrides::merge_config;
pub use prior::{PooledPrior, SharedModel};
pub use types::{
    CameraJson, CreateSession, FrameData, FramePolicy, Owner, PoseJson, Progress, SessionId,
    SessionInfo, SessionKind, SessionRequest, SessionState,
};
pub use upload::ArchiveKind;
