//! Finding and verifying keyframe-to-keyframe constraints (LSD-SLAM §3.5 "Constraint search";
//! `TrackableKeyFrameSearch` and `SlamSystem::{findConstraintsForNewKeyFrames, testConstraint,
//! tryTrackSim3}` in tum-vision/lsd_slam).
//!
//! Candidates for a new keyframe come from two sources: keyframes whose pose is close (distance
//! in units of scene depth, viewing directions within a fraction of the field of view), and —
//! for loop closures whose drifted poses are far apart — keyframes that *look* alike (a tiny
//! normalised thumbnail compared by correlation, standing in for LSD-SLAM's optional FAB-MAP).
//! Every candidate is verified by the *reciprocal* test: Sim(3) alignment in both directions,
//! coarse-to-fine in three stages, each accepted only if both alignments are good and their
//! composition `T_ba·T_ab` is the identity within the propagated uncertainty (Mahalanobis
//! distance below a threshold), which rejects the wrong minima single alignments fall into.

use std::sync::Arc;

use super::config::BackendConfig;
use super::points::KeyframeLevels;
use super::pose_graph::Constraint;
use super::sim3_tracker::{Sim3TrackResult, Sim3Tracker};
use super::KeyframeId;
use crate::frame::{Frame, PYRAMID_LEVELS};
use crate::geometry::{Matrix7, Sim3};
use crate::mapping::DepthMap;
use crate::Result;

/// Thumbnail size of the appearance descriptor (columns × rows).
pub const THUMBNAIL_SIZE: (usize, usize) = (16, 12);

/// A cheap global image descriptor: the coarsest pyramid level resampled to
/// [`THUMBNAIL_SIZE`], minus its mean, scaled to unit norm. Two views of the same place from
/// nearby viewpoints correlate strongly; it is neither rotation- nor scale-invariant, which is
/// acceptable because a proposal is verified by Sim(3) alignment from the identity anyway.
#[derive(Clone, Debug, PartialEq)]
pub struct Thumbnail(Vec<f32>);

impl Thumbnail {
    /// The descriptor of `frame`.
    pub fn new(frame: &Frame) -> Self {
        let level = frame.pyramid.levels.len().min(PYRAMID_LEVELS).saturating_sub(1);
        let img = &frame.level(level).image;
        let (tw, th) = THUMBNAIL_SIZE;
        let mut v = Vec::with_capacity(tw * th);
        for j in 0..th {
            for i in 0..tw {
                let x = (i as f32 + 0.5) * img.width as f32 / tw as f32 - 0.5;
                let y = (j as f32 + 0.5) * img.height as f32 / th as f32 - 0.5;
                let x = x.clamp(0.0, (img.width - 1) as f32);
                let y = y.clamp(0.0, (img.height - 1) as f32);
                v.push(img.bilinear(x, y).unwrap_or(0.0));
            }
        }
        let mean = v.iter().sum::<f32>() / v.len() as f32;
        v.iter_mut().for_each(|x| *x -= mean);
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        if norm > 1e-3 {
            v.iter_mut().for_each(|x| *x /= norm);
        } else {
            v.iter_mut().for_each(|x| *x = 0.0);
        }
        Self(v)
    }

    /// Normalised cross-correlation in [−1, 1] (0 for a textureless thumbnail).
    pub fn score(&self, other: &Thumbnail) -> f64 {
        self.0.iter().zip(&other.0).map(|(a, b)| f64::from(a * b)).sum()
    }
}

/// A keyframe as the back end keeps it: image, published depth, depth pyramid and descriptor.
#[derive(Clone, Debug)]
pub struct Keyframe {
    pub id: KeyframeId,
    pub frame: Arc<Frame>,
    pub depth: Arc<DepthMap>,
    pub levels: KeyframeLevels,
    pub thumbnail: Thumbnail,
}

impl Keyframe {
    /// Builds the depth pyramid and descriptor (fails when depth and frame sizes differ).
    pub fn new(id: KeyframeId, frame: Arc<Frame>, depth: Arc<DepthMap>) -> Result<Self> {
        let levels = KeyframeLevels::new(&frame, &depth)?;
        let thumbnail = Thumbnail::new(&frame);
        Ok(Self { id, frame, depth, levels, thumbnail })
    }

    /// Horizontal and vertical field of view (radians).
    pub fn field_of_view(&self) -> (f64, f64) {
        let c = &self.frame.camera;
        (
            2.0 * (f64::from(c.width) / (2.0 * c.fx)).atan(),
            2.0 * (f64::from(c.height) / (2.0 * c.fy)).atan(),
        )
    }
}

