//! How well a second sequence was localised in a saved map (issue 24's measure).
//!
//! The map's frame is tied to the ground truth by the Sim(3) that aligns the map's own
//! keyframes to *their* ground truth (from the mapping sequence only): the localised poses are
//! not re-aligned, so a localiser cannot look good by fitting its own output. Frames of the
//! second sequence "see the mapped area" when their true pose is within
//! [`OverlapParams::distance_m`] and [`OverlapParams::angle_deg`] of a true pose of the mapping
//! sequence.

use serde::Serialize;

use super::{AlignMode, DEFAULT_MAX_DT, align, associate_poses};
use crate::dataset::trajectory::StampedPose;
use crate::{Error, Result};

/// What counts as a view of the mapped area.
#[derive(Clone, Copy, Debug)]
pub struct OverlapParams {
    pub distance_m: f64,
    pub angle_deg: f64,
}

impl Default for OverlapParams {
    /// 0.3 m and 25°, as issue 24 states its goal.
    fn default() -> Self {
        Self {
            distance_m: 0.3,
            angle_deg: 25.0,
        }
    }
}

/// The scores.
#[derive(Clone, Debug, Serialize)]
pub struct LocalizationScores {
    /// Frames of the second sequence with ground truth.
    pub frames: usize,
    /// Of which see the mapped area.
    pub overlapping: usize,
    /// Of those, localised.
    pub overlapping_localized: usize,
    /// `overlapping_localized / overlapping`.
    pub recall: f64,
    /// RMS position error (metres) of the localised overlapping frames.
    pub overlapping_rms_m: f64,
    /// Localised frames in all, and their RMS and largest position error.
    pub localized: usize,
    pub localized_rms_m: f64,
    pub localized_max_m: f64,
    /// Localised frames that do not see the mapped area, and of all localised frames those
    /// more than `wrong_m` off (a wrong pose given with confidence).
    pub localized_outside: usize,
    pub wrong: usize,
    pub wrong_m: f64,
    /// The map keyframes' own ATE under the alignment (metres): the floor of the errors above.
    pub map_keyframe_rms_m: f64,
    pub map_keyframes: usize,
}

/// Scores `localized` (timestamp, map pose) of a sequence with ground truth `gt`, for a map
/// whose keyframes `map_keyframes` come from a sequence with ground truth `map_gt`. Frames more
/// than `wrong_m` off count as wrong.
pub fn score_localization(
    map_gt: &[StampedPose],
    map_keyframes: &[StampedPose],
    gt: &[StampedPose],
    localized: &[StampedPose],
    overlap: OverlapParams,
    wrong_m: f64,
) -> Result<LocalizationScores> {
    let matched_map = associate_poses(map_gt, map_keyframes, DEFAULT_MAX_DT)?;
    if matched_map.gt.len() < 3 {
        return Err(Error::Eval(
            "fewer than 3 map keyframes have ground truth".into(),
        ));
    }
    let gt_from_map = align(&matched_map, AlignMode::Sim3)?;
    let map_keyframe_rms_m = rms(matched_map.gt.iter().zip(&matched_map.est).map(|(g, e)| {
        (g.world_from_camera.translation - gt_from_map.act(&e.world_from_camera.translation)).norm()
    }));
    let cos_limit = overlap.angle_deg.to_radians().cos();
    // The angle between the optical axes (the viewing directions), as for keyframe overlap.
    let axis = |p: &StampedPose| p.world_from_camera.rotation.matrix().column(2).into_owned();
    let sees_map = |p: &StampedPose| {
        map_gt.iter().any(|m| {
            (m.world_from_camera.translation - p.world_from_camera.translation).norm()
                < overlap.distance_m
                && axis(m).dot(&axis(p)) > cos_limit
        })
    };
    let overlapping: Vec<&StampedPose> = gt.iter().filter(|p| sees_map(p)).collect();
    let matched = associate_poses(gt, localized, DEFAULT_MAX_DT).unwrap_or(super::Matched {
        gt: Vec::new(),
        est: Vec::new(),
    });
    let mut errors_overlapping = Vec::new();
    let mut errors = Vec::new();
    let mut outside = 0;
    for (g, e) in matched.gt.iter().zip(&matched.est) {
        let error = (g.world_from_camera.translation
            - gt_from_map.act(&e.world_from_camera.translation))
        .norm();
        errors.push(error);
        if sees_map(g) {
            errors_overlapping.push(error);
        } else {
            outside += 1;
        }
    }
    Ok(LocalizationScores {
        frames: gt.len(),
        overlapping: overlapping.len(),
        overlapping_localized: errors_overlapping.len(),
        recall: errors_overlapping.len() as f64 / overlapping.len().max(1) as f64,
        overlapping_rms_m: rms(errors_overlapping.iter().copied()),
        localized: errors.len(),
        localized_rms_m: rms(errors.iter().copied()),
        localized_max_m: errors.iter().copied().fold(0.0, f64::max),
        localized_outside: outside,
        wrong: errors.iter().filter(|&&e| e > wrong_m).count(),
        wrong_m,
        map_keyframe_rms_m,
        map_keyframes: matched_map.gt.len(),
    })
}

fn rms(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
    if n == 0 { 0.0 } else { (sum / n as f64).sqrt() }
}
