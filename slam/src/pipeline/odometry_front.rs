//! The pipeline driven by the DSO-class odometry (`pipeline.frontend = "dso"`, issue 35).
//!
//! The odometry ([`crate::odometry`]) poses every frame and chooses the keyframes; each of its
//! keyframes becomes the pipeline's. The semi-dense depth filter no longer carries the pose or
//! the scale: it observes every frame *at the odometry's pose* and is propagated from keyframe
//! to keyframe along them, so that each keyframe still gets the semi-dense map that the dense
//! layer, the back end's loop closures and a saved map need. The first keyframe's filter is
//! seeded from the initialiser's points (mean inverse depth 1, so the world's unit is the
//! odometry's). A keyframe's parent edge is the odometry's relative pose, trusted: the back
//! end does not replace it by a Sim(3) alignment of the two depth maps (the coordinate descent
//! along the bas-relief ambiguity that the window exists to avoid), and searches loop
//! closures as before.
//!
//! Not used with this front end: LSD's relocalisation (the odometry takes its best
//! hypothesis on a bad frame, as DSO does; when it can track nothing for
//! `pipeline.new_fragment_after_lost_s` it starts again and begins a map fragment) and
//! re-activation; extending a saved map needs the LSD front end.

use std::sync::Arc;

use nalgebra::Matrix6;

use super::Pipeline;
use super::events::{Event, PoseEvent, TrackingState};
use super::keyframes::{FrameRecord, KeyframeCandidate};
use super::mapper::Observation;
use crate::dense::layer::SharedPrior;
use crate::frame::Frame;
use crate::geometry::{SE3, Sim3};
use crate::image::ImageF32;
use crate::mapping::DepthFilter;
use crate::odometry::metric::points_image;
use crate::odometry::{FirstKeyframe, FrameOutcome, MetricModel, Odometry};
use crate::{Error, Result};

/// The odometry and what ties its frames and keyframes to the pipeline's.
pub(super) struct OdometryFront {
    odometry: Odometry,
    /// Where the next first keyframe goes in the world: the identity for the map's first,
    /// where the camera was last seen for a fragment's.
    origin: Sim3,
    /// Frames that arrived while the odometry initialised, `(frame id, timestamp)`: their
    /// poses are known once it has.
    waiting: Vec<(u64, f64)>,
    /// Per pipeline keyframe: the odometry's id of its frame, and the length of one unit of
    /// its depth map in the odometry's units (each keyframe's map is scale-normalised).
    keyframes: Vec<(u64, f64)>,
    /// The metric depth prior, for every odometry this front end starts.
    metric: Option<MetricModel>,
}

impl std::fmt::Debug for OdometryFront {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OdometryFront")
            .field("odometry", &self.odometry)
            .field("keyframes", &self.keyframes.len())
            .field("metric", &self.metric.is_some())
            .finish_non_exhaustive()
    }
}

impl OdometryFront {
    /// The front end; with a metric depth prior (`metric`), the window's points take the
    /// prior's depths as weak priors ([`crate::odometry::metric`]).
    pub(super) fn new(config: &super::Config, metric: Option<SharedPrior>) -> Result<Self> {
        let metric = metric.map(|prior| -> MetricModel {
            Arc::new(move |frame: &Frame| match &frame.rgb {
                Some(rgb) => crate::dense::layer::predict(&prior, rgb).map(Some),
                None => Ok(None),
            })
        });
        Ok(Self {
            odometry: Self::start(config, metric.clone())?,
            origin: Sim3::identity(),
            waiting: Vec::new(),
            keyframes: Vec::new(),
            metric,
        })
    }

    /// A new odometry, on its own thread unless `deterministic`.
    fn start(config: &super::Config, metric: Option<MetricModel>) -> Result<Odometry> {
        let threaded = !config.pipeline.deterministic;
        Odometry::start_observed(config.odometry.clone(), 0, threaded, None, metric)
    }

    /// Waits for the window to finish its queued work (the end of a session).
    pub(super) fn finish(&mut self) -> Result<()> {
        self.odometry.finish()
    }

    /// `keyframe_from_frame` of a frame at the odometry's `world_from_camera`, relative to
    /// pipeline keyframe `id` and in its map's units, from the odometry's latest estimate of
    /// that keyframe (the window moves keyframes after they are made; the frame's pose is
    /// relative to the window as it stands now).
    fn relative(&self, id: usize, world_from_camera: &SE3) -> Result<SE3> {
        let (odometry_id, unit) = self.keyframes[id];
        let world_from_keyframe = self.odometry.keyframe_pose(odometry_id).ok_or_else(|| {
            Error::Config(format!(
                "the odometry has no pose for keyframe frame {odometry_id}"
            ))
        })?;
        let relative = world_from_keyframe.inverse() * *world_from_camera;
        Ok(SE3::new(relative.rotation, relative.translation / unit))
    }
}

