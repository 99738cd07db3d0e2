//! Parameters of the SE(3) direct image alignment, with LSD-SLAM's defaults
//! (`DenseDepthTrackerSettings` and the constants of `util/settings.h` in tum-vision/lsd_slam).

use serde::{Deserialize, Serialize};

use crate::frame::PYRAMID_LEVELS;
use crate::{Error, Result};

/// Configuration of [`super::SE3Tracker`]. Every field has LSD-SLAM's value as its default, so a
/// config file only lists what it changes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingConfig {
    /// Finest pyramid level optimised. Default 1 (`SE3TRACKING_MIN_LEVEL`): LSD-SLAM skips full
    /// resolution for frame-to-keyframe tracking because it costs four times level 1. 0 adds
    /// a full-resolution refinement on every `level0_point_step`-th point, measured on
    /// 7-Scenes redkitchen (deterministic, PyDNet++, with `max_iterations[0] = 1`, before
    /// `mapping.propagation_var_inc` was introduced): ATE
    /// 0.097 → 0.076 m, tracking 6.0 → 8.2–9.0 ms per frame (on the mapping thread 11.5 →
    /// 14.6 ms per frame unpaced, past issue 3's 13 ms); but the translation gets shorter
    /// still against the map's depth in the rotation-heavy middle, so densified depth scored
    /// at the trajectory's scale falls from 21.9 to 10.7 % correct, and the synthetic orbit's
    /// ATE rises from 1.06 to 1.23 cm. Not a net gain, hence not the default.
    pub min_level: usize,
    /// With `min_level = 0`, level 0 is optimised on every `level0_point_step`-th reference
    /// point only. Default 4: a semi-dense keyframe has ~100 k points at 640×480, a quarter
    /// still over-determines six parameters, and level 0 then costs about what level 1 does.
    /// The pixel-count tracking checks (`min_good_per_all*`) count each used point for this
    /// many pixels.
    pub level0_point_step: usize,
    /// Coarsest pyramid level, where the optimisation starts. Default 4
    /// (`SE3TRACKING_MAX_LEVEL` − 1): 40×30 at 640×480, wide enough a basin for hand-held motion.
    pub max_level: usize,
    /// Maximum Levenberg–Marquardt iterations per level, finest first. Default
    /// `[5, 20, 50, 100, 100]` (`maxItsPerLvl`): cheap coarse levels may iterate long, the fine
    /// levels only refine.
    pub max_iterations: [usize; PYRAMID_LEVELS],
    /// Initial LM damping λ at every level. Default 0 (`lambdaInitial`): start with
    /// Gauss–Newton, damp only after a rejected step.
    pub lambda_initial: f64,
    /// λ is multiplied by this after an accepted step (and reset to 0 once ≤ 0.2). Default 0.5
    /// (`lambdaSuccessFac`).
    pub lambda_success_factor: f64,
    /// After the k-th rejected try of an iteration λ is multiplied by this to the power k (or
    /// set to 0.2 if it was 0). Default 2 (`lambdaFailFac`).
    pub lambda_fail_factor: f64,
    /// A level ends when a rejected increment δ has `|δ|² ≤` this. Default 1e-8 (`stepSizeMin`).
    pub step_size_min: f64,
    /// A level ends when an accepted step leaves `cost_new / cost_old >` this (less than 0.1 %
    /// improvement). Default 0.999 (`convergenceEps`).
    pub convergence_eps: f64,
    /// Image-noise variance (8-bit units²) in the residual variance
    /// `σ_r² = camera_pixel_noise2 + var_weight · (∂r/∂d)² · V_d` (ECCV 2014 eq. (13), where it
    /// is written `2σ_I²`). Default 16 = 4² (`cameraPixelNoise2`), the value LSD-SLAM's code
    /// adds once for both images.
    pub camera_pixel_noise2: f32,
    /// Multiplier on the inverse-depth variance in `σ_r²`. Default 1 (`var_weight`).
    pub var_weight: f32,
    /// Huber width on the variance-normalised residual: weights are 1 below `huber_d / 2` and
    /// `(huber_d/2)/|r/σ|` above, exactly as LSD-SLAM's `calcWeightsAndResidual`. Default 3
    /// (`huber_d`).
    pub huber_d: f32,
    /// A warped point counts as *good* when `r² < max_diff_constant + max_diff_grad_mult·|∇I|²`.
    /// Default 40² (`MAX_DIFF_CONSTANT`).
    pub max_diff_constant: f32,
    /// Gradient term of the good-point test (edges tolerate larger photometric errors). Default
    /// 0.5² (`MAX_DIFF_GRAD_MULT`).
    pub max_diff_grad_mult: f32,
    /// Tracking is lost unless `good / (good + bad) >` this at the finest level. Default 0.5
    /// (`MIN_GOODPERGOODBAD_PIXEL`).
    pub min_good_per_good_bad: f32,
    /// Tracking is lost unless `good / (level width · height) >` this at the finest level: too
    /// few constraints for a trustworthy pose. Default 0.04 (`MIN_GOODPERALL_PIXEL`).
    pub min_good_per_all: f32,
    /// The optimisation diverged (lost) when fewer than this share of the level's pixels
    /// received a warped reference point at any evaluation. Default 0.01
    /// (`MIN_GOODPERALL_PIXEL_ABSMIN`).
    pub min_good_per_all_absmin: f32,
    /// Tracking is lost unless the Pearson correlation between keyframe intensities and frame
    /// intensities at the warped points of the finest level exceeds this. Default 0.5.
    ///
    /// Not in LSD-SLAM (relfusion addition): LSD's good-pixel test (`max_diff_*`) accepts
    /// intensity differences up to ~45 grey levels at edges, so an *unrelated* image still
    /// scores `good_ratio` 0.55–0.9 and passes. The correlation is invariant to the affine
    /// brightness change and separates the cases clearly: correctly tracked frames give
    /// 0.93–1.0 on synthetic rooms and 0.85–0.995 on 7-Scenes / TUM fr1 with sensor depth,
    /// unrelated rooms or scenes −0.05–0.31, gross drift (tens of degrees) 0.4–0.6.
    pub min_correlation: f32,
    /// Estimate an affine brightness change `I_frame ≈ a·I_ref + b` between keyframe and frame
    /// (auto exposure). Default true (`useAffineLightningEstimation`).
    pub affine_lighting: bool,
    /// A relocalisation candidate is accepted when its tracking is good and
    /// `point_usage · good_ratio >` this. Default 0.7 (`relocalizationTH`).
    pub relocalization_threshold: f32,
}

