//! relfusion-viz: a session for viewers, shared by the command line (`relfusion stream/run
//! --mcap --foxglove --rerun`) and the service (a session's `recording.mcap`).
//!
//! - [`session_log`]: what a viewer's log of a session is given ([`SessionLog`]).
//! - [`foxglove_log`]: MCAP files and the Foxglove WebSocket protocol, with Foxglove's schemas;
//!   [`foxglove_front`] lets viewers in with either name of the protocol.
//! - [`rerun_log`] (feature `rerun`): rerun `.rrd` recordings.
//! - [`clouds`]: what a log keeps of each keyframe, its points on disk, so that a rescaled
//!   keyframe is sent again.
//! - [`ros2`]: the session as ROS 2 messages (CDR, REP-2011 type hashes) for rmw_zenoh.
//! - [`pipeline_log`] (feature `pipeline`): the pipeline's events given to a [`SessionLog`].

pub mod clouds;
pub mod foxglove_front;
pub mod foxglove_log;
#[cfg(feature = "pipeline")]
pub mod pipeline_log;
#[cfg(feature = "rerun")]
pub mod rerun_log;
pub mod ros2;
pub mod session_log;

pub use session_log::SessionLog;
