//! Parameters of the SE(3) direct image alignment, with LSD-SLAM's defaults
//! (`DenseDepthTrackerSettings` and the constants of `util/settings.h` in tum-vision/lsd_slam).

use serde::{Deserialize, Serialize};

use crate::frame::PYRAMID_LEVELS;
use crate::optim::{LmSchedule, PhotometricParams};
use crate::{Error, Result};

/// Configuration of [`super::SE3Tracker`]. Every field has LSD-SLAM's value as its default, so a
/// config file only lists what it changes. Its user settings are listed in
/// [`crate::pipeline::user_config`]; the rest is expert level (LSD-SLAM's constants).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingConfig {
    /// Finest pyramid level optimised. Default 1 (`SE3TRACKING_MIN_LEVEL`): full resolution
    /// costs four times level 1. 0 adds a refinement on every `level0_point_step`-th point; it
    /// did not pay overall (docs/tuning.md, "Tracking at full resolution").
    pub min_level: usize,
    /// With `min_level = 0`, level 0 is optimised on every `level0_point_step`-th reference
    /// point only. Default 4: a quarter of a 640×480 keyframe's ~100 k points still
    /// over-determines six parameters, at level 1's cost. The pixel-count checks
    /// (`min_good_per_all*`) count each used point for this many pixels.
    pub level0_point_step: usize,
    /// Coarsest pyramid level, where the optimisation starts. Default 4
    /// (`SE3TRACKING_MAX_LEVEL` − 1): 40×30 at 640×480, a wide basin for hand-held motion.
    pub max_level: usize,
    /// The Levenberg–Marquardt schedule (LSD-SLAM's).
    pub lm: LmSchedule,
    /// The photometric residual model (LSD-SLAM's).
    pub photometric: PhotometricParams,
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
    /// Tracking is lost unless the Pearson correlation between keyframe and frame intensities
    /// at the warped points of the finest level exceeds this. Default 0.5. Not in LSD-SLAM:
    /// its good-pixel test lets an unrelated image pass, the (brightness-invariant)
    /// correlation does not (docs/tuning.md, "Tracking correlation").
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
            lm: LmSchedule::default(),
            photometric: PhotometricParams::default(),
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
        self.lm.validate("tracking")?;
        self.photometric.validate("tracking")?;
        let non_negative = [
            ("min_good_per_good_bad", self.min_good_per_good_bad),
            ("min_good_per_all", self.min_good_per_all),
            ("min_good_per_all_absmin", self.min_good_per_all_absmin),
            ("relocalization_threshold", self.relocalization_threshold),
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
