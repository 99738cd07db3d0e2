//! Parameters of the back end: Sim(3) keyframe-to-keyframe alignment, constraint search and
//! pose-graph optimisation, with LSD-SLAM's defaults (`DenseDepthTrackerSettings`,
//! `util/settings.{h,cpp}`, `SlamSystem::testConstraint` in tum-vision/lsd_slam) except where the
//! DeepRelativeFusion paper changes them (`KFDistWeight` = 7.5, §IV).

use serde::{Deserialize, Serialize};

use crate::frame::PYRAMID_LEVELS;
use crate::optim::{LmSchedule, PhotometricParams};
use crate::{Error, Result};

/// Configuration of [`super::Sim3Tracker`], the constraint search and [`super::Backend`]. Every
/// field has a default, so a config file only lists what it changes. Its user settings are
/// listed in [`crate::pipeline::user_config`]; the rest is expert level. Measured trade-offs of the defaults are in docs/tuning.md ("Back end").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BackendConfig {
    // ---------------------------------------------------------------- Sim(3) tracking
    /// Finest pyramid level of a full coarse-to-fine Sim(3) alignment. Default 1
    /// (`SIM3TRACKING_MIN_LEVEL`): level 1 is sub-pixel accurate for semi-dense depth noise.
    pub min_level: usize,
    /// Coarsest level, where the alignment starts. Default 4 (`SIM3TRACKING_MAX_LEVEL` − 1).
    pub max_level: usize,
    /// The Levenberg–Marquardt schedule (LSD-SLAM's).
    pub lm: LmSchedule,
    /// The photometric residual model, `σ_p² = camera_pixel_noise2 + var_weight·V_d·(∂r_p/∂d)²`
    /// (ECCV 2014 eq. (16)); its Huber width acts on the summed normalised residual
    /// `|r_p|/σ_p + |r_d|/σ_d` of a point (`calcSim3WeightsAndResidual`).
    pub photometric: PhotometricParams,
    /// Fit an affine brightness change `a·I + b` between the two keyframes (auto exposure), as
    /// SE(3) tracking does. Default true (LSD-SLAM's `useAffineLightningEstimation`;
    /// docs/tuning.md, "Scale drift, issue 22").
    pub affine_lighting: bool,
    /// A Sim(3) alignment is *good* only if `good / (good + bad) ≥` this at its finest level.
    /// Default 0.5 (`MIN_GOODPERGOODBAD_PIXEL`; LSD-SLAM applies it to SE(3) tracking only;
    /// here it also rejects unrelated views before the costlier finer stages).
    pub min_good_ratio: f64,
    /// The alignment diverged when fewer than this share of a level's pixels received a warped
    /// reference point (or fewer than 10 points). Default 0.01 (`MIN_GOODPERALL_PIXEL_ABSMIN`,
    /// used with a factor 0.5 as in `Sim3Tracker::trackFrameSim3`).
    pub min_warped_share: f64,

    // ---------------------------------------------------------------- constraint search
    /// Weight of the keyframe distance in LSD-SLAM's keyframe score; candidates lie within
    /// squared distance `close_distance / kf_dist_weight²` (in units of the mean depth).
    /// Default 7.5 (DeepRelativeFusion §IV; LSD-SLAM's default is 4).
    pub kf_dist_weight: f64,
    /// Numerator of the candidate distance threshold. Default 15
    /// (`TrackableKeyFrameSearch::findCandidates`: `15 / KFDistWeight²`).
    pub close_distance: f64,
    /// Candidates' viewing directions differ by at most this fraction of the mean field of
    /// view. Default 0.75 (`findCandidates`: `1 − 0.25·closenessTH` with closenessTH = 1).
    pub close_angle_fraction: f64,
    /// At most this many pose-proximity candidates are tracked per keyframe (the best
    /// connected ones are dropped first). Default 10 (`maxLoopClosureCandidates`).
    pub max_loop_closure_candidates: usize,
    /// Propose far-away keyframes by appearance (the role FAB-MAP plays in LSD-SLAM, here a
    /// box-averaged 32×24 thumbnail compared by shift-tolerant correlation, see
    /// [`super::Thumbnail`]). Default true.
    pub appearance_search: bool,
    /// Minimum thumbnail correlation (in [−1, 1]) of an appearance candidate. Default 0.8,
    /// between a revisit and another view of the same room (docs/tuning.md).
    pub appearance_min_score: f64,
    /// At most this many appearance candidates per keyframe. Default 5 (LSD-SLAM keeps
    /// `max(5, (maxLoopClosureCandidates + 1)/2)` far candidates).
    pub max_far_candidates: usize,
    /// Appearance candidates must be at least this many graph edges away from the new
    /// keyframe's parent (closer ones are already constrained). Default 4
    /// (`findConstraintsForNewKeyFrames`).
    pub min_far_graph_distance: usize,
    /// Keyframes created before this many others are never constraint candidates (LSD-SLAM
    /// skips 5, `INITIALIZATION_PHASE_COUNT`, whose depth comes from its random
    /// initialisation). Default 0: the first keyframes set the map's scale, and linking them
    /// to later ones keeps it from drifting (docs/tuning.md).
    pub skip_initial_keyframes: usize,
    /// Multiplier on the reciprocal-consistency thresholds. Default 4.5, three times LSD-SLAM's
    /// 1.5 (`loopclosureStrictness`): at 1.5 the test rejects most constraints between
    /// keyframes 4–15 apart on real hand-held sequences, and the graph degenerates into a
    /// chain whose errors add up; unrelated views still fail at stage 0 (docs/tuning.md).
    pub loop_closure_strictness: f64,
    /// Strictness used for the new keyframe's tracking parent, whose constraint is forced.
    /// Default 100 (`testConstraint(parent, …, 100)`).
    pub parent_strictness: f64,
    /// The staged reciprocal test: the two directions are aligned on levels
    /// `max_level..=stage_levels[0]`, then `stage_levels[1]`, then `stage_levels[2]`, and after
    /// each stage the Mahalanobis distance of `T_ab·T_ba` from identity must stay below
    /// `stage_thresholds[k]·strictness`. Defaults `[3, 2, 1]` (`testConstraint`).
    pub stage_levels: [usize; 3],
    /// Thresholds of the staged reciprocal test (squared Mahalanobis distances). Default
    /// `[3000, 4000, 6000]` (`testConstraint`).
    pub stage_thresholds: [f64; 3],
    /// Skip a candidate that already failed against this keyframe from an initial relative
    /// pose within this `|log|` of the current one. Default 0.1 (`trackingFailed` check).
    pub retry_min_change: f64,

    // ---------------------------------------------------------------- pose graph
    /// LM iterations of the pose graph after new constraints. Default 100
    /// (`maxOptimizationIterations`).
    pub max_optimization_iterations: usize,
    /// A live pass (not the session's final one) moves at most this many keyframes: those
    /// nearest by edges to what changed, unless a new edge closes a loop beyond them
    /// (`graph::scope`). Default 500, about 7 minutes of hand-held 640×480 keyframes: every
    /// shorter session is optimised whole, and an hour-long one no longer holds a factor of its
    /// whole graph at every pass (docs/tuning.md, issue 37).
    pub live_optimization_vertices: usize,
    /// A live pass that a new loop edge would make whole waits until the graph has grown by
    /// this fraction since its last whole pass, moving the neighbourhood meanwhile
    /// ([`super::PoseGraph::set_loop_pass_growth`]). Default 0.05: whole passes cost time
    /// linear in the graph, so one per 5 % of growth keeps their share of the back end's time
    /// constant; an hour-long session at one per new loop edge spent its back end on them and
    /// queued ever more keyframes (docs/tuning.md, thirty-fifth stop). 0 moves it at once.
    pub loop_pass_growth: f64,
    /// Huber width on `sqrt(rᵀΩr)` of a pose-graph edge; `None` disables it. Default
    /// `5·sqrt(6000·1.5)` ≈ 474 (`kernelDelta` of `testConstraint` at LSD-SLAM's strictness).
    pub pose_graph_huber: Option<f64>,
    /// Commands waiting for the back end's thread; a full queue makes the frame path wait.
    /// Default 256: below the frame path's priority the back end may fall tens of keyframes
    /// behind under overload, and a short queue then stalls the frame path (docs/tuning.md).
    /// A queued keyframe costs its compact form alone (`KeyframeMaps::Shared`), a depth
    /// update its compact depth.
    pub channel_capacity: usize,
    /// Full constraint searches per back-end pass while it is behind (more new keyframes than
    /// this queued since its last pass), and deferred searches and depth refreshes caught up
    /// per pass otherwise (`graph::backend::schedule`). Default 2: a pass with one or two new
    /// keyframes is the normal case and is searched in full, as LSD-SLAM does.
    pub catch_up_searches: usize,
    /// Deferred searches (and depth refreshes) kept waiting at most; older ones are given up,
    /// their keyframes staying candidates of later searches. Default 64, about a minute of
    /// hand-held 640×480 keyframes.
    pub deferred_max: usize,
    /// Keyframes held in full (pyramid, alignment levels; about 16 MB at 640×480) by the back
    /// end and, for relocalisation, by the pipeline; older ones keep a compact form (colour
    /// image, depth map, descriptor) and are rebuilt, identical, when a constraint search or
    /// relocalisation needs them (`graph::resident`). Default 8: the newest keyframes, which
    /// the constraint search and relocalisation try first. 0 rebuilds on every use; at most 64.
    pub resident_keyframes: usize,
    /// Keyframes older than the resident ones whose compact form stays in memory; older ones
    /// spill to the session's store when it has one (`crate::spill`: about 2.7 MB each at
    /// 640×480 in memory, a few kB once spilled) and are read back when needed. Default 24:
    /// loop closures and relocalisation mostly revisit recent keyframes, and reading one back
    /// costs a store round trip. 0 spills every keyframe that leaves the resident set.
    pub held_keyframes: usize,

    /// Unary scale factors from a metric depth prior (issue 39); unused with a relative prior.
    pub metric_scale: MetricScaleConfig,

    // ---------------------------------------------------------------- window
    /// The windowed photometric bundle adjustment of the latest keyframes
    /// ([`crate::window`]), whose result enters the pose graph as edges.
    pub window: crate::window::WindowConfig,
}

