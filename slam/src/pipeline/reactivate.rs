//! Keyframe re-activation (LSD-SLAM's `doKFReActivation`: `SlamSystem::changeKeyframe`,
//! `TrackableKeyFrameSearch::findRePositionCandidate`). Before a frame becomes a new keyframe,
//! the old keyframes near it are tried as its tracking reference; the best one that tracks
//! well and would not itself need replacing becomes the current keyframe again. A camera that
//! keeps revisiting a place then stops adding keyframes for it (issue 37: a looping session
//! made 68 keyframes a minute for the same room).
//!
//! - **Candidates.** Finished keyframes whose current pose puts the frame within keyframe
//!   distance (the distance term of [`keyframe_score`] below the threshold) and whose optical
//!   axis is within [`VIEW_ANGLE_OF_FOV`] of the mean field of view of the frame's (LSD's
//!   `findEuclideanOverlapFrames`), nearest first, at most `pipeline.reactivation_candidates`.
//! - **Test.** SE(3) tracking from the relative pose the poses imply; accepted when good and
//!   the full score (distance and point usage) is below the keyframe threshold.
//! - **Re-activated.** The old keyframe's published depth seeds a depth filter (LSD's
//!   `setFromExistingKF`) that the following frames refine, so the next new keyframe is
//!   propagated from a map that kept converging. The keyframe as handed on (back end, dense
//!   layer, fusion, spilled data, saved map) does not change: it was finished once.
//! - **Hand-over.** The keyframe being left gets the tracking estimate between it and the
//!   re-activated one, from the frame tracked against both ([`NewKeyframe::handover`]), so the
//!   new keyframes' chain stays joined to the old map without waiting for a search.
//!
//! [`NewKeyframe::handover`]: crate::graph::NewKeyframe::handover

use std::sync::Arc;

use nalgebra::{Matrix6, Vector3};

use super::Pipeline;
use super::events::{Event, TrackingState};
use super::mapper::Observation;
use crate::Result;
use crate::frame::Frame;
use crate::geometry::{SE3, Sim3};
use crate::graph::{KeyframeId, ParentEdge};
use crate::mapping::{DepthFilter, keyframe_score, keyframe_threshold};
use crate::tracking::TrackingResult;

/// Largest angle between the optical axes of a frame and a candidate, as a share of the mean
/// field of view: LSD-SLAM's 0.75 (`findRePositionCandidate` → `findEuclideanOverlapFrames`).
pub const VIEW_ANGLE_OF_FOV: f64 = 0.75;

/// The old keyframe currently re-activated.
#[derive(Clone, Copy, Debug)]
pub(super) struct Reactivated {
    pub id: KeyframeId,
    /// Its pose when re-activated: the frames tracked against it are reported from it (its pose
    /// at creation is older than the back end's).
    pub world_from_keyframe: Sim3,
}

/// A candidate that tracked well enough to be re-activated.
struct Found {
    id: KeyframeId,
    result: TrackingResult,
    score: f64,
}

impl Pipeline {
    /// Where frames tracked against keyframe `id` are reported from: its pose at
    /// re-activation while re-activated, its pose at creation otherwise.
    pub(super) fn tracking_pose(&self, id: KeyframeId) -> Sim3 {
        match self.reactivated {
            Some(r) if r.id == id => r.world_from_keyframe,
            _ => self.keyframes[id].world_from_keyframe,
        }
    }

