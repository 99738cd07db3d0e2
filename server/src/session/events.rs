//! What a session tells its subscribers (SSE as JSON, WebSocket and Zenoh as protobuf).

use relfusion_proto::v1;
use std::sync::Arc;

use relfusion_slam::dense::{DenseKeyframe, DenseMode};
use relfusion_slam::fusion::{BlockIndex, BlockMesh, MeshDelta};
use relfusion_slam::pipeline::TrackingState;
use serde::Serialize;

use relfusion_slam::geometry::Sim3;

use super::types::{SessionInfo, SessionState, pose_as_json};
use crate::convert::{camera_to_proto, sim3_to_proto, tracking_state_to_proto};

/// A keyframe's pose after a pose-graph optimisation.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct KeyframePose {
    pub keyframe_id: u64,
    /// The (client's) frame the keyframe was made from.
    pub frame_id: u64,
    pub timestamp: f64,
    #[serde(serialize_with = "pose_as_json")]
    pub pose: Sim3,
}

/// One event of a session's stream. Frame ids are the client's.
#[derive(Clone, Debug, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum SessionEvent {
    /// A frame was tracked (or lost).
    Pose {
        frame_id: u64,
        timestamp: f64,
        #[serde(serialize_with = "pose_as_json")]
        pose: Sim3,
        state: TrackingState,
        is_keyframe: bool,
        keyframe_id: u64,
    },
    /// A keyframe was created.
    Keyframe {
        keyframe_id: u64,
        frame_id: u64,
        timestamp: f64,
        #[serde(serialize_with = "pose_as_json")]
        pose: Sim3,
    },
    /// The pose graph moved keyframes (loop closure, final optimisation): the current pose of
    /// every keyframe, so subscribers can re-anchor the frames tracked against them.
    KeyframePoses { poses: Vec<KeyframePose> },
    /// The dense layer finished a keyframe (its dense inverse depth and variance travel only
    /// on the WebSocket and Zenoh, as `KeyframeUpdate.depth`; SSE gets the summary).
    KeyframeDensified {
        keyframe_id: u64,
        frame_id: u64,
        timestamp: f64,
        #[serde(serialize_with = "pose_as_json")]
        pose: Sim3,
        mode: DenseMode,
        width: usize,
        height: usize,
        #[serde(skip)]
        dense: Arc<DenseKeyframe>,
    },
    /// The fused mesh changed: the blocks' new triangles travel on the WebSocket and on Zenoh
    /// (`MeshUpdate` on `…/mesh`); SSE gets the summary.
    MeshUpdated {
        revision: u64,
        changed_blocks: usize,
        removed_blocks: usize,
        #[serde(skip)]
        delta: Arc<MeshDelta>,
    },
    /// Frames were dropped because the stream outran the pipeline (running total).
    Dropped { frames_dropped: u64 },
    /// The session finished; results are final.
    Finished { info: Box<SessionInfo> },
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
            SessionEvent::KeyframeDensified { .. } => "keyframe_densified",
            SessionEvent::MeshUpdated { .. } => "mesh",
            SessionEvent::Dropped { .. } => "dropped",
            SessionEvent::Finished { .. } => "finished",
            SessionEvent::Failed { .. } => "failed",
        }
    }

    /// The last event of an ended session with this info: `Failed` with its error, else
    /// `Finished`.
    pub fn last_of(info: SessionInfo) -> Self {
        if info.state == SessionState::Failed {
            SessionEvent::Failed {
                message: info.error.clone().unwrap_or_default(),
            }
        } else {
            SessionEvent::Finished {
                info: Box::new(info),
            }
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
    /// `KeyframeUpdate` (pose only), KeyframeDensified → `KeyframeUpdate` with its depth,
    /// MeshUpdated → `MeshUpdate`, Failed → `Error`; the others have no wire form.
    pub fn to_proto(&self, session_id: &str) -> Vec<v1::ServerMessage> {
        use v1::server_message::Message;
        let keyframe = |keyframe_id: u64, frame_id: u64, timestamp: f64, pose: &Sim3| {
            Message::Keyframe(v1::KeyframeUpdate {
                session_id: session_id.to_string(),
                keyframe_id,
                frame_id,
                timestamp,
                world_from_camera: Some(sim3_to_proto(pose)),
                depth: None,
            })
        };
        let messages = match self {
            SessionEvent::Pose {
                frame_id,
                timestamp,
                pose,
                state,
                is_keyframe,
                keyframe_id,
            } => vec![Message::Pose(v1::PoseUpdate {
                session_id: session_id.to_string(),
                frame_id: *frame_id,
                timestamp: *timestamp,
                world_from_camera: Some(sim3_to_proto(pose)),
                tracking_state: tracking_state_to_proto(*state) as i32,
                is_keyframe: *is_keyframe,
                keyframe_id: *keyframe_id,
            })],
            SessionEvent::Keyframe {
                keyframe_id,
                frame_id,
                timestamp,
                pose,
            } => vec![keyframe(*keyframe_id, *frame_id, *timestamp, pose)],
            // KeyframeUpdate without depth = "only the pose changed" (updates.proto).
            SessionEvent::KeyframePoses { poses } => poses
                .iter()
                .map(|k| keyframe(k.keyframe_id, k.frame_id, k.timestamp, &k.pose))
                .collect(),
            SessionEvent::KeyframeDensified {
                keyframe_id,
                frame_id,
                timestamp,
                pose,
                dense,
                ..
            } => vec![Message::Keyframe(v1::KeyframeUpdate {
                session_id: session_id.to_string(),
                keyframe_id: *keyframe_id,
                frame_id: *frame_id,
                timestamp: *timestamp,
                world_from_camera: Some(sim3_to_proto(pose)),
                depth: Some(keyframe_depth(dense)),
            })],
            SessionEvent::MeshUpdated { delta, .. } => {
                vec![Message::Mesh(mesh_update(session_id, delta))]
            }
            SessionEvent::Failed { message } => vec![Message::Error(v1::Error {
                code: v1::ErrorCode::Internal as i32,
                message: message.clone(),
            })],
            SessionEvent::Dropped { .. } | SessionEvent::Finished { .. } => Vec::new(),
        };
        messages
            .into_iter()
            .map(|message| v1::ServerMessage {
                message: Some(message),
            })
            .collect()
    }
}

/// The wire form of a mesh delta.
pub fn mesh_update(session_id: &str, delta: &MeshDelta) -> v1::MeshUpdate {
    v1::MeshUpdate {
        session_id: session_id.to_string(),
        revision: delta.revision,
        changed_blocks: delta.changed.iter().map(mesh_block).collect(),
        removed_blocks: delta.removed.iter().map(|b| block_index(*b)).collect(),
        block_size: delta.block_size,
    }
}

fn block_index(b: BlockIndex) -> v1::BlockIndex {
    v1::BlockIndex {
        x: b.x,
        y: b.y,
        z: b.z,
    }
}

/// One block's triangles as `updates.proto` packs them (little-endian f32 triplets, RGB bytes).
pub fn mesh_block(m: &BlockMesh) -> v1::MeshBlock {
    let floats = |v: &[[f32; 3]]| {
        v.iter()
            .flatten()
            .flat_map(|c| c.to_le_bytes())
            .collect::<Vec<u8>>()
    };
    v1::MeshBlock {
        index: Some(block_index(m.index)),
        vertices: floats(&m.positions),
        colors: m.colors.iter().flatten().copied().collect(),
        normals: floats(&m.normals),
        indices: m.indices.clone(),
    }
}

/// The wire form of a dense keyframe: little-endian f32 maps plus the camera they belong to.
fn keyframe_depth(dense: &DenseKeyframe) -> v1::KeyframeDepth {
    let bytes = |data: &[f32]| {
        data.iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>()
    };
    v1::KeyframeDepth {
        width: dense.idepth.width as u32,
        height: dense.idepth.height as u32,
        inverse_depth: bytes(&dense.idepth.data),
        variance: bytes(&dense.variance.data),
        camera: Some(camera_to_proto(&dense.camera)),
        mode: match dense.mode {
            DenseMode::Prior => v1::DenseMode::Prior,
            DenseMode::NoModel => v1::DenseMode::NoModel,
        } as i32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_and_proto_forms() {
        let pose = Sim3::new(
            relfusion_slam::geometry::SO3::identity(),
            nalgebra::Vector3::new(1.0, 2.0, 3.0),
            1.0,
        );
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
        assert_eq!(json["pose"]["t"], serde_json::json!([1.0, 2.0, 3.0]));
        assert_eq!(json["pose"]["q"], serde_json::json!([0.0, 0.0, 0.0, 1.0]));
        let messages = e.to_proto("s-1");
        let [
            v1::ServerMessage {
                message: Some(v1::server_message::Message::Pose(p)),
            },
        ] = messages.as_slice()
        else {
            panic!("not one pose update");
        };
        assert_eq!((p.frame_id, p.session_id.as_str()), (7, "s-1"));
        assert!(
            SessionEvent::Dropped { frames_dropped: 1 }
                .to_proto("s")
                .is_empty()
        );
        let moved = SessionEvent::KeyframePoses {
            poses: vec![
                KeyframePose {
                    keyframe_id: 0,
                    frame_id: 0,
                    timestamp: 1.0,
                    pose,
                },
                KeyframePose {
                    keyframe_id: 1,
                    frame_id: 9,
                    timestamp: 1.3,
                    pose,
                },
            ],
        };
        let updates = moved.to_proto("s");
        assert_eq!(
            updates.len(),
            2,
            "one pose-only KeyframeUpdate per keyframe"
        );
        let Some(v1::server_message::Message::Keyframe(k)) = &updates[1].message else {
            panic!("not a keyframe update");
        };
        assert_eq!((k.keyframe_id, k.frame_id), (1, 9));
        assert!(k.depth.is_none());
    }
}
