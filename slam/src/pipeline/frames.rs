//! One frame through the front end: undistortion and pyramid, tracking against the current
//! keyframe (constant-velocity guess optional), then either an observation for the
//! keyframe's depth or the choice of a new keyframe; a frame that cannot be tracked tries
//! relocalisation against recent keyframes.

use std::sync::Arc;

use super::Pipeline;
use super::events::{Event, PoseEvent, TrackingState};
use super::keyframes::{FrameRecord, KeyframeCandidate};
use super::mapper::Observation;
use crate::frame::Frame;
use crate::geometry::{SE3, Sim3};
use crate::graph::KeyframeId;
use crate::mapping::{DepthFilter, needs_new_keyframe};
use crate::tracking::{SE3Tracker, TrackingReference, TrackingResult};
use crate::{Error, Result};

use super::FrameInput;

impl Pipeline {
    /// Tracks one frame (or starts the map with it) and maps it or makes it a keyframe.
    pub(super) fn push_frame(&mut self, input: FrameInput) -> Result<Vec<Event>> {
        let frame = Arc::new(self.make_frame(input)?);
        self.stats.frames += 1;
        if self.odometry.is_some() {
            return self.push_odometry(frame);
        }
        if self.current.is_none() {
            return match self.map {
                Some(_) => self.start_in_map(frame),
                None => self.start(frame),
            };
        }
        let kf_id = self.current.unwrap_or_default();
        let mapped = self.mapper.published()?;
        let t0 = std::time::Instant::now();
        let velocity = self
            .velocity
            .filter(|_| self.config.pipeline.constant_velocity && !self.lost);
        let result = track_with_motion_model(
            &mut self.tracker,
            &mapped.reference,
            &frame,
            &self.last_frame_from_keyframe,
            velocity,
        );
        self.stats.tracking_s += t0.elapsed().as_secs_f64();
        if !result.good {
            return self.lost_or_relocalised(&frame);
        }
        self.lost_since = None;
        let state = if std::mem::take(&mut self.lost) {
            TrackingState::Relocalized
        } else {
            TrackingState::Tracking
        };
        let keyframe_from_frame = result.frame_from_keyframe.inverse();
        self.velocity = Some(result.frame_from_keyframe * self.last_frame_from_keyframe.inverse());
        self.last_frame_from_keyframe = result.frame_from_keyframe;

        let make_keyframe = needs_new_keyframe(
            &self.config.mapping,
            &keyframe_from_frame,
            mapped.mean_idepth.unwrap_or(1.0),
            result.point_usage,
            self.keyframes.len(),
            mapped.frames_mapped,
        );
        // Let go of the reference, so that the mapping can rebuild it in place.
        drop(mapped);
        if make_keyframe {
            if let Some(events) = self.try_reactivation(&frame, kf_id, &result, state)? {
                return Ok(events);
            }
            let candidate = KeyframeCandidate {
                frame: frame.clone(),
                source_id: kf_id,
                frame_from_source: result.frame_from_keyframe,
                information: result.information,
                state,
            };
            // On the mapping thread too, the queued frames are mapped first: a keyframe made
            // while tracking went on against the old one mapped fewer frames and drifted more
            // (docs/tuning.md, "Mapping thread").
            let propagated = self.propagate_current(&frame, &result.frame_from_keyframe)?;
            return self.new_keyframe(candidate, propagated);
        }
        self.observe_and_record(frame, kf_id, keyframe_from_frame, result.residual, state)
    }

    /// The current keyframe's depth propagated into `frame` (after the frames queued for
    /// mapping), for the keyframe `frame` becomes; timed as keyframe creation.
    pub(super) fn propagate_current(
        &mut self,
        frame: &Arc<Frame>,
        frame_from_keyframe: &SE3,
    ) -> Result<DepthFilter> {
        let t0 = std::time::Instant::now();
        let propagated = self
            .mapper
            .with_filter(|filter| filter.propagate_to(frame.clone(), frame_from_keyframe))?;
        self.keyframe_creation_s += t0.elapsed().as_secs_f64();
        Ok(propagated)
    }

    /// A tracked frame that stays a frame: the current keyframe's depth filter observes it
    /// (with its tracking residual) and its pose is recorded and reported.
    pub(super) fn observe_and_record(
        &mut self,
        frame: Arc<Frame>,
        keyframe: KeyframeId,
        keyframe_from_frame: SE3,
        residual: f32,
        state: TrackingState,
    ) -> Result<Vec<Event>> {
        self.mapper.observe(Observation {
            frame: frame.clone(),
            keyframe_from_frame,
            residual,
        })?;
        Ok(vec![self.record_frame(
            &frame,
            keyframe,
            keyframe_from_frame,
            state,
        )])
    }

    /// Records a frame's pose relative to its keyframe and reports it.
    pub(super) fn record_frame(
        &mut self,
        frame: &Frame,
        keyframe: KeyframeId,
        keyframe_from_frame: SE3,
        state: TrackingState,
    ) -> Event {
        self.frames.push(FrameRecord {
            timestamp: frame.timestamp,
            keyframe,
            keyframe_from_frame,
            lost: state == TrackingState::Lost,
        });
        let world_from_camera =
            self.tracking_pose(keyframe) * Sim3::from_se3(&keyframe_from_frame, 1.0);
        Event::Pose(PoseEvent {
            frame_id: frame.input_id,
            timestamp: frame.timestamp,
            world_from_camera,
            state,
            keyframe_id: keyframe,
            is_keyframe: false,
        })
    }

