//! A keyframe's life in the pipeline: the first frame becomes the first keyframe (depth from
//! the prior, or random); a frame chosen as the next keyframe gets the current keyframe's
//! depth propagated into it (holes filled from the prior under rotation), scale-normalised;
//! the finished keyframe goes to the back end with its tracking edge and to the dense layer.

use std::sync::Arc;

use nalgebra::{Matrix6, Vector3};

use super::events::{Event, KeyframeEvent, PoseEvent, TrackingState};
use super::{DepthInit, Pipeline};
use crate::dense::layer::{DenseJob, predict};
use crate::frame::Frame;
use crate::frame_log::LogRecord;
use crate::geometry::{Matrix7, PinholeCamera, SE3, SO3, Sim3};
use crate::graph::{KeyframeData, KeyframeId, KeyframeMaps, NewKeyframe, ParentEdge, Thumbnail};
use crate::image::ImageF32;
use crate::mapping::{CompactDepth, DepthFilter, DepthMap, PriorFillParams};
use crate::spill::{Reader, Writer};
use crate::tracking::TrackingReference;
use crate::{Error, Result};

/// Where each frame ended up, kept so that the final trajectory follows the optimised
/// keyframe poses.
#[derive(Clone, Copy, Debug)]
pub(super) struct FrameRecord {
    pub timestamp: f64,
    pub keyframe: KeyframeId,
    pub keyframe_from_frame: SE3,
    pub lost: bool,
}

impl LogRecord for FrameRecord {
    fn encode(&self, out: &mut Writer) {
        out.f64(self.timestamp);
        out.u64(self.keyframe as u64);
        out.sim3(&Sim3::from_se3(&self.keyframe_from_frame, 1.0));
        out.u8(u8::from(self.lost));
    }

    fn decode(input: &mut Reader<'_>) -> Result<Self> {
        let timestamp = input.f64()?;
        let keyframe = input.usize()?;
        let pose = input.sim3()?;
        Ok(Self {
            timestamp,
            keyframe,
            keyframe_from_frame: SE3::new(pose.rotation, pose.translation),
            lost: input.u8()? != 0,
        })
    }
}

/// A finished (or current) keyframe.
#[derive(Debug)]
pub(super) struct KeyframeRecord {
    /// Its timestamp and undistorted camera (kept while its image may be spilled).
    pub timestamp: f64,
    /// The caller's id of the frame it was made from (`FrameInput::frame_id`); `None` for a
    /// keyframe of the saved map an extending pipeline started from.
    pub frame_id: Option<u64>,
    pub camera: PinholeCamera,
    /// Its image without the pyramid and its semi-dense depth as last published (final once
    /// the keyframe is finished), in compact form, always kept: in memory, or in the session's
    /// store once older than `backend.resident_keyframes + backend.held_keyframes` (issue 37).
    pub data: KeyframeData,
    /// The full frame while the keyframe is among the `backend.resident_keyframes` newest;
    /// older keyframes drop it with `reference` ([`Pipeline::retire_keyframes`]) and
    /// [`Pipeline::keyframe_frame`] rebuilds it, identical.
    pub frame: Option<Arc<Frame>>,
    /// Its place-recognition descriptor (what a saved map keeps).
    pub thumbnail: Thumbnail,
    /// Its semi-dense depth in full while resident (dropped with `frame`;
    /// [`Pipeline::keyframe_depth`]).
    pub depth: Option<Arc<DepthMap>>,
    /// Pose at creation (the front end's estimate, before any optimisation).
    pub world_from_keyframe: Sim3,
    /// For relocalisation against finished keyframes; dropped with `frame`
    /// ([`Pipeline::keyframe_reference`] rebuilds it).
    pub reference: Option<Arc<TrackingReference>>,
    /// The tracking constraint to the keyframe it was created from, until it is sent with the
    /// finished keyframe to the back end (which keeps it). Boxed, as `handover`: the record
    /// lives as long as the session (issue 37).
    pub parent: Option<Box<ParentEdge>>,
    /// The tracking constraint to the old keyframe re-activated when this one was left
    /// (`super::reactivate`), sent with it like `parent`.
    pub handover: Option<Box<ParentEdge>>,
    /// Mean inverse depth of its semi-dense depth as last published (keyframe distances are
    /// measured in it); `None` without estimates.
    pub mean_idepth: Option<f64>,
    /// The prior's raw output for this image when hole filling already ran the network.
    pub prior: Option<Arc<ImageF32>>,
}

/// A frame chosen as the next keyframe, with its tracking edge from the keyframe whose depth
/// is propagated into it (LSD-SLAM's `createNewKeyFrame`).
#[derive(Debug)]
pub(super) struct KeyframeCandidate {
    pub frame: Arc<Frame>,
    pub source_id: KeyframeId,
    pub frame_from_source: SE3,
    pub information: Matrix6<f64>,
    pub state: TrackingState,
}

