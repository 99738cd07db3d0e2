//! Parameters of the sliding-window odometry back end, with DSO's defaults where DSO has one
//! (Engel, Koltun and Cremers, TPAMI 2018; `settings.cpp` of JakobEngel/dso, read, not copied).

use serde::{Deserialize, Serialize};

use crate::frame::PYRAMID_LEVELS;
use crate::{Error, Result};

/// Most initialisers [`OdometryConfig::focal_candidates`] may start (each costs one
/// initialiser's work per frame until the hand-over).
const MAX_FOCAL_CANDIDATES: usize = 8;

/// Configuration of [`super::SlidingWindow`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OdometryConfig {
    /// Most keyframes in the window (`setting_maxFrames` = 7); the one past it is marginalised.
    pub max_frames: usize,
    /// Fewest keyframes kept when marginalising by rule (`setting_minFrames` = 5).
    pub min_frames: usize,
    /// Pyramid level the window's residuals live on. Default 0: DSO optimises at full
    /// resolution; coarse levels are the tracker's job.
    pub level: usize,
    /// Gauss–Newton iterations per optimisation (DSO runs ≈ 6 per keyframe).
    pub iterations: usize,
    /// Huber width of one pattern pixel's weighted residual, grey levels (`setting_huberTH`).
    pub huber: f64,
    /// Constant `c` of the gradient weight `c² / (c² + |∇I|²)` (`setting_outlierTHSumComponent`
    /// = 50²): edges, where a sub-pixel error means a large residual, count less.
    pub gradient_weight_c: f64,
    /// A point's pattern in one target is an outlier when its energy exceeds this squared per
    /// pattern pixel (`setting_outlierTH` = 12²·8).
    pub outlier_threshold: f64,
    /// Information of the affine brightness `a` of every keyframe about 0 (DSO keeps a prior
    /// on `a` and `b` so that brightness changes are allowed but not free). It also fixes the
    /// brightness gauge, which the photometric residuals leave open.
    pub affine_prior_a: f64,
    /// Information of the affine offset `b` about 0, per grey level².
    pub affine_prior_b: f64,
    /// Weight of what marginalised points leave in the prior (`setting_margWeightFac` = 0.5²):
    /// the prior is linearised once and cannot be relinearised, so it is trusted less.
    pub marginalisation_weight: f64,
    /// A keyframe leaves the window when fewer than this share of its points are still seen
    /// in the newest keyframe (`setting_minPointsRemaining` = 0.05).
    pub min_points_remaining: f64,
    /// …or when its brightness differs from the newest's by more than `e^this`
    /// (`setting_maxLogAffFacInWindow` = 0.7).
    pub max_log_affine_in_window: f64,
    /// Active points the window keeps (`setting_desiredPointDensity` = 2000).
    pub active_points: usize,
    /// Candidates selected per new keyframe (`setting_desiredImmatureDensity` = 1500).
    pub candidate_points: usize,
    /// A new keyframe when `t·f_t + r·f_rt + a·|Δa| > 1`, `f_t` the RMS image motion of the
    /// reference points from translation alone and `f_rt` from the whole motion, in pixels at
    /// 640×480 (scaled with `width + height`), `Δa` the log brightness change. DSO's weights:
    /// `t` = 0.04 (`setting_maxShiftWeightT`), `r` = 0.02 (`…RT`), `a` = 2 (`…Affine`).
    pub keyframe_translation_weight: f64,
    pub keyframe_rotation_weight: f64,
    pub keyframe_affine_weight: f64,
    /// Rolling shutter: seconds from reading the first image row to the last (0: a global
    /// shutter). Each row's pose then follows the keyframe's tracked velocity. Default 0: it
    /// helps rendered rolling-shutter video, but 23 or 30 ms made the real sequences worse
    /// (docs/tuning.md, 2026-11-28, fifth stop); a camera's known read-out time may be set.
    pub rolling_shutter_readout: f64,
    /// Least baseline, in mean depths of the first frame (`|t| · mean ρ`), at which the
    /// initialiser hands over; 0: DSO's rule alone (five frames after the snap). 1/60 is DSO's
    /// own snap threshold `√(alphaK/alphaW)` in scale-free units: it takes redkitchen 0-299
    /// from 0.104 to 0.023 m (nine orders of its first frame), but started 5-25 frames later
    /// only one of five starts gains, so it is not the default (docs/tuning.md, 2026-12-07).
    pub init_min_parallax: f64,
    /// Focal lengths tried at initialisation, relative to the given one, each by its own
    /// initialiser on the same frames; the one whose map and poses fit the images best is
    /// kept for the whole run ([`super::focal`]). Empty: the given focal length alone. For a
    /// camera whose focal length is not known or suspect, e.g. `[0.9, 1.0, 1.1]` (about 3×
    /// the initialiser's work, and a joint refinement per candidate at the hand-over). Not
    /// the default: it chose the true focal length in 76 % of rendered starts and waits for
    /// twice the parallax (docs/tuning.md, 2026-12-07).
    pub focal_candidates: Vec<f64>,
    /// Whether the initialiser waits for the two-view geometry of tracked corners (an
    /// essential matrix with a clear winner and 1° of parallax, as ORB-SLAM's) and starts its
    /// map from it ([`super::two_view`]); off: DSO's photometric initialiser alone, which
    /// hands over inverted maps in about half the starts (docs/tuning.md, 2026-12-07).
    pub init_two_view: bool,
    /// With a metric depth model: information of a window point's relative inverse depth
    /// `(ρ − ρ_model)/ρ_model` about the model's, in the photometric energy's units (a weak
    /// per-point prior, as D3VO's and CNN-SVO's, that pulls the window's depths to the
    /// model's metres where the photometric terms leave them free); 0: off. Ignored without
    /// a metric model. Off by default: with FastDepth 30 takes redkitchen 0-299 from 0.027 to
    /// 0.019 m, but TUM fr1/rpy (rotation, a poor fit of the model) gets worse from 30 and
    /// loses 62 of its frames at 100 (docs/tuning.md, 2026-12-07, fiftieth stop).
    pub metric_prior_weight: f64,
    /// Relative inverse-depth error past which that prior is linear (Huber): a single-image
    /// network is wrong by far on some pixels (20 %, not swept).
    pub metric_prior_huber: f64,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self {
            max_frames: 7,
            min_frames: 5,
            level: 0,
            iterations: 6,
            huber: 9.0,
            gradient_weight_c: 50.0,
            outlier_threshold: 12.0,
            affine_prior_a: 1e4,
            affine_prior_b: 1.0,
            marginalisation_weight: 0.25,
            min_points_remaining: 0.05,
            max_log_affine_in_window: 0.7,
            active_points: 2000,
            candidate_points: 1500,
            keyframe_translation_weight: 0.04,
            keyframe_rotation_weight: 0.02,
            keyframe_affine_weight: 2.0,
            rolling_shutter_readout: 0.0,
            init_min_parallax: 0.0,
            focal_candidates: Vec::new(),
            init_two_view: true,
            metric_prior_weight: 0.0,
            metric_prior_huber: 0.2,
        }
    }
}

