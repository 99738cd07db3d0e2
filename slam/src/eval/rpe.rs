//! Relative pose error (Sturm et al., IROS 2012, §VI.A; evo's `evo_rpe`): the drift of the
//! estimate over a fixed number of frames.
//!
//! For matched poses Qᵢ (ground truth) and Pᵢ (estimate), both `world_from_camera`, and a frame
//! offset Δ, the error of the pair (i, i+Δ) is
//!
//! ```text
//! Eᵢ = (Qᵢ⁻¹ · Q_{i+Δ})⁻¹ · (Pᵢ⁻¹ · P_{i+Δ})
//! ```
//!
//! whose translation norm is the translational RPE and whose rotation angle is the rotational
//! RPE. As in evo (without `--all_pairs`), the pairs are consecutive *non-overlapping* ones:
//! (0, Δ), (Δ, 2Δ), ... over the matched poses; Δ counts matched poses, not input lines.
//!
//! evo_rpe does not align by default. A rigid alignment cannot change Eᵢ (it cancels in
//! Pᵢ⁻¹·P_{i+Δ}); a Sim(3) alignment rescales the estimate's translations, which is what a
//! monocular estimate needs for its RPE to be in metres (`evo_rpe -a -s`).

use serde::Serialize;

use super::Stats;
use super::associate::{DEFAULT_MAX_DT, Matched, associate_poses};
use super::ate::{AlignMode, align, apply_alignment};
use crate::dataset::trajectory::StampedPose;
use crate::{Error, Result};

/// RPE of one estimate for one frame offset.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RpeResult {
    /// RMSE of ‖trans(Eᵢ)‖, in ground-truth metres (after the alignment's scale, if any).
    pub trans_rmse: f64,
    /// RMSE of the rotation angle of Eᵢ, in degrees.
    pub rot_rmse_deg: f64,
    /// All statistics of the translational errors.
    pub trans: Stats,
    /// All statistics of the rotational errors (degrees).
    pub rot_deg: Stats,
    /// Frame offset Δ.
    pub delta: usize,
    /// Number of pose pairs (i, i+Δ).
    pub pairs: usize,
    pub align: AlignMode,
    /// Scale applied to the estimate (1 unless [`AlignMode::Sim3`]).
    pub scale: f64,
}

/// RPE of `est` against `gt` for a frame offset `delta`, associating poses by nearest timestamp
/// within [`DEFAULT_MAX_DT`].
pub fn rpe(
    gt: &[StampedPose],
    est: &[StampedPose],
    delta: usize,
    mode: AlignMode,
) -> Result<RpeResult> {
    rpe_matched(&associate_poses(gt, est, DEFAULT_MAX_DT)?, delta, mode)
}

/// RPE of already matched poses.
pub fn rpe_matched(matched: &Matched, delta: usize, mode: AlignMode) -> Result<RpeResult> {
    if delta == 0 {
        return Err(Error::Eval("RPE frame offset must be at least 1".into()));
    }
    if matched.len() <= delta {
        return Err(Error::Eval(format!(
            "RPE with a {delta}-frame offset needs more than {delta} matched poses, got {}",
            matched.len()
        )));
    }
    let alignment = align(matched, mode)?;
    let est: Vec<_> = matched
        .est
        .iter()
        .map(|p| apply_alignment(&alignment, &p.world_from_camera))
        .collect();
    let gt: Vec<_> = matched.gt.iter().map(|p| p.world_from_camera).collect();
    let (mut trans, mut rot) = (Vec::new(), Vec::new());
    let starts: Vec<usize> = (0..matched.len()).step_by(delta).collect();
    for w in starts.windows(2) {
        let (i, j) = (w[0], w[1]);
        let gt_rel = gt[i].inverse() * gt[j];
        let est_rel = est[i].inverse() * est[j];
        let e = gt_rel.inverse() * est_rel;
        trans.push(e.translation.norm());
        rot.push(e.rotation.log().norm().to_degrees());
    }
    let trans = Stats::from_errors(&trans)?;
    let rot_deg = Stats::from_errors(&rot)?;
    Ok(RpeResult {
        trans_rmse: trans.rmse,
        rot_rmse_deg: rot_deg.rmse,
        trans,
        rot_deg,
        delta,
        pairs: trans.count,
        align: mode,
        scale: alignment.scale,
    })
}

