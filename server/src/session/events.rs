//! What a session tells its subscribers (SSE as JSON, WebSocket and Zenoh as protobuf).

use relfusion_proto::v1;
use relfusion_slam::pipeline::TrackingState;
use serde::Serialize;

use super::types::{PoseJson, SessionInfo};
use crate::convert::{pose_json_to_proto, tracking_state_to_proto};

/// One event of a session's stream. Frame ids are the client's.
#[derive(Clone, Debug, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum SessionEvent {
    /// A frame was tracked (or lost).
    Pose {
        frame_id: u64,
        timestamp: f64,
        pose: PoseJson,
        state: TrackingState,
        is_keyframe: bool,
        keyframe_id: u64,
    },
    /// A keyframe was created.
    Keyframe {
        keyframe_id: u64,
        frame_id: u64,
        timestamp: f64,
        pose: PoseJson,
    },
    /// The pose graph moved keyframes: the current pose of every keyframe.
    KeyframePoses { poses: Vec<(u64, PoseJson)> },
    /// Frames were dropped because the stream outran the pipeline (running total).
    Dropped { frames_dropped: u64 },
    /// The session finished; results are final.
    Finished { info: SessionInfo },
    /// The session stopped with an error (or the server is shutting down).
    Failed { message: String },
}

impl SessionEvent {
    /// The event's name (`event:` of SSE).
    pub fn kind(&self) -> &'static str {
        match self {
            SessionEvent::Pose { .. } => "pose",
            SessionEvent::Keyframe { .. } => "keyframe",
            SessionEvent::KeyframePoses { .. } => "keyframe_poses",
            SessionEvent::Dropped { .. } => "dropped",
            SessionEvent::Finished { .. } => "finished",
            SessionEvent::Failed { .. } => "failed",
        }
    }

    /// Whether no event follows this one.
    pub fn is_last(&self) -> bool {
        matches!(
            self,
            SessionEvent::Finished { .. } | SessionEvent::Failed { .. }
        )
    }

    /// The protobuf message of the stream envelopes: Pose → `PoseUpdate`, Keyframe →
    /// `KeyframeUpdate` (pose only; the dense depth comes with the dense layer), Failed →
    /// `Error`; the others have no wire form.
    pub fn to_proto(&self, session_id: &str) -> Option<v1::ServerMessage> {
        use v1::server_message::Message;
        let message = match self {
            SessionEvent::Pose {
                frame_id,
                timestamp,
                pose,
                state,
                is_keyframe,
                ..
            } => Message::Pose(v1::PoseUpdate {
                session_id: session_id.to_string(),
                frame_id: *frame_id,
                timestamp: *timestamp,
                world_from_camera: Some(pose_json_to_proto(pose)),
                tracking_state: tracking_state_to_proto(*state) as i32,
                is_keyframe: *is_keyframe,
            }),
            SessionEvent::Keyframe {
                keyframe_id,
                frame_id,
                timestamp,
                pose,
            } => Message::Keyframe(v1::KeyframeUpdate {
                session_id: session_id.to_string(),
                keyframe_id: *keyframe_id,
                frame_id: *frame_id,
                timestamp: *timestamp,
                world_from_camera: Some(pose_json_to_proto(pose)),
                depth: None,
            }),
            SessionEvent::Failed { message } => Message::Error(v1::Error {
                code: v1::ErrorCode::Internal as i32,
                message: message.clone(),
            }),
            _ => return None,
        };
        Some(v1::ServerMessage {
            message: Some(message),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_and_proto_forms() {
        let pose = PoseJson {
            t: [1.0, 2.0, 3.0],
            q: [0.0, 0.0, 0.0, 1.0],
            s: 1.0,
        };
        let e = SessionEvent::Pose {
            frame_id: 7,
            timestamp: 1.5,
            pose,
            state: TrackingState::Tracking,
            is_keyframe: false,
            keyframe_id: 0,
        };
        let json = serde_json::to_value(&e).expect("json");
        assert_eq!(json["type"], "pose");
        assert_eq!(json["frame_id"], 7);
        assert_eq!(json["state"], "tracking");
        let Some(v1::ServerMessage {
            message: Some(v1::server_message::Message::Pose(p)),
        }) = e.to_proto("s-1")
        else {
            panic!("not a pose update");
        };
        assert_eq!((p.frame_id, p.session_id.as_str()), (7, "s-1"));
        assert!(
            SessionEvent::Dropped { frames_dropped: 1 }
                .to_proto("s")
                .is_none()
        );
    }
}
