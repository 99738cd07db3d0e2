//! The window's side of the odometry (DSO's mapping thread, `FullSystem::mappingLoop`): tracked
//! frames in, candidates traced in them; a keyframe is activated into the window, optimised
//! and marginalised, and the newest keyframe's tracking reference is published. It runs as a
//! [`Service`], in step with tracking (deterministic runs) or on its own thread, so that
//! tracking never waits for an optimisation.

use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{Vector2, Vector6};

use super::immature::{ImmaturePoint, TraceConfig, TraceStatus, TraceTarget};
use super::init::{HANDOVER_PRIOR_WEIGHT, Initialised};
use super::metric::{self, MetricPrior};
use super::residual::FrameState;
use super::select::select_candidates;
use super::{DepthPrior, OdometryConfig, SlidingWindow};
use crate::Result;
use crate::background::Service;
use crate::frame::Frame;
use crate::geometry::SE3;
use crate::image::ImageF32;
use crate::mapping::{DepthMap, InverseDepth};
use crate::tracking::TrackingReference;

/// Variance given to a window point's inverse depth in the tracking reference (its relative
/// weight against the photometric noise; the window's depths are the best the system has).
const TRACKING_IDEPTH_VAR: f32 = 1e-4;

/// Mixed into a non-zero activation seed.
const SHUFFLE_SEED: u64 = 0x9E37_79B9_7F4A_7C15;

/// Tracked frames a thread that fell behind still traces before a keyframe; older ones are
/// skipped (DSO skips them the same way when its mapping lags): a keyframe is never skipped.
const TRACED_BACKLOG: usize = 3;

/// The order in which candidates with these `hosts` are offered for activation: oldest host
/// first (its candidates were traced in the most frames), and within a host as selected
/// (`state` 0) or in a pseudo-random order (xorshift on `state`).
pub(super) fn activation_order(hosts: &[u64], state: &mut u64) -> Vec<usize> {
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

/// The generator state of an activation seed (0: the selection's own order).
pub(super) fn shuffle_state(seed: u64) -> u64 {
    match seed {
        0 => 0,
        s => (SHUFFLE_SEED ^ s.wrapping_mul(0xD1B5_4A32_D192_ED03)).max(1),
    }
}

/// What the window side is asked to do.
#[derive(Debug)]
pub enum MapJob {
    /// The initialiser finished: its first frame becomes the first keyframe.
    Start(Initialised),
    /// A tracked frame: trace the candidates in it.
    Frame { frame: Arc<Frame>, pose: SE3 },
    /// A tracked frame that becomes a keyframe, with its tracked velocity (a twist per
    /// second in its own frame).
    Keyframe {
        frame: Arc<Frame>,
        pose: SE3,
        velocity: Vector6<f64>,
    },
}

/// A window point as published: host keyframe, pixel at the window's level, inverse depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PublishedPoint {
    pub host: u64,
    pub uv: Vector2<f64>,
    pub idepth: f64,
}

/// The window after a keyframe, for those who look at it from outside (benchmarks, probes).
#[derive(Clone, Debug, Default)]
pub struct WindowSnapshot {
    /// Pyramid level the points' pixels are on.
    pub level: usize,
    /// `(id, world_from_camera, affine (a, b))` of the window's keyframes, oldest first.
    pub frames: Vec<(u64, SE3, (f64, f64))>,
    pub points: Vec<PublishedPoint>,
}

/// What the window side publishes after each keyframe.
#[derive(Clone, Debug)]
pub struct Published {
    /// The newest keyframe, its optimised pose and its tracking reference.
    pub keyframe: u64,
    pub world_from_keyframe: SE3,
    pub reference: Arc<TrackingReference>,
    /// Latest poses of the window's keyframes and of those it marginalised just now.
    pub keyframes: Vec<(u64, SE3)>,
    pub window: Arc<WindowSnapshot>,
}

/// Called with the window right after each keyframe's optimisation, on the window's
/// thread: how benchmarks probe the window (`truth::probe`) without the window knowing them.
#[derive(Clone)]
pub struct WindowObserver(pub Arc<dyn Fn(&SlidingWindow) + Send + Sync>);

impl std::fmt::Debug for WindowObserver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("WindowObserver")
    }
}

/// The window, its candidates and the activation order's generator.
#[derive(Debug)]
pub struct WindowMapper {
    config: OdometryConfig,
    trace: TraceConfig,
    window: SlidingWindow,
    candidates: Vec<ImmaturePoint>,
    /// State of the generator behind [`activation_order`]; 0: no shuffle.
    shuffle: u64,
    observer: Option<WindowObserver>,
    /// A metric depth model's prior on the points the window activates, when there is one.
    metric: Option<MetricPrior>,
}

impl Service for WindowMapper {
    type Job = MapJob;
    type Reply = Published;
    const BATCH: bool = true;

    fn handle(&mut self, jobs: Vec<MapJob>, reply: &mut dyn FnMut(Published)) -> Result<()> {
        // Frames followed by more than TRACED_BACKLOG others are skipped (a thread behind).
        let n = jobs.len();
        for (i, job) in jobs.into_iter().enumerate() {
            match job {
                MapJob::Start(done) => reply(self.start(&done)?),
                MapJob::Frame { frame, pose } => {
                    if n - i <= TRACED_BACKLOG {
                        self.trace_candidates(&frame, &pose);
                    }
                }
                MapJob::Keyframe {
                    frame,
                    pose,
                    velocity,
                } => {
                    self.trace_candidates(&frame, &pose);
                    reply(self.make_keyframe(frame, pose, velocity)?);
                }
            }
        }
        Ok(())
    }
}

