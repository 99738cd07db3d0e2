//! The odometry loop: frames in, poses out (DSO's `FullSystem`, TPAMI 2018 §3, in our own
//! words). Each frame is tracked against the window's points projected into the newest
//! keyframe; candidates of the window's keyframes are traced in it; when the image has moved
//! enough it becomes a keyframe: candidates are activated, the window is optimised, points
//! and keyframes leave it by marginalisation, and the new keyframe's candidates are selected.

use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{Vector2, Vector3};

use super::immature::{ImmaturePoint, TraceConfig, TraceStatus, TraceTarget};
use super::init::{HANDOVER_PRIOR_WEIGHT, Initialiser};
use super::residual::FrameState;
use super::select::select_candidates;
use super::{DepthPrior, OdometryConfig, SlidingWindow};
use crate::Result;
use crate::frame::Frame;
use crate::geometry::SE3;
use crate::mapping::{DepthMap, InverseDepth};
use crate::tracking::{SE3Tracker, TrackingConfig, TrackingReference};

/// Variance given to a window point's inverse depth in the tracking reference (its relative
/// weight against the photometric noise; the window's depths are the best the system has).
const TRACKING_IDEPTH_VAR: f32 = 1e-4;

/// Mixed into a non-zero seed of [`Odometry::with_seed`].
const SHUFFLE_SEED: u64 = 0x9E37_79B9_7F4A_7C15;

/// The order in which candidates with these `hosts` are offered for activation: oldest host
/// first (its candidates were traced in the most frames), and within a host as selected
/// (`state` 0) or in a pseudo-random order (xorshift on `state`).
fn activation_order(hosts: &[u64], state: &mut u64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..hosts.len()).collect();
    if *state == 0 {
        order.sort_by_key(|&i| hosts[i]);
        return order;
    }
    for i in (1..order.len()).rev() {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        order.swap(i, (*state % (i as u64 + 1)) as usize);
    }
    // Host ids grow with time; a stable sort keeps the shuffle within each host.
    order.sort_by_key(|&i| hosts[i]);
    order
}

/// What happened to one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameOutcome {
    pub world_from_camera: SE3,
    pub keyframe: bool,
    /// False while initialising or when tracking failed (the pose is then the motion model's).
    pub tracked: bool,
}

/// A frame's pose relative to the keyframe it was tracked against.
#[derive(Clone, Copy, Debug)]
struct FramePose {
    keyframe: u64,
    keyframe_from_frame: SE3,
}

/// The DSO-class odometry.
#[derive(Debug)]
pub struct Odometry {
    config: OdometryConfig,
    trace: TraceConfig,
    window: SlidingWindow,
    tracker: SE3Tracker,
    reference: Option<TrackingReference>,
    candidates: Vec<ImmaturePoint>,
    initialiser: Option<Initialiser>,
    frames: Vec<(u64, FramePose)>,
    /// Latest pose of every keyframe (marginalised ones keep their last).
    keyframes: HashMap<u64, SE3>,
    /// World poses of the last two frames (the motion model).
    last: Option<(SE3, SE3)>,
    /// Tracking residual of the first frame after the newest keyframe.
    first_residual: Option<f32>,
    /// State of the generator behind [`activation_order`]; 0: no shuffle.
    shuffle: u64,
}

impl Odometry {
    pub fn new(config: OdometryConfig) -> Result<Self> {
        let tracking = TrackingConfig {
            min_level: 0,
            level0_point_step: 1,
            min_good_per_all: 0.001,
            min_good_per_all_absmin: 0.0005,
            ..TrackingConfig::default()
        };
        Ok(Self {
            window: SlidingWindow::new(config.clone())?,
            tracker: SE3Tracker::new(tracking)?,
            config,
            trace: TraceConfig::default(),
            reference: None,
            candidates: Vec::new(),
            initialiser: None,
            frames: Vec::new(),
            keyframes: HashMap::new(),
            last: None,
            first_residual: None,
            shuffle: 0,
        })
    }