impl Pipeline {
    /// The first frame becomes the first keyframe, its depth initialised from the prior (or
    /// randomly); with a metric prior its scale makes the world's unit the metre.
    pub(super) fn start(&mut self, frame: Arc<Frame>) -> Result<Vec<Event>> {
        self.start_at(frame, Sim3::identity())
    }

    /// Tracking stayed lost for `pipeline.new_fragment_after_lost_s`: the frame begins a new
    /// map fragment, initialised like the first keyframe and placed where the camera was last
    /// seen (the last good frame's pose, in the current keyframe's scale). The back end holds
    /// it apart from the map until a constraint joins them.
    pub(super) fn start_fragment(&mut self, frame: Arc<Frame>) -> Result<Vec<Event>> {
        let last_seen = self.leave_for_fragment(&frame)?;
        self.start_at(frame, last_seen)
    }

    /// Finishes the current keyframe for a new map fragment that `frame` begins, forgets the
    /// lost run and the motion, and returns where the camera was last seen (the last good
    /// frame's pose, in the current keyframe's scale; the identity without a keyframe): where
    /// the fragment is placed.
    pub(super) fn leave_for_fragment(&mut self, frame: &Frame) -> Result<Sim3> {
        let last_seen = self.current.map_or_else(Sim3::identity, |id| {
            self.current_pose(id) * Sim3::from_se3(&self.last_frame_from_keyframe.inverse(), 1.0)
        });
        self.finish_current()?;
        self.lost = false;
        self.lost_since = None;
        self.velocity = None;
        self.stats.fragments += 1;
        tracing::info!(
            frame = frame.id,
            keyframe = self.keyframes.len(),
            "tracking stayed lost: new map fragment"
        );
        Ok(last_seen)
    }

    /// A keyframe with no parent (a map's or a fragment's first) at `world_from_keyframe`.
    fn start_at(&mut self, frame: Arc<Frame>, world_from_keyframe: Sim3) -> Result<Vec<Event>> {
        let mut filter = DepthFilter::new(frame.clone(), self.config.mapping.clone())?;
        let prior_depth = match (
            self.config.pipeline.init,
            self.prior.as_ref(),
            frame.rgb.as_ref(),
        ) {
            (DepthInit::Prior, Some(prior), Some(rgb)) => Some(Arc::new(predict(prior, rgb)?)),
            _ => None,
        };
        let mut world_from_keyframe = world_from_keyframe;
        match &prior_depth {
            Some(idepth) => {
                let (normalised, factor) = normalise_mean(idepth)?;
                filter.init_from_depth(&normalised, self.config.pipeline.prior_init_var)?;
                // A metric prior's inverse depths times `factor` are the keyframe's, so its
                // scale in a world of metres is `factor` (`crate::metric_scale`).
                if self.metric {
                    world_from_keyframe.scale = f64::from(factor);
                }
            }
            None => filter.init_random(self.config.pipeline.seed),
        }
        filter.regularize();
        self.begin_keyframe(
            frame,
            filter,
            world_from_keyframe,
            None,
            prior_depth,
            Some(TrackingState::Initializing),
        )
    }

    /// The candidate's frame becomes the next keyframe, with `filter` (the depth of its source
    /// keyframe propagated into it) scale-normalised (mean inverse depth 1, LSD-SLAM's gauge);
    /// the current keyframe is finished and goes to the back end.
    pub(super) fn new_keyframe(
        &mut self,
        candidate: KeyframeCandidate,
        mut filter: DepthFilter,
    ) -> Result<Vec<Event>> {
        let KeyframeCandidate {
            frame,
            source_id,
            frame_from_source,
            information,
            state,
        } = candidate;
        let t0 = std::time::Instant::now();
        let prior = self.fill_from_prior(&mut filter)?;
        // New inverse depths are multiplied by `factor`, so new-keyframe coordinates shrink by
        // it: source_from_new = [R t] · diag(factor).
        let factor = filter.normalize_scale();
        // The new keyframe's lengths are the old ones divided by `factor`.
        self.velocity = self
            .velocity
            .map(|v| SE3::new(v.rotation, v.translation / factor));
        let source_from_new = Sim3::from_se3(&frame_from_source.inverse(), 1.0)
            * Sim3::new(SO3::identity(), Vector3::zeros(), factor);
        // The tracking information is for a right perturbation of frame_from_source; for its
        // inverse, δ' = −Ad(T)·δ, so Λ' = Ad(T⁻¹)ᵀ Λ Ad(T⁻¹).
        let ad = frame_from_source.inverse().adjoint();
        let mut parent = ParentEdge::from_se3_information(
            source_id,
            source_from_new,
            &(ad.transpose() * information * ad),
        );
        // The odometry's relative pose comes from its window's joint optimisation.
        parent.trusted = self.odometry.is_some();
        let world_from_source = self.current_pose(source_id);
        self.finish_current()?;
        let events = self.begin_keyframe(
            frame,
            filter,
            world_from_source * source_from_new,
            Some(parent),
            prior,
            Some(state),
        )?;
        self.keyframe_creation_s += t0.elapsed().as_secs_f64();
        Ok(events)
    }

