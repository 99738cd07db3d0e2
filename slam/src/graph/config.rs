//! Parameters of the back end: Sim(3) keyframe-to-keyframe alignment, constraint search and
//! pose-graph optimisation, with LSD-SLAM's defaults (`DenseDepthTrackerSettings`,
//! `util/settings.{h,cpp}`, `SlamSystem::testConstraint` in tum-vision/lsd_slam) except where the
//! DeepRelativeFusion paper changes them (`KFDistWeight` = 7.5, §IV).

use serde::{Deserialize, Serialize};

use crate::frame::PYRAMID_LEVELS;
use crate::{Error, Result};

/// Configuration of [`super::Sim3Tracker`], the constraint search and [`super::Backend`]. Every
/// field has a default, so a config file only lists what it changes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BackendConfig {
    // ---------------------------------------------------------------- Sim(3) tracking
    /// Finest pyramid level of a full coarse-to-fine Sim(3) alignment. Default 1
    /// (`SIM3TRACKING_MIN_LEVEL`): level 1 is sub-pixel accurate for semi-dense depth noise.
    pub min_level: usize,
    /// Coarsest level, where the alignment starts. Default 4 (`SIM3TRACKING_MAX_LEVEL` − 1).
    pub max_level: usize,
    /// Maximum Levenberg–Marquardt iterations per level, finest first. Default
    /// `[5, 20, 50, 100, 100]` (`maxItsPerLvl`).
    pub max_iterations: [usize; PYRAMID_LEVELS],
    /// Initial LM damping λ per level. Default 0 (`lambdaInitial`): start as Gauss–Newton.
    pub lambda_initial: f64,
    /// λ ← λ·this after an accepted step (and λ ← 0 once ≤ 0.2). Default 0.5
    /// (`lambdaSuccessFac`).
    pub lambda_success_factor: f64,
    /// After the k-th rejected try λ ← λ·this^k (0 becomes 0.2). Default 2 (`lambdaFailFac`).
    pub lambda_fail_factor: f64,
    /// A level ends when a rejected increment has `|δ|² ≤` this. Default 1e-8 (`stepSizeMin`).
    pub step_size_min: f64,
    /// A level ends when an accepted step leaves `cost_new / cost_old >` this. Default 0.999
    /// (`convergenceEps`).
    pub convergence_eps: f64,
    /// Image-noise variance (8-bit units²) of a photometric residual,
    /// `σ_p² = camera_pixel_noise2 + var_weight·V_d·(∂r_p/∂d)²` (ECCV 2014 eq. (13)/(16)).
    /// Default 16 = 4² (`cameraPixelNoise2`).
    pub camera_pixel_noise2: f64,
    /// Multiplier on every inverse-depth variance (LSD-SLAM calls the filter's variances
    /// over-confident). Default 1 (`var_weight`).
    pub var_weight: f64,
    /// Huber width on the summed normalised residual `|r_p|/σ_p + |r_d|/σ_d` of a point: weight
    /// 1 below, `huber_d / (…)` above (`Sim3Tracker::calcSim3WeightsAndResidual`). Default 3
    /// (`huber_d`).
    pub huber_d: f64,
    /// A warped point is *good* when `r_p² < max_diff_constant + max_diff_grad_mult·|∇I|²`.
    /// Default 40² (`MAX_DIFF_CONSTANT`).
    pub max_diff_constant: f64,
    /// Gradient term of the good-point test. Default 0.5² (`MAX_DIFF_GRAD_MULT`).
    pub max_diff_grad_mult: f64,
    /// A Sim(3) alignment is *good* only if `good / (good + bad) ≥` this at its finest level.
    /// Default 0.5 (`MIN_GOODPERGOODBAD_PIXEL`; LSD-SLAM applies it to SE(3) tracking and
    /// relies on the reciprocal check alone for Sim(3); here both apply, which rejects
    /// unrelated views before the costlier finer stages).
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
    /// Minimum thumbnail correlation (in [−1, 1]) of an appearance candidate. Default 0.8
    /// (measured on the synthetic room: a revisit 5 cm / 2° from a keyframe scores 0.96, the
    /// opposite wall 0.43 and another room from the same pose 0.57).
    pub appearance_min_score: f64,
    /// At most this many appearance candidates per keyframe. Default 5 (LSD-SLAM keeps
    /// `max(5, (maxLoopClosureCandidates + 1)/2)` far candidates).
    pub max_far_candidates: usize,
    /// Appearance candidates must be at least this many graph edges away from the new
    /// keyframe's parent (closer ones are already constrained). Default 4
    /// (`findConstraintsForNewKeyFrames`).
    pub min_far_graph_distance: usize,
    /// Keyframes created before this many others are never constraint candidates. LSD-SLAM
    /// skips its first 5 (`INITIALIZATION_PHASE_COUNT` in `findConstraintsForNewKeyFrames`),
    /// whose depth comes from its random initialisation. Default 0: every keyframe may be
    /// linked. Why: the first keyframes are where the map's scale is set, and a monocular
    /// traverse that cannot link them to the keyframes that follow carries their scale error
    /// forward as drift; the pose graph repairs a poor early depth better than the skip
    /// protects against it, with the prior initialisation (the default) and with the random
    /// one alike. Measured at a `loop_closure_strictness` of 3, deterministic / 5 default
    /// threaded runs two at a time (trajectory / keyframe ATE, m), 5 → 0: 7-Scenes redkitchen
    /// 0.0461 / 0.0393 → 0.0334 / 0.0303, threaded 0.047–0.050 / 0.040–0.043 → 0.027–0.042 /
    /// 0.026–0.035; TUM fr1/rpy 0.0313 / 0.0289 → 0.0285 / 0.0263, threaded 0.031–0.037 /
    /// 0.030–0.035 → 0.025–0.027 / 0.021–0.026; the synthetic orbit (640×480, random
    /// initialisation, keyframes) 18.4 → 4.0 mm on seed 0, 10.9 → 4.0 on seed 1, 35.1 → 17.2
    /// on seed 2. Values 1–4 land in between, unevenly (redkitchen 0.0489, 0.0308, 0.0417,
    /// 0.0446 deterministic). The cost, on the real sequences only: depth scored at the
    /// trajectory's scale (`eval depth`, `eval mesh`) drops — redkitchen densified 48.3 →
    /// 43.5 % correct, fused mesh accuracy / completeness 0.39 / 0.37 → 0.28 / 0.30; fr1/rpy
    /// densified 21.2 → 11.1 % — while the synthetic orbit gains (mesh 0.76 / 0.78 → 0.79 /
    /// 0.82). The keyframes agree better with one another (the spread over keyframes of the
    /// median log ratio of sensor to estimated depth: redkitchen 0.030 → 0.023, fr1/rpy 0.37 →
    /// 0.30), but as a whole their depths now sit off the path's scale (that median: −0.006 →
    /// −0.056 and 0.23 → 0.33). Presumably no single scale fits both the path and depths whose
    /// shape the prior compressed; the old default's chain happened to match them on
    /// redkitchen. At the default strictness of 4.5 the offset grows on redkitchen (−0.071;
    /// densified 40.1 %, mesh 0.25 / 0.27) and shrinks on fr1/rpy (0.18; densified 24.5 %).
    pub skip_initial_keyframes: usize,
    /// Multiplier on the reciprocal-consistency thresholds. Default 4.5, three times LSD-SLAM's
    /// 1.5 (`loopclosureStrictness`). Why: at 1.5 the test rejects most constraints between
    /// keyframes 4–15 apart on real hand-held sequences (consistencies of 9,000–30,000 for
    /// pairs that, once accepted, lower the ATE), so without loops the graph is a chain of
    /// short links whose errors add up. Unrelated views still fail at stage 0 (the alignment
    /// diverges or is not good), before the threshold matters. Measured with
    /// `skip_initial_keyframes` = 0 (trajectory / keyframe ATE, m; deterministic, then 5
    /// default threaded runs one at a time): 7-Scenes redkitchen 0.0334 / 0.0303 and
    /// 0.028–0.044 / 0.026–0.037 at 3 (three of the five near 0.043), 0.0297 / 0.0274 and
    /// 0.029–0.030 / 0.027–0.028 at 4.5, 0.029–0.032 / 0.027–0.029 threaded at 6; TUM fr1/rpy
    /// 0.0285 / 0.0263 and 0.024–0.025 / 0.020–0.021 at 3, 0.0244 / 0.0221 and 0.023–0.030 /
    /// 0.019–0.024 at 4.5, 0.0311 / 0.0272 deterministic at 10; the synthetic orbit's keyframes
    /// (seeds 0, 1, 2) 4.0 / 4.0 / 17.2 mm at 3, 4.5 / 3.5 / 18.8 at 4.5. The cost: keyframes
    /// placed to agree with distant ones sit further from the path's scale (see
    /// `skip_initial_keyframes`), redkitchen's densified depth 43.5 → 40.1 % correct and fused
    /// mesh accuracy / completeness 0.28 / 0.30 → 0.25 / 0.27 (deterministic, 3 → 4.5). Earlier,
    /// with the skip at 5: redkitchen 0.052–0.053 / 0.044–0.045 at 1.5, 0.046–0.049 /
    /// 0.040–0.042 at 3, 0.044–0.048 / 0.037–0.041 at 6 (5 threaded runs each).
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
    /// Huber width on `sqrt(rᵀΩr)` of a pose-graph edge; `None` disables it. Default
    /// `5·sqrt(6000·1.5)` ≈ 474 (`kernelDelta` of `testConstraint` at LSD-SLAM's strictness;
    /// tying it to the strictness of 3, ≈ 671, changed no ATE by more than 0.0005 m).
    pub pose_graph_huber: Option<f64>,
    /// Capacity of the command channel of a spawned back end; a full channel makes the frame
    /// path wait. Default 256. The back end runs below the frame path's priority
    /// ([`crate::background::Priority::Graph`]), so under overload (four sessions on two cores)
    /// it falls tens of keyframes behind and catches up when the load eases; with 16 the
    /// sessions' frame paths then stalled for seconds. The commands are keyframes, which the
    /// graph keeps anyway, and shared depth maps, so a long queue costs no memory beyond the
    /// map's own.
    pub channel_capacity: usize,
}

