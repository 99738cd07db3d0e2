//! A session as a rerun recording (`relfusion stream/run … --rerun FILE.rrd`, cargo feature
//! `rerun`), to open in the rerun viewer: camera images with the pinhole, every pose as the
//! camera's transform, the trajectory, keyframes with their dense depth as points, and the fused
//! mesh block by block (`Mesh3D` per block, `Clear` when a block loses its surface) — the same
//! deltas the service streams, so the recording shows the map grow.
//!
//! Entity paths (the world frame is the first camera's, x right, y down, z forward):
//! `world/camera` (Transform3D per frame), `world/camera/image` (Pinhole, EncodedImage),
//! `world/trajectory` (LineStrips3D), `world/keyframes/<id>` (Transform3D) and
//! `world/keyframes/<id>/points` (Points3D), `world/mesh/<x>_<y>_<z>` (Mesh3D / Clear).
//! Timelines: `frame` (the frame id) and `capture_time` (the frame's timestamp, seconds).

use std::path::Path;

use relfusion_core::geometry::PinholeCamera;

use crate::session_log::{DepthRef, LogCounts, LogError, MeshBlockRef, Pose, SessionLog};

/// Most dense points logged per keyframe: a pixel step keeps within it.
const POINTS_PER_KEYFRAME: usize = 20_000;

fn log_error(e: impl std::fmt::Display) -> LogError {
    LogError::Write {
        what: "rerun",
        message: e.to_string(),
    }
}

fn transform(pose: &Pose) -> rerun::Transform3D {
    let f = |v: f64| v as f32;
    rerun::Transform3D::from_translation_rotation_scale(
        [f(pose.t[0]), f(pose.t[1]), f(pose.t[2])],
        rerun::Quaternion::from_xyzw([f(pose.q[0]), f(pose.q[1]), f(pose.q[2]), f(pose.q[3])]),
        f(pose.s),
    )
}

fn position(pose: &Pose) -> [f32; 3] {
    [pose.t[0] as f32, pose.t[1] as f32, pose.t[2] as f32]
}

/// An open `.rrd` file being written.
pub struct RerunLog {
    stream: rerun::RecordingStream,
    trajectory: Vec<[f32; 3]>,
    counts: LogCounts,
    /// The newest frame (id, timestamp): keyframe moves, depth and mesh blocks are logged at
    /// its time, since that is when they happen.
    now: (u64, f64),
    keyframes: std::collections::HashSet<u64>,
}

impl std::fmt::Debug for RerunLog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RerunLog")
            .field("counts", &self.counts)
            .finish()
    }
}

fn block_path(index: [i32; 3]) -> String {
    format!("world/mesh/{}_{}_{}", index[0], index[1], index[2])
}

impl RerunLog {
    /// Creates `path` (an `.rrd` file) for a camera with these intrinsics.
    pub fn create(path: &Path, camera: &PinholeCamera) -> Result<RerunLog, LogError> {
        let stream = rerun::RecordingStreamBuilder::new("relfusion")
            .save(path)
            .map_err(|e| LogError::Create {
                what: "the rerun recording",
                path: path.display().to_string(),
                message: e.to_string(),
            })?;
        stream
            .log_static("world", &rerun::ViewCoordinates::RDF())
            .map_err(log_error)?;
        let pinhole = rerun::Pinhole::from_focal_length_and_resolution(
            [camera.fx as f32, camera.fy as f32],
            [camera.width as f32, camera.height as f32],
        )
        .with_principal_point([camera.cx as f32, camera.cy as f32]);
        stream
            .log_static("world/camera/image", &pinhole)
            .map_err(log_error)?;
        Ok(RerunLog {
            stream,
            trajectory: Vec::new(),
            counts: LogCounts::default(),
            now: (0, 0.0),
            keyframes: Default::default(),
        })
    }

    /// Moves the recording's clock forward to a frame (never back).
    fn advance(&mut self, frame_id: u64, timestamp: f64) {
        if frame_id >= self.now.0 {
            self.now = (frame_id, timestamp);
        }
    }