impl OdometryConfig {
    /// Checks sizes and factors.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str| Err(Error::Config(format!("odometry: {what}")));
        if self.max_frames < 3 || self.max_frames > 16 {
            return bad("max_frames must be in 3..=16");
        }
        if self.min_frames < 2 || self.min_frames > self.max_frames {
            return bad("min_frames must be in 2..=max_frames");
        }
        if self.level >= PYRAMID_LEVELS {
            return bad("level outside the pyramid");
        }
        if self.iterations == 0 || self.iterations > 100 {
            return bad("iterations must be in 1..=100");
        }
        for (v, name) in [
            (self.huber, "huber"),
            (self.gradient_weight_c, "gradient_weight_c"),
            (self.outlier_threshold, "outlier_threshold"),
            (self.affine_prior_a, "affine_prior_a"),
            (self.affine_prior_b, "affine_prior_b"),
            (self.marginalisation_weight, "marginalisation_weight"),
            (self.max_log_affine_in_window, "max_log_affine_in_window"),
            (
                self.keyframe_translation_weight,
                "keyframe_translation_weight",
            ),
            (self.keyframe_rotation_weight, "keyframe_rotation_weight"),
            (self.keyframe_affine_weight, "keyframe_affine_weight"),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(&format!("{name} must be positive"));
            }
        }
        if !(self.rolling_shutter_readout.is_finite()
            && (0.0..=1.0).contains(&self.rolling_shutter_readout))
        {
            return bad("rolling_shutter_readout must be in 0..=1 s");
        }
        if !(self.init_min_parallax.is_finite() && (0.0..=1.0).contains(&self.init_min_parallax)) {
            return bad("init_min_parallax must be in 0..=1 mean depths");
        }
        if self.focal_candidates.len() > MAX_FOCAL_CANDIDATES
            || !self
                .focal_candidates
                .iter()
                .all(|s| s.is_finite() && (0.5..=2.0).contains(s))
        {
            return bad(
                "focal_candidates: at most 8, each in 0.5..=2 times the given focal length",
            );
        }
        if !(self.metric_prior_weight.is_finite() && self.metric_prior_weight >= 0.0) {
            return bad("metric_prior_weight must be ≥ 0");
        }
        if !(self.metric_prior_huber.is_finite() && self.metric_prior_huber > 0.0) {
            return bad("metric_prior_huber must be positive");
        }
        if self.active_points == 0 || self.active_points > 20_000 {
            return bad("active_points must be in 1..=20000");
        }
        if self.candidate_points == 0 || self.candidate_points > 20_000 {
            return bad("candidate_points must be in 1..=20000");
        }
        if !(0.0..1.0).contains(&self.min_points_remaining) {
            return bad("min_points_remaining must be in [0, 1)");
        }
        Ok(())
    }
}
