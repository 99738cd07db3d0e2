//! Absolute trajectory error (Sturm et al., IROS 2012, §VI.B; evo's `evo_ape`, translation
//! part): the distance between ground-truth and estimated camera positions after aligning the
//! estimate to the ground truth with [`umeyama`](super::umeyama::umeyama).
//!
//! A monocular system such as the paper's recovers the trajectory up to a similarity, so its
//! ATE is reported after Sim(3) alignment (`evo_ape tum gt est -a -s`); the alignment's scale is
//! also the "optimal trajectory scale" the paper (§V.A) applies to depth maps before
//! measuring the percentage of correct depth.

use std::fmt;
use std::str::FromStr;

use nalgebra::Vector3;
use serde::Serialize;

use super::Stats;
use super::associate::{DEFAULT_MAX_DT, Matched, associate_poses};
use super::umeyama::umeyama;
use crate::dataset::trajectory::StampedPose;
use crate::geometry::{SE3, SO3, Sim3};
use crate::{Error, Result};

/// How the estimate is aligned to the ground truth before errors are measured.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum AlignMode {
    /// Rotation, translation and scale (`evo_ape -a -s`): for monocular estimates.
    #[default]
    Sim3,
    /// Rotation and translation (`evo_ape -a`): for metric estimates (stereo, RGB-D).
    Se3,
    /// No alignment (`evo_ape` without flags): both trajectories share a world frame.
    None,
}

impl FromStr for AlignMode {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "sim3" => Ok(Self::Sim3),
            "se3" => Ok(Self::Se3),
            "none" => Ok(Self::None),
            other => Err(Error::Config(format!(
                "alignment `{other}`: expected sim3, se3 or none"
            ))),
        }
    }
}

impl fmt::Display for AlignMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Sim3 => "sim3",
            Self::Se3 => "se3",
            Self::None => "none",
        })
    }
}

/// ATE of one estimate. Statistics are over the matched poses, in metres of the ground truth.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AteResult {
    pub rmse: f64,
    pub mean: f64,
    pub median: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
    /// Sum of squared errors.
    pub sse: f64,
    /// Scale of the alignment (1 unless [`AlignMode::Sim3`]): ground-truth metres per
    /// estimate unit.
    pub scale: f64,
    /// Number of matched poses the errors are taken over.
    pub matched: usize,
    pub align: AlignMode,
    /// `gt_from_est`: maps estimated positions onto the ground truth (`s·R·p + t`).
    #[serde(skip)]
    pub alignment: Sim3,
    /// Per matched pose, ‖p_gt − alignment(p_est)‖, in matching order.
    #[serde(skip)]
    pub errors: Vec<f64>,
}

/// The alignment `gt_from_est` of matched poses for `mode` (identity for [`AlignMode::None`]).
pub fn align(matched: &Matched, mode: AlignMode) -> Result<Sim3> {
    let identity = Sim3 {
        rotation: SO3::identity(),
        translation: Vector3::zeros(),
        scale: 1.0,
    };
    let with_scale = match mode {
        AlignMode::None => return Ok(identity),
        AlignMode::Se3 => false,
        AlignMode::Sim3 => true,
    };
    let est: Vec<_> = matched
        .est
        .iter()
        .map(|p| p.world_from_camera.translation)
        .collect();
    let gt: Vec<_> = matched
        .gt
        .iter()
        .map(|p| p.world_from_camera.translation)
        .collect();
    umeyama(&est, &gt, with_scale)
}

/// Applies `gt_from_est` to an estimated camera pose: the camera centre moves with the full
/// similarity, the attitude with its rotation (evo's `scale` then `transform`).
pub(crate) fn apply_alignment(gt_from_est: &Sim3, pose: &SE3) -> SE3 {
    SE3::new(
        gt_from_est.rotation * pose.rotation,
        gt_from_est.act(&pose.translation),
    )
}

/// ATE of `est` against `gt`, associating poses by nearest timestamp within
/// [`DEFAULT_MAX_DT`]. Use [`associate_poses`] and [`ate_matched`] for another window.
pub fn ate(gt: &[StampedPose], est: &[StampedPose], mode: AlignMode) -> Result<AteResult> {
    ate_matched(&associate_poses(gt, est, DEFAULT_MAX_DT)?, mode)
}