impl Default for TrackingConfig {
    fn default() -> Self {
        Self {
            min_level: 1,
            level0_point_step: 4,
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
            min_good_per_good_bad: 0.5,
            min_good_per_all: 0.04,
            min_good_per_all_absmin: 0.01,
            min_correlation: 0.5,
            affine_lighting: true,
            relocalization_threshold: 0.7,
        }
    }
}

impl TrackingConfig {
    /// Checks the level range and that every factor is positive and finite.
    pub fn validate(&self) -> Result<()> {
        if self.min_level > self.max_level || self.max_level >= PYRAMID_LEVELS {
            return Err(Error::Config(format!(
                "tracking: levels {}..={} outside 0..{PYRAMID_LEVELS}",
                self.min_level, self.max_level
            )));
        }
        if self.level0_point_step == 0 {
            return Err(Error::Config(
                "tracking: level0_point_step must be ≥ 1".into(),
            ));
        }
        let positive = [
            ("lambda_success_factor", self.lambda_success_factor),
            ("lambda_fail_factor", self.lambda_fail_factor),
            ("convergence_eps", self.convergence_eps),
            ("camera_pixel_noise2", f64::from(self.camera_pixel_noise2)),
            ("huber_d", f64::from(self.huber_d)),
            ("max_diff_constant", f64::from(self.max_diff_constant)),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::Config(format!(
                    "tracking: {name} must be > 0, got {v}"
                )));
            }
        }
        let non_negative = [
            ("lambda_initial", self.lambda_initial),
            ("step_size_min", self.step_size_min),
            ("var_weight", f64::from(self.var_weight)),
            ("max_diff_grad_mult", f64::from(self.max_diff_grad_mult)),
            (
                "min_good_per_good_bad",
                f64::from(self.min_good_per_good_bad),
            ),
            ("min_good_per_all", f64::from(self.min_good_per_all)),
            (
                "min_good_per_all_absmin",
                f64::from(self.min_good_per_all_absmin),
            ),
            (
                "relocalization_threshold",
                f64::from(self.relocalization_threshold),
            ),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::Config(format!(
                    "tracking: {name} must be ≥ 0, got {v}"
                )));
            }
        }
        if !(-1.0..=1.0).contains(&self.min_correlation) {
            return Err(Error::Config(format!(
                "tracking: min_correlation must be in [-1, 1] (-1 disables it), got {}",
                self.min_correlation
            )));
        }
        Ok(())
    }
}