impl Default for BackendConfig {
    fn default() -> Self {
        Self {
            min_level: 1,
            max_level: PYRAMID_LEVELS - 1,
            max_iterations: [5, 20, 50, 100, 100],
            lambda_initial: 0.0,
            lambda_success_factor: 0.5,
            lambda_fail_factor: 2.0,
            step_size_min: 1e-8,
            convergence_eps: 0.999,
            camera_pixel_noise2: 16.0,
            var_weight: 1.0,
            huber_d: 3.0,
            max_diff_constant: 40.0 * 40.0,
            max_diff_grad_mult: 0.5 * 0.5,
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
            pose_graph_huber: Some(5.0 * (6000.0f64 * 1.5).sqrt()),
            channel_capacity: 256,
        }
    }
}

impl BackendConfig {
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
        let positive = [
            ("lambda_success_factor", self.lambda_success_factor),
            ("lambda_fail_factor", self.lambda_fail_factor),
            ("convergence_eps", self.convergence_eps),
            ("camera_pixel_noise2", self.camera_pixel_noise2),
            ("var_weight", self.var_weight),
            ("huber_d", self.huber_d),
            ("max_diff_constant", self.max_diff_constant),
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
        if self.channel_capacity == 0 {
            return Err(Error::Config(
                "backend: channel_capacity must be ≥ 1".into(),
            ));
        }
        Ok(())
    }
}
