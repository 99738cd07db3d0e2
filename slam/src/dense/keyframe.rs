//! What the dense layer produces per keyframe, and the stage maps kept for evaluation.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::geometry::{PinholeCamera, Sim3};
use crate::graph::KeyframeId;
use crate::image::ImageF32;
use crate::scale_shift::ScaleShift;

/// How a keyframe was densified.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DenseMode {
    /// With the depth prior (the paper's method).
    Prior,
    /// No model loaded, or the prior could not be aligned to this keyframe: densified from the
    /// filtered semi-dense depth with image-edge-aware smoothness (issue 4, item 5).
    NoModel,
}

/// Every intermediate map of one keyframe at the working resolution, all inverse depths in the
/// keyframe's own gauge (0 = no value). Kept when `dense.keep_stages` is set, for
/// `relfusion eval depth` and `relfusion eval ablation`.
#[derive(Clone, Debug, PartialEq)]
pub struct DenseStages {
    /// Keyframe intensity (0..255).
    pub intensity: ImageF32,
    /// The network's raw relative inverse depth `D_CNN` (None without a model).
    pub prior: Option<ImageF32>,
    /// `D'_CNN = a·D_CNN + b` (eq. 2–3), when the alignment succeeded.
    pub prior_aligned: Option<ImageF32>,
    /// Raw semi-dense inverse depth and variance (LSD-SLAM's map, resampled).
    pub semidense: ImageF32,
    pub semidense_var: ImageF32,
    /// After the adaptive filter (eqs. 4–9); equal to the raw map when the filter is off.
    pub filtered: ImageF32,
    pub filtered_var: ImageF32,
}

/// Wall times of one keyframe's dense stages (milliseconds). Also the `timings` record of
/// `keyframes/index.json` (`dense::store`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DenseTimings {
    pub prior_ms: f64,
    pub align_ms: f64,
    pub filter_ms: f64,
    pub densify_ms: f64,
    pub two_view_ms: f64,
}

/// One densified keyframe (the `KeyframeDensified` event's payload).
#[derive(Clone, Debug, PartialEq)]
pub struct DenseKeyframe {
    pub keyframe_id: KeyframeId,
    pub timestamp: f64,
    /// Undistorted pinhole camera at the working resolution.
    pub camera: PinholeCamera,
    /// Keyframe pose when it was densified (the back end may move it later).
    pub world_from_keyframe: Sim3,
    /// Dense inverse depth `D_opt` in the keyframe's gauge (0 = invalid).
    pub idepth: Arc<ImageF32>,
    /// Its variance: the filtered semi-dense variance on semi-dense pixels, the pose-uncertainty
    /// propagation (eq. 16) elsewhere, plus the growth with the distance to the semi-dense
    /// pixels (`dense.support_variance`, `dense::support`).
    pub variance: Arc<ImageF32>,
    pub mode: DenseMode,
    /// The scale/shift of eq. (3), when the prior was aligned.
    pub align: Option<ScaleShift>,
    /// Why the prior was not used for this keyframe, if it was not.
    pub align_error: Option<String>,
    /// Pixels that passed the two-view consistency check (eq. 15) and went to the back end.
    pub consistent_pixels: usize,
    pub timings: DenseTimings,
    pub stages: Option<Arc<DenseStages>>,
}

impl DenseKeyframe {
    /// Bytes of its maps (depth, variance and, when kept, the stages).
    pub fn heap_bytes(&self) -> usize {
        let image = |i: &ImageF32| 4 * i.data.len();
        let stages = self.stages.as_deref().map_or(0, |s| {
            [
                Some(&s.intensity),
                s.prior.as_ref(),
                s.prior_aligned.as_ref(),
                Some(&s.semidense),
                Some(&s.semidense_var),
                Some(&s.filtered),
                Some(&s.filtered_var),
            ]
            .into_iter()
            .flatten()
            .map(image)
            .sum()
        });
        image(&self.idepth) + image(&self.variance) + stages
    }
}
