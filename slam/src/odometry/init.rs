//! Initialisation without a prior shape: the first frame's points start at inverse depth 1
//! and are optimised jointly with the pose of each following frame, coarse to fine, until the
//! translation gives enough parallax (DSO's coarse initialiser, TPAMI 2018 §3.1,
//! `CoarseInitializer.cpp`, in our own words).
//!
//! Why: a first keyframe whose shape is taken from a single-image prior or random depths is
//! almost flat, and the LSD-style loop never recovers from it (issue 35: slope 0.10-0.15 for
//! 5 s). Here the shape is measured: by the time the first keyframe is made, every point's
//! depth is what the parallax of the first frames says.

use std::sync::Arc;

use nalgebra::Vector2;

use super::residual::FrameState;
use super::select::select_candidates;
use super::{OdometryConfig, SlidingWindow};
use crate::frame::Frame;
use crate::geometry::SE3;

/// Coarsest pyramid level the initialiser starts on (80×60 at 640×480).
const COARSEST: usize = 3;
/// RMS image motion from translation alone, level-0 pixels, that counts as enough parallax
/// (DSO snaps at 2.5 pixels of translational flow).
const MIN_TRANSLATION_FLOW: f64 = 2.5;
/// Frames optimised after parallax was reached before the first keyframe is made (DSO: 5).
const FRAMES_AFTER_SNAP: usize = 5;

/// The first keyframe and what the initialiser measured.
#[derive(Clone, Debug)]
pub struct Initialised {
    pub first: Arc<Frame>,
    /// Level-0 pixels of the first frame's points and their inverse depths.
    pub points: Vec<(Vector2<f64>, f64)>,
    /// `world_from_camera` of the frames given so far (the first is the identity).
    pub poses: Vec<SE3>,
}

/// Coarse initialiser state.
#[derive(Debug)]
pub struct Initialiser {
    config: OdometryConfig,
    first: Arc<Frame>,
    points: Vec<(Vector2<f64>, f64)>,
    poses: Vec<SE3>,
    frames_since_snap: Option<usize>,
}

impl Initialiser {
    /// Starts from `first` with about `points` candidates at inverse depth 1.
    pub fn new(config: &OdometryConfig, first: Arc<Frame>, points: usize) -> Self {
        let candidates = select_candidates(first.level(0), points);
        Self {
            config: config.clone(),
            points: candidates.into_iter().map(|uv| (uv, 1.0)).collect(),
            first,
            poses: vec![SE3::identity()],
            frames_since_snap: None,
        }
    }

    /// Optimises `frame`'s pose with the first frame's depths; `Some` once there has been
    /// enough parallax for long enough.
    pub fn push(&mut self, frame: Arc<Frame>) -> Option<Initialised> {
        let n = self.poses.len();
        let guess = match n {
            1 => SE3::identity(),
            _ => {
                let (a, b) = (self.poses[n - 2], self.poses[n - 1]);
                b * (a.inverse() * b)
            }
        };
        let pose = self.optimize(&frame, guess);
        self.poses.push(pose);
        if self.translation_flow(&pose) > MIN_TRANSLATION_FLOW {
            let since = self.frames_since_snap.get_or_insert(0);
            *since += 1;
        }
        if self
            .frames_since_snap
            .is_some_and(|s| s >= FRAMES_AFTER_SNAP)
        {
            return Some(Initialised {
                first: self.first.clone(),
                points: self.points.clone(),
                poses: self.poses.clone(),
            });
        }
        None
    }

    /// Joint optimisation of the first frame's depths and `frame`'s pose, coarse to fine.
    fn optimize(&mut self, frame: &Arc<Frame>, guess: SE3) -> SE3 {
        let mut pose = guess;
        let top = COARSEST.min(frame.pyramid.levels.len() - 1);
        for level in (0..=top).rev() {
            let config = OdometryConfig {
                level,
                iterations: 8,
                ..self.config.clone()
            };
            let Ok(mut window) = SlidingWindow::new(config) else {
                return pose;
            };
            let identity = FrameState {
                world_from_camera: SE3::identity(),
                affine: (0.0, 0.0),
            };
            let current = FrameState {
                world_from_camera: pose,
                affine: (0.0, 0.0),
            };
            if window.add_frame(0, self.first.clone(), identity).is_err()
                || window.add_frame(1, frame.clone(), current).is_err()
            {
                return pose;
            }
            let factor = f64::from(1u32 << level);
            let mut kept = Vec::new();
            for (i, (uv, idepth)) in self.points.iter().enumerate() {
                if window.add_point(0, uv / factor, *idepth) {
                    kept.push(i);
                }
            }
            window.optimize();
            // Re-express in the first frame's coordinates (the gauge-free step may move it).
            let first = window.frames()[0].state.world_from_camera;
            pose = first.inverse() * window.frames()[1].state.world_from_camera;
            for (&i, p) in kept.iter().zip(window.points()) {
                self.points[i].1 = p.idepth;
            }
        }
        pose
    }

    /// RMS image motion of the points from `pose`'s translation alone, level-0 pixels.
    fn translation_flow(&self, pose: &SE3) -> f64 {
        let camera = &self.first.camera;
        let t = pose.inverse().translation;
        let mut sum = 0.0;
        for (uv, idepth) in &self.points {
            let moved = camera.unproject(uv, 1.0) + t * *idepth;
            if moved.z <= 1e-6 {
                continue;
            }
            sum += (camera.project(&moved) - uv).norm_squared();
        }
        (sum / self.points.len().max(1) as f64).sqrt()
    }
}