    /// Fills the holes of a new keyframe's propagated depth from the depth prior
    /// (`pipeline.prior_fill`; nothing without a prior or an RGB image).
    /// Returns the prior's output when the network ran, for the dense layer to reuse.
    pub(super) fn fill_from_prior(
        &mut self,
        filter: &mut DepthFilter,
    ) -> Result<Option<Arc<ImageF32>>> {
        let cfg = &self.config.pipeline;
        let (true, Some(prior), Some(rgb)) = (
            cfg.prior_fill,
            self.prior.as_ref(),
            filter.keyframe().rgb.clone(),
        ) else {
            return Ok(None);
        };
        // The network runs only for keyframes the prior will fill.
        if filter.coverage() > cfg.prior_fill_max_coverage {
            return Ok(None);
        }
        let prior_inv = predict(prior, &rgb)?;
        let params = PriorFillParams {
            var: cfg.prior_fill_var,
            validity: cfg.prior_fill_validity,
            min_fit_pixels: cfg.prior_fill_min_pixels,
            max_coverage: cfg.prior_fill_max_coverage,
        };
        // `None`: no trustworthy alignment; the keyframe keeps its propagated depth only.
        filter.fill_from_prior(&prior_inv, &params)?;
        Ok(Some(Arc::new(prior_inv)))
    }

    /// Registers `frame` as the current keyframe and reports it; with `report_frame`, also its
    /// pose as a frame (already reported when the keyframe was made on the mapping thread).
    pub(super) fn begin_keyframe(
        &mut self,
        frame: Arc<Frame>,
        filter: DepthFilter,
        world_from_keyframe: Sim3,
        parent: Option<ParentEdge>,
        prior: Option<Arc<ImageF32>>,
        report_frame: Option<TrackingState>,
    ) -> Result<Vec<Event>> {
        let id = self.keyframes.len();
        let mapped = self.mapper.begin(filter)?;
        self.keyframes.push(KeyframeRecord {
            timestamp: frame.timestamp,
            frame_id: Some(frame.input_id),
            camera: frame.camera,
            data: KeyframeData::new(
                &self.spill,
                frame.compact(),
                CompactDepth::of(&mapped.depth),
            ),
            thumbnail: Thumbnail::new(&frame),
            frame: Some(frame.clone()),
            depth: Some(mapped.depth),
            world_from_keyframe,
            reference: Some(mapped.reference),
            parent: parent.map(Box::new),
            handover: None,
            mean_idepth: mapped.mean_idepth,
            prior,
        });
        self.current = Some(id);
        self.stats.keyframes = self.keyframes.len();
        let mut events = vec![Event::Keyframe(KeyframeEvent {
            keyframe_id: id,
            frame_id: frame.input_id,
            timestamp: frame.timestamp,
            world_from_keyframe,
        })];
        // A keyframe made on the mapping thread was reported (and recorded) as a tracked frame
        // when it arrived.
        if let Some(state) = report_frame {
            self.frames.push(FrameRecord {
                timestamp: frame.timestamp,
                keyframe: id,
                keyframe_from_frame: SE3::identity(),
                lost: false,
            });
            self.last_frame_from_keyframe = SE3::identity();
            events.push(Event::Pose(PoseEvent {
                frame_id: frame.input_id,
                timestamp: frame.timestamp,
                world_from_camera: world_from_keyframe,
                state,
                keyframe_id: id,
                is_keyframe: true,
            }));
        }
        Ok(events)
    }