    /// Sets the time of the next log call. Rerun keeps the time per thread, and an async
    /// caller may move between threads: so it is set right before every log call.
    fn stamp(&self) {
        let (frame_id, timestamp) = self.now;
        self.stream
            .set_time_sequence("frame", i64::try_from(frame_id).unwrap_or(i64::MAX));
        self.stream.set_duration_secs("capture_time", timestamp);
    }

    fn mesh_block(&mut self, block: &MeshBlockRef<'_>) -> Result<(), LogError> {
        let triangles: Vec<[u32; 3]> = block
            .indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect();
        let mut mesh =
            rerun::Mesh3D::new(block.positions.iter().copied()).with_triangle_indices(triangles);
        if block.colors.len() == block.positions.len() {
            mesh = mesh.with_vertex_colors(
                block
                    .colors
                    .iter()
                    .map(|c| rerun::Color::from_rgb(c[0], c[1], c[2])),
            );
        }
        if block.normals.len() == block.positions.len() {
            mesh = mesh.with_vertex_normals(block.normals.iter().copied());
        }
        self.stamp();
        self.stream
            .log(block_path(block.index), &mesh)
            .map_err(log_error)?;
        self.counts.mesh_blocks_logged += 1;
        Ok(())
    }

    fn log_trajectory(&mut self) -> Result<(), LogError> {
        if self.trajectory.len() < 2 {
            return Ok(());
        }
        self.stamp();
        self.stream
            .log(
                "world/trajectory",
                &rerun::LineStrips3D::new([self.trajectory.clone()]),
            )
            .map_err(log_error)
    }
}

impl SessionLog for RerunLog {
    fn image(&mut self, frame_id: u64, timestamp: f64, encoded: &[u8]) -> Result<(), LogError> {
        self.advance(frame_id, timestamp);
        self.stamp();
        self.stream
            .log(
                "world/camera/image",
                &rerun::EncodedImage::from_file_contents(encoded.to_vec()),
            )
            .map_err(log_error)?;
        self.counts.images += 1;
        Ok(())
    }

    fn pose(&mut self, frame_id: u64, timestamp: f64, pose: &Pose) -> Result<(), LogError> {
        self.advance(frame_id, timestamp);
        self.stamp();
        self.stream
            .log("world/camera", &transform(pose))
            .map_err(log_error)?;
        self.trajectory.push(position(pose));
        self.counts.poses += 1;
        Ok(())
    }

    fn keyframe(&mut self, keyframe_id: u64, pose: &Pose) -> Result<(), LogError> {
        let new = self.keyframes.insert(keyframe_id);
        self.stamp();
        self.stream
            .log(format!("world/keyframes/{keyframe_id}"), &transform(pose))
            .map_err(log_error)?;
        if new {
            self.counts.keyframes += 1;
            // The trajectory so far, refreshed once per keyframe (not per frame: O(n²) data).
            self.log_trajectory()?;
        }
        Ok(())
    }

    fn keyframe_depth(&mut self, keyframe_id: u64, depth: &DepthRef<'_>) -> Result<(), LogError> {
        let points = depth.points(POINTS_PER_KEYFRAME);
        if points.is_empty() {
            return Ok(());
        }
        self.stamp();
        self.stream
            .log(
                format!("world/keyframes/{keyframe_id}/points"),
                &rerun::Points3D::new(points),
            )
            .map_err(log_error)
    }

    fn mesh_update(
        &mut self,
        changed: &[MeshBlockRef<'_>],
        removed: &[[i32; 3]],
    ) -> Result<(), LogError> {
        for index in removed {
            self.stamp();
            self.stream
                .log(block_path(*index), &rerun::Clear::flat())
                .map_err(log_error)?;
            self.counts.mesh_blocks_cleared += 1;
        }
        for block in changed {
            self.mesh_block(block)?;
        }
        Ok(())
    }

    fn finish(mut self: Box<Self>) -> Result<serde_json::Value, LogError> {
        self.log_trajectory()?;
        self.stream.flush_blocking().map_err(log_error)?;
        serde_json::to_value(self.counts).map_err(log_error)
    }
}