impl Default for BackendConfig {
    fn default() -> Self {
        Self {
            min_level: 1,
            max_level: PYRAMID_LEVELS - 1,
            lm: LmSchedule::default(),
            photometric: PhotometricParams::default(),
            affine_lighting: true,
            min_good_ratio: 0.5,
            min_warped_share: 0.01,
            kf_dist_weight: 7.5,
            close_distance: 15.0,
            close_angle_fraction: 0.75,
            max_loop_closure_candidates: 10,
            appearance_search: true,
            appearance_min_score: 0.8,
            max_far_candidates: 5,
            min_far_graph_distance: 4,
            skip_initial_keyframes: 0,
            loop_closure_strictness: 4.5,
            parent_strictness: 100.0,
            stage_levels: [3, 2, 1],
            stage_thresholds: [3000.0, 4000.0, 6000.0],
            retry_min_change: 0.1,
            max_optimization_iterations: 100,
            live_optimization_vertices: 500,
            loop_pass_growth: 0.05,
            pose_graph_huber: Some(5.0 * (6000.0f64 * 1.5).sqrt()),
            channel_capacity: 256,
            catch_up_searches: 2,
            deferred_max: 64,
            resident_keyframes: 8,
            held_keyframes: 24,
            metric_scale: MetricScaleConfig::default(),
            window: crate::window::WindowConfig::default(),
        }
    }
}