    /// `frame`, tracked against the current keyframe `current` as `tracked`, was chosen as a new
    /// keyframe: re-activates an old keyframe instead when one qualifies (see the module docs)
    /// and returns the frame's events; `None` when none does.
    pub(super) fn try_reactivation(
        &mut self,
        frame: &Arc<Frame>,
        current: KeyframeId,
        tracked: &TrackingResult,
        state: TrackingState,
    ) -> Result<Option<Vec<Event>>> {
        if self.config.pipeline.reactivation_candidates == 0 {
            return Ok(None);
        }
        tracing::debug!(frame = frame.id, current, "keyframe decision");
        let world_from_frame = self.tracking_pose(current)
            * Sim3::from_se3(&tracked.frame_from_keyframe.inverse(), 1.0);
        let threshold = keyframe_threshold(&self.config.mapping, self.keyframes.len());
        let mut best: Option<Found> = None;
        for (id, guess, mean_idepth) in
            self.reactivation_candidates(frame, &world_from_frame, current, threshold)
        {
            let reference = self.keyframe_reference(id)?;
            let result = self.tracker.track(&reference, frame, &guess);
            let score = keyframe_score(
                &self.config.mapping,
                &result.frame_from_keyframe.inverse(),
                mean_idepth,
                result.point_usage,
            );
            tracing::debug!(
                keyframe = id,
                frame = frame.id,
                good = result.good,
                score,
                threshold,
                "re-activation candidate"
            );
            if result.good && score < threshold && best.as_ref().is_none_or(|b| score < b.score) {
                best = Some(Found { id, result, score });
            }
        }
        let Some(Found { id, result, .. }) = best else {
            return Ok(None);
        };
        if self.reactivated.is_none() {
            self.keyframes[current].handover = handover_edge(
                id,
                &result,
                self.current_pose(id).scale,
                current,
                tracked,
                self.current_pose(current).scale,
            )
            .map(Box::new);
        }
        self.finish_current()?;
        let filter = DepthFilter::from_depth_map(
            self.keyframe_frame(id)?,
            self.keyframe_depth(id)?.as_ref(),
            self.config.mapping.clone(),
        )?;
        self.mapper.begin(filter)?;
        self.current = Some(id);
        self.reactivated = Some(Reactivated {
            id,
            world_from_keyframe: self.current_pose(id),
        });
        self.stats.keyframes_reactivated += 1;
        self.backend.send(crate::graph::BackendCommand::CatchUp)?;
        tracing::debug!(keyframe = id, frame = frame.id, "keyframe re-activated");
        // The motion model's lengths were in the old keyframe's scale.
        self.velocity = None;
        self.last_frame_from_keyframe = result.frame_from_keyframe;
        let keyframe_from_frame = result.frame_from_keyframe.inverse();
        self.mapper.observe(Observation {
            frame: frame.clone(),
            keyframe_from_frame,
            residual: result.residual,
        })?;
        Ok(Some(vec![self.record_frame(
            frame,
            id,
            keyframe_from_frame,
            state,
        )]))
    }

    /// Old keyframes that may see what `frame` (at `world_from_frame`) sees, nearest first,
    /// each with the `frame_from_keyframe` their poses imply and its mean inverse depth:
    /// those within keyframe distance (`threshold`) and the view angle.
    fn reactivation_candidates(
        &self,
        frame: &Frame,
        world_from_frame: &Sim3,
        current: KeyframeId,
        threshold: f64,
    ) -> Vec<(KeyframeId, SE3, f64)> {
        let n = self.config.pipeline.reactivation_candidates;
        let camera = &frame.camera;
        let fov = (f64::from(camera.width) / (2.0 * camera.fx)).atan()
            + (f64::from(camera.height) / (2.0 * camera.fy)).atan();
        let min_cos = (VIEW_ANGLE_OF_FOV * fov).cos();
        let axis = world_from_frame.rotation.act(&Vector3::z());
        let poses = self.backend.poses();
        let mut near: Vec<(f64, KeyframeId, SE3, f64)> = self
            .keyframes
            .iter()
            .enumerate()
            .filter(|(id, _)| *id != current)
            .filter_map(|(id, record)| {
                let mean_idepth = record.mean_idepth?;
                let world_from_keyframe = poses
                    .get(&id)
                    .copied()
                    .unwrap_or(record.world_from_keyframe);
                if world_from_keyframe.rotation.act(&Vector3::z()).dot(&axis) < min_cos {
                    return None;
                }
                let keyframe_from_frame = world_from_keyframe.inverse() * *world_from_frame;
                let guess = SE3::new(
                    keyframe_from_frame.rotation,
                    keyframe_from_frame.translation,
                );
                let distance = keyframe_score(&self.config.mapping, &guess, mean_idepth, 1.0);
                (distance < threshold).then(|| (distance, id, guess.inverse(), mean_idepth))
            })
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        near.into_iter()
            .take(n)
            .map(|(_, id, guess, mean_idepth)| (id, guess, mean_idepth))
            .collect()
    }
}

