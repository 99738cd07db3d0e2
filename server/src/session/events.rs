//! What a session tells its subscribers (SSE as JSON, WebSocket and Zenoh as protobuf): the
//! pipeline's own events (`relfusion_slam::pipeline::Event`, whose frame ids are the client's:
//! the pipeline echoes them), plus what only a session knows. This module holds the two wire
//! forms of them, JSON ([`SessionEvent`]'s `Serialize`) and protobuf ([`SessionEvent::to_proto`]).

use relfusion_proto::v1;

use relfusion_slam::dense::{DenseKeyframe, DenseMode};
use relfusion_slam::fusion::{BlockIndex, BlockMesh, MeshDelta};
use relfusion_slam::pipeline::{Event, KeyframePose, TrackingState};
use serde::{Serialize, Serializer};

use relfusion_slam::geometry::Sim3;

use super::types::{SessionInfo, SessionState, pose_as_json};
use crate::convert::{camera_to_proto, sim3_to_proto, tracking_state_to_proto};

/// One event of a session's stream.
#[derive(Clone, Debug)]
pub enum SessionEvent {
    /// What the pipeline reported: a frame's pose, a new keyframe, keyframes the pose graph
    /// moved (those of the session's own frames: a saved map's keyframes are not listed), a
    /// densified keyframe (its dense inverse depth and variance travel only on the WebSocket
    /// and Zenoh, as `KeyframeUpdate.depth`; SSE gets the summary), a mesh delta (its blocks'
    /// triangles on the WebSocket and Zenoh, as `MeshUpdate`; SSE gets the summary).
    Pipeline(Event),
    /// Frames were dropped because the stream outran the pipeline (running total).
    Dropped { frames_dropped: u64 },
    /// The session finished; results are final.
    Finished { info: Box<SessionInfo> },
    /// The session stopped with an error (or the server is shutting down).
    Failed { message: String },
}

/// The JSON form of a pose (`{t, q, s}`) behind a reference.
fn pose_ref<S: Serializer>(pose: &&Sim3, s: S) -> Result<S::Ok, S::Error> {
    pose_as_json(pose, s)
}

/// A keyframe's pose as SSE sends it.
#[derive(Serialize)]
struct KeyframeJson<'a> {
    keyframe_id: u64,
    frame_id: u64,
    timestamp: f64,
    #[serde(serialize_with = "pose_ref")]
    pose: &'a Sim3,
}

impl<'a> From<&'a KeyframePose> for KeyframeJson<'a> {
    fn from(k: &'a KeyframePose) -> Self {
        KeyframeJson {
            keyframe_id: k.keyframe_id as u64,
            frame_id: k.frame_id.unwrap_or(0),
            timestamp: k.timestamp,
            pose: &k.world_from_keyframe,
        }
    }
}

/// The JSON form of a [`SessionEvent`] (SSE's `data:`).
#[derive(Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
enum Json<'a> {
    Pose {
        frame_id: u64,
        timestamp: f64,
        #[serde(serialize_with = "pose_ref")]
        pose: &'a Sim3,
        state: TrackingState,
        is_keyframe: bool,
        keyframe_id: u64,
    },
    Keyframe(KeyframeJson<'a>),
    KeyframePoses {
        poses: Vec<KeyframeJson<'a>>,
    },
    KeyframeDensified {
        #[serde(flatten)]
        keyframe: KeyframeJson<'a>,
        mode: DenseMode,
        width: usize,
        height: usize,
    },
    MeshUpdated {
        revision: u64,
        changed_blocks: usize,
        removed_blocks: usize,
    },
    Dropped {
        frames_dropped: u64,
    },
    Finished {
        info: &'a SessionInfo,
    },
    Failed {
        message: &'a str,
    },
}

impl Serialize for SessionEvent {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let json = match self {
            SessionEvent::Pipeline(Event::Pose(p)) => Json::Pose {
                frame_id: p.frame_id,
                timestamp: p.timestamp,
                pose: &p.world_from_camera,
                state: p.state,
                is_keyframe: p.is_keyframe,
                keyframe_id: p.keyframe_id as u64,
            },
            SessionEvent::Pipeline(Event::Keyframe(k)) => Json::Keyframe(KeyframeJson {
                keyframe_id: k.keyframe_id as u64,
                frame_id: k.frame_id,
                timestamp: k.timestamp,
                pose: &k.world_from_keyframe,
            }),
            SessionEvent::Pipeline(Event::KeyframePoses { poses }) => Json::KeyframePoses {
                poses: poses.iter().map(KeyframeJson::from).collect(),
            },
            SessionEvent::Pipeline(Event::KeyframeDensified {
                keyframe_id,
                frame_id,
                keyframe,
                ..
            }) => Json::KeyframeDensified {
                keyframe: KeyframeJson {
                    keyframe_id: *keyframe_id as u64,
                    frame_id: frame_id.unwrap_or(0),
                    timestamp: keyframe.timestamp,
                    pose: &keyframe.world_from_keyframe,
                },
                mode: keyframe.mode,
                width: keyframe.idepth.width,
                height: keyframe.idepth.height,
            },
            SessionEvent::Pipeline(Event::MeshUpdated { delta, .. }) => Json::MeshUpdated {
                revision: delta.revision,
                changed_blocks: delta.changed.len(),
                removed_blocks: delta.removed.len(),
            },
            SessionEvent::Dropped { frames_dropped } => Json::Dropped {
                frames_dropped: *frames_dropped,
            },
            SessionEvent::Finished { info } => Json::Finished { info },
            SessionEvent::Failed { message } => Json::Failed { message },
        };
        json.serialize(s)
    }
}