impl BackendConfig {
    /// The finest pyramid level any alignment of the back end uses (keyframes keep no
    /// alignment data below it).
    pub fn finest_level(&self) -> usize {
        self.stage_levels
            .iter()
            .copied()
            .fold(self.min_level, usize::min)
    }

    /// Checks level ranges and that every factor is positive and finite.
    pub fn validate(&self) -> Result<()> {
        if self.min_level > self.max_level || self.max_level >= PYRAMID_LEVELS {
            return Err(Error::Config(format!(
                "backend: levels {}..={} outside 0..{PYRAMID_LEVELS}",
                self.min_level, self.max_level
            )));
        }
        if self.stage_levels.iter().any(|&l| l > self.max_level)
            || self.stage_levels.windows(2).any(|w| w[1] > w[0])
        {
            return Err(Error::Config(format!(
                "backend: stage_levels {:?} must be non-increasing and ≤ max_level {}",
                self.stage_levels, self.max_level
            )));
        }
        self.lm.validate("backend")?;
        self.photometric.validate("backend")?;
        let positive = [
            ("kf_dist_weight", self.kf_dist_weight),
            ("close_distance", self.close_distance),
            ("close_angle_fraction", self.close_angle_fraction),
            ("loop_closure_strictness", self.loop_closure_strictness),
            ("parent_strictness", self.parent_strictness),
        ];
        for (name, v) in positive
            .into_iter()
            .chain(
                self.stage_thresholds
                    .iter()
                    .map(|&t| ("stage_thresholds", t)),
            )
            .chain(self.pose_graph_huber.map(|h| ("pose_graph_huber", h)))
        {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::Config(format!(
                    "backend: {name} must be > 0, got {v}"
                )));
            }
        }
        if !(self.loop_pass_growth.is_finite() && self.loop_pass_growth >= 0.0) {
            return Err(Error::Config(format!(
                "backend: loop_pass_growth must be finite and ≥ 0, got {}",
                self.loop_pass_growth
            )));
        }
        if self.catch_up_searches == 0 {
            return Err(Error::Config(
                "backend: catch_up_searches must be ≥ 1".into(),
            ));
        }
        if self.channel_capacity == 0 {
            return Err(Error::Config(
                "backend: channel_capacity must be ≥ 1".into(),
            ));
        }
        if self.resident_keyframes > 64 {
            return Err(Error::Config(format!(
                "backend: resident_keyframes must be ≤ 64, got {}",
                self.resident_keyframes
            )));
        }
        if self.held_keyframes > 4096 {
            return Err(Error::Config(format!(
                "backend: held_keyframes must be ≤ 4096, got {}",
                self.held_keyframes
            )));
        }
        self.metric_scale.validate()?;
        self.window.validate()
    }
}

