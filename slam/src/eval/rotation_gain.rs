//! Per-axis rotation gain: the share of the ground truth's relative rotation that the estimate
//! recovers about each camera axis. A diagnostic of the focal length and of the depth map's
//! shape, not an accuracy metric.
//!
//! For the same non-overlapping pose pairs (i, i+Δ) as [`super::rpe`], let aᵢ = log(Qᵢ⁻¹·Q_{i+Δ})
//! and bᵢ = log(Pᵢ⁻¹·P_{i+Δ}) be the relative rotations (rotation vectors in camera axes) of
//! ground truth and estimate. The gain about axis k is the least-squares slope
//!
//! ```text
//! g_k = Σᵢ a_ik·b_ik / Σᵢ a_ik²
//! ```
//!
//! Why it is worth printing: a rotation θ about the camera's x or y axis moves the image by
//! about f·θ pixels, so a tracker given a focal length f′ recovers f/f′ of it, while a roll
//! (about the optical axis, z) moves pixels independently of f. Gains below 1 about x and y
//! with a z gain near 1 are therefore the signature of a focal length set too long, or of
//! rotation mistaken for translation; tracking noise alone leaves all three near 1. Over a
//! narrow field of view a yaw and a sideways translation move the image almost alike, and the
//! map's depths decide the split (figures on the shared sequences: docs/tuning.md,
//! "Diagnostics").
//!
//! Relative rotations do not depend on the world frame, so no alignment is applied. A fixed
//! rotation between the estimate's and the ground truth's camera axes (e.g. a colour camera
//! tracked against a depth camera's ground truth) would mix the axes; for a rigid rig it is
//! well below a degree.

use serde::Serialize;

use super::associate::Matched;
use crate::dataset::trajectory::StampedPose;
use crate::{Error, Result};

/// Per-axis rotation gains of one estimate for one frame offset.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RotationGain {
    /// Gain about the camera's x (pitch), y (yaw) and z (roll) axes; `None` for an axis the
    /// ground truth hardly turns about (RMS below [`MIN_AXIS_RMS_DEG`]), whose slope is noise.
    pub gain: [Option<f64>; 3],
    /// RMS of the ground truth's relative rotation about each axis, in degrees.
    pub gt_rms_deg: [f64; 3],
    /// Frame offset Δ.
    pub delta: usize,
    /// Number of pose pairs (i, i+Δ).
    pub pairs: usize,
}

/// Axes whose ground-truth relative rotation has a smaller RMS (degrees) get no gain.
pub const MIN_AXIS_RMS_DEG: f64 = 0.05;

/// Rotation gains of matched poses over pairs `delta` frames apart.
pub fn rotation_gain(matched: &Matched, delta: usize) -> Result<RotationGain> {
    if delta == 0 || matched.len() <= delta {
        return Err(Error::Eval(format!(
            "rotation gain with a {delta}-frame offset needs an offset ≥ 1 and more matched \
             poses than it, got {}",
            matched.len()
        )));
    }
    let (mut ab, mut aa) = ([0.0f64; 3], [0.0f64; 3]);
    let starts: Vec<usize> = (0..matched.len()).step_by(delta).collect();
    for w in starts.windows(2) {
        let (i, j) = (w[0], w[1]);
        let relative = |poses: &[StampedPose]| {
            (poses[i].world_from_camera.rotation.inverse() * poses[j].world_from_camera.rotation)
                .log()
        };
        let (a, b) = (relative(&matched.gt), relative(&matched.est));
        for k in 0..3 {
            ab[k] += a[k] * b[k];
            aa[k] += a[k] * a[k];
        }
    }
    let pairs = starts.len() - 1;
    let gt_rms_deg = aa.map(|s| (s / pairs as f64).sqrt().to_degrees());
    let gain = std::array::from_fn(|k| (gt_rms_deg[k] >= MIN_AXIS_RMS_DEG).then(|| ab[k] / aa[k]));
    Ok(RotationGain {
        gain,
        gt_rms_deg,
        delta,
        pairs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{SE3, SO3};
    use nalgebra::Vector3;

    /// Poses turning by `rate(i)` (a rotation vector, radians) per frame in camera axes, scaled
    /// per axis by `scale`, with some translation that must not matter.
    fn turning(n: usize, scale: [f64; 3]) -> Vec<StampedPose> {
        let mut pose = SE3::identity();
        (0..n)
            .map(|i| {
                let t = i as f64;
                let step = Vector3::new(
                    0.02 * (0.3 * t).sin() * scale[0],
                    0.03 * (0.2 * t).cos() * scale[1],
                    0.01 * (0.5 * t).sin() * scale[2],
                );
                let out = StampedPose {
                    timestamp: t,
                    world_from_camera: pose,
                };
                pose = pose * SE3::new(SO3::exp(&step), Vector3::new(0.01, 0.0, 0.02 * t));
                out
            })
            .collect()
    }

    #[test]
    fn eval_rotation_gain_recovers_a_per_axis_scale() {
        let gt = turning(61, [1.0; 3]);
        let same = Matched {
            gt: gt.clone(),
            est: gt.clone(),
        };
        let g = rotation_gain(&same, 1).expect("gain");
        assert_eq!(g.pairs, 60);
        for k in 0..3 {
            assert!((g.gain[k].expect("turns") - 1.0).abs() < 1e-9, "{g:?}");
        }
        // A tracker with a focal length 25 % too long under-turns pitch and yaw, not roll.
        let short = Matched {
            gt,
            est: turning(61, [0.8, 0.8, 1.0]),
        };
        let g = rotation_gain(&short, 1).expect("gain");
        assert!((g.gain[0].expect("x") - 0.8).abs() < 0.01, "{g:?}");
        assert!((g.gain[1].expect("y") - 0.8).abs() < 0.01, "{g:?}");
        assert!((g.gain[2].expect("z") - 1.0).abs() < 0.01, "{g:?}");
        // Compounded steps are not exactly the sum of the per-frame vectors: larger offsets
        // still see the same gain.
        let g5 = rotation_gain(&short, 5).expect("gain");
        assert_eq!(g5.pairs, 12);
        assert!((g5.gain[0].expect("x") - 0.8).abs() < 0.03, "{g5:?}");
    }

    #[test]
    fn eval_rotation_gain_skips_still_axes_and_bad_offsets() {
        let gt = turning(21, [1.0, 1.0, 0.0]);
        let m = Matched {
            gt: gt.clone(),
            est: gt,
        };
        let g = rotation_gain(&m, 1).expect("gain");
        assert!(g.gain[2].is_none() && g.gt_rms_deg[2] < 1e-9, "{g:?}");
        assert!(rotation_gain(&m, 0).is_err());
        assert!(rotation_gain(&m, 21).is_err());
    }
}
