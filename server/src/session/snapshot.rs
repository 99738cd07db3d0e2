//! A session's whole map as it stands, as a protobuf `MapSnapshot` (trajectory, keyframes,
//! mesh blocks): what the Zenoh map queryable and `GET /v1/sessions/{id}/map` serve. Poses are
//! those of the downloadable TUM files, value for value.
//!
//! The protobuf is encoded with the mesh streamed into it ([`snapshot_bytes`]): the mesh of a
//! long session is read back a slab of spilled chunks at a time and each block encoded into
//! the message as it comes, so the message is the only whole copy (issue 37), bytes identical
//! to encoding the [`snapshot`] message.

use relfusion_proto::Message as _;
use relfusion_proto::v1::{self, MapSnapshot, StampedPose};
use relfusion_slam::geometry::Sim3;

use super::outputs::Poses;
use super::{Session, SessionState, mesh_block};
use crate::ApiError;
use crate::convert::sim3_to_proto;

/// The session's map as it stands (final once the session has finished), as a message (the
/// JSON form; [`snapshot_bytes`] encodes the same without holding the mesh twice).
pub fn snapshot(session: &Session) -> Result<MapSnapshot, ApiError> {
    let mut snapshot = without_mesh(session)?;
    let mut blocks = Vec::new();
    let (mesh_revision, block_size) = session
        .each_mesh_block(&mut |b| blocks.push(mesh_block(b)))
        .map_err(ApiError::internal)?;
    snapshot.mesh_blocks = blocks;
    snapshot.mesh_revision = mesh_revision;
    snapshot.block_size = block_size;
    Ok(snapshot)
}

/// [`snapshot`] encoded as protobuf: the fields before the mesh, then each mesh block encoded
/// into the message as it is read, then the fields after it. A message is its fields in tag
/// order, so these are the bytes of encoding the whole message at once.
pub fn snapshot_bytes(session: &Session) -> Result<Vec<u8>, ApiError> {
    let (head, mut tail) = split_at_mesh(&without_mesh(session)?);
    let mut out = head.encode_to_vec();
    let (mesh_revision, block_size) = session
        .each_mesh_block(&mut |b| {
            prost::encoding::message::encode(MESH_BLOCKS_TAG, &mesh_block(b), &mut out)
        })
        .map_err(ApiError::internal)?;
    tail.mesh_revision = mesh_revision;
    tail.block_size = block_size;
    tail.encode(&mut out).expect("a Vec grows");
    Ok(out)
}

/// `mesh_blocks` in `MapSnapshot` (updates.proto).
const MESH_BLOCKS_TAG: u32 = 6;

/// The message's fields before `mesh_blocks`, and those after it.
fn split_at_mesh(snapshot: &MapSnapshot) -> (MapSnapshot, MapSnapshot) {
    let head = MapSnapshot {
        mesh_blocks: Vec::new(),
        block_size: 0.0,
        mesh_revision: 0,
        frames_received: 0,
        frames_dropped: 0,
        ..snapshot.clone()
    };
    let tail = MapSnapshot {
        block_size: snapshot.block_size,
        mesh_revision: snapshot.mesh_revision,
        frames_received: snapshot.frames_received,
        frames_dropped: snapshot.frames_dropped,
        ..MapSnapshot::default()
    };
    (head, tail)
}

/// Everything of the snapshot but its mesh (blocks, revision, block size).
fn without_mesh(session: &Session) -> Result<MapSnapshot, ApiError> {
    let info = session.info();
    Ok(MapSnapshot {
        session_id: info.id.clone(),
        state: state_name(info.state),
        frames_processed: info.frames_processed,
        frames_received: info.frames_received,
        frames_dropped: info.frames_dropped,
        trajectory: stamped_poses(session.trajectory().map_err(ApiError::internal)?)?,
        keyframes: stamped_poses(session.keyframes())?,
        ..MapSnapshot::default()
    })
}

/// The state as the HTTP API spells it (`"running"`, `"finished"`, ...).
pub fn state_name(state: SessionState) -> String {
    serde_json::to_value(state)
        .ok()
        .and_then(|v| v.as_str().map(String::from))
        .unwrap_or_default()
}

/// A session's poses on the wire: converted from the typed poses while it runs, parsed from
/// the stored file once it has ended (the same values either way: the files print every
/// `f64` exactly, and carry no scale).
fn stamped_poses(poses: Poses) -> Result<Vec<StampedPose>, ApiError> {
    match poses {
        Poses::Stored(text) => parse_tum(&text),
        Poses::Live(poses) => Ok(poses
            .iter()
            .map(|p| StampedPose {
                timestamp: p.timestamp,
                world_from_camera: Some(sim3_to_proto(&Sim3::from_se3(&p.world_from_camera, 1.0))),
            })
            .collect()),
    }
}

