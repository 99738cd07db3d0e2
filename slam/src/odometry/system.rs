//! The odometry loop: frames in, poses out (DSO's `FullSystem`, TPAMI 2018 §3, in our own
//! words). Until there is parallax the initialiser poses the frames; then each frame is
//! tracked against the newest keyframe's reference and handed to the window side
//! ([`super::mapper`]), which traces candidates in it and, when the image has moved enough,
//! makes it a keyframe: activation, optimisation, marginalisation, a new reference. The window
//! side runs in step (deterministic) or on its own thread; tracking then goes on against the
//! last published reference and never waits for an optimisation.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use nalgebra::{Matrix6, Vector3, Vector6};

use super::OdometryConfig;
use super::focal::{FocalSearch, with_focal};
use super::init::FirstMap;
use super::mapper::{MapJob, Published, WindowMapper, WindowObserver, WindowSnapshot};
use super::metric::{MetricModel, MetricPrior};
use crate::background::{Link, Priority, WorkerSpec};
use crate::frame::Frame;
use crate::geometry::SE3;
use crate::tracking::{SE3Tracker, TrackingConfig};
use crate::{Error, Result};

/// Jobs the window's thread may have queued before tracking waits for room (DSO's queue is
/// unbounded; a bounded one keeps a stalled thread from holding every frame in memory).
pub const WINDOW_QUEUE: usize = 16;
/// Longest wait for the window's first keyframe after the initialiser finished.
const FIRST_KEYFRAME_TIMEOUT: Duration = Duration::from_secs(60);

/// What happened to one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameOutcome {
    pub world_from_camera: SE3,
    /// The frame was handed to the window as a keyframe.
    pub keyframe: bool,
    /// False while initialising or when tracking failed (the pose is then the motion model's).
    pub tracked: bool,
    /// The tracking residual (grey levels; infinite when not tracked), LSD's
    /// `initialTrackedResidual`, for a depth filter fed by these poses.
    pub residual: f32,
    /// Information of the tracked pose relative to the keyframe it was tracked against (a
    /// right perturbation, as [`crate::tracking::TrackingResult::information`]; zero when not
    /// tracked).
    pub information: Matrix6<f64>,
}

impl FrameOutcome {
    fn untracked(world_from_camera: SE3) -> Self {
        Self {
            world_from_camera,
            keyframe: false,
            tracked: false,
            residual: f32::INFINITY,
            information: Matrix6::zeros(),
        }
    }
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
    tracker: SE3Tracker,
    window: Link<WindowMapper>,
    initialiser: Option<FocalSearch>,
    /// The focal length the initialisation chose, relative to the frames' own (1 until then
    /// and without [`OdometryConfig::focal_candidates`]): every frame is taken with it.
    focal_scale: f64,
    /// The window's last publication: newest keyframe, its pose and tracking reference.
    current: Option<Published>,
    /// Publications so far (a benchmark polls it to see a new window).
    published: u64,
    /// Jobs handed to the window so far.
    sent: u64,
    frames: Vec<(u64, FramePose)>,
    /// Latest pose of every keyframe (marginalised ones keep their last).
    keyframes: HashMap<u64, SE3>,
    /// The frame handed over as a keyframe and its tracked pose, until the window publishes
    /// it: no other keyframe is asked for meanwhile (DSO's `needNewKFAfter`).
    pending: Option<(u64, SE3)>,
    /// World poses of the last two frames (the motion model).
    last: Option<(SE3, SE3)>,
    /// Timestamp of the last frame (for the velocity a rolling shutter needs).
    last_stamp: Option<f64>,
    /// Tracking residual of the first frame after the newest keyframe.
    first_residual: Option<f32>,
    /// Replaces the initialiser's map (a probe; `None` in every live use).
    first_map: Option<FirstMap>,
    /// The window's first keyframe and its points (level-0 pixel, inverse depth), from the
    /// initialisation until [`Odometry::take_first_keyframe`].
    first_keyframe: Option<FirstKeyframe>,
    /// Whether tracked frames go into `frames` ([`Odometry::trajectory`]); a caller that
    /// keeps its own turns it off, so that an hour's frames cost nothing here.
    record_trajectory: bool,
}