    /// The same odometry with another order in which the candidates of one host are offered
    /// for activation: seed 0 (the default) offers them as selected, row by row; any other
    /// seed shuffles them. Runs with different seeds show how much a result owes to chance:
    /// the core is deterministic, but not stable (docs/tuning.md, 2026-11-28, third stop).
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.shuffle = match seed {
            0 => 0,
            s => (SHUFFLE_SEED ^ s.wrapping_mul(0xD1B5_4A32_D192_ED03)).max(1),
        };
        self
    }

    pub fn window(&self) -> &SlidingWindow {
        &self.window
    }

    /// Number of keyframes made so far.
    pub fn keyframe_count(&self) -> usize {
        self.keyframes.len()
    }

    /// Every frame's pose with the keyframes' latest estimates: `(frame id, world_from_camera)`.
    pub fn trajectory(&self) -> Vec<(u64, SE3)> {
        self.frames
            .iter()
            .map(|(id, p)| {
                let kf = self
                    .keyframes
                    .get(&p.keyframe)
                    .copied()
                    .unwrap_or_else(SE3::identity);
                (*id, kf * p.keyframe_from_frame)
            })
            .collect()
    }

    /// Processes the next frame.
    pub fn push(&mut self, frame: Arc<Frame>) -> Result<FrameOutcome> {
        if self.window.frames().is_empty() {
            return self.initialise(frame);
        }
        let newest = self
            .window
            .frames()
            .last()
            .map(|f| (f.id, f.state))
            .unwrap_or_else(|| unreachable!("window is not empty"));
        let (kf_id, kf_state) = newest;
        let world_from_kf = kf_state.world_from_camera;
        let guess = match self.last {
            Some((prev, last)) => last * (prev.inverse() * last),
            None => world_from_kf,
        };
        let (pose, tracked, residual) = self.track(&frame, &world_from_kf, &guess);
        self.last = Some((self.last.map_or(pose, |l| l.1), pose));
        self.frames.push((
            frame.id,
            FramePose {
                keyframe: kf_id,
                keyframe_from_frame: world_from_kf.inverse() * pose,
            },
        ));
        if !tracked {
            return Ok(FrameOutcome {
                world_from_camera: pose,
                keyframe: false,
                tracked,
            });
        }
        self.trace_candidates(&frame, &pose);
        let first = *self.first_residual.get_or_insert(residual);
        let keyframe = self.needs_keyframe(&frame, &world_from_kf, &pose) || residual > 2.0 * first;
        if keyframe {
            self.make_keyframe(frame, pose)?;
        }
        Ok(FrameOutcome {
            world_from_camera: pose,
            keyframe,
            tracked,
        })
    }

    fn initialise(&mut self, frame: Arc<Frame>) -> Result<FrameOutcome> {
        let first_id = self.frames.first().map_or(frame.id, |(_, p)| p.keyframe);
        // Frames during initialisation get the finished initialiser's poses.
        self.frames.push((
            frame.id,
            FramePose {
                keyframe: first_id,
                keyframe_from_frame: SE3::identity(),
            },
        ));
        let untracked = FrameOutcome {
            world_from_camera: SE3::identity(),
            keyframe: false,
            tracked: false,
        };
        let Some(init) = self.initialiser.as_mut() else {
            self.initialiser = Some(Initialiser::new(
                &self.config,
                frame,
                self.config.active_points,
            ));
            return Ok(untracked);
        };
        let Some(done) = init.push(frame) else {
            return Ok(untracked);
        };
        for ((_, p), pose) in self.frames.iter_mut().zip(&done.poses) {
            p.keyframe_from_frame = *pose;
        }
        let pose = done.poses.last().copied().unwrap_or_else(SE3::identity);
        let state = FrameState {
            world_from_camera: SE3::identity(),
            affine: (0.0, 0.0),
        };
        self.window.add_frame(first_id, done.first.clone(), state)?;
        let factor = f64::from(1u32 << self.config.level);
        for (uv, idepth) in &done.points {
            let prior = DepthPrior {
                idepth: *idepth,
                weight: HANDOVER_PRIOR_WEIGHT,
            };
            self.window
                .add_point(first_id, uv / factor, *idepth, Some(prior));
        }
        self.keyframes.insert(first_id, SE3::identity());
        self.initialiser = None;
        self.add_candidates(&done.first);
        self.rebuild_reference()?;
        let previous = done
            .poses
            .get(done.poses.len().saturating_sub(2))
            .copied()
            .unwrap_or(pose);
        self.last = Some((previous, pose));
        Ok(FrameOutcome {
            world_from_camera: pose,
            keyframe: true,
            tracked: true,
        })
    }

    /// Tracks `frame` against the newest keyframe from DSO's motion hypotheses (constant
    /// velocity, double, half and no velocity, then small rotations about each axis): the
    /// first good result wins; when none is good, the lowest residual of those that
    /// converged (DSO never stops tracking on a bad frame, it takes the best it has);
    /// `(pose, tracked, residual)`.
    fn track(&mut self, frame: &Frame, world_from_kf: &SE3, guess: &SE3) -> (SE3, bool, f32) {
        let Some(reference) = &self.reference else {
            return (*guess, false, f32::INFINITY);
        };
        let last = self.last.map_or(*world_from_kf, |l| l.1);
        let velocity = last.inverse() * *guess;
        let half = SE3::exp(&(0.5 * velocity.log()));
        let mut hypotheses = vec![*guess, *guess * velocity, last * half, last];
        for axis in 0..3 {
            for sign in [-1.0, 1.0] {
                let mut xi = nalgebra::Vector6::zeros();
                xi[3 + axis] = sign * 0.01;
                hypotheses.push(*guess * SE3::exp(&xi));
            }
        }
        let mut best: Option<(SE3, f32)> = None;
        for hypothesis in &hypotheses {
            let initial = hypothesis.inverse() * *world_from_kf;
            let result = self.tracker.track(reference, frame, &initial);
            if !result.residual.is_finite() {
                continue;
            }
            let pose = *world_from_kf * result.frame_from_keyframe.inverse();
            if result.good {
                return (pose, true, result.residual);
            }
            if best.is_none_or(|b| result.residual < b.1) {
                best = Some((pose, result.residual));
            }
        }
        match best {
            Some((pose, residual)) => (pose, true, residual),
            None => (*guess, false, f32::INFINITY),
        }
    }

    /// DSO's keyframe rule on the reference points' image motion.
    fn needs_keyframe(&self, frame: &Frame, world_from_kf: &SE3, pose: &SE3) -> bool {
        let Some(reference) = &self.reference else {
            return false;
        };
        let points = reference.level(0);
        let camera = &frame.camera;
        let frame_from_kf = pose.inverse() * *world_from_kf;
        let (mut ft, mut frt, mut n) = (0.0, 0.0, 0usize);
        for i in (0..points.len()).step_by(4) {
            let x = Vector3::new(
                f64::from(points.x[i]),
                f64::from(points.y[i]),
                f64::from(points.z[i]),
            );
            let moved = frame_from_kf.act(&x);
            let shifted = x + frame_from_kf.translation;
            if moved.z <= 1e-6 || shifted.z <= 1e-6 {
                continue;
            }
            let u = camera.project(&x);
            ft += (camera.project(&shifted) - u).norm_squared();
            frt += (camera.project(&moved) - u).norm_squared();
            n += 1;
        }
        if n == 0 {
            return true;
        }
        let size = f64::from(camera.width + camera.height) / 1120.0;
        let (ft, frt) = (
            (ft / n as f64).sqrt() / size,
            (frt / n as f64).sqrt() / size,
        );
        self.config.keyframe_translation_weight * ft + self.config.keyframe_rotation_weight * frt
            > 1.0
    }

    /// Traces every candidate of the window's keyframes in `frame`.
    fn trace_candidates(&mut self, frame: &Frame, world_from_frame: &SE3) {
        let frame_from_world = world_from_frame.inverse();
        let hosts: HashMap<u64, (SE3, crate::geometry::PinholeCamera)> = self
            .window
            .frames()
            .iter()
            .map(|f| (f.id, (f.state.world_from_camera, f.frame.camera)))
            .collect();
        let level = frame.level(0);
        for c in &mut self.candidates {
            let Some((world_from_host, camera)) = hosts.get(&c.host) else {
                continue;
            };
            let target_from_host = frame_from_world * *world_from_host;
            let target = TraceTarget {
                host_camera: camera,
                level,
                camera: &frame.camera,
                target_from_host: &target_from_host,
                affine: (1.0, 0.0, 0.0),
            };
            c.trace(&self.trace, &target);
        }
        self.candidates
            .retain(|c| c.status != TraceStatus::OutOfBounds && c.outliers < 2);
    }

    fn add_candidates(&mut self, keyframe: &Frame) {
        for uv in select_candidates(keyframe.level(0), self.config.candidate_points) {
            if let Some(c) = ImmaturePoint::new(keyframe.id, keyframe.level(0), uv) {
                self.candidates.push(c);
            }
        }
    }

    fn make_keyframe(&mut self, frame: Arc<Frame>, pose: SE3) -> Result<()> {
        let affine = self
            .window
            .frames()
            .last()
            .map_or((0.0, 0.0), |f| f.state.affine);
        self.window.add_frame(
            frame.id,
            frame.clone(),
            FrameState {
                world_from_camera: pose,
                affine,
            },
        )?;
        self.activate();
        self.window.optimize();
        self.window.prune_outliers();
        let out_of_view = self.window.out_of_view();
        self.window.marginalize_points(&out_of_view);
        for id in self.window.frames_to_marginalize() {
            if let Some(state) = self.window.state(id) {
                self.keyframes.insert(id, state.world_from_camera);
            }
            self.window.marginalize_frame(id)?;
            self.candidates.retain(|c| c.host != id);
        }
        for f in self.window.frames() {
            self.keyframes.insert(f.id, f.state.world_from_camera);
        }
        self.add_candidates(&frame);
        self.rebuild_reference()?;
        self.first_residual = None;
        self.last = self.last.map(|(prev, _)| (prev, self.keyframes[&frame.id]));
        Ok(())
    }

    /// Activates candidates with a sharp depth until the window has its active points,
    /// spread over the newest keyframe's image (one per cell of a grid sized for the target).
    fn activate(&mut self) {
        let Some(newest) = self.window.frames().last() else {
            return;
        };
        let camera = newest.frame.camera;
        let wanted = self
            .config
            .active_points
            .saturating_sub(self.window.points().len());
        if wanted == 0 {
            return;
        }
        let (w, h) = (f64::from(camera.width), f64::from(camera.height));
        let cell = (w * h / self.config.active_points as f64).sqrt().max(2.0);
        let columns = (w / cell).ceil() as usize + 1;
        let mut occupied = vec![false; columns * ((h / cell).ceil() as usize + 1)];
        let cell_of = |window: &SlidingWindow, host: u64, uv: &Vector2<f64>, idepth: f64| {
            let (u, _) = window.project_to_newest(host, uv, idepth)?;
            Some((u.y / cell) as usize * columns + (u.x / cell) as usize)
        };
        for p in self.window.points() {
            if let Some(i) = cell_of(&self.window, p.host, &p.uv, p.idepth) {
                occupied[i] = true;
            }
        }
        let factor = f64::from(1u32 << self.config.level);
        let mut added = 0;
        let mut remaining = Vec::with_capacity(self.candidates.len());
        let hosts: Vec<u64> = self.candidates.iter().map(|c| c.host).collect();
        let order = activation_order(&hosts, &mut self.shuffle);
        let mut candidates: Vec<Option<ImmaturePoint>> = std::mem::take(&mut self.candidates)
            .into_iter()
            .map(Some)
            .collect();
        for c in order.into_iter().filter_map(|i| candidates[i].take()) {
            if added < wanted && c.can_activate(&self.trace) {
                let uv = c.uv / factor;
                let free = cell_of(&self.window, c.host, &uv, c.idepth()).filter(|&i| !occupied[i]);
                if let Some(i) = free {
                    // A candidate the window rejects is dropped, as DSO does.
                    if let Some(idepth) = self.window.refine_candidate(c.host, uv, c.idepth())
                        && self.window.add_point(c.host, uv, idepth, None)
                    {
                        occupied[i] = true;
                        added += 1;
                    }
                    continue;
                }
            }
            remaining.push(c);
        }
        self.candidates = remaining;
    }

    /// The tracking reference of the newest keyframe: every active point of the window
    /// projected into it, each spread over its 3×3 neighbourhood where empty (DSO dilates the
    /// projected depth the same way, so that the tracker has support on every level).
    fn rebuild_reference(&mut self) -> Result<()> {
        let Some(newest) = self.window.frames().last() else {
            return Ok(());
        };
        let (w, h) = (
            newest.frame.camera.width as usize,
            newest.frame.camera.height as usize,
        );
        let mut depth = DepthMap::unknown(w, h);
        let mut seeds = Vec::new();
        for p in self.window.points() {
            let Some((u, idepth)) = self.window.project_to_newest(p.host, &p.uv, p.idepth) else {
                continue;
            };
            let (x, y) = (u.x.round() as usize, u.y.round() as usize);
            if x >= 1 && y >= 1 && x + 1 < w && y + 1 < h {
                let i = y * w + x;
                depth.pixels[i] = InverseDepth::Estimate {
                    idepth: idepth as f32,
                    var: TRACKING_IDEPTH_VAR,
                };
                seeds.push(i);
            }
        }
        for i in seeds {
            let value = depth.pixels[i];
            for dy in [-1isize, 0, 1] {
                for dx in [-1isize, 0, 1] {
                    let j = (i as isize + dy * w as isize + dx) as usize;
                    if depth.pixels[j] == InverseDepth::Unknown {
                        depth.pixels[j] = value;
                    }
                }
            }
        }
        match &mut self.reference {
            Some(r) => r.rebuild(&newest.frame, &depth)?,
            None => self.reference = Some(TrackingReference::new(&newest.frame, &depth)?),
        }
        Ok(())
    }
}

#[cfg(test)]
mod order_tests {
    use super::*;

    #[test]
    fn activation_order_is_oldest_host_first_and_shuffled_only_with_a_seed() {
        let hosts = [3u64, 1, 3, 2, 1, 3, 2, 1, 3, 3];
        let plain = activation_order(&hosts, &mut 0);
        assert_eq!(plain, vec![1, 4, 7, 3, 6, 0, 2, 5, 8, 9]);
        let mut state = Odometry::new(OdometryConfig::default())
            .expect("odometry")
            .with_seed(7)
            .shuffle;
        assert_ne!(state, 0);
        let shuffled = activation_order(&hosts, &mut state);
        let mut sorted = shuffled.clone();
        sorted.sort_unstable();
        assert_eq!(
            sorted,
            (0..hosts.len()).collect::<Vec<_>>(),
            "not a permutation"
        );
        assert!(
            shuffled.windows(2).all(|w| hosts[w[0]] <= hosts[w[1]]),
            "a younger host before an older one: {shuffled:?}"
        );
        let again = activation_order(&hosts, &mut state);
        assert_ne!(shuffled, again, "the generator did not advance");
    }
}