/// A stored TUM trajectory text → stamped poses, value for value (no re-normalisation: a client gets
/// exactly the numbers of the downloadable file).
fn parse_tum(text: &str) -> Result<Vec<StampedPose>, ApiError> {
    let mut poses = Vec::new();
    for (index, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let values: Vec<f64> = line
            .split([' ', '\t', ','])
            .filter(|f| !f.is_empty())
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|e| ApiError::internal(format!("trajectory line {}: {e}", index + 1)))?;
        let [timestamp, tx, ty, tz, qx, qy, qz, qw] = values[..] else {
            return Err(ApiError::internal(format!(
                "trajectory line {}: expected 8 values, got {}",
                index + 1,
                values.len()
            )));
        };
        poses.push(StampedPose {
            timestamp,
            world_from_camera: Some(v1::Sim3Pose {
                translation: Some(v1::Vector3 {
                    x: tx,
                    y: ty,
                    z: tz,
                }),
                rotation: Some(v1::Quaternion {
                    x: qx,
                    y: qy,
                    z: qz,
                    w: qw,
                }),
                scale: 1.0,
            }),
        });
    }
    Ok(poses)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mesh_streamed_into_the_message_gives_its_own_encoding() {
        let block = |i: i32| v1::MeshBlock {
            index: Some(v1::BlockIndex {
                x: i,
                y: -i,
                z: 2 * i,
            }),
            vertices: (0..36).map(|b| (b * i) as u8).collect(),
            colors: vec![255, 0, 255, 1, 2, 3],
            normals: vec![7; 36],
            indices: vec![0, 1, 2],
        };
        let pose = StampedPose {
            timestamp: 1.5,
            world_from_camera: Some(v1::Sim3Pose {
                scale: 2.0,
                ..Default::default()
            }),
        };
        let whole = MapSnapshot {
            session_id: "s-1".into(),
            state: "running".into(),
            frames_processed: 12,
            trajectory: vec![pose; 3],
            keyframes: vec![pose],
            mesh_blocks: (1..5).map(block).collect(),
            block_size: 0.08,
            mesh_revision: 9,
            frames_received: 14,
            frames_dropped: 2,
        };
        let streamed = |m: &MapSnapshot| {
            let (head, tail) = split_at_mesh(m);
            let mut out = head.encode_to_vec();
            for b in &m.mesh_blocks {
                prost::encoding::message::encode(MESH_BLOCKS_TAG, b, &mut out);
            }
            tail.encode(&mut out).expect("a Vec grows");
            out
        };
        assert_eq!(streamed(&whole), whole.encode_to_vec());
        assert_eq!(
            MapSnapshot::decode(&streamed(&whole)[..]).expect("decodes"),
            whole
        );
        // Without a mesh, and with nothing after it.
        let bare = MapSnapshot {
            session_id: "s-2".into(),
            ..MapSnapshot::default()
        };
        assert_eq!(streamed(&bare), bare.encode_to_vec());
    }

    #[test]
    fn tum_text_becomes_stamped_poses_value_for_value() {
        let text =
            "# comment\n1.5 0.1 0.2 0.30000000000000004 0 0 0 1\n\n2.25 -1 -2 -3 0.5 0.5 0.5 0.5\n";
        let poses = parse_tum(text).expect("valid");
        assert_eq!(poses.len(), 2);
        let p = poses[0].world_from_camera.expect("pose");
        assert_eq!(poses[0].timestamp, 1.5);
        assert_eq!(p.translation.expect("t").z, 0.30000000000000004);
        assert_eq!(p.scale, 1.0);
        assert_eq!(
            poses[1]
                .world_from_camera
                .expect("pose")
                .rotation
                .expect("q")
                .w,
            0.5
        );
        assert!(parse_tum("1 2 3").is_err());
        assert!(parse_tum("1 2 3 4 5 6 7 x").is_err());
    }

    #[test]
    fn live_poses_equal_their_tum_text_value_for_value() {
        use relfusion_slam::dataset::trajectory::stamped_se3;
        use relfusion_slam::geometry::SO3;
        let poses: Vec<(f64, Sim3)> = (0..5)
            .map(|i| {
                let f = f64::from(i);
                let pose = Sim3::new(
                    SO3::exp(&nalgebra::Vector3::new(0.1 * f, -0.03, 0.2)),
                    nalgebra::Vector3::new(f / 3.0, -0.7, 1e-3 * f),
                    0.8 + 0.1 * f,
                );
                (1.0 + f / 30.0, pose)
            })
            .collect();
        let live = Poses::Live(stamped_se3(&poses));
        let text = live.clone().into_tum();
        assert_eq!(
            stamped_poses(live).expect("typed"),
            stamped_poses(Poses::Stored(text)).expect("parsed")
        );
    }

    #[test]
    fn states_are_named_like_the_http_api() {
        assert_eq!(state_name(SessionState::Finished), "finished");
        assert_eq!(state_name(SessionState::Running), "running");
    }
}