/// The window's first keyframe as the initialiser handed it over: the frame (at the
/// identity) and its points, `(level-0 pixel, inverse depth)` with mean inverse depth 1.
#[derive(Clone, Debug)]
pub struct FirstKeyframe {
    pub frame: Arc<Frame>,
    pub points: Vec<(nalgebra::Vector2<f64>, f64)>,
}

impl Odometry {
    /// The odometry in step: every frame's window work is done before [`Odometry::push`]
    /// returns (deterministic), candidates offered for activation in their selection order.
    pub fn new(config: OdometryConfig) -> Result<Self> {
        Self::start(config, 0, false)
    }

    /// The odometry with the window on its own thread when `threaded` (tracking goes on
    /// against the last published keyframe while the window optimises), and `seed` for the
    /// order in which one host's candidates are offered for activation: 0 as selected, row
    /// by row; any other seed shuffles them. Runs with different seeds show how much a result
    /// owes to chance: the core is deterministic, but not stable (docs/tuning.md,
    /// 2026-11-28, third stop).
    pub fn start(config: OdometryConfig, seed: u64, threaded: bool) -> Result<Self> {
        Self::start_observed(config, seed, threaded, None, None)
    }

    /// [`Odometry::start`] with an observer of the window after each optimisation and a
    /// metric depth model whose prediction for each keyframe is a weak prior on its points'
    /// depths ([`super::metric`]).
    pub fn start_observed(
        config: OdometryConfig,
        seed: u64,
        threaded: bool,
        observer: Option<WindowObserver>,
        metric: Option<MetricModel>,
    ) -> Result<Self> {
        config.validate()?;
        let tracking = TrackingConfig {
            min_level: 0,
            level0_point_step: 1,
            min_good_per_all: 0.001,
            min_good_per_all_absmin: 0.0005,
            ..TrackingConfig::default()
        };
        let mapper_config = config.clone();
        let spec = WorkerSpec {
            name: "odometry-window",
            priority: Priority::Frame,
            queue: WINDOW_QUEUE,
        };
        Ok(Self {
            window: Link::new(threaded, spec, move || {
                WindowMapper::new(mapper_config, seed, observer, metric.map(MetricPrior::new))
            })?,
            tracker: SE3Tracker::new(tracking)?,
            config,
            initialiser: None,
            focal_scale: 1.0,
            current: None,
            published: 0,
            sent: 0,
            frames: Vec::new(),
            keyframes: HashMap::new(),
            pending: None,
            last: None,
            last_stamp: None,
            first_residual: None,
            first_map: None,
            first_keyframe: None,
            record_trajectory: true,
        })
    }

    /// The odometry starting its window from the map `first_map` makes of the initialiser's
    /// (a probe of how much a run owes to its first map).
    pub fn with_first_map(mut self, first_map: FirstMap) -> Self {
        self.first_map = Some(first_map);
        self
    }

    /// The window as last published (after its latest keyframe).
    pub fn window(&self) -> Option<&WindowSnapshot> {
        self.current.as_ref().map(|c| c.window.as_ref())
    }

    /// How many times the window has published so far.
    pub fn published(&self) -> u64 {
        self.published
    }

    /// Number of keyframes the window has made so far.
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

    /// Waits for the window to handle every frame handed over, so that [`Odometry::trajectory`]
    /// has the final keyframe poses. The odometry takes no more frames after it.
    pub fn finish(&mut self) -> Result<()> {
        for published in self.window.finish()? {
            self.apply(published);
        }
        Ok(())
    }

    /// The focal length chosen at initialisation relative to the frames' own
    /// ([`OdometryConfig::focal_candidates`]); 1 before.
    pub fn focal_scale(&self) -> f64 {
        self.focal_scale
    }

    /// The latest estimate of keyframe `id`'s pose (the window's, or its tracked pose while
    /// the window has not published it yet); `None` for a frame that is no keyframe.
    pub fn keyframe_pose(&self, id: u64) -> Option<SE3> {
        match self.pending {
            Some((pending, pose)) if pending == id => Some(pose),
            _ => self.keyframes.get(&id).copied(),
        }
    }