    /// Undistorts and converts the input; rejects a size that does not match the camera.
    fn make_frame(&mut self, input: FrameInput) -> Result<Frame> {
        let (w, h) = input.rgb.dimensions();
        let mut frame = Frame::from_camera_rgb(
            self.next_frame_id,
            input.timestamp,
            &self.camera,
            self.undistort.as_ref(),
            input.rgb,
        )?;
        frame.input_id = input.frame_id.unwrap_or(frame.id);
        self.next_frame_id += 1;
        let sensor_depth = match input.depth {
            Some(depth) if self.config.dense.two_view.ground_truth_depth => {
                if (depth.width, depth.height) != (w as usize, h as usize) {
                    return Err(Error::Shape(format!(
                        "depth is {}x{} but the frame is {w}x{h}",
                        depth.width, depth.height
                    )));
                }
                Some(Arc::new(match &self.undistort {
                    Some(map) => map.apply_nearest(&depth)?,
                    None => depth,
                }))
            }
            _ => None,
        };
        frame.sensor_depth = sensor_depth;
        Ok(frame)
    }

    /// Tracking failed: try the current and the most recent keyframes. On success the frame
    /// becomes a new keyframe whose depth is propagated from the keyframe it relocalised
    /// against; otherwise it is reported lost.
    fn lost_or_relocalised(&mut self, frame: &Arc<Frame>) -> Result<Vec<Event>> {
        // The motion since the last good frame is unknown.
        self.velocity = None;
        let current_id = self.current.unwrap_or(0);
        let n = self.config.pipeline.relocalisation_candidates;
        let candidates: Vec<KeyframeId> = std::iter::once(current_id)
            .chain(
                (0..self.keyframes.len())
                    .rev()
                    .filter(|&id| id != current_id),
            )
            .take(n.max(1))
            .collect();
        let held = candidates
            .iter()
            .map(|&id| self.keyframe_reference(id))
            .collect::<Result<Vec<_>>>()?;
        let guess = |id: KeyframeId| {
            if id == current_id {
                self.last_frame_from_keyframe
            } else {
                SE3::identity()
            }
        };
        let refs: Vec<(&TrackingReference, SE3)> = held
            .iter()
            .zip(&candidates)
            .map(|(reference, &id)| (reference.as_ref(), guess(id)))
            .collect();
        if let Some((i, result)) = self.tracker.try_relocalise(&refs, frame) {
            return self.relocalised_at(frame, candidates[i], &result);
        }
        if let Some(events) = self.relocalise_in_map(frame)? {
            return Ok(events);
        }
        let since = *self.lost_since.get_or_insert(frame.timestamp);
        let after = self.config.pipeline.new_fragment_after_lost_s;
        if after > 0.0 && frame.timestamp - since >= after {
            return self.start_fragment(frame.clone());
        }
        self.lost = true;
        self.stats.frames_lost += 1;
        let keyframe_from_frame = self.last_frame_from_keyframe.inverse();
        Ok(vec![self.record_frame(
            frame,
            current_id,
            keyframe_from_frame,
            TrackingState::Lost,
        )])
    }

    /// `frame` was relocalised against keyframe `kf`: it becomes a new keyframe whose depth is
    /// propagated from `kf`'s (its live filter when it is the current keyframe).
    pub(super) fn relocalised_at(
        &mut self,
        frame: &Arc<Frame>,
        kf: KeyframeId,
        result: &TrackingResult,
    ) -> Result<Vec<Event>> {
        self.lost = false;
        self.lost_since = None;
        self.velocity = None;
        let t0 = std::time::Instant::now();
        let propagated = match self.current {
            Some(current) if current == kf => self.mapper.with_filter(|filter| {
                filter.propagate_to(frame.clone(), &result.frame_from_keyframe)
            })?,
            _ => DepthFilter::from_depth_map(
                self.keyframe_frame(kf)?,
                self.keyframe_depth(kf)?.as_ref(),
                self.config.mapping.clone(),
            )?
            .propagate_to(frame.clone(), &result.frame_from_keyframe)?,
        };
        self.keyframe_creation_s += t0.elapsed().as_secs_f64();
        let candidate = KeyframeCandidate {
            frame: frame.clone(),
            source_id: kf,
            frame_from_source: result.frame_from_keyframe,
            information: result.information,
            state: TrackingState::Relocalized,
        };
        self.new_keyframe(candidate, propagated)
    }
}

/// Tracks `frame` against `reference` from the constant-velocity guess
/// `velocity · last_frame_from_keyframe` when `velocity` is given (`pipeline.constant_velocity`,
/// the camera keeps moving as it did between the last two frames), falling back to LSD-SLAM's
/// guess, the last frame's pose (`SlamSystem::trackFrame`), when that fails (a sudden stop).
fn track_with_motion_model(
    tracker: &mut SE3Tracker,
    reference: &TrackingReference,
    frame: &Frame,
    last_frame_from_keyframe: &SE3,
    velocity: Option<SE3>,
) -> TrackingResult {
    if let Some(v) = velocity {
        let result = tracker.track(reference, frame, &(v * *last_frame_from_keyframe));
        if result.good {
            return result;
        }
    }
    tracker.track(reference, frame, last_frame_from_keyframe)
}