/// The hand-over edge `old_from_left` (in the graph's parent-edge form) from one frame tracked
/// against the keyframe being left (`left_tracked`) and the re-activated one (`old_tracked`).
/// The two keyframes' depth units differ: the frame's lengths in the left one's units become
/// the old one's by `k = s_left / s_old` (their current world scales), and the scale itself is
/// only weakly constrained, as for any tracking edge. The covariance is the sum of the two
/// trackings', each carried to the edge's tangent; `None` when either is singular.
fn handover_edge(
    old: KeyframeId,
    old_tracked: &TrackingResult,
    old_scale: f64,
    left: KeyframeId,
    left_tracked: &TrackingResult,
    left_scale: f64,
) -> Option<ParentEdge> {
    let k = left_scale / old_scale;
    if !(k.is_finite() && k > 0.0) {
        return None;
    }
    let frame_from_old = old_tracked.frame_from_keyframe;
    let frame_from_left = left_tracked.frame_from_keyframe;
    // old_from_left = old_from_frame · diag(k) · frame_from_left.
    let old_from_left = Sim3::from_se3(&frame_from_old.inverse(), 1.0)
        * Sim3::new(crate::geometry::SO3::identity(), Vector3::zeros(), k)
        * Sim3::from_se3(&frame_from_left, 1.0);
    // A right perturbation ε of old_from_frame moves to the edge's right end through
    // diag(k)⁻¹ (translation / k) and Ad(left_from_frame); ε itself is Ad(frame_from_old)·η
    // for the tracking's own perturbation η (see `Pipeline::new_keyframe`).
    let sigma_old = old_tracked.information.try_inverse()?;
    let sigma_left = left_tracked.information.try_inverse()?;
    let mut unscale = Matrix6::identity();
    for i in 0..3 {
        unscale[(i, i)] = 1.0 / k;
    }
    let carry = frame_from_left.inverse().adjoint() * unscale * frame_from_old.adjoint();
    let sigma = carry * sigma_old * carry.transpose() + sigma_left;
    let information = sigma.try_inverse()?;
    let information = (information + information.transpose()) * 0.5;
    tracing::debug!(keyframe = left, old, "hand-over edge");
    Some(ParentEdge::from_se3_information(
        old,
        old_from_left,
        &information,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::SO3;

    fn tracked(frame_from_keyframe: SE3, information: f64) -> TrackingResult {
        TrackingResult {
            frame_from_keyframe,
            good: true,
            residual: 1.0,
            good_ratio: 1.0,
            point_usage: 1.0,
            iterations: 1,
            correlation: 1.0,
            information: Matrix6::identity() * information,
        }
    }

    #[test]
    fn the_handover_edge_is_the_similarity_between_the_two_keyframes() {
        // Two keyframes of different depth scales and a frame between them.
        let world_from_old = Sim3::new(
            SO3::exp(&Vector3::new(0.1, -0.2, 0.05)),
            Vector3::new(0.3, 0.1, -0.2),
            0.8,
        );
        let world_from_left = Sim3::new(
            SO3::exp(&Vector3::new(-0.05, 0.1, 0.0)),
            Vector3::new(0.5, 0.0, 0.1),
            1.3,
        );
        let world_from_frame = Sim3::new(
            SO3::exp(&Vector3::new(0.0, 0.05, 0.02)),
            Vector3::new(0.45, 0.05, 0.0),
            1.1,
        );
        // What tracking measures: the frame's rigid pose in each keyframe's coordinates and
        // units.
        let frame_from = |world_from_keyframe: &Sim3| {
            let keyframe_from_frame = world_from_keyframe.inverse() * world_from_frame;
            SE3::new(
                keyframe_from_frame.rotation,
                keyframe_from_frame.translation,
            )
            .inverse()
        };
        let edge = handover_edge(
            1,
            &tracked(frame_from(&world_from_old), 1e4),
            world_from_old.scale,
            2,
            &tracked(frame_from(&world_from_left), 1e4),
            world_from_left.scale,
        )
        .expect("an edge");
        let expected = world_from_old.inverse() * world_from_left;
        assert_eq!(edge.id, 1);
        let error = (edge.parent_from_keyframe * expected.inverse())
            .log()
            .norm();
        assert!(error < 1e-9, "edge off the true similarity by {error}");
        // Two measurements composed: the edge is less certain than either, but still certain.
        let block = edge
            .information
            .matrix()
            .fixed_view::<6, 6>(0, 0)
            .into_owned();
        let eigen = block.symmetric_eigenvalues();
        assert!(eigen.min() > 0.0, "not positive definite: {eigen}");
        assert!(
            eigen.max() <= 1e4 * (1.0 + 1e-9),
            "more certain than a tracking: {eigen}"
        );
        assert!(edge.information.at(6, 6) > 0.0);
        // A singular tracking gives no edge.
        let mut singular = tracked(frame_from(&world_from_left), 1e4);
        singular.information = Matrix6::zeros();
        assert!(
            handover_edge(1, &singular, 0.8, 2, &singular, 1.3).is_none(),
            "an edge from singular trackings"
        );
    }
}