    /// The window's first keyframe, once, after the initialisation handed it over (how a
    /// pipeline driven by this odometry begins its map at the same frame).
    pub fn take_first_keyframe(&mut self) -> Option<FirstKeyframe> {
        self.first_keyframe.take()
    }

    /// Stops recording tracked frames for [`Odometry::trajectory`] (the frames of the
    /// initialisation stay): for a caller that records every frame's pose itself.
    pub fn stop_recording_trajectory(&mut self) {
        self.record_trajectory = false;
    }

    /// Processes the next frame.
    pub fn push(&mut self, frame: Arc<Frame>) -> Result<FrameOutcome> {
        self.poll();
        let frame = with_focal(&frame, self.focal_scale);
        let Some(current) = &self.current else {
            return self.initialise(frame);
        };
        let (kf_id, world_from_kf) = (current.keyframe, current.world_from_keyframe);
        let guess = match self.last {
            Some((prev, last)) => last * (prev.inverse() * last),
            None => world_from_kf,
        };
        let (pose, tracked, residual, information) = self.track(&frame, &world_from_kf, &guess);
        let velocity = match (self.last, self.last_stamp) {
            (Some((_, before)), Some(t)) if frame.timestamp > t => {
                (before.inverse() * pose).log() / (frame.timestamp - t)
            }
            _ => Vector6::zeros(),
        };
        self.last = Some((self.last.map_or(pose, |l| l.1), pose));
        self.last_stamp = Some(frame.timestamp);
        if self.record_trajectory {
            self.frames.push((
                frame.id,
                FramePose {
                    keyframe: kf_id,
                    keyframe_from_frame: world_from_kf.inverse() * pose,
                },
            ));
        }
        if !tracked {
            return Ok(FrameOutcome::untracked(pose));
        }
        let first = *self.first_residual.get_or_insert(residual);
        let keyframe = self.pending.is_none()
            && (self.needs_keyframe(&frame, &world_from_kf, &pose) || residual > 2.0 * first);
        let job = if keyframe {
            self.pending = Some((frame.id, pose));
            MapJob::Keyframe {
                frame,
                pose,
                velocity,
            }
        } else {
            MapJob::Frame { frame, pose }
        };
        self.send(job)?;
        // In step the window has already answered; on a thread, whatever it has so far.
        self.poll();
        Ok(FrameOutcome {
            world_from_camera: pose,
            keyframe,
            tracked,
            residual,
            information,
        })
    }

