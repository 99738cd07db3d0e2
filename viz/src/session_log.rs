//! What a viewer's log of a session is given, whatever it writes: the camera's images, every
//! tracked pose, keyframes as they are made and moved, their dense depth, and the fused mesh
//! block by block. `relfusion stream` and `relfusion run` translate their events into these
//! calls once (`cli::recorders`), and each log ([`crate::foxglove_log`] for MCAP files and
//! the Foxglove WebSocket, [`crate::rerun_log`] for rerun) turns them into its own messages.
//!
//! The world frame is the first camera's: x right, y down, z forward.

use relfusion_core::geometry::Sim3;

/// A camera-to-world similarity: `p_world = s·R(q)·p + t`, q = (x, y, z, w).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub t: [f64; 3],
    pub q: [f64; 4],
    pub s: f64,
}

impl Pose {
    pub const IDENTITY: Pose = Pose {
        t: [0.0; 3],
        q: [0.0, 0.0, 0.0, 1.0],
        s: 1.0,
    };
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

/// Most dense points a viewer is sent per keyframe: enough for its shape, small enough to keep
/// each keyframe's (for a re-send when the pose graph rescales it).
pub const POINTS_PER_KEYFRAME: usize = 5_000;

/// A keyframe's points are sent again when its scale changed by more than this (a point
/// cloud hangs in its keyframe's frame, and a frame transform carries no scale).
pub const RESCALE_TOLERANCE: f64 = 0.01;

/// Nanoseconds of a capture time in seconds (0 for negative or non-finite times).
pub fn nanos(seconds: f64) -> u64 {
    if seconds.is_finite() && seconds > 0.0 {
        (seconds * 1e9).min(u64::MAX as f64) as u64
    } else {
        0
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

impl DepthRef<'_> {
    /// The map back-projected into the keyframe's own frame (unscaled), on a pixel grid whose
    /// step keeps it within `max_points`: a viewer needs the shape, not every pixel.
    pub fn points(&self, max_points: usize) -> Vec<[f32; 3]> {
        let (w, h) = (self.width, self.height);
        if self.inverse_depth.len() != w * h || w == 0 || h == 0 {
            return Vec::new();
        }
        let step = ((w * h) as f64 / max_points.max(1) as f64)
            .sqrt()
            .ceil()
            .max(1.0) as usize;
        let mut points = Vec::new();
        for y in (0..h).step_by(step) {
            for x in (0..w).step_by(step) {
                let d = self.inverse_depth[y * w + x];
                if d > 0.0 && d.is_finite() {
                    let z = 1.0 / f64::from(d);
                    points.push([
                        ((x as f64 - self.cx) / self.fx * z) as f32,
                        ((y as f64 - self.cy) / self.fy * z) as f32,
                        z as f32,
                    ]);
                }
            }
        }
        points
    }
}

/// What a log holds, for the caller's summary.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct LogCounts {
    pub images: u64,
    pub poses: u64,
    pub keyframes: u64,
    pub mesh_blocks_logged: u64,
    pub mesh_blocks_cleared: u64,
}

/// Why a log could not be written.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("cannot create {what} {path}: {message}")]
    Create {
        what: &'static str,
        path: String,
        message: String,
    },
    #[error("{what}: {message}")]
    Write { what: &'static str, message: String },
}

/// A viewer's log of one session. Calls come in the order things happened; `frame_id` and
/// `timestamp` (seconds) are the frame's, and what is not about a frame (keyframes, depth,
/// mesh) happens at the time of the newest frame.
pub trait SessionLog: std::fmt::Debug + Send {
    /// The camera image of a frame, as its file's bytes (JPEG or PNG).
    fn image(&mut self, frame_id: u64, timestamp: f64, encoded: &[u8]) -> Result<(), LogError>;
    /// The pose of a tracked frame (lost frames have none).
    fn pose(&mut self, frame_id: u64, timestamp: f64, pose: &Pose) -> Result<(), LogError>;
    /// A keyframe was made or moved (by the pose graph).
    fn keyframe(&mut self, keyframe_id: u64, pose: &Pose) -> Result<(), LogError>;
    /// A keyframe's dense depth, in its own frame (so it moves with the keyframe).
    fn keyframe_depth(&mut self, keyframe_id: u64, depth: &DepthRef<'_>) -> Result<(), LogError>;
    /// The fused mesh changed: these blocks have a new surface, those lost theirs.
    fn mesh_update(
        &mut self,
        changed: &[MeshBlockRef<'_>],
        removed: &[[i32; 3]],
    ) -> Result<(), LogError>;
    /// Writes everything out; what the log holds, for the summary.
    fn finish(self: Box<Self>) -> Result<serde_json::Value, LogError>;
}

/// The image format of encoded bytes, by their magic number ("jpeg", "png"; "" if neither).
pub fn image_format(encoded: &[u8]) -> &'static str {
    if encoded.starts_with(&[0xFF, 0xD8, 0xFF]) {
        "jpeg"
    } else if encoded.starts_with(b"\x89PNG\r\n\x1a\n") {
        "png"
    } else {
        ""
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_points_keep_within_the_budget_and_back_project() {
        let (w, h) = (40, 30);
        let mut idepth = vec![0.5f32; w * h];
        idepth[0] = 0.0;
        let depth = DepthRef {
            width: w,
            height: h,
            inverse_depth: &idepth,
            fx: 20.0,
            fy: 20.0,
            cx: 20.0,
            cy: 15.0,
        };
        let all = depth.points(usize::MAX);
        assert_eq!(all.len(), w * h - 1, "the hole is skipped");
        // Pixel (1, 0): x = (1 - 20) / 20 · 2.
        assert!((all[0][0] - (-1.9)).abs() < 1e-6 && (all[0][2] - 2.0).abs() < 1e-6);
        let few = depth.points(100);
        assert!(few.len() <= 100 && few.len() > 25, "{}", few.len());
        assert!(DepthRef { width: 41, ..depth }.points(100).is_empty());
    }

    #[test]
    fn image_formats_are_told_by_their_magic() {
        assert_eq!(image_format(&[0xFF, 0xD8, 0xFF, 0xE0]), "jpeg");
        assert_eq!(image_format(b"\x89PNG\r\n\x1a\n...."), "png");
        assert_eq!(image_format(b"GIF89a"), "");
    }
}
