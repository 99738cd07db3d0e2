//! The DSO-class odometry back end: a sliding window of keyframes whose poses, affine
//! brightness and point depths are estimated jointly, old keyframes leaving through
//! marginalisation (Engel, Koltun and Cremers, "Direct Sparse Odometry", TPAMI 2018;
//! `../shared/design-odometry.md` maps the method).
//!
//! Why: the LSD-style loop (track against a fixed map, update depths as if the pose were
//! exact, propagate) is coordinate descent along the rotation–translation ambiguity, so the
//! map's depth shape and then its scale drift (issue 35). In a joint window a wrong shape costs
//! residual in every keyframe that sees it, and the prior carries what old keyframes measured,
//! relative scale included, instead of fixing them.
//!
//! - [`residual`]: the 8-pixel photometric residual and its first-estimate Jacobians;
//! - [`energy`]: robust weights, outliers, normal equations with the depths kept apart;
//! - [`solve`]: Levenberg–Marquardt with the Schur complement, the step out of the gauge;
//! - [`prior`]: the marginalisation prior; [`gauge`]: the 7 unobservable directions;
//! - [`select`]: candidate points spread over the image by a region-adaptive threshold;
//! - [`init`]: the coarse initialiser; [`focal`]: initialisers competing over the focal
//!   length; [`immature`]: candidates traced along epipolar lines;
//! - [`metric`]: a metric depth model's weak prior on every point the window activates;
//! - [`mapper`]: the window's side (tracing, activation, keyframes), in step or on a thread;
//!   [`system`]: the tracking side, which drives it;
//! - [`truth`]: a benchmark's probe of where the window's energy has its minimum against the
//!   ground truth.

pub mod config;
pub mod energy;
pub mod focal;
pub mod gauge;
pub mod immature;
pub mod init;
pub mod klt;
pub mod mapper;
pub mod memory;
pub mod metric;
pub mod prior;
pub mod residual;
pub mod select;
pub mod solve;
pub mod system;
pub mod truth;
pub mod two_view;

use std::sync::Arc;

use nalgebra::{Vector2, Vector6};

pub use config::OdometryConfig;
pub use init::FirstMap;
pub use mapper::{PublishedPoint, WindowObserver, WindowSnapshot};
pub use metric::MetricModel;
pub use prior::MarginalisationPrior;
pub use residual::{FrameState, Linearisation, PATTERN};
pub use solve::{Anchor, SolveReport};
pub use system::{FirstKeyframe, FrameOutcome, Odometry};

use crate::frame::Frame;
use crate::{Error, Result};

/// Gauss–Newton steps on a candidate's depth before it is activated
/// (`setting_GNItsOnPointActivation` = 3).
const ACTIVATION_ITERATIONS: usize = 3;
/// Keyframes in which a candidate must be an inlier to be activated
/// (`setting_minGoodActiveResForMarg` = 3).
const MIN_GOOD_TARGETS: usize = 3;

/// A keyframe of the window.
#[derive(Clone, Debug)]
pub struct WindowFrame {
    pub id: u64,
    pub frame: Arc<Frame>,
    pub state: FrameState,
    /// The state at which its Jacobians are evaluated: where it entered the window.
    pub first_estimate: FrameState,
    /// The window's level of its image, interleaved for sampling.
    pub samples: Arc<residual::Interleaved>,
    /// The camera's motion when it was taken, a twist per second in its own frame (as
    /// tracked): with a rolling shutter each row has its own pose.
    pub velocity: Vector6<f64>,
}

/// An active point: one inverse depth in its host keyframe's camera.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowPoint {
    /// Id of the host keyframe.
    pub host: u64,
    /// Pixel in the host at the window's pyramid level.
    pub uv: Vector2<f64>,
    pub idepth: f64,
    /// Host intensities at the pattern pixels.
    pub intensity: [f64; PATTERN.len()],
    /// A quadratic prior on the inverse depth, if any.
    pub prior: Option<DepthPrior>,
}

/// `½ · weight · (idepth − idepth₀)²` added to the window's energy for one point, Huber-robust
/// past `huber` (in units of `√weight · |idepth − idepth₀|`): DSO's regulariser of the
/// initialiser's depths and its prior on the depths the initialiser hands over
/// (`setting_idepthFixPrior`, quadratic), and a metric depth model's weak prior on every
/// point (robust: a single-image network is wrong by far on some pixels); weights in the
/// photometric energy's units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthPrior {
    pub idepth: f64,
    pub weight: f64,
    pub huber: f64,
}