/// Whether two keyframes are close enough to try a constraint (LSD-SLAM's
/// `findEuclideanOverlapFrames` with `checkBothScales`): the squared distance between the
/// camera centres, in units of the smaller of the two mean scene depths, is at most
/// `close_distance / kf_dist_weight²`, and the optical axes differ by at most
/// `close_angle_fraction` of the mean field of view. Returns the squared distance when close.
pub fn pose_proximity(
    config: &BackendConfig,
    a: &Keyframe,
    world_from_a: &Sim3,
    b: &Keyframe,
    world_from_b: &Sim3,
) -> Option<f64> {
    // World distances × (mean inverse depth / world scale) = distances in units of the depth.
    let fac_a = a.levels.mean_idepth / world_from_a.scale;
    let fac_b = b.levels.mean_idepth / world_from_b.scale;
    let dist2 = (world_from_a.translation - world_from_b.translation).norm_squared()
        * fac_a.min(fac_b).powi(2);
    if !(dist2 <= config.close_distance / (config.kf_dist_weight * config.kf_dist_weight)) {
        return None;
    }
    let (fx, fy) = a.field_of_view();
    let cos_limit = (config.close_angle_fraction * 0.5 * (fx + fy)).cos();
    let axis_a = world_from_a.rotation.matrix().column(2).into_owned();
    let axis_b = world_from_b.rotation.matrix().column(2).into_owned();
    (axis_a.dot(&axis_b) >= cos_limit).then_some(dist2)
}

/// Squared Mahalanobis distance of `b_from_a · a_from_b` from the identity, for estimates with
/// right-perturbation informations `info_ba`, `info_ab`: `d = log(T_ba·T_ab)` varies as
/// `Ad(T_ab⁻¹)·δ_ba + δ_ab`, so `Σ_d = Ad(T_ab⁻¹)·Ω_ba⁻¹·Ad(T_ab⁻¹)ᵀ + Ω_ab⁻¹` and the result is
/// `dᵀ Σ_d⁻¹ d` (LSD-SLAM's `reciprocalConsistency`). `None` when an information is singular.
pub fn reciprocal_consistency(
    b_from_a: &Sim3,
    info_ba: &Matrix7,
    a_from_b: &Sim3,
    info_ab: &Matrix7,
) -> Option<f64> {
    let d = (*b_from_a * *a_from_b).log();
    let adj = a_from_b.inverse().adjoint();
    let cov = adj * info_ba.try_inverse()? * adj.transpose() + info_ab.try_inverse()?;
    let cov = 0.5 * (cov + cov.transpose());
    let m = d.dot(&(cov.try_inverse()? * d));
    m.is_finite().then_some(m)
}

/// Result of a reciprocal test between keyframes a and b.
#[derive(Clone, Debug, PartialEq)]
pub struct ReciprocalCheck {
    /// The two constraints `a → b` and `b → a` when accepted.
    pub constraints: Option<(Constraint, Constraint)>,
    /// The stage (0, 1, 2) at which the test stopped, `None` when accepted.
    pub failed_stage: Option<usize>,
    /// Squared Mahalanobis inconsistency of the last stage evaluated (∞ when an alignment
    /// was not good).
    pub consistency: f64,
    /// The two alignments of the last stage run (a as reference, then b as reference).
    pub forward: Option<Sim3TrackResult>,
    pub backward: Option<Sim3TrackResult>,
}

/// The staged reciprocal test of LSD-SLAM's `testConstraint`: for each stage, align b to a and
/// a to b (each from its previous estimate) on the stage's levels, and stop as soon as either is
/// not good or their inconsistency exceeds `stage_thresholds[k]·strictness`. Stage 0 runs from
/// [`BackendConfig::max_level`] down to `stage_levels[0]`, later stages on `stage_levels[k]`
/// alone. The accepted constraints carry the finest stage's informations.
pub fn reciprocal_test(
    tracker: &Sim3Tracker,
    a: &Keyframe,
    b: &Keyframe,
    initial_b_from_a: &Sim3,
    strictness: f64,
) -> ReciprocalCheck {
    let cfg = tracker.config();
    let mut b_from_a = *initial_b_from_a;
    let mut a_from_b = initial_b_from_a.inverse();
    let mut check = ReciprocalCheck {
        constraints: None,
        failed_stage: None,
        consistency: f64::INFINITY,
        forward: None,
        backward: None,
    };
    for (stage, (&level, &threshold)) in
        cfg.stage_levels.iter().zip(&cfg.stage_thresholds).enumerate()
    {
        let coarsest = if stage == 0 { cfg.max_level } else { level };
        let forward =
            tracker.track_levels(&a.levels, &b.frame, &b.levels, &b_from_a, coarsest, level);
        let good_forward = forward.good;
        b_from_a = forward.frame_from_reference;
        check.forward = Some(forward);
        if !good_forward {
            check.failed_stage = Some(stage);
            check.consistency = f64::INFINITY;
            return check;
        }
        let backward =
            tracker.track_levels(&b.levels, &a.frame, &a.levels, &a_from_b, coarsest, level);
        let good_backward = backward.good;
        a_from_b = backward.frame_from_reference;
        check.backward = Some(backward);
        if !good_backward {
            check.failed_stage = Some(stage);
            check.consistency = f64::INFINITY;
            return check;
        }
        let (Some(fw), Some(bw)) = (&check.forward, &check.backward) else {
            check.failed_stage = Some(stage);
            return check;
        };
        check.consistency =
            reciprocal_consistency(&b_from_a, &fw.information, &a_from_b, &bw.information)
                .unwrap_or(f64::INFINITY);
        if !(check.consistency <= threshold * strictness) {
            check.failed_stage = Some(stage);
            return check;
        }
    }
    if let (Some(fw), Some(bw)) = (&check.forward, &check.backward) {
        check.constraints = Some((
            Constraint { from: a.id, to: b.id, to_from_from: b_from_a, information: fw.information },
            Constraint { from: b.id, to: a.id, to_from_from: a_from_b, information: bw.information },
        ));
    }
    check
}