    /// Finishes the current keyframe: its final depth is published and it goes to the back
    /// end (constraint search and pose-graph optimisation) and to the dense layer.
    pub(super) fn finish_current(&mut self) -> Result<()> {
        let Some(id) = self.current.take() else {
            return Ok(());
        };
        if self.reactivated.take().is_some_and(|r| r.id == id) {
            // It was finished once and handed on; its refined depth served tracking and the
            // propagation into the next keyframe (`super::reactivate`).
            self.mapper.finish()?;
            self.retire_keyframes();
            return Ok(());
        }
        // The final depth is what the mapping published last (its tracking reference serves
        // relocalisation from now on).
        let mapped = self
            .mapper
            .finish()?
            .ok_or_else(|| Error::Config("the current keyframe has no depth filter".into()))?;
        let frame = self.keyframe_frame(id)?;
        let record = &mut self.keyframes[id];
        record.data = record.data.with_depth(CompactDepth::of(&mapped.depth));
        record.depth = Some(mapped.depth.clone());
        record.reference = Some(mapped.reference);
        record.mean_idepth = mapped.mean_idepth;
        let pose_covariance = record
            .parent
            .as_ref()
            .map_or_else(Matrix7::zeros, |p| covariance(&p.information.matrix()));
        let new = NewKeyframe {
            id,
            maps: KeyframeMaps::Shared {
                frame: Arc::downgrade(&frame),
                depth: Arc::downgrade(&mapped.depth),
                data: record.data.clone(),
            },
            world_from_keyframe: record.world_from_keyframe,
            // The back end keeps it from here on: a record lives as long as the session (few
            // keyframes have a hand-over).
            parent: record.parent.take().map(|p| *p),
            handover: record.handover.as_deref().cloned(),
            thumbnail: Some(record.thumbnail.clone()),
        };
        let job = DenseJob {
            keyframe_id: id,
            frame,
            depth: mapped.depth,
            poses: Vec::new(),
            pose_covariance,
            prior: record.prior.take(),
        };
        self.backend.add_keyframe(new)?;
        self.retire_keyframes();
        self.densify(job)
    }

    /// Keyframes older than the `backend.resident_keyframes` newest let go of their full
    /// frame, full depth map and tracking reference; those older than the newest
    /// `resident_keyframes + held_keyframes` also spill their compact data to the session's
    /// store when it has one. The current one never does either.
    fn retire_keyframes(&mut self) {
        let keep = self.config.backend.resident_keyframes;
        let held = keep + self.config.backend.held_keyframes;
        let n = self.keyframes.len();
        let current = self.current;
        for (id, record) in self.keyframes.iter_mut().enumerate() {
            if Some(id) == current {
                continue;
            }
            if id + keep < n {
                record.frame = None;
                record.depth = None;
                record.reference = None;
            }
            if id + held < n {
                record.data.spill();
                if let Some(dense) = self.dense_keyframes.get(&id)
                    && let Err(e) = dense.spill()
                {
                    tracing::warn!(keyframe = id, error = %e, "dense keyframe kept in memory: spilling failed");
                }
            }
        }
    }

    /// Keyframe `id`'s full frame, rebuilt from its compact image when it was retired.
    pub(super) fn keyframe_frame(&self, id: KeyframeId) -> Result<Arc<Frame>> {
        let record = &self.keyframes[id];
        match &record.frame {
            Some(frame) => Ok(frame.clone()),
            None => Ok(Arc::new(record.data.frame()?)),
        }
    }

    /// Keyframe `id`'s semi-dense depth as last published, expanded from its compact form
    /// when it was retired.
    pub(super) fn keyframe_depth(&self, id: KeyframeId) -> Result<Arc<DepthMap>> {
        let record = &self.keyframes[id];
        match &record.depth {
            Some(depth) => Ok(depth.clone()),
            None => Ok(Arc::new(record.data.depth_map()?)),
        }
    }

    /// Keyframe `id`'s tracking reference, rebuilt from its image and depth when it was
    /// retired (the same as the mapping published) and kept until the next keyframe retires
    /// it again: a lost camera tries the same keyframes frame after frame.
    pub(super) fn keyframe_reference(&mut self, id: KeyframeId) -> Result<Arc<TrackingReference>> {
        if let Some(reference) = &self.keyframes[id].reference {
            return Ok(reference.clone());
        }
        let reference = Arc::new(TrackingReference::new(
            self.keyframe_frame(id)?.as_ref(),
            self.keyframe_depth(id)?.as_ref(),
        )?);
        self.keyframes[id].reference = Some(reference.clone());
        Ok(reference)
    }
}

/// Σ of a pose from its information matrix; zero (no uncertainty propagated) when the
/// information is singular.
fn covariance(information: &Matrix7) -> Matrix7 {
    information.try_inverse().unwrap_or_else(Matrix7::zeros)
}

/// Scales a relative inverse-depth map so that its mean over positive pixels is 1 (the
/// keyframe scale gauge), leaving non-positive pixels at 0 ("no prediction"); returns the map
/// and the factor applied.
fn normalise_mean(idepth: &ImageF32) -> Result<(ImageF32, f32)> {
    let (sum, n) = idepth
        .data
        .iter()
        .filter(|v| v.is_finite() && **v > 0.0)
        .fold((0.0f64, 0usize), |(s, n), &v| (s + f64::from(v), n + 1));
    if n == 0 {
        return Err(Error::Prior(
            "the depth prior predicted no positive inverse depth".into(),
        ));
    }
    let k = (n as f64 / sum) as f32;
    let data = idepth
        .data
        .iter()
        .map(|&v| if v.is_finite() && v > 0.0 { v * k } else { 0.0 })
        .collect();
    Ok((ImageF32::from_vec(idepth.width, idepth.height, data)?, k))
}
