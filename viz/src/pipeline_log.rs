//! The pipeline's events given to a [`SessionLog`]: the one translation, used by the command
//! line's recorders (`relfusion run --mcap/--foxglove/--rerun`) and by the service's session
//! recording and ROS 2 topics.

use relfusion_slam::pipeline::{Event, TrackingState};

use crate::session_log::{DepthRef, LogError, MeshBlockRef, Pose, SessionLog};

/// Gives `log` what `event` holds for a viewer: poses of tracked frames (lost ones have none
/// worth drawing), keyframes made or moved, dense depth and mesh updates.
pub fn log_event(log: &mut dyn SessionLog, event: &Event) -> Result<(), LogError> {
    match event {
        Event::Pose(p) if p.state != TrackingState::Lost => {
            log.pose(p.frame_id, p.timestamp, &Pose::from(&p.world_from_camera))
        }
        Event::Pose(_) => Ok(()),
        Event::Keyframe(k) => {
            log.keyframe(k.keyframe_id as u64, &Pose::from(&k.world_from_keyframe))
        }
        Event::KeyframePoses { poses } => poses.iter().try_for_each(|k| {
            log.keyframe(k.keyframe_id as u64, &Pose::from(&k.world_from_keyframe))
        }),
        Event::KeyframeDensified {
            keyframe_id,
            keyframe,
            ..
        } => {
            let c = &keyframe.camera;
            log.keyframe_depth(
                *keyframe_id as u64,
                &DepthRef {
                    width: keyframe.idepth.width,
                    height: keyframe.idepth.height,
                    inverse_depth: &keyframe.idepth.data,
                    fx: c.fx,
                    fy: c.fy,
                    cx: c.cx,
                    cy: c.cy,
                },
            )
        }
        Event::MeshUpdated { delta, .. } => {
            let removed: Vec<[i32; 3]> = delta.removed.iter().map(|b| [b.x, b.y, b.z]).collect();
            let changed: Vec<MeshBlockRef<'_>> = delta
                .changed
                .iter()
                .map(|b| MeshBlockRef {
                    index: [b.index.x, b.index.y, b.index.z],
                    positions: &b.positions,
                    colors: &b.colors,
                    normals: &b.normals,
                    indices: &b.indices,
                })
                .collect();
            log.mesh_update(&changed, &removed)
        }
    }
}
