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

use relfusion_slam::geometry::{PinholeCamera, Sim3};

/// Most dense points logged per keyframe: a pixel step keeps within it.
const POINTS_PER_KEYFRAME: usize = 20_000;

/// Why a recording could not be written.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("cannot write the rerun recording {path}: {message}")]
    Create { path: String, message: String },
    #[error("rerun: {0}")]
    Log(String),
}

fn log_error(e: impl std::fmt::Display) -> RecordingError {
    RecordingError::Log(e.to_string())
}

/// A camera-to-world similarity: `p_world = s·R(q)·p + t`, q = (x, y, z, w).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub t: [f64; 3],
    pub q: [f64; 4],
    pub s: f64,
}

impl From<&Sim3> for Pose {
    fn from(p: &Sim3) -> Self {
        let q = p.rotation.quaternion();
        Pose {
            t: [p.translation.x, p.translation.y, p.translation.z],
            q: [q.i, q.j, q.k, q.w],
            s: p.scale,
        }
    }
}

impl Pose {
    fn transform(&self) -> rerun::Transform3D {
        let f = |v: f64| v as f32;
        rerun::Transform3D::from_translation_rotation_scale(
            [f(self.t[0]), f(self.t[1]), f(self.t[2])],
            rerun::Quaternion::from_xyzw([f(self.q[0]), f(self.q[1]), f(self.q[2]), f(self.q[3])]),
            f(self.s),
        )
    }

    fn position(&self) -> [f32; 3] {
        [self.t[0] as f32, self.t[1] as f32, self.t[2] as f32]
    }
}

/// One block of the fused surface (world coordinates).
#[derive(Clone, Copy, Debug)]
pub struct MeshBlockRef<'a> {
    pub index: [i32; 3],
    pub positions: &'a [[f32; 3]],
    pub colors: &'a [[u8; 3]],
    pub normals: &'a [[f32; 3]],
    /// Three vertex indices per triangle.
    pub indices: &'a [u32],
}

/// A dense inverse-depth map of a keyframe, row-major, 0 = no estimate.
#[derive(Clone, Copy, Debug)]
pub struct DepthRef<'a> {
    pub width: usize,
    pub height: usize,
    pub inverse_depth: &'a [f32],
    /// Undistorted intrinsics at this map's resolution.
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// What a recording holds, for the caller's summary.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct RecordingCounts {
    pub images: u64,
    pub poses: u64,
    pub keyframes: u64,
    pub mesh_blocks_logged: u64,
    pub mesh_blocks_cleared: u64,
}

/// An open `.rrd` file being written.
pub struct Recording {
    stream: rerun::RecordingStream,
    trajectory: Vec<[f32; 3]>,
    counts: RecordingCounts,
    /// The newest frame (id, timestamp): keyframe moves, depth and mesh blocks are logged at
    /// its time, since that is when they happen.
    now: (u64, f64),
    keyframes: std::collections::HashSet<u64>,
}

impl std::fmt::Debug for Recording {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("counts", &self.counts)
            .finish()
    }
}

fn block_path(index: [i32; 3]) -> String {
    format!("world/mesh/{}_{}_{}", index[0], index[1], index[2])
}

impl Recording {
    /// Creates `path` (an `.rrd` file) for a camera with these intrinsics.
    pub fn create(path: &Path, camera: &PinholeCamera) -> Result<Recording, RecordingError> {
        let stream = rerun::RecordingStreamBuilder::new("relfusion")
            .save(path)
            .map_err(|e| RecordingError::Create {
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
        Ok(Recording {
            stream,
            trajectory: Vec::new(),
            counts: RecordingCounts::default(),
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

    /// The camera image of a frame, as its file's bytes (JPEG or PNG).
    pub fn image(
        &mut self,
        frame_id: u64,
        timestamp: f64,
        encoded: Vec<u8>,
    ) -> Result<(), RecordingError> {
        self.advance(frame_id, timestamp);
        self.stamp();
        self.stream
            .log(
                "world/camera/image",
                &rerun::EncodedImage::from_file_contents(encoded),
            )
            .map_err(log_error)?;
        self.counts.images += 1;
        Ok(())
    }

    /// The pose of a tracked frame (lost frames have none).
    pub fn pose(
        &mut self,
        frame_id: u64,
        timestamp: f64,
        pose: &Pose,
    ) -> Result<(), RecordingError> {
        self.advance(frame_id, timestamp);
        self.stamp();
        self.stream
            .log("world/camera", &pose.transform())
            .map_err(log_error)?;
        self.trajectory.push(pose.position());
        self.counts.poses += 1;
        Ok(())
    }

    /// A keyframe was made or moved (by the pose graph).
    pub fn keyframe(&mut self, keyframe_id: u64, pose: &Pose) -> Result<(), RecordingError> {
        let new = self.keyframes.insert(keyframe_id);
        self.stamp();
        self.stream
            .log(format!("world/keyframes/{keyframe_id}"), &pose.transform())
            .map_err(log_error)?;
        if new {
            self.counts.keyframes += 1;
            // The trajectory so far, refreshed once per keyframe (not per frame: O(n²) data).
            self.log_trajectory()?;
        }
        Ok(())
    }

    /// A keyframe's dense depth, back-projected into its own frame (so it moves with it).
    pub fn keyframe_depth(
        &mut self,
        keyframe_id: u64,
        depth: &DepthRef<'_>,
    ) -> Result<(), RecordingError> {
        let (w, h) = (depth.width, depth.height);
        if depth.inverse_depth.len() != w * h || w == 0 || h == 0 {
            return Ok(());
        }
        self.stamp();
        let step = ((w * h) as f64 / POINTS_PER_KEYFRAME as f64)
            .sqrt()
            .ceil()
            .max(1.0) as usize;
        let mut points = Vec::new();
        for y in (0..h).step_by(step) {
            for x in (0..w).step_by(step) {
                let d = depth.inverse_depth[y * w + x];
                if d > 0.0 && d.is_finite() {
                    let z = 1.0 / f64::from(d);
                    points.push([
                        ((x as f64 - depth.cx) / depth.fx * z) as f32,
                        ((y as f64 - depth.cy) / depth.fy * z) as f32,
                        z as f32,
                    ]);
                }
            }
        }
        self.stream
            .log(
                format!("world/keyframes/{keyframe_id}/points"),
                &rerun::Points3D::new(points),
            )
            .map_err(log_error)
    }

    /// A block of the fused surface changed.
    pub fn mesh_block(&mut self, block: &MeshBlockRef<'_>) -> Result<(), RecordingError> {
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

    /// A block has no surface any more.
    pub fn mesh_block_removed(&mut self, index: [i32; 3]) -> Result<(), RecordingError> {
        self.stamp();
        self.stream
            .log(block_path(index), &rerun::Clear::flat())
            .map_err(log_error)?;
        self.counts.mesh_blocks_cleared += 1;
        Ok(())
    }

    fn log_trajectory(&mut self) -> Result<(), RecordingError> {
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

    /// Logs the whole trajectory and writes everything out.
    pub fn finish(mut self) -> Result<RecordingCounts, RecordingError> {
        self.log_trajectory()?;
        self.stream.flush_blocking().map_err(log_error)?;
        Ok(self.counts)
    }
}