/// The information of a pose whose translation is divided by `unit`, from that of the pose
/// in the original units (right perturbations `(ρ, φ)`: ρ scales by 1/`unit`).
fn rescaled_information(information: &Matrix6<f64>, unit: f64) -> Matrix6<f64> {
    let mut jacobian = Matrix6::identity();
    for i in 0..3 {
        jacobian[(i, i)] = unit;
    }
    jacobian.transpose() * information * jacobian
}

impl Pipeline {
    /// One frame through the odometry: a pose for every frame; once it has initialised, the
    /// frame is observed by the current keyframe's depth filter or becomes the next keyframe
    /// when the odometry made it one.
    pub(super) fn push_odometry(&mut self, frame: Arc<Frame>) -> Result<Vec<Event>> {
        let front = self.odometry_front()?;
        let t0 = std::time::Instant::now();
        let outcome = front.odometry.push(frame.clone())?;
        let first = front.odometry.take_first_keyframe();
        self.stats.tracking_s += t0.elapsed().as_secs_f64();
        let Some(kf_id) = self.current else {
            return match first {
                Some(first) => self.start_from_odometry(first, &frame, &outcome),
                None => {
                    self.odometry_front()?
                        .waiting
                        .push((frame.id, frame.timestamp));
                    Ok(vec![Event::Pose(PoseEvent {
                        frame_id: frame.input_id,
                        timestamp: frame.timestamp,
                        world_from_camera: Sim3::identity(),
                        state: TrackingState::Initializing,
                        keyframe_id: self.keyframes.len(),
                        is_keyframe: false,
                    })])
                }
            };
        };
        let keyframe_from_frame = self
            .odometry_front()?
            .relative(kf_id, &outcome.world_from_camera)?;
        if !outcome.tracked {
            let since = *self.lost_since.get_or_insert(frame.timestamp);
            let after = self.config.pipeline.new_fragment_after_lost_s;
            if after > 0.0 && frame.timestamp - since >= after {
                return self.restart_odometry(frame);
            }
            self.stats.frames_lost += 1;
            return Ok(vec![self.record_frame(
                &frame,
                kf_id,
                keyframe_from_frame,
                TrackingState::Lost,
            )]);
        }
        self.lost_since = None;
        self.last_frame_from_keyframe = keyframe_from_frame.inverse();
        if outcome.keyframe {
            return self.odometry_keyframe(frame, kf_id, keyframe_from_frame, &outcome);
        }
        self.observe_and_record(
            frame,
            kf_id,
            keyframe_from_frame,
            outcome.residual,
            TrackingState::Tracking,
        )
    }

    /// The odometry has tracked nothing for `pipeline.new_fragment_after_lost_s`: it has no
    /// relocalisation, and a frame it cannot track never becomes a keyframe, so it would
    /// stay lost. A new odometry starts from `frame`, and its first keyframe begins a map
    /// fragment where the camera was last seen, held apart until the back end finds a
    /// constraint to the map (as the LSD front end's fragments, ORB-SLAM3's Atlas).
    fn restart_odometry(&mut self, frame: Arc<Frame>) -> Result<Vec<Event>> {
        let last_seen = self.leave_for_fragment(&frame)?;
        let metric = self.odometry_front()?.metric.clone();
        let odometry = OdometryFront::start(&self.config, metric)?;
        let front = self.odometry_front()?;
        front.odometry = odometry;
        front.origin = last_seen;
        self.push_odometry(frame)
    }

    fn odometry_front(&mut self) -> Result<&mut OdometryFront> {
        self.odometry
            .as_deref_mut()
            .ok_or_else(|| Error::Config("the pipeline has no odometry front end".into()))
    }

    /// The odometry made `frame` a keyframe: the current keyframe's depth is propagated into
    /// it, and it becomes the pipeline's next keyframe with the odometry's relative pose as
    /// its trusted parent edge.
    fn odometry_keyframe(
        &mut self,
        frame: Arc<Frame>,
        source_id: usize,
        source_from_frame: SE3,
        outcome: &FrameOutcome,
    ) -> Result<Vec<Event>> {
        let frame_from_source = source_from_frame.inverse();
        let propagated = self.propagate_current(&frame, &frame_from_source)?;
        let source_unit = self.odometry_front()?.keyframes[source_id].1;
        // Tracking's information is about the odometry's units; the edge is in the source's.
        let candidate = KeyframeCandidate {
            frame: frame.clone(),
            source_id,
            frame_from_source,
            information: rescaled_information(&outcome.information, source_unit),
            state: TrackingState::Tracking,
        };
        let source_scale = self.current_pose(source_id).scale;
        let events = self.new_keyframe(candidate, propagated)?;
        let id = self.keyframes.len() - 1;
        // The new map's unit is the source's times the normalisation factor.
        let factor = self.keyframes[id].world_from_keyframe.scale / source_scale;
        self.odometry_front()?
            .keyframes
            .push((frame.id, source_unit * factor));
        Ok(events)
    }