    /// Waits until the window has handled every frame handed to it (at most `timeout`) and
    /// takes in what it published: a threaded run then stands where a run in step would.
    pub fn catch_up(&mut self, timeout: Duration) -> Result<()> {
        let deadline = Instant::now() + timeout;
        while let Some(worker) = self.window.worker()
            && worker.handled() < self.sent
        {
            if Instant::now() > deadline {
                return Err(Error::Config(format!(
                    "the odometry window did not catch up within {timeout:?}"
                )));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        self.poll();
        Ok(())
    }

    /// Hands `job` to the window (waiting for queue room if its thread is far behind); an
    /// error the thread met is this call's.
    fn send(&mut self, job: MapJob) -> Result<()> {
        if let Some(error) = self.window.worker().and_then(|w| w.last_error()) {
            return Err(Error::Config(format!(
                "the odometry window failed: {error}"
            )));
        }
        self.window.send(job)?;
        self.sent += 1;
        Ok(())
    }

    /// Takes in what the window published since the last call.
    fn poll(&mut self) {
        for published in self.window.poll() {
            self.apply(published);
        }
    }

    /// A new keyframe from the window: its poses, and the motion model moved with the
    /// keyframe from where it was tracked to where the window put it.
    fn apply(&mut self, published: Published) {
        self.keyframes.extend(published.keyframes.iter().copied());
        if let Some((id, tracked)) = self.pending
            && id == published.keyframe
        {
            // In step the last frame is the keyframe itself: it takes the window's pose.
            let moved = published.world_from_keyframe * tracked.inverse();
            self.last = self.last.map(|(prev, last)| {
                let last = if last == tracked {
                    published.world_from_keyframe
                } else {
                    moved * last
                };
                (prev, last)
            });
            self.pending = None;
        }
        self.first_residual = None;
        self.published += 1;
        self.current = Some(published);
    }

    fn initialise(&mut self, frame: Arc<Frame>) -> Result<FrameOutcome> {
        let frame_timestamp = frame.timestamp;
        let first_id = self.frames.first().map_or(frame.id, |(_, p)| p.keyframe);
        // Frames during initialisation get the finished initialiser's poses.
        self.frames.push((
            frame.id,
            FramePose {
                keyframe: first_id,
                keyframe_from_frame: SE3::identity(),
            },
        ));
        let untracked = FrameOutcome::untracked(SE3::identity());
        let Some(search) = self.initialiser.as_mut() else {
            self.initialiser = Some(FocalSearch::new(
                &self.config,
                &frame,
                self.config.active_points,
            ));
            return Ok(untracked);
        };
        let Some(chosen) = search.push(&frame) else {
            return Ok(untracked);
        };
        self.focal_scale = chosen.scale;
        let mut done = chosen.initialised;
        if let Some(map) = &self.first_map {
            done.points = (map.0)(&done.first, &done.points);
        }
        // Frames before a restarted initialisation's first are put at it: they gave no
        // parallax (or no tracks) to measure their motion by, and every frame has a pose.
        let skipped = done.skipped.min(self.frames.len());
        let poses = std::iter::repeat_n(SE3::identity(), skipped).chain(done.poses.iter().copied());
        for ((_, p), pose) in self.frames.iter_mut().zip(poses) {
            p.keyframe = done.first.id;
            p.keyframe_from_frame = pose;
        }
        let pose = done.poses.last().copied().unwrap_or_else(SE3::identity);
        let previous = done
            .poses
            .get(done.poses.len().saturating_sub(2))
            .copied()
            .unwrap_or(pose);
        self.initialiser = None;
        self.first_keyframe = Some(FirstKeyframe {
            frame: done.first.clone(),
            points: done.points.clone(),
        });
        self.send(MapJob::Start(done))?;
        // Nothing can be tracked before the first keyframe's reference: wait for it.
        self.catch_up(FIRST_KEYFRAME_TIMEOUT)?;
        if self.current.is_none() {
            return Err(Error::Config(
                "the odometry window published no first keyframe".into(),
            ));
        }
        self.last = Some((previous, pose));
        self.last_stamp = Some(frame_timestamp);
        Ok(FrameOutcome {
            world_from_camera: pose,
            keyframe: true,
            tracked: true,
            residual: 0.0,
            information: Matrix6::zeros(),
        })
    }

    /// Tracks `frame` against the newest keyframe from DSO's motion hypotheses (constant
    /// velocity, double, half and no velocity, then small rotations about each axis): the
    /// first good result wins; when none is good, the lowest residual of those that
    /// converged (DSO never stops tracking on a bad frame, it takes the best it has);
    /// `(pose, tracked, residual, information)`.
    fn track(
        &mut self,
        frame: &Frame,
        world_from_kf: &SE3,
        guess: &SE3,
    ) -> (SE3, bool, f32, Matrix6<f64>) {
        let Some(current) = &self.current else {
            return (*guess, false, f32::INFINITY, Matrix6::zeros());
        };
        let reference = current.reference.as_ref();
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
        let mut best: Option<(SE3, f32, Matrix6<f64>)> = None;
        for hypothesis in &hypotheses {
            let initial = hypothesis.inverse() * *world_from_kf;
            let result = self.tracker.track(reference, frame, &initial);
            if !result.residual.is_finite() {
                continue;
            }
            let pose = *world_from_kf * result.frame_from_keyframe.inverse();
            if result.good {
                return (pose, true, result.residual, result.information);
            }
            if best.as_ref().is_none_or(|b| result.residual < b.1) {
                best = Some((pose, result.residual, result.information));
            }
        }
        match best {
            Some((pose, residual, information)) => (pose, true, residual, information),
            None => (*guess, false, f32::INFINITY, Matrix6::zeros()),
        }
    }

    /// DSO's keyframe rule on the reference points' image motion.
    fn needs_keyframe(&self, frame: &Frame, world_from_kf: &SE3, pose: &SE3) -> bool {
        let Some(current) = &self.current else {
            return false;
        };
        let reference = current.reference.as_ref();
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
}
