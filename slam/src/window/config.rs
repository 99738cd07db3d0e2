//! Parameters of the windowed photometric bundle adjustment, with DSO's defaults where DSO has
//! one (Engel et al., TPAMI 2018; `settings.cpp` of JakobEngel/dso).

use serde::{Deserialize, Serialize};

use crate::frame::PYRAMID_LEVELS;
use crate::{Error, Result};

/// Configuration of [`super::WindowOptimizer`]. Expert level; `enabled` switches it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WindowConfig {
    /// Run the window after every new keyframe of the back end.
    pub enabled: bool,
    /// Keyframes in the window. Default 7 (DSO keeps 5-7 active keyframes).
    pub keyframes: usize,
    /// The oldest keyframes of the window whose poses and brightness are held fixed: they
    /// carry the gauge (position, orientation and scale) from the previous windows. Default 2,
    /// the fewest that fix the scale.
    pub fixed_keyframes: usize,
    /// Points hosted per keyframe, one per grid cell of the strongest gradient that has a
    /// semi-dense depth. Default 400 (DSO activates ≈ 2000 over its window).
    pub points_per_keyframe: usize,
    /// Pyramid level the residuals are evaluated on. Default 1 (half resolution: a wide
    /// enough basin for the poses the pose graph hands over, sub-pixel accurate at 640×480).
    pub level: usize,
    /// Levenberg–Marquardt iterations. Default 10.
    pub iterations: usize,
    /// Huber width of a pattern pixel's weighted residual, grey levels. Default 9
    /// (`setting_huberTH`).
    pub huber: f64,
    /// Gradient-dependent weight `c² / (c² + |∇I|²)` of a residual (`setting_outlierTHSumComponent`
    /// = 50²): edges, where a sub-pixel error means a large residual, count less.
    pub gradient_weight_c: f64,
    /// A point's residual in a target is dropped when its pattern energy exceeds this per pixel,
    /// grey levels (`setting_outlierTH` = 12² per pattern pixel).
    pub outlier_threshold: f64,
    /// Information of a window edge relative to the Sim(3) alignment of the same pair in the
    /// pose graph. Default 4: the window, which sees every point in every keyframe, outweighs
    /// a pairwise alignment.
    pub edge_weight: f64,
}

impl Default for WindowConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            keyframes: 7,
            fixed_keyframes: 2,
            points_per_keyframe: 400,
            level: 1,
            iterations: 10,
            huber: 9.0,
            gradient_weight_c: 50.0,
            outlier_threshold: 12.0,
            edge_weight: 4.0,
        }
    }
}

impl WindowConfig {
    /// Checks sizes and factors.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str| Err(Error::Config(format!("backend.window: {what}")));
        if self.keyframes < 3 || self.keyframes > 32 {
            return bad("keyframes must be in 3..=32");
        }
        if self.fixed_keyframes < 1 || self.fixed_keyframes >= self.keyframes {
            return bad("fixed_keyframes must be at least 1 and fewer than keyframes");
        }
        if self.points_per_keyframe == 0 || self.points_per_keyframe > 20_000 {
            return bad("points_per_keyframe must be in 1..=20000");
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
            (self.edge_weight, "edge_weight"),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(&format!("{name} must be positive"));
            }
        }
        Ok(())
    }
}