    /// The odometry has initialised: its first keyframe becomes the map's, its depth filter
    /// seeded from the initialiser's points (holes filled from the prior when there is one);
    /// the frames that waited get their poses, and `frame` (the one that completed the
    /// initialisation, the widest baseline so far) is the filter's first observation.
    fn start_from_odometry(
        &mut self,
        first: FirstKeyframe,
        frame: &Arc<Frame>,
        outcome: &FrameOutcome,
    ) -> Result<Vec<Event>> {
        let keyframe = first.frame;
        let mut filter = DepthFilter::new(keyframe.clone(), self.config.mapping.clone())?;
        let seed = points_image(&keyframe, &first.points)?;
        filter.init_from_depth(&seed, self.config.pipeline.prior_init_var)?;
        let prior = self.fill_from_prior(&mut filter)?;
        // The points' mean inverse depth is 1: the map's unit is the odometry's.
        let mut origin = std::mem::replace(&mut self.odometry_front()?.origin, Sim3::identity());
        // With a metric prior the keyframe's scale in a world of metres is the median ratio
        // of the initialiser's inverse depths to the prior's (as the LSD front end's first
        // keyframe), so the first seconds are metric too.
        if let Some(scale) = self.metric_scale_of(&seed, &keyframe, prior.as_deref())? {
            origin.scale = scale;
        }
        let mut events =
            self.begin_keyframe(keyframe.clone(), filter, origin, None, prior, None)?;
        let id = self.keyframes.len() - 1;
        let front = self.odometry_front()?;
        front.keyframes.push((keyframe.id, 1.0));
        let waiting = std::mem::take(&mut front.waiting);
        let poses: std::collections::HashMap<u64, SE3> =
            front.odometry.trajectory().into_iter().collect();
        // From here on the pipeline records every frame itself.
        front.odometry.stop_recording_trajectory();
        let world_from_keyframe = front.odometry.keyframe_pose(keyframe.id);
        let world_from_keyframe = world_from_keyframe.unwrap_or_else(SE3::identity);
        for (frame_id, timestamp) in waiting {
            let pose = poses.get(&frame_id).copied().unwrap_or_else(SE3::identity);
            self.frames.push(FrameRecord {
                timestamp,
                keyframe: id,
                keyframe_from_frame: world_from_keyframe.inverse() * pose,
                lost: false,
            });
        }
        let keyframe_from_frame = world_from_keyframe.inverse() * outcome.world_from_camera;
        self.mapper.observe(Observation {
            frame: frame.clone(),
            keyframe_from_frame,
            residual: 0.0,
        })?;
        events.push(self.record_frame(frame, id, keyframe_from_frame, TrackingState::Tracking));
        Ok(events)
    }
}

impl Pipeline {
    /// With a metric prior, the scale `s` of a keyframe whose inverse depths are `depth`
    /// (`ρ_kf = s·ρ_metric`, [`crate::metric_scale`]); `prior` is the keyframe's prediction
    /// when one was made already. `None` without a metric prior or without votes.
    fn metric_scale_of(
        &self,
        depth: &ImageF32,
        keyframe: &Frame,
        prior: Option<&ImageF32>,
    ) -> Result<Option<f64>> {
        let (true, Some(model), Some(rgb)) = (self.metric, self.prior.as_ref(), &keyframe.rgb)
        else {
            return Ok(None);
        };
        let predicted;
        let prior = match prior {
            Some(prior) => prior,
            None => {
                predicted = crate::dense::layer::predict(model, rgb)?;
                &predicted
            }
        };
        Ok(crate::metric_scale::observe(depth, prior).map(|o| o.scale()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn information_follows_the_unit_of_the_translation() {
        // A pose measured with information I in metres; the same pose in units of 2 m has
        // translations half as long, so their information is 4× (rotations unchanged).
        let information = Matrix6::identity();
        let rescaled = rescaled_information(&information, 2.0);
        assert!((rescaled[(0, 0)] - 4.0).abs() < 1e-12);
        assert!((rescaled[(5, 5)] - 1.0).abs() < 1e-12);
    }
}