impl DepthPrior {
    /// A quadratic prior (no robust kernel).
    pub fn quadratic(idepth: f64, weight: f64) -> Self {
        Self {
            idepth,
            weight,
            huber: f64::INFINITY,
        }
    }

    /// Its normalised residual at `idepth`.
    fn residual(&self, idepth: f64) -> f64 {
        self.weight.sqrt() * (idepth - self.idepth)
    }

    /// Its energy at `idepth`.
    pub fn energy(&self, idepth: f64) -> f64 {
        let r = self.residual(idepth).abs();
        if r <= self.huber {
            0.5 * self.weight * (idepth - self.idepth).powi(2)
        } else {
            self.huber * (r - 0.5 * self.huber)
        }
    }

    /// Its Gauss–Newton weight at `idepth` (iteratively reweighted past the Huber width):
    /// `h_dd += w`, `b_d += w · (idepth − idepth₀)` is the energy's gradient there.
    pub fn weight_at(&self, idepth: f64) -> f64 {
        let r = self.residual(idepth).abs();
        if r <= self.huber {
            self.weight
        } else {
            self.weight * self.huber / r
        }
    }
}

/// `point`'s energy in `views` (its host is `views[k]`): photometric plus its depth prior.
fn point_energy(
    config: &OdometryConfig,
    point: &WindowPoint,
    k: usize,
    views: &[residual::FrameView<'_>],
) -> f64 {
    energy::photometric_energy(config, std::slice::from_ref(point), &[k], views).0
        + energy::depth_prior_energy(std::slice::from_ref(point))
}

/// Levenberg–Marquardt on `point`'s inverse depth alone, everything else fixed, for at most
/// `iterations` steps (each at most halves or doubles it).
fn refine_depth(
    config: &OdometryConfig,
    point: &mut WindowPoint,
    k: usize,
    views: &[residual::FrameView<'_>],
    iterations: usize,
) {
    let mut current = point_energy(config, point, k, views);
    let mut lambda = 0.1;
    for _ in 0..iterations {
        let mut eq = energy::NormalEquations::zeros(views.len());
        eq.add_point(config, point, k, views, Linearisation::Current);
        let sys = &eq.points[0];
        if sys.h_dd <= 1e-12 {
            break;
        }
        let step = -sys.b_d / (sys.h_dd * (1.0 + lambda));
        let trial = WindowPoint {
            idepth: (point.idepth + step).clamp(0.5 * point.idepth, 2.0 * point.idepth),
            ..point.clone()
        };
        let e = point_energy(config, &trial, k, views);
        if e < current {
            *point = trial;
            current = e;
            lambda *= 0.5;
        } else {
            lambda *= 5.0;
        }
    }
}

/// The sliding window: keyframes, their active points and the marginalisation prior.
#[derive(Clone, Debug)]
pub struct SlidingWindow {
    config: OdometryConfig,
    frames: Vec<WindowFrame>,
    points: Vec<WindowPoint>,
    prior: MarginalisationPrior,
    linearisation: Linearisation,
    anchor: Option<solve::Anchor>,
}

impl SlidingWindow {
    /// An empty window.
    pub fn new(config: OdometryConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            config,
            frames: Vec::new(),
            points: Vec::new(),
            prior: MarginalisationPrior::default(),
            linearisation: Linearisation::FirstEstimate,
            anchor: None,
        })
    }

    /// The same window with Jacobians at the current state instead of the first estimates:
    /// only to measure what first-estimate Jacobians prevent.
    pub fn with_linearisation(mut self, linearisation: Linearisation) -> Self {
        self.linearisation = linearisation;
        self
    }

    fn priors(&self) -> solve::Priors<'_> {
        solve::Priors {
            marginalisation: &self.prior,
            anchor: self.anchor.as_ref(),
        }
    }

    /// Anchors the window ([`solve::Anchor`]), or frees it to the gauge projection.
    pub fn set_anchor(&mut self, anchor: Option<solve::Anchor>) {
        self.anchor = anchor;
    }

    pub fn config(&self) -> &OdometryConfig {
        &self.config
    }

    /// Keyframes, oldest first.
    pub fn frames(&self) -> &[WindowFrame] {
        &self.frames
    }

    pub fn points(&self) -> &[WindowPoint] {
        &self.points
    }

    pub fn prior(&self) -> &MarginalisationPrior {
        &self.prior
    }

    fn index_of(&self, id: u64) -> Option<usize> {
        self.frames.iter().position(|f| f.id == id)
    }

    /// Index in [`Self::frames`] of every point's host.
    fn hosts(&self) -> Vec<usize> {
        self.points
            .iter()
            .map(|p| {
                self.index_of(p.host)
                    .unwrap_or_else(|| unreachable!("hosts stay in the window"))
            })
            .collect()
    }

    /// Adds keyframe `id` at `state`, which also becomes its first estimate.
    pub fn add_frame(&mut self, id: u64, frame: Arc<Frame>, state: FrameState) -> Result<()> {
        if self.index_of(id).is_some() {
            return Err(Error::Config(format!(
                "keyframe {id} is already in the window"
            )));
        }
        if frame.pyramid.levels.len() <= self.config.level {
            return Err(Error::Shape(format!(
                "keyframe {id} has {} pyramid levels, the window works on level {}",
                frame.pyramid.levels.len(),
                self.config.level
            )));
        }
        self.frames.push(WindowFrame {
            id,
            samples: Arc::new(residual::Interleaved::new(frame.level(self.config.level))),
            frame,
            state,
            first_estimate: state,
            velocity: Vector6::zeros(),
        });
        self.prior.push_frame();
        Ok(())
    }

    /// Sets keyframe `id`'s velocity ([`WindowFrame::velocity`]).
    pub fn set_velocity(&mut self, id: u64, velocity: Vector6<f64>) {
        if let Some(k) = self.index_of(id) {
            self.frames[k].velocity = velocity;
        }
    }

    /// DSO's `optimizeImmaturePoint`: a candidate's inverse depth refined by a few
    /// Gauss–Newton steps on its residuals in every keyframe of the window, before it joins.
    /// `None` when it is an inlier in fewer than [`MIN_GOOD_TARGETS`] keyframes (or all but
    /// its host, in a smaller window), or its depth leaves the positive range: the epipolar
    /// search saw one frame, the window sees all of them.
    pub fn refine_candidate(&self, host: u64, uv: Vector2<f64>, idepth: f64) -> Option<f64> {
        let k = self.index_of(host)?;
        let mut point = self.sample_point(k, host, uv, idepth)?;
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        let views = solve::views(&self.config, &self.frames, &states);
        refine_depth(&self.config, &mut point, k, &views, ACTIVATION_ITERATIONS);
        let mut eq = energy::NormalEquations::zeros(self.frames.len());
        eq.add_point(&self.config, &point, k, &views, Linearisation::Current);
        let needed = MIN_GOOD_TARGETS
            .min(self.frames.len().saturating_sub(1))
            .max(1);
        (eq.points[0].inlier_targets >= needed && point.idepth.is_finite() && point.idepth > 0.0)
            .then_some(point.idepth)
    }

    /// The point of keyframe `k` (id `host`) at `uv` with the host's pattern intensities;
    /// `None` when the depth is not positive or the pattern leaves the image.
    fn sample_point(
        &self,
        k: usize,
        host: u64,
        uv: Vector2<f64>,
        idepth: f64,
    ) -> Option<WindowPoint> {
        if !(idepth.is_finite() && idepth > 0.0) {
            return None;
        }
        let level = self.frames[k].frame.level(self.config.level);
        let mut intensity = [0.0; PATTERN.len()];
        for (value, (ox, oy)) in intensity.iter_mut().zip(PATTERN) {
            *value = f64::from(
                level
                    .image
                    .bilinear((uv.x + ox) as f32, (uv.y + oy) as f32)?,
            );
        }
        Some(WindowPoint {
            host,
            uv,
            idepth,
            intensity,
            prior: None,
        })
    }

    /// Activates a point of keyframe `host` at pixel `uv` (window level) with inverse depth
    /// `idepth` and an optional prior on it; `false` when the host is not in the window, the
    /// depth is not positive or the pattern leaves the image.
    pub fn add_point(
        &mut self,
        host: u64,
        uv: Vector2<f64>,
        idepth: f64,
        prior: Option<DepthPrior>,
    ) -> bool {
        let Some(point) = self
            .index_of(host)
            .and_then(|k| self.sample_point(k, host, uv, idepth))
        else {
            return false;
        };
        self.points.push(WindowPoint { prior, ..point });
        true
    }

    /// Optimises every keyframe and point of the window jointly.
    pub fn optimize(&mut self) -> SolveReport {
        let hosts = self.hosts();
        solve::optimize(
            &self.config,
            &mut self.frames,
            &mut self.points,
            &hosts,
            &solve::Priors {
                marginalisation: &self.prior,
                anchor: self.anchor.as_ref(),
            },
            self.linearisation,
        )
    }

    /// The window's normal equations at the current state with every depth eliminated:
    /// `(H, b)` over the keyframes' parameters (what the solver steps on, undamped).
    pub fn reduced_system(&self) -> (nalgebra::DMatrix<f64>, nalgebra::DVector<f64>) {
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        solve::normal_equations(
            &self.config,
            &self.frames,
            &states,
            &self.points,
            &self.hosts(),
            &self.priors(),
            self.linearisation,
        )
        .reduced(0.0)
    }

    /// The current state of keyframe `id`.
    pub fn state(&self, id: u64) -> Option<FrameState> {
        self.index_of(id).map(|k| self.frames[k].state)
    }

    /// Drops the active points that are an inlier in no other keyframe of the window (DSO
    /// drops a residual once it is an outlier and the point once it has no residual left;
    /// dropping on "outlier in most keyframes" instead lost 0.004 m ATE on redkitchen
    /// 600-999 and halved the synthetic orbit's accuracy, docs/tuning.md).
    pub fn prune_outliers(&mut self) -> usize {
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        let views = solve::views(&self.config, &self.frames, &states);
        let hosts = self.hosts();
        let keep: Vec<bool> = self
            .points
            .iter()
            .zip(&hosts)
            .map(|(p, &h)| {
                views.iter().enumerate().any(|(t, target)| {
                    t != h
                        && energy::pattern(
                            &self.config,
                            p,
                            &views[h],
                            target,
                            Linearisation::Current,
                        )
                        .is_some()
                })
            })
            .collect();
        let before = self.points.len();
        let mut flags = keep.into_iter();
        self.points.retain(|_| flags.next().unwrap_or(false));
        before - self.points.len()
    }

    /// The keyframes to marginalise now, by DSO's rules (`flagFramesForMarginalization`):
    /// those of which fewer than `min_points_remaining` of the points are still in the
    /// newest keyframe's image or whose brightness drifted too far from it, as long as
    /// `min_frames` stay; then, while the window is still full, the one whose removal keeps
    /// the window best spread (close to the others, far from the newest).
    pub fn frames_to_marginalize(&self) -> Vec<u64> {
        let n = self.frames.len();
        let Some(newest) = self.frames.last() else {
            return Vec::new();
        };
        let mut flagged = Vec::new();
        for f in &self.frames[..n - 1] {
            if n - flagged.len() <= self.config.min_frames {
                break;
            }
            let hosted = self.points.iter().filter(|p| p.host == f.id);
            let total = hosted.clone().count();
            let seen = hosted
                .filter(|p| self.project_to_newest(p.host, &p.uv, p.idepth).is_some())
                .count();
            let remaining = seen as f64 / total.max(1) as f64;
            let brightness = (f.state.affine.0 - newest.state.affine.0).abs();
            if remaining < self.config.min_points_remaining
                || brightness > self.config.max_log_affine_in_window
            {
                flagged.push(f.id);
            }
        }
        if n - flagged.len() >= self.config.max_frames {
            let distance = |a: &WindowFrame, b: &WindowFrame| {
                (a.state.world_from_camera.translation - b.state.world_from_camera.translation)
                    .norm()
            };
            let candidates = self.frames[..n.saturating_sub(2)]
                .iter()
                .filter(|f| !flagged.contains(&f.id));
            let score = |f: &WindowFrame| {
                let closeness: f64 = self.frames[..n - 1]
                    .iter()
                    .filter(|g| g.id != f.id && !flagged.contains(&g.id))
                    .map(|g| 1.0 / (distance(f, g) + 1e-5))
                    .sum();
                closeness * distance(f, newest).sqrt()
            };
            if let Some(f) = candidates.max_by(|a, b| score(a).total_cmp(&score(b))) {
                flagged.push(f.id);
            }
        }
        flagged
    }

    /// Marginalises keyframe `id`: its points ([`Self::marginalize_points`]) and its affine
    /// prior go into the prior, then the keyframe itself is eliminated from the prior;
    /// residuals of other points in it are dropped (DSO, `FullSystemMarginalize.cpp`).
    pub fn marginalize_frame(&mut self, id: u64) -> Result<()> {
        let k = self
            .index_of(id)
            .ok_or_else(|| Error::Config(format!("keyframe {id} is not in the window")))?;
        let hosted: Vec<bool> = self.points.iter().map(|p| p.host == id).collect();
        self.marginalize_points(&hosted);
        // The keyframe's own affine prior goes with it (it would otherwise be lost): in the
        // prior's coordinates it is the same quadratic written at the first estimate.
        let first = self.frames[k].first_estimate;
        solve::add_affine_prior(
            &self.config,
            k,
            &first,
            &mut self.prior.h,
            &mut self.prior.b,
        );
        self.prior.remove_frame(k);
        self.frames.remove(k);
        Ok(())
    }

    /// Marginalises the points flagged in `which` (one flag per point): their residuals (weighted by
    /// `marginalisation_weight`) go into the prior with their depths eliminated, and they
    /// leave the window. DSO does this for points its newest keyframes no longer see, so that
    /// what they measured stays while the window's point budget goes to what is in view.
    pub fn marginalize_points(&mut self, which: &[bool]) -> usize {
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        let views = solve::views(&self.config, &self.frames, &states);
        let hosts = self.hosts();
        let mut eq = energy::NormalEquations::zeros(self.frames.len());
        let mut gone = 0;
        for ((p, &h), &flag) in self.points.iter().zip(&hosts).zip(which) {
            if flag {
                eq.add_point(&self.config, p, h, &views, self.linearisation);
                gone += 1;
            }
        }
        if gone == 0 {
            return 0;
        }
        let (mut h, mut g) = eq.reduced(0.0);
        h *= self.config.marginalisation_weight;
        g *= self.config.marginalisation_weight;
        self.prior
            .add_linearised(&h, &g, &solve::offsets(&self.frames, &states));
        let mut flags = which.iter();
        self.points
            .retain(|_| !flags.next().copied().unwrap_or(false));
        gone
    }

    /// One flag per point: hosted in an older keyframe and out of the newest one's image.
    pub fn out_of_view(&self) -> Vec<bool> {
        let newest = self.frames.last().map(|f| f.id);
        self.points
            .iter()
            .map(|p| Some(p.host) != newest && !self.in_newest(p))
            .collect()
    }

    /// Whether `point` lands in the image of the newest keyframe.
    pub fn in_newest(&self, point: &WindowPoint) -> bool {
        self.project_to_newest(point.host, &point.uv, point.idepth)
            .is_some()
    }

    /// Where the point of keyframe `host` at pixel `uv` (window level) with inverse depth
    /// `idepth` lands in the newest keyframe: its level-0 pixel and its inverse depth there;
    /// `None` behind the camera, outside the image or for a host not in the window.
    pub fn project_to_newest(
        &self,
        host: u64,
        uv: &Vector2<f64>,
        idepth: f64,
    ) -> Option<(Vector2<f64>, f64)> {
        let newest = self.frames.last()?;
        let host = &self.frames[self.index_of(host)?];
        let newest_from_host =
            newest.state.world_from_camera.inverse() * host.state.world_from_camera;
        let ray = host.frame.camera_at(self.config.level).unproject(uv, 1.0);
        let x = newest_from_host.act(&(ray / idepth));
        let camera = &newest.frame.camera;
        let u = camera.project(&x);
        (x.z > 1e-6
            && u.x >= 0.0
            && u.y >= 0.0
            && u.x < f64::from(camera.width)
            && u.y < f64::from(camera.height))
        .then(|| (u, 1.0 / x.z))
    }
}

#[cfg(test)]
mod tests;

#[cfg(test)]
mod system_tests;

#[cfg(test)]
mod prior_tests;