#[cfg(test)]
mod tests {
    use super::super::ate::tests::{helix, transformed};
    use super::*;
    use crate::geometry::{SE3, SO3, Sim3};
    use nalgebra::Vector3;

    #[test]
    fn eval_rpe_ignores_a_rigid_offset_but_not_a_scale() {
        let gt = helix(61);
        let rigid = Sim3 {
            rotation: SO3::exp(&Vector3::new(1.0, 0.2, -0.4)),
            translation: Vector3::new(5.0, 6.0, 7.0),
            scale: 1.0,
        };
        let est = transformed(&gt, &rigid);
        let r = rpe(&gt, &est, 1, AlignMode::None).expect("rpe");
        assert_eq!(r.pairs, 60);
        assert!(r.trans_rmse < 1e-12 && r.rot_rmse_deg < 1e-9, "{r:?}");

        let scaled = transformed(
            &gt,
            &Sim3 {
                scale: 2.0,
                ..rigid
            },
        );
        let raw = rpe(&gt, &scaled, 1, AlignMode::None).expect("rpe");
        assert!(raw.trans_rmse > 1e-3 && raw.rot_rmse_deg < 1e-9, "{raw:?}");
        let aligned = rpe(&gt, &scaled, 1, AlignMode::Sim3).expect("rpe");
        assert!(aligned.trans_rmse < 1e-9, "{aligned:?}");
        assert!((aligned.scale - 0.5).abs() < 1e-9);
    }

    #[test]
    fn eval_rpe_measures_a_known_drift() {
        // Ground truth steps 1 m along z; the estimate steps 1.1 m: every relative pose is off by
        // 0.1 m; a 2-frame offset doubles it. The estimate also yaws (about z) 0.5° per frame.
        let pose = |i: usize, step: f64, yaw_deg: f64| StampedPose {
            timestamp: i as f64,
            world_from_camera: SE3::new(
                SO3::exp(&Vector3::new(0.0, 0.0, (yaw_deg * i as f64).to_radians())),
                Vector3::new(0.0, 0.0, step * i as f64),
            ),
        };
        let gt: Vec<_> = (0..11).map(|i| pose(i, 1.0, 0.0)).collect();
        let est: Vec<_> = (0..11).map(|i| pose(i, 1.1, 0.5)).collect();
        let d1 = rpe(&gt, &est, 1, AlignMode::None).expect("rpe");
        assert_eq!(d1.pairs, 10);
        assert!((d1.rot_rmse_deg - 0.5).abs() < 1e-9, "{d1:?}");
        // The relative translation is expressed in frame i; a yaw leaves the z axis in place.
        assert!((d1.trans_rmse - 0.1).abs() < 1e-9, "{d1:?}");
        let d2 = rpe(&gt, &est, 2, AlignMode::None).expect("rpe");
        assert_eq!(d2.pairs, 5, "pairs (0,2), (2,4), ..., (8,10)");
        assert!((d2.trans_rmse - 0.2).abs() < 1e-9 && (d2.rot_rmse_deg - 1.0).abs() < 1e-9);
    }

    #[test]
    fn eval_rpe_rejects_bad_offsets() {
        let gt = helix(5);
        assert!(rpe(&gt, &gt, 0, AlignMode::None).is_err());
        assert!(rpe(&gt, &gt, 5, AlignMode::None).is_err());
        assert_eq!(
            rpe(&gt, &gt, 4, AlignMode::None).expect("one pair").pairs,
            1
        );
    }
}