/// How a metric depth prior (a model config with `metric = true`, e.g. FastDepth) anchors the
/// map's scale: the first keyframe's depth is taken in metres, and every densified keyframe's
/// observed scale ([`crate::metric_scale::observe`]) enters the pose graph as a weak unary
/// factor on its vertex's scale ([`super::ScalePrior`]), as CNN-SLAM lets a network's depth
/// hold a monocular map's scale. `enabled` is a user setting; the rest is expert level.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MetricScaleConfig {
    /// Anchor the scale when the prior is metric. Default true (a relative prior never does).
    pub enabled: bool,
    /// Fewest semi-dense pixels that must vote before a keyframe's scale is observed.
    /// Default 500: fewer cover too little of the image to average the network's local
    /// errors.
    pub min_pixels: usize,
    /// Floor of the factor's σ (natural log of the scale). Default 0.1: a metric network's
    /// per-image scale is rarely better than 10 % (FastDepth on 7-Scenes: 41 % of pixels
    /// within 10 % with no alignment, shared data README §5), however tight the votes.
    pub min_sigma: f64,
    /// Multiplier on the votes' robust spread to give the factor's σ. Default 1: the spread
    /// of one pixel's vote, not of their mean (a network's scale error is shared by the whole
    /// image, see [`crate::metric_scale`]).
    pub sigma_factor: f64,
    /// Huber width of the factor in units of σ. Default 2: a keyframe whose prior is off by
    /// more than 2σ pulls with a constant force instead of a growing one.
    pub huber: f64,
    /// Floor of every pose-graph edge's relative-scale σ (natural log) once factors exist
    /// ([`super::PoseGraph::set_edge_scale_sigma`]). The photometric Hessian claims ~3·10⁻⁴;
    /// the front end's scale drifts by about 1-3 % per keyframe (scale drift 1.4-3.3 over
    /// 25-35 keyframes on the shared sequences), so the default is 0.02.
    pub edge_scale_sigma: f64,
}

impl Default for MetricScaleConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            min_pixels: 500,
            min_sigma: 0.1,
            sigma_factor: 1.0,
            huber: 2.0,
            edge_scale_sigma: 0.02,
        }
    }
}

impl MetricScaleConfig {
    /// The pose-graph factor of an observation, `None` when too few pixels voted.
    pub fn factor(&self, obs: &crate::metric_scale::ScaleObservation) -> Option<super::ScalePrior> {
        (obs.pixels >= self.min_pixels && obs.log_scale.is_finite()).then(|| super::ScalePrior {
            log_scale: obs.log_scale,
            sigma: (self.sigma_factor * obs.log_spread).max(self.min_sigma),
            huber: self.huber,
        })
    }

    fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("min_sigma", self.min_sigma),
            ("sigma_factor", self.sigma_factor),
            ("huber", self.huber),
            ("edge_scale_sigma", self.edge_scale_sigma),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::Config(format!(
                    "backend.metric_scale.{name} must be > 0, got {v}"
                )));
            }
        }
        Ok(())
    }
}
