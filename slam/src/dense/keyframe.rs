//! What the dense layer produces per keyframe, and the stage maps kept for evaluation.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::geometry::{PinholeCamera, Sim3};
use crate::graph::KeyframeId;
use crate::image::ImageF32;
use crate::scale_shift::ScaleShift;
use crate::spill::{Reader, Spillable, Writer};
use crate::{Error, Result};

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

/// Dense keyframes older than the session's working set spill with the keyframe's compact data
/// (issue 37): their maps are read back, bit-identical, by the exports and saved maps.
impl Spillable for DenseKeyframe {
    fn encode(&self, out: &mut Writer) {
        out.u64(self.keyframe_id as u64);
        out.f64(self.timestamp);
        out.camera(&self.camera);
        out.sim3(&self.world_from_keyframe);
        out.image(&self.idepth);
        out.image(&self.variance);
        out.u8(match self.mode {
            DenseMode::Prior => 0,
            DenseMode::NoModel => 1,
        });
        match &self.align {
            Some(fit) => {
                out.u8(1);
                out.f64(fit.a);
                out.f64(fit.b);
                out.u64(fit.used as u64);
            }
            None => out.u8(0),
        }
        match &self.align_error {
            Some(e) => {
                out.u8(1);
                out.str(e);
            }
            None => out.u8(0),
        }
        out.u64(self.consistent_pixels as u64);
        let t = &self.timings;
        for v in [
            t.prior_ms,
            t.align_ms,
            t.filter_ms,
            t.densify_ms,
            t.two_view_ms,
        ] {
            out.f64(v);
        }
        match &self.stages {
            Some(s) => {
                out.u8(1);
                out.image(&s.intensity);
                out.opt_image(s.prior.as_ref());
                out.opt_image(s.prior_aligned.as_ref());
                for image in [&s.semidense, &s.semidense_var, &s.filtered, &s.filtered_var] {
                    out.image(image);
                }
            }
            None => out.u8(0),
        }
    }

    fn decode(input: &mut Reader<'_>) -> Result<Self> {
        let keyframe_id = input.usize()?;
        let timestamp = input.f64()?;
        let camera = input.camera()?;
        let world_from_keyframe = input.sim3()?;
        let idepth = Arc::new(input.image()?);
        let variance = Arc::new(input.image()?);
        let mode = match input.u8()? {
            0 => DenseMode::Prior,
            1 => DenseMode::NoModel,
            m => return Err(Error::Spill(format!("unknown dense mode {m}"))),
        };
        let align = match input.u8()? {
            0 => None,
            _ => Some(ScaleShift {
                a: input.f64()?,
                b: input.f64()?,
                used: input.usize()?,
            }),
        };
        let align_error = match input.u8()? {
            0 => None,
            _ => Some(input.string()?),
        };
        let consistent_pixels = input.usize()?;
        let timings = DenseTimings {
            prior_ms: input.f64()?,
            align_ms: input.f64()?,
            filter_ms: input.f64()?,
            densify_ms: input.f64()?,
            two_view_ms: input.f64()?,
        };
        let stages = match input.u8()? {
            0 => None,
            _ => Some(Arc::new(DenseStages {
                intensity: input.image()?,
                prior: input.opt_image()?,
                prior_aligned: input.opt_image()?,
                semidense: input.image()?,
                semidense_var: input.image()?,
                filtered: input.image()?,
                filtered_var: input.image()?,
            })),
        };
        Ok(Self {
            keyframe_id,
            timestamp,
            camera,
            world_from_keyframe,
            idepth,
            variance,
            mode,
            align,
            align_error,
            consistent_pixels,
            timings,
            stages,
        })
    }

    fn heap_bytes(&self) -> usize {
        DenseKeyframe::heap_bytes(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{SO3, Sim3};

    fn image(w: usize, h: usize, seed: f32) -> ImageF32 {
        ImageF32 {
            width: w,
            height: h,
            data: (0..w * h).map(|i| seed + i as f32 * 0.25).collect(),
        }
    }

    #[test]
    fn a_dense_keyframe_reads_back_equal() {
        let camera = PinholeCamera::new(50.0, 51.0, 15.5, 11.5, 32, 24).expect("camera");
        let pose = Sim3::new(
            SO3::exp(&nalgebra::Vector3::new(0.1, -0.2, 0.3)),
            nalgebra::Vector3::new(1.0, 2.0, -3.0),
            0.7,
        );
        let mut kf = DenseKeyframe {
            keyframe_id: 9,
            timestamp: 12.25,
            camera,
            world_from_keyframe: pose,
            idepth: Arc::new(image(32, 24, 0.5)),
            variance: Arc::new(image(32, 24, 0.01)),
            mode: DenseMode::Prior,
            align: Some(ScaleShift {
                a: 1.5,
                b: -0.25,
                used: 321,
            }),
            align_error: None,
            consistent_pixels: 77,
            timings: DenseTimings {
                prior_ms: 1.0,
                align_ms: 2.0,
                filter_ms: 3.0,
                densify_ms: 4.0,
                two_view_ms: 5.0,
            },
            stages: None,
        };
        let back = crate::spill::round_trip(&kf).expect("round trip");
        assert_eq!(back, kf);
        kf.mode = DenseMode::NoModel;
        kf.align = None;
        kf.align_error = Some("too few pixels".into());
        kf.stages = Some(Arc::new(DenseStages {
            intensity: image(32, 24, 1.0),
            prior: None,
            prior_aligned: Some(image(32, 24, 2.0)),
            semidense: image(32, 24, 3.0),
            semidense_var: image(32, 24, 4.0),
            filtered: image(32, 24, 5.0),
            filtered_var: image(32, 24, 6.0),
        }));
        assert_eq!(crate::spill::round_trip(&kf).expect("round trip"), kf);
    }
}