impl SessionEvent {
    /// The event's name (`event:` of SSE).
    pub fn kind(&self) -> &'static str {
        match self {
            SessionEvent::Pipeline(Event::Pose(_)) => "pose",
            SessionEvent::Pipeline(Event::Keyframe(_)) => "keyframe",
            SessionEvent::Pipeline(Event::KeyframePoses { .. }) => "keyframe_poses",
            SessionEvent::Pipeline(Event::KeyframeDensified { .. }) => "keyframe_densified",
            SessionEvent::Pipeline(Event::MeshUpdated { .. }) => "mesh",
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

    /// The protobuf message of the stream envelopes: a pose → `PoseUpdate`, a keyframe →
    /// `KeyframeUpdate` (pose only), keyframe poses → one pose-only `KeyframeUpdate` each, a
    /// densified keyframe → `KeyframeUpdate` with its depth, a mesh delta → `MeshUpdate`,
    /// Failed → `Error`; the others have no wire form.
    pub fn to_proto(&self, session_id: &str) -> Vec<v1::ServerMessage> {
        use v1::server_message::Message;
        let keyframe =
            |keyframe_id: usize, frame_id: u64, timestamp: f64, pose: &Sim3| v1::KeyframeUpdate {
                session_id: session_id.to_string(),
                keyframe_id: keyframe_id as u64,
                frame_id,
                timestamp,
                world_from_camera: Some(sim3_to_proto(pose)),
                depth: None,
            };
        let messages = match self {
            SessionEvent::Pipeline(Event::Pose(p)) => vec![Message::Pose(v1::PoseUpdate {
                session_id: session_id.to_string(),
                frame_id: p.frame_id,
                timestamp: p.timestamp,
                world_from_camera: Some(sim3_to_proto(&p.world_from_camera)),
                tracking_state: tracking_state_to_proto(p.state) as i32,
                is_keyframe: p.is_keyframe,
                keyframe_id: p.keyframe_id as u64,
            })],
            SessionEvent::Pipeline(Event::Keyframe(k)) => vec![Message::Keyframe(keyframe(
                k.keyframe_id,
                k.frame_id,
                k.timestamp,
                &k.world_from_keyframe,
            ))],
            // KeyframeUpdate without depth = "only the pose changed" (updates.proto).
            SessionEvent::Pipeline(Event::KeyframePoses { poses }) => poses
                .iter()
                .map(|k| {
                    Message::Keyframe(keyframe(
                        k.keyframe_id,
                        k.frame_id.unwrap_or(0),
                        k.timestamp,
                        &k.world_from_keyframe,
                    ))
                })
                .collect(),
            SessionEvent::Pipeline(Event::KeyframeDensified {
                keyframe_id,
                frame_id,
                keyframe: dense,
                ..
            }) => vec![Message::Keyframe(v1::KeyframeUpdate {
                depth: Some(keyframe_depth(dense)),
                ..keyframe(
                    *keyframe_id,
                    frame_id.unwrap_or(0),
                    dense.timestamp,
                    &dense.world_from_keyframe,
                )
            })],
            SessionEvent::Pipeline(Event::MeshUpdated { delta, .. }) => {
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
    use relfusion_slam::pipeline::{KeyframeEvent, PoseEvent};
    use serde_json::json;

    #[test]
    fn json_and_proto_forms() {
        let pose = Sim3::new(
            relfusion_slam::geometry::SO3::identity(),
            nalgebra::Vector3::new(1.0, 2.0, 3.0),
            1.0,
        );
        let pose_json = json!({"t": [1.0, 2.0, 3.0], "q": [0.0, 0.0, 0.0, 1.0], "s": 1.0});
        let e = SessionEvent::Pipeline(Event::Pose(PoseEvent {
            frame_id: 7,
            timestamp: 1.5,
            world_from_camera: pose,
            state: TrackingState::Tracking,
            keyframe_id: 0,
            is_keyframe: false,
        }));
        assert_eq!(
            serde_json::to_value(&e).expect("json"),
            json!({"type": "pose", "frame_id": 7, "timestamp": 1.5, "pose": pose_json,
                   "state": "tracking", "is_keyframe": false, "keyframe_id": 0})
        );
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
        let keyframe = SessionEvent::Pipeline(Event::Keyframe(KeyframeEvent {
            keyframe_id: 2,
            frame_id: 9,
            timestamp: 1.3,
            world_from_keyframe: pose,
        }));
        assert_eq!(
            serde_json::to_value(&keyframe).expect("json"),
            json!({"type": "keyframe", "keyframe_id": 2, "frame_id": 9, "timestamp": 1.3,
                   "pose": pose_json})
        );
        let moved = SessionEvent::Pipeline(Event::KeyframePoses {
            poses: vec![
                KeyframePose {
                    keyframe_id: 0,
                    frame_id: Some(0),
                    timestamp: 1.0,
                    world_from_keyframe: pose,
                },
                KeyframePose {
                    keyframe_id: 1,
                    frame_id: Some(9),
                    timestamp: 1.3,
                    world_from_keyframe: pose,
                },
            ],
        });
        assert_eq!(
            serde_json::to_value(&moved).expect("json"),
            json!({"type": "keyframe_poses", "poses": [
                {"keyframe_id": 0, "frame_id": 0, "timestamp": 1.0, "pose": pose_json},
                {"keyframe_id": 1, "frame_id": 9, "timestamp": 1.3, "pose": pose_json},
            ]})
        );
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
        assert_eq!(
            serde_json::to_value(SessionEvent::Failed {
                message: "gone".into()
            })
            .expect("json"),
            json!({"type": "failed", "message": "gone"})
        );
    }
}