impl WindowMapper {
    pub fn new(
        config: OdometryConfig,
        seed: u64,
        observer: Option<WindowObserver>,
        metric: Option<MetricPrior>,
    ) -> Result<Self> {
        Ok(Self {
            window: SlidingWindow::new(config.clone())?,
            config,
            trace: TraceConfig::default(),
            candidates: Vec::new(),
            shuffle: shuffle_state(seed),
            observer,
            metric,
        })
    }

    /// The first keyframe from the initialiser: its points with the handover prior.
    fn start(&mut self, done: &Initialised) -> Result<Published> {
        let id = done.first.id;
        let state = FrameState {
            world_from_camera: SE3::identity(),
            affine: (0.0, 0.0),
        };
        self.window.add_frame(id, done.first.clone(), state)?;
        let factor = f64::from(1u32 << self.config.level);
        for (uv, idepth) in &done.points {
            let prior = DepthPrior::quadratic(*idepth, HANDOVER_PRIOR_WEIGHT);
            self.window.add_point(id, uv / factor, *idepth, Some(prior));
        }
        let model = match &mut self.metric {
            Some(metric) => metric.start(&done.first, &done.points)?,
            None => None,
        };
        self.add_candidates(&done.first, model.as_ref());
        self.publish(Vec::new())
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

    /// Selects `keyframe`'s candidates, each with the metric `model`'s inverse depth at its
    /// pixel (window units) when there is one.
    fn add_candidates(&mut self, keyframe: &Frame, model: Option<&ImageF32>) {
        for uv in select_candidates(keyframe.level(0), self.config.candidate_points) {
            if let Some(mut c) = ImmaturePoint::new(keyframe.id, keyframe.level(0), uv) {
                c.metric_idepth = model.and_then(|m| metric::sample(m, &uv));
                self.candidates.push(c);
            }
        }
    }

    /// The metric model's prior for the newest keyframe `frame`; `None` without a model.
    fn metric_prior(&self, frame: &Frame) -> Result<Option<ImageF32>> {
        match &self.metric {
            Some(metric) => metric.keyframe(frame),
            None => Ok(None),
        }
    }

    fn make_keyframe(
        &mut self,
        frame: Arc<Frame>,
        pose: SE3,
        velocity: Vector6<f64>,
    ) -> Result<Published> {
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
        self.window.set_velocity(frame.id, velocity);
        self.activate();
        self.window.optimize();
        if let Some(observer) = &self.observer {
            (observer.0)(&self.window);
        }
        self.window.prune_outliers();
        let out_of_view = self.window.out_of_view();
        self.window.marginalize_points(&out_of_view);
        let mut left = Vec::new();
        for id in self.window.frames_to_marginalize() {
            if let Some(state) = self.window.state(id) {
                left.push((id, state.world_from_camera));
            }
            self.window.marginalize_frame(id)?;
            self.candidates.retain(|c| c.host != id);
        }
        let model = self.metric_prior(&frame)?;
        self.add_candidates(&frame, model.as_ref());
        self.publish(left)
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
                    let prior = c
                        .metric_idepth
                        .and_then(|m| metric::point_prior(&self.config, m));
                    if let Some(idepth) = self.window.refine_candidate(c.host, uv, c.idepth())
                        && self.window.add_point(c.host, uv, idepth, prior)
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

    /// The newest keyframe's pose, its tracking reference and the window's state, with the
    /// last poses of the keyframes that `left` it.
    fn publish(&self, left: Vec<(u64, SE3)>) -> Result<Published> {
        let newest = self
            .window
            .frames()
            .last()
            .ok_or_else(|| crate::Error::Config("the window has no keyframe".into()))?;
        let mut keyframes = left;
        keyframes.extend(
            self.window
                .frames()
                .iter()
                .map(|f| (f.id, f.state.world_from_camera)),
        );
        let window = WindowSnapshot {
            level: self.config.level,
            frames: self
                .window
                .frames()
                .iter()
                .map(|f| (f.id, f.state.world_from_camera, f.state.affine))
                .collect(),
            points: self
                .window
                .points()
                .iter()
                .map(|p| PublishedPoint {
                    host: p.host,
                    uv: p.uv,
                    idepth: p.idepth,
                })
                .collect(),
        };
        Ok(Published {
            keyframe: newest.id,
            world_from_keyframe: newest.state.world_from_camera,
            reference: Arc::new(self.reference()?),
            keyframes,
            window: Arc::new(window),
        })
    }

    /// The tracking reference of the newest keyframe: every active point of the window
    /// projected into it, each spread over its 3×3 neighbourhood where empty (DSO dilates the
    /// projected depth the same way, so that the tracker has support on every level).
    fn reference(&self) -> Result<TrackingReference> {
        let newest = self
            .window
            .frames()
            .last()
            .ok_or_else(|| crate::Error::Config("the window has no keyframe".into()))?;
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
        TrackingReference::new(&newest.frame, &depth)
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
        let mut state = shuffle_state(7);
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