/// ATE of already matched poses.
pub fn ate_matched(matched: &Matched, mode: AlignMode) -> Result<AteResult> {
    let alignment = align(matched, mode)?;
    let errors: Vec<f64> = matched
        .gt
        .iter()
        .zip(&matched.est)
        .map(|(g, e)| {
            (g.world_from_camera.translation - alignment.act(&e.world_from_camera.translation))
                .norm()
        })
        .collect();
    let s = Stats::from_errors(&errors)?;
    Ok(AteResult {
        rmse: s.rmse,
        mean: s.mean,
        median: s.median,
        std: s.std,
        min: s.min,
        max: s.max,
        sse: s.sse,
        scale: alignment.scale,
        matched: matched.len(),
        align: mode,
        alignment,
        errors,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A helix with a varying attitude, 30 Hz.
    pub(crate) fn helix(n: usize) -> Vec<StampedPose> {
        (0..n)
            .map(|i| {
                let t = i as f64 / 30.0;
                StampedPose {
                    timestamp: 10.0 + t,
                    world_from_camera: SE3::new(
                        SO3::exp(&Vector3::new(0.2 * t.sin(), 0.5 * t, 0.1)),
                        Vector3::new(t.cos(), t.sin(), 0.3 * t),
                    ),
                }
            })
            .collect()
    }

    pub(crate) fn transformed(poses: &[StampedPose], t: &Sim3) -> Vec<StampedPose> {
        poses
            .iter()
            .map(|p| StampedPose {
                timestamp: p.timestamp,
                world_from_camera: apply_alignment(t, &p.world_from_camera),
            })
            .collect()
    }

    #[test]
    fn eval_ate_is_zero_for_a_similar_copy_only_with_sim3() {
        let gt = helix(90);
        let est_from_gt = Sim3 {
            rotation: SO3::exp(&Vector3::new(0.4, -1.0, 2.0)),
            translation: Vector3::new(3.0, -1.0, 0.5),
            scale: 0.25,
        };
        let est = transformed(&gt, &est_from_gt);
        let sim3 = ate(&gt, &est, AlignMode::Sim3).expect("ate");
        assert_eq!(sim3.matched, 90);
        assert!(sim3.rmse < 1e-9 && sim3.max < 1e-9, "{sim3:?}");
        assert!((sim3.scale - 4.0).abs() < 1e-9, "scale {}", sim3.scale);
        let se3 = ate(&gt, &est, AlignMode::Se3).expect("ate");
        assert_eq!(se3.scale, 1.0);
        assert!(
            se3.rmse > 0.1,
            "a scaled copy cannot be fitted rigidly: {}",
            se3.rmse
        );
        let none = ate(&gt, &est, AlignMode::None).expect("ate");
        assert!(
            none.rmse > se3.rmse,
            "alignment must not increase the error"
        );
    }

    #[test]
    fn eval_ate_none_measures_raw_offsets() {
        let gt = helix(40);
        let shift = Sim3 {
            rotation: SO3::identity(),
            translation: Vector3::new(0.0, 0.3, 0.4),
            scale: 1.0,
        };
        let est = transformed(&gt, &shift);
        let none = ate(&gt, &est, AlignMode::None).expect("ate");
        assert!(
            (none.rmse - 0.5).abs() < 1e-12 && (none.std).abs() < 1e-12,
            "{none:?}"
        );
        assert!(ate(&gt, &est, AlignMode::Se3).expect("ate").rmse < 1e-9);
    }

    #[test]
    fn eval_ate_uses_only_matched_poses() {
        let gt = helix(60);
        let mut est = gt[10..50].to_vec();
        for p in &mut est {
            p.timestamp += 0.005;
        }
        let r = ate(&gt, &est, AlignMode::Sim3).expect("ate");
        assert_eq!(r.matched, 40);
        assert_eq!(r.errors.len(), 40);
    }

    #[test]
    fn eval_align_mode_parses() {
        assert_eq!("SIM3".parse::<AlignMode>().expect("sim3"), AlignMode::Sim3);
        assert_eq!("se3".parse::<AlignMode>().expect("se3"), AlignMode::Se3);
        assert_eq!("none".parse::<AlignMode>().expect("none"), AlignMode::None);
        assert!("affine".parse::<AlignMode>().is_err());
        assert_eq!(AlignMode::Se3.to_string(), "se3");
    }
}
