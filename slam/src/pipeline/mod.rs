//! The SLAM pipeline: frames in, events out (`Pipeline::push`).
//!
//! A thin orchestration over the components, in LSD-SLAM's order (Engel et al. ECCV 2014,
//! Fig. 3): each frame is tracked against the current keyframe (SE(3) direct alignment); a good
//! frame refines the keyframe's semi-dense depth (epipolar stereo + filtering); when the camera
//! has moved far enough, the frame becomes the next keyframe (depth propagated, scale
//! normalised) and the finished keyframe goes to the back end (Sim(3) constraints, pose graph).
//! Tracking and mapping run in the caller's thread, one frame at a time; the back end runs on
//! its own thread unless `pipeline.deterministic` is set. Each finished keyframe also goes to
//! the dense layer (DeepRelativeFusion §III-B..E, [`crate::dense::layer`]), on its own thread
//! likewise; its two-view consistent depth comes back to refine the keyframe's constraints.
//! Densified keyframes are fused into the TSDF at their current poses and meshed
//! ([`crate::fusion`]), on a third thread; pose-graph moves re-integrate them.

pub mod config;
pub mod events;
mod mapper;
#[cfg(test)]
mod tests;

use std::sync::Arc;

use nalgebra::{Matrix6, Vector3};

pub use config::{Config, DepthInit, PipelineConfig};
pub use events::{Event, KeyframeEvent, PoseEvent, TrackingState};

use crate::dense::DenseKeyframe;
use crate::dense::layer::{DenseJob, DenseLayer, DenseOutput, DenseWorker, SharedPrior, predict};
use crate::dense::prior::DepthPrior;
use crate::export::ColoredPoint;
use crate::frame::Frame;
use crate::fusion::Mesh;
use crate::fusion::fuser::{Fuser, FusionStats, MeshDelta};
use crate::fusion::worker::{FusionJob, FusionReply, FusionWorker, process as fuse_in_step};
use crate::geometry::{Matrix7, PinholeCamera, SE3, SO3, Sim3, UndistortMap};
use crate::graph::{Backend, BackendHandle, KeyframeId, NewKeyframe, ParentEdge};
use crate::image::ImageF32;
use crate::mapping::{DepthFilter, DepthMap, PriorFillParams, needs_new_keyframe};
use crate::tracking::{SE3Tracker, TrackingReference};
use crate::{Error, Result};
use mapper::{KeyframeMapper, Observation};

/// One input frame: a colour image (distorted as the camera delivers it) and its time.
#[derive(Clone, Debug)]
pub struct FrameInput {
    pub timestamp: f64,
    pub rgb: ::image::RgbImage,
    /// Metric depth registered to `rgb` (same size, distorted alike; metres, 0 = none), from
    /// an RGB-D dataset: used only by the ground-truth refinement baseline
    /// (`dense.two_view.ground_truth_depth`) and dropped otherwise.
    pub depth: Option<ImageF32>,
}

/// Where each frame ended up, kept so that the final trajectory follows the optimised
/// keyframe poses.
#[derive(Clone, Copy, Debug)]
struct FrameRecord {
    timestamp: f64,
    keyframe: KeyframeId,
    keyframe_from_frame: SE3,
    lost: bool,
}

/// A finished (or current) keyframe.
#[derive(Debug)]
struct KeyframeRecord {
    frame: Arc<Frame>,
    /// Its semi-dense depth as last published (final once the keyframe is finished).
    depth: Arc<DepthMap>,
    /// Pose at creation (the front end's estimate, before any optimisation).
    world_from_keyframe: Sim3,
    /// For relocalisation against finished keyframes.
    reference: Arc<TrackingReference>,
    /// The tracking constraint to the keyframe it was created from (sent with it to the back
    /// end once the keyframe is finished).
    parent: Option<ParentEdge>,
    /// The prior's raw output for this image when hole filling already ran the network.
    prior: Option<Arc<ImageF32>>,
}

/// A frame chosen as the next keyframe, with its tracking edge from the keyframe whose depth
/// is propagated into it. On the mapping thread it waits as `Pipeline::pending_keyframe` while
/// tracking goes on against the current keyframe (LSD-SLAM's `createNewKeyFrame`).
#[derive(Debug)]
struct KeyframeCandidate {
    frame: Arc<Frame>,
    source_id: KeyframeId,
    frame_from_source: SE3,
    information: Matrix6<f64>,
    state: TrackingState,
}

/// Where the back end runs.
#[derive(Debug)]
enum BackendLink {
    InStep(Box<Backend>),
    Threaded(BackendHandle),
}

/// Where the dense layer runs (like the back end: in step when deterministic).
#[derive(Debug)]
enum DenseLink {
    InStep(Box<DenseLayer>),
    Threaded(DenseWorker),
}

/// Where the fusion runs (in step when deterministic); `Done` holds the fuser after
/// [`Pipeline::finish`], for the final mesh.
#[derive(Debug)]
enum FusionLink {
    InStep(Box<Fuser>),
    Threaded(FusionWorker),
    Done(Box<Fuser>),
}

/// Summary counters of a run.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Stats {
    pub frames: usize,
    pub keyframes: usize,
    pub frames_lost: usize,
    /// Accumulated wall time of tracking, mapping and keyframe creation (seconds).
    pub tracking_s: f64,
    pub mapping_s: f64,
    /// Good frames the mapping thread did not observe because it was busy with an earlier one
    /// (`pipeline.mapping_thread`; always 0 in step).
    pub frames_not_mapped: usize,
    /// Keyframes the dense layer finished.
    pub keyframes_densified: usize,
    /// Keyframes it skipped (queue full) or failed on (reason logged).
    pub keyframes_not_densified: usize,
    /// `"prior"`, or `"no_model"` when no depth model is loaded (the dense layer then densifies
    /// from the semi-dense depth alone); `"off"` when the dense layer is disabled.
    pub dense_mode: &'static str,
    /// Dense keyframes whose two-view consistent depth went to the back end (§III-E).
    pub depth_refinements: usize,
    /// Dense keyframes fused into the TSDF.
    pub keyframes_fused: usize,
    /// Dense keyframes the fusion skipped (queue full) or failed on (reason logged).
    pub keyframes_not_fused: usize,
    /// Revision of the last mesh update.
    pub mesh_revision: u64,
}

/// The pipeline of one session.
#[derive(Debug)]
pub struct Pipeline {
    config: Config,
    /// The camera as given (possibly distorted).
    camera: PinholeCamera,
    undistort: Option<UndistortMap>,
    prior: Option<SharedPrior>,
    tracker: SE3Tracker,
    backend: BackendLink,
    dense: Option<DenseLink>,
    fusion: Option<FusionLink>,
    /// The latest dense result of each keyframe, by keyframe id.
    dense_keyframes: std::collections::BTreeMap<KeyframeId, Arc<DenseKeyframe>>,
    /// Events produced outside a frame's own processing (dense results), returned with the
    /// next [`Pipeline::push`] or by [`Pipeline::take_events`].
    pending_events: Vec<Event>,
    keyframes: Vec<KeyframeRecord>,
    /// The keyframe being mapped; its depth filter is in `mapper`.
    current: Option<KeyframeId>,
    mapper: KeyframeMapper,
    /// The next keyframe while the mapping thread propagates into it.
    pending_keyframe: Option<KeyframeCandidate>,
    /// Seconds spent creating keyframes (propagation); the mapper adds its own.
    keyframe_creation_s: f64,
    frames: Vec<FrameRecord>,
    /// Pose of the last good frame relative to the current keyframe (the tracking prior).
    last_frame_from_keyframe: SE3,
    /// Motion of the camera between the last two good frames, `last_from_previous`, in the
    /// current keyframe's scale (the constant-velocity model of the tracking guess).
    velocity: Option<SE3>,
    lost: bool,
    next_frame_id: u64,
    stats: Stats,
    /// The back end's poses after [`Pipeline::finish`] (the threaded back end is gone then).
    final_poses: Option<std::collections::HashMap<KeyframeId, Sim3>>,
}

impl Pipeline {
    /// A pipeline for frames of `camera` (with its distortion, if any). `prior` initialises the
    /// first keyframe's depth when `config.pipeline.init` is `Prior`.
    pub fn new(
        mut config: Config,
        camera: PinholeCamera,
        prior: Option<Box<dyn DepthPrior>>,
    ) -> Result<Self> {
        config.validate()?;
        let mapping_thread = config.pipeline.maps_on_thread();
        if mapping_thread {
            config.mapping.threads = config.pipeline.mapping_thread_workers;
        }
        let undistort = camera
            .distortion
            .is_some()
            .then(|| UndistortMap::new(&camera));
        let tracker = SE3Tracker::new(config.tracking.clone())?;
        let backend = if config.pipeline.deterministic {
            BackendLink::InStep(Box::new(Backend::new(config.backend.clone())?))
        } else {
            BackendLink::Threaded(Backend::spawn(config.backend.clone())?)
        };
        let prior: Option<SharedPrior> = prior.map(|p| Arc::new(std::sync::Mutex::new(p)));
        let dense = match (config.dense.enabled, config.pipeline.deterministic) {
            (false, _) => None,
            (true, true) => Some(DenseLink::InStep(Box::new(DenseLayer::new(
                config.dense.clone(),
                prior.clone(),
            )?))),
            (true, false) => Some(DenseLink::Threaded(DenseWorker::spawn(
                config.dense.clone(),
                prior.clone(),
            )?)),
        };
        let fusion = match (
            config.fusion.enabled && config.dense.enabled,
            config.pipeline.deterministic,
        ) {
            (false, _) => None,
            (true, true) => Some(FusionLink::InStep(Box::new(Fuser::new(
                config.fusion.clone(),
                None,
            )?))),
            (true, false) => Some(FusionLink::Threaded(FusionWorker::spawn(
                config.fusion.clone(),
            )?)),
        };
        let mapper = KeyframeMapper::new(mapping_thread)?;
        let dense_mode = match (&dense, &prior) {
            (None, _) => "off",
            (Some(_), Some(_)) => "prior",
            (Some(_), None) => "no_model",
        };
        Ok(Self {
            config,
            camera,
            undistort,
            prior,
            tracker,
            backend,
            dense,
            fusion,
            dense_keyframes: std::collections::BTreeMap::new(),
            pending_events: Vec::new(),
            keyframes: Vec::new(),
            current: None,
            mapper,
            pending_keyframe: None,
            keyframe_creation_s: 0.0,
            frames: Vec::new(),
            last_frame_from_keyframe: SE3::identity(),
            velocity: None,
            lost: false,
            next_frame_id: 0,
            stats: Stats {
                dense_mode,
                ..Stats::default()
            },
            final_poses: None,
        })
    }

    /// The configuration in force.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Counters so far.
    pub fn stats(&self) -> &Stats {
        &self.stats
    }

    /// Processes one frame and returns what happened (a pose event always; keyframe events
    /// when one was created; dense keyframes as the dense layer finishes them).
    pub fn push(&mut self, input: FrameInput) -> Result<Vec<Event>> {
        let mut events = self.push_frame(input)?;
        self.poll_dense()?;
        self.poll_fusion();
        self.update_mapping_stats();
        events.append(&mut self.pending_events);
        Ok(events)
    }

    fn update_mapping_stats(&mut self) {
        let (mapping_s, not_mapped) = self.mapper.counters();
        self.stats.mapping_s = self.keyframe_creation_s + mapping_s;
        self.stats.frames_not_mapped = not_mapped;
    }

    /// Events produced since the last [`Pipeline::push`] outside a frame's processing: the
    /// dense keyframes [`Pipeline::finish`] waited for.
    pub fn take_events(&mut self) -> Vec<Event> {
        std::mem::take(&mut self.pending_events)
    }

    /// The latest dense result of every densified keyframe with its current pose (optimised
    /// after [`Pipeline::finish`]).
    pub fn dense_keyframes(&self) -> Vec<(Arc<DenseKeyframe>, Sim3)> {
        let poses = self.keyframe_poses();
        self.dense_keyframes
            .values()
            .map(|kf| (kf.clone(), poses[kf.keyframe_id].1))
            .collect()
    }

    fn push_frame(&mut self, input: FrameInput) -> Result<Vec<Event>> {
        let frame = Arc::new(self.make_frame(input)?);
        self.stats.frames += 1;
        if self.current.is_none() {
            return self.start(frame);
        }
        self.switch_to_pending_keyframe(false)?;
        let kf_id = self.current.unwrap_or_default();
        let mapped = self.mapper.published()?;
        let t0 = std::time::Instant::now();
        let result = track_with_motion_model(
            &mut self.tracker,
            &mapped.reference,
            &frame,
            &self.last_frame_from_keyframe,
            self.velocity
                .filter(|_| self.config.pipeline.constant_velocity && !self.lost),
        );
        self.stats.tracking_s += t0.elapsed().as_secs_f64();
        if !result.good {
            return self.lost_or_relocalised(&frame);
        }
        let state = if std::mem::take(&mut self.lost) {
            TrackingState::Relocalized
        } else {
            TrackingState::Tracking
        };
        let keyframe_from_frame = result.frame_from_keyframe.inverse();
        self.velocity = Some(result.frame_from_keyframe * self.last_frame_from_keyframe.inverse());
        self.last_frame_from_keyframe = result.frame_from_keyframe;

        // While the next keyframe is being made, frames are only tracked.
        let keyframe_pending = self.pending_keyframe.is_some();
        let make_keyframe = !keyframe_pending
            && needs_new_keyframe(
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
            let candidate = KeyframeCandidate {
                frame: frame.clone(),
                source_id: kf_id,
                frame_from_source: result.frame_from_keyframe,
                information: result.information,
                state,
            };
            if !self.mapper.is_threaded() {
                let t1 = std::time::Instant::now();
                let propagated = self.mapper.with_filter(|filter| {
                    filter.propagate_to(frame.clone(), &result.frame_from_keyframe)
                })?;
                self.keyframe_creation_s += t1.elapsed().as_secs_f64();
                return self.new_keyframe(candidate, propagated, None);
            }
            self.mapper
                .propagate_on_thread(frame.clone(), result.frame_from_keyframe);
            self.pending_keyframe = Some(candidate);
        } else if !keyframe_pending {
            self.mapper.observe(Observation {
                frame: frame.clone(),
                keyframe_from_frame,
                residual: result.residual,
            })?;
        }

        self.frames.push(FrameRecord {
            timestamp: frame.timestamp,
            keyframe: kf_id,
            keyframe_from_frame,
            lost: false,
        });
        let world_from_camera =
            self.keyframes[kf_id].world_from_keyframe * Sim3::from_se3(&keyframe_from_frame, 1.0);
        Ok(vec![Event::Pose(PoseEvent {
            frame_id: frame.id,
            timestamp: frame.timestamp,
            world_from_camera,
            state,
            keyframe_id: kf_id,
            is_keyframe: false,
        })])
    }

    /// Ends the session: finishes the last keyframe, runs the final pose-graph optimisation
    /// and returns the optimised pose of every keyframe.
    pub fn finish(&mut self) -> Result<Vec<(KeyframeId, Sim3)>> {
        self.switch_to_pending_keyframe(true)?;
        self.finish_current()?;
        self.update_mapping_stats();
        if let Some(DenseLink::Threaded(worker)) = &mut self.dense {
            let replies = worker.finish();
            self.apply_dense(replies)?;
        }
        let poses = match &mut self.backend {
            BackendLink::InStep(backend) => {
                backend.optimize_full()?;
                backend.poses()
            }
            BackendLink::Threaded(handle) => handle.finish()?,
        };
        self.final_poses = Some(poses);
        let poses = self.keyframe_poses();
        self.finish_fusion(&poses)?;
        Ok(poses)
    }

    /// The fused mesh (at the optimised poses after [`Pipeline::finish`]); `None` without
    /// fusion, while it runs on its thread, or before any surface.
    pub fn mesh(&mut self) -> Result<Option<Mesh>> {
        let fuser = match &mut self.fusion {
            Some(FusionLink::InStep(f) | FusionLink::Done(f)) => f,
            _ => return Ok(None),
        };
        let mesh = fuser.mesh()?;
        Ok((!mesh.is_empty()).then_some(mesh))
    }

    /// The fusion's figures (voxel size, blocks, timings), when the fuser is at hand (in step,
    /// or after [`Pipeline::finish`]).
    pub fn fusion_stats(&self) -> Option<FusionStats> {
        match &self.fusion {
            Some(FusionLink::InStep(f) | FusionLink::Done(f)) => Some(f.stats()),
            _ => None,
        }
    }

    /// Hands a densified keyframe to the fusion with the current keyframe poses (which
    /// re-integrate keyframes the pose graph moved).
    fn fuse(&mut self, keyframe: Arc<DenseKeyframe>) -> Result<()> {
        if self.fusion.is_none() {
            return Ok(());
        }
        let id = keyframe.keyframe_id;
        let job = FusionJob {
            rgb: self.keyframes[id].frame.rgb.clone(),
            pose: self.current_pose(id),
            keyframe,
        };
        let poses = self.keyframe_poses();
        match &mut self.fusion {
            Some(FusionLink::InStep(fuser)) => {
                let reply = fuse_in_step(fuser, &self.config.fusion, Some(job), Some(poses));
                self.apply_fusion(vec![(true, reply)]);
            }
            Some(FusionLink::Threaded(worker)) => {
                worker.post_poses(poses);
                if !worker.submit(job)? {
                    tracing::warn!(keyframe = id, "fusion busy: keyframe not fused");
                    self.stats.keyframes_not_fused += 1;
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// Collects the fusion thread's mesh deltas.
    fn poll_fusion(&mut self) {
        if let Some(FusionLink::Threaded(worker)) = &self.fusion {
            let replies = worker.poll();
            self.apply_fusion(replies);
        }
    }

    /// Turns fusion replies into `MeshUpdated` events; a keyframe the fusion failed on is
    /// logged and counted (the mesh goes on without it).
    fn apply_fusion(&mut self, replies: Vec<FusionReply>) {
        for (had_keyframe, reply) in replies {
            match reply {
                Ok(delta) => {
                    self.stats.keyframes_fused += usize::from(had_keyframe);
                    if let Some(delta) = delta {
                        self.push_mesh_event(delta);
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, "fusion failed");
                    self.stats.keyframes_not_fused += usize::from(had_keyframe);
                }
            }
        }
    }

    fn push_mesh_event(&mut self, delta: MeshDelta) {
        self.stats.mesh_revision = delta.revision;
        self.pending_events.push(Event::MeshUpdated {
            revision: delta.revision,
            delta: Arc::new(delta),
        });
    }

    /// Re-integrates at the final poses, meshes, and keeps the fuser for [`Pipeline::mesh`].
    fn finish_fusion(&mut self, poses: &[(KeyframeId, Sim3)]) -> Result<()> {
        let fuser = match self.fusion.take() {
            None => return Ok(()),
            Some(FusionLink::InStep(mut fuser) | FusionLink::Done(mut fuser)) => {
                let reply =
                    fuse_in_step(&mut fuser, &self.config.fusion, None, Some(poses.to_vec()));
                self.apply_fusion(vec![(false, reply)]);
                Some(fuser)
            }
            Some(FusionLink::Threaded(mut worker)) => {
                worker.post_poses(poses.to_vec());
                let (replies, fuser) = worker.finish();
                self.apply_fusion(replies);
                fuser.map(Box::new)
            }
        };
        self.fusion = fuser.map(FusionLink::Done);
        Ok(())
    }

    /// Current pose of every keyframe: optimised where the back end has one, else the front
    /// end's estimate.
    pub fn keyframe_poses(&self) -> Vec<(KeyframeId, Sim3)> {
        let poses = match (&self.final_poses, &self.backend) {
            (Some(poses), _) => poses.clone(),
            (None, BackendLink::InStep(backend)) => backend.poses(),
            (None, BackendLink::Threaded(handle)) => handle.poses(),
        };
        self.keyframe_poses_from(&poses)
    }

    fn keyframe_poses_from(
        &self,
        optimised: &std::collections::HashMap<KeyframeId, Sim3>,
    ) -> Vec<(KeyframeId, Sim3)> {
        (0..self.keyframes.len())
            .map(|id| {
                (
                    id,
                    optimised
                        .get(&id)
                        .copied()
                        .unwrap_or(self.keyframes[id].world_from_keyframe),
                )
            })
            .collect()
    }

    /// Keyframe timestamps with their current poses (for `keyframes.txt`).
    pub fn keyframe_trajectory(&self) -> Vec<(f64, Sim3)> {
        self.keyframe_poses()
            .into_iter()
            .map(|(id, pose)| (self.keyframes[id].frame.timestamp, pose))
            .collect()
    }

    /// Every frame's pose (camera-to-world) through its keyframe's current pose; lost frames
    /// are left out.
    pub fn trajectory(&self) -> Vec<(f64, Sim3)> {
        let poses = self.keyframe_poses();
        self.frames
            .iter()
            .filter(|f| !f.lost)
            .map(|f| {
                (
                    f.timestamp,
                    poses[f.keyframe].1 * Sim3::from_se3(&f.keyframe_from_frame, 1.0),
                )
            })
            .collect()
    }

    /// The semi-dense points of every keyframe at its current pose, coloured from its image.
    pub fn semidense_points(&self) -> Vec<ColoredPoint> {
        let poses = self.keyframe_poses();
        let mut points = Vec::new();
        let current_depth = self.current.zip(self.mapper.latest_depth());
        for (id, (kf, (_, world_from_kf))) in self.keyframes.iter().zip(poses).enumerate() {
            let depth = match &current_depth {
                Some((current, depth)) if *current == id => depth.clone(),
                _ => kf.depth.clone(),
            };
            let camera = &kf.frame.camera;
            for y in 0..depth.height {
                for x in 0..depth.width {
                    let Some((idepth, _)) = depth.at(x, y).estimate() else {
                        continue;
                    };
                    if idepth <= 0.0 {
                        continue;
                    }
                    let p = camera.unproject(
                        &nalgebra::Vector2::new(x as f64, y as f64),
                        1.0 / f64::from(idepth),
                    );
                    let w: Vector3<f64> = world_from_kf.act(&p);
                    let color = kf
                        .frame
                        .rgb
                        .as_ref()
                        .map(|rgb| rgb.get_pixel(x as u32, y as u32).0)
                        .unwrap_or([200, 200, 200]);
                    points.push(ColoredPoint {
                        position: [w.x as f32, w.y as f32, w.z as f32],
                        color,
                    });
                }
            }
        }
        points
    }

    /// Every densified keyframe back-projected at its current pose (optimised after
    /// [`Pipeline::finish`]), coloured from its image: the dense point cloud (`dense.ply`).
    pub fn dense_points(&self) -> Result<Vec<ColoredPoint>> {
        let mut points = Vec::new();
        for (kf, world_from_kf) in self.dense_keyframes() {
            let (w, h) = (kf.idepth.width, kf.idepth.height);
            let colors = match &self.keyframes[kf.keyframe_id].frame.rgb {
                Some(rgb) => Some(crate::dense::resample::box_downsample_rgb(rgb, w, h)?),
                None => None,
            };
            for y in 0..h {
                for x in 0..w {
                    let idepth = kf.idepth.at(x, y);
                    if !(idepth.is_finite() && idepth > 0.0) {
                        continue;
                    }
                    let p = kf.camera.unproject(
                        &nalgebra::Vector2::new(x as f64, y as f64),
                        1.0 / f64::from(idepth),
                    );
                    let p: Vector3<f64> = world_from_kf.act(&p);
                    points.push(ColoredPoint {
                        position: [p.x as f32, p.y as f32, p.z as f32],
                        color: colors.as_ref().map_or([200, 200, 200], |c| c[y * w + x]),
                    });
                }
            }
        }
        Ok(points)
    }

    /// Undistorts and converts the input; rejects a size that does not match the camera.
    fn make_frame(&mut self, input: FrameInput) -> Result<Frame> {
        let (w, h) = input.rgb.dimensions();
        if (w, h) != (self.camera.width, self.camera.height) {
            return Err(Error::Shape(format!(
                "frame is {w}x{h} but the camera is {}x{}",
                self.camera.width, self.camera.height
            )));
        }
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
        let rgb = match &self.undistort {
            Some(map) => map.apply_rgb(&input.rgb)?,
            None => input.rgb,
        };
        let gray = ImageF32::from_rgb8(&rgb);
        let id = self.next_frame_id;
        self.next_frame_id += 1;
        let mut frame = Frame::new(
            id,
            input.timestamp,
            self.camera.undistorted(),
            &gray,
            Some(Arc::new(rgb)),
        )?;
        frame.sensor_depth = sensor_depth;
        Ok(frame)
    }

    /// The first frame becomes the first keyframe, its depth initialised from the prior (or
    /// randomly).
    fn start(&mut self, frame: Arc<Frame>) -> Result<Vec<Event>> {
        let mut filter = DepthFilter::new(frame.clone(), self.config.mapping.clone())?;
        let prior_depth = match (
            self.config.pipeline.init,
            self.prior.as_ref(),
            frame.rgb.as_ref(),
        ) {
            (DepthInit::Prior, Some(prior), Some(rgb)) => Some(Arc::new(predict(prior, rgb)?)),
            _ => None,
        };
        match &prior_depth {
            Some(idepth) => filter.init_from_depth(
                &normalise_mean(idepth)?,
                self.config.pipeline.prior_init_var,
            )?,
            None => filter.init_random(self.config.pipeline.seed),
        }
        filter.regularize();
        self.begin_keyframe(
            frame,
            filter,
            Sim3::identity(),
            None,
            prior_depth,
            Some(TrackingState::Initializing),
        )
    }

    /// The candidate's frame becomes the next keyframe, with `filter` (the depth of its source
    /// keyframe propagated into it) scale-normalised (mean inverse depth 1, LSD-SLAM's gauge);
    /// the current keyframe is finished and goes to the back end. `last_from_frame`: the pose
    /// of the latest tracked frame relative to the candidate when frames were tracked after it
    /// (a keyframe made on the mapping thread); the candidate's own frame was reported then.
    fn new_keyframe(
        &mut self,
        candidate: KeyframeCandidate,
        mut filter: DepthFilter,
        last_from_frame: Option<SE3>,
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
        let parent = ParentEdge::from_se3_information(
            source_id,
            source_from_new,
            &(ad.transpose() * information * ad),
        );
        let world_from_source = self.current_pose(source_id);
        self.finish_current()?;
        let events = self.begin_keyframe(
            frame,
            filter,
            world_from_source * source_from_new,
            Some(parent),
            prior,
            last_from_frame.is_none().then_some(state),
        )?;
        if let Some(last_from_frame) = last_from_frame {
            // The latest frame was tracked against the previous keyframe; in the new
            // keyframe's scale, lengths are divided by `factor`.
            self.last_frame_from_keyframe = SE3::new(
                last_from_frame.rotation,
                last_from_frame.translation / factor,
            );
        }
        self.keyframe_creation_s += t0.elapsed().as_secs_f64();
        Ok(events)
    }

    /// Makes the pending keyframe current once the mapping thread has propagated its depth
    /// (with `wait`, waits for that); its events are returned with the next push. Frames were
    /// tracked against the previous keyframe meanwhile: the latest one's pose is re-expressed
    /// relative to the new keyframe.
    fn switch_to_pending_keyframe(&mut self, wait: bool) -> Result<()> {
        if self.pending_keyframe.is_none() {
            return Ok(());
        }
        let Some(propagated) = self.mapper.take_propagated(wait) else {
            return Ok(());
        };
        let Some(candidate) = self.pending_keyframe.take() else {
            return Ok(());
        };
        let last_from_frame = self.last_frame_from_keyframe * candidate.frame_from_source.inverse();
        let mut events = self.new_keyframe(candidate, propagated?, Some(last_from_frame))?;
        self.pending_events.append(&mut events);
        Ok(())
    }

    /// Fills the holes of a new keyframe's propagated depth from the depth prior
    /// (`pipeline.prior_fill`; nothing without a prior or an RGB image).
    /// Returns the prior's output when the network ran, for the dense layer to reuse.
    fn fill_from_prior(&mut self, filter: &mut DepthFilter) -> Result<Option<Arc<ImageF32>>> {
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
    fn begin_keyframe(
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
            frame: frame.clone(),
            depth: mapped.depth,
            world_from_keyframe,
            reference: mapped.reference,
            parent,
            prior,
        });
        self.current = Some(id);
        self.stats.keyframes = self.keyframes.len();
        let mut events = vec![Event::Keyframe(KeyframeEvent {
            keyframe_id: id,
            frame_id: frame.id,
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
                frame_id: frame.id,
                timestamp: frame.timestamp,
                world_from_camera: world_from_keyframe,
                state,
                keyframe_id: id,
                is_keyframe: true,
            }));
        }
        if id > 0 && self.config.pipeline.deterministic {
            events.push(Event::KeyframePoses {
                poses: self.keyframe_poses(),
            });
        }
        Ok(events)
    }

    /// Finishes the current keyframe: its final depth is published and it goes to the back
    /// end (constraint search and pose-graph optimisation; in step when deterministic).
    fn finish_current(&mut self) -> Result<()> {
        let Some(id) = self.current.take() else {
            return Ok(());
        };
        // The final depth is what the mapping published last (its tracking reference serves
        // relocalisation from now on).
        let mapped = self
            .mapper
            .finish()?
            .ok_or_else(|| Error::Config("the current keyframe has no depth filter".into()))?;
        let record = &mut self.keyframes[id];
        record.depth = mapped.depth;
        record.reference = mapped.reference;
        let new = NewKeyframe {
            id,
            frame: record.frame.clone(),
            depth: record.depth.clone(),
            world_from_keyframe: record.world_from_keyframe,
            parent: record.parent.clone(),
        };
        let pose_covariance = record
            .parent
            .as_ref()
            .map_or_else(Matrix7::zeros, |p| covariance(&p.information));
        let job = DenseJob {
            keyframe_id: id,
            frame: record.frame.clone(),
            depth: record.depth.clone(),
            poses: Vec::new(),
            pose_covariance,
            prior: record.prior.take(),
        };
        match &mut self.backend {
            BackendLink::InStep(backend) => {
                backend.add_keyframe(new)?;
                backend.process()?;
            }
            BackendLink::Threaded(handle) => handle.add_keyframe(new)?,
        }
        self.densify(job)
    }

    /// Hands a finished keyframe to the dense layer (in step when deterministic).
    fn densify(&mut self, mut job: DenseJob) -> Result<()> {
        if self.dense.is_none() {
            return Ok(());
        }
        job.poses = self.keyframe_poses();
        let id = job.keyframe_id;
        match self.dense.as_mut() {
            Some(DenseLink::InStep(layer)) => {
                let reply = layer.process(job);
                self.apply_dense(vec![(id, reply)])
            }
            Some(DenseLink::Threaded(worker)) => {
                if !worker.submit(job)? {
                    tracing::warn!(keyframe = id, "dense layer busy: keyframe not densified");
                    self.stats.keyframes_not_densified += 1;
                }
                Ok(())
            }
            None => Ok(()),
        }
    }

    /// Collects the dense worker's finished keyframes.
    fn poll_dense(&mut self) -> Result<()> {
        let replies = match &self.dense {
            Some(DenseLink::Threaded(worker)) => worker.poll(),
            _ => return Ok(()),
        };
        self.apply_dense(replies)
    }

    /// Records dense results, sends their two-view consistent depth to the back end (§III-E)
    /// and queues their events. A keyframe the layer failed on is logged and counted: the
    /// semi-dense SLAM goes on without it.
    fn apply_dense(&mut self, replies: Vec<(KeyframeId, Result<DenseOutput>)>) -> Result<()> {
        for (id, reply) in replies {
            let output = match reply {
                Ok(output) => output,
                Err(e) => {
                    tracing::warn!(keyframe = id, error = %e, "dense layer failed on a keyframe");
                    self.stats.keyframes_not_densified += 1;
                    continue;
                }
            };
            if let Some(depth) = output.refined_depth {
                self.stats.depth_refinements += 1;
                match &mut self.backend {
                    BackendLink::InStep(backend) => {
                        backend.update_keyframe_depth(id, depth)?;
                        backend.process()?;
                    }
                    BackendLink::Threaded(handle) => {
                        handle.send(crate::graph::BackendCommand::UpdateDepth { id, depth })?
                    }
                }
            }
            let kf = output.keyframe;
            self.stats.keyframes_densified += 1;
            self.pending_events.push(Event::KeyframeDensified {
                keyframe_id: id,
                timestamp: kf.timestamp,
                mode: kf.mode,
                keyframe: kf.clone(),
            });
            self.dense_keyframes.insert(id, kf.clone());
            self.fuse(kf)?;
        }
        Ok(())
    }

    /// The best current estimate of a keyframe's pose: the back end's once it has one.
    fn current_pose(&self, id: KeyframeId) -> Sim3 {
        let optimised = match &self.backend {
            BackendLink::InStep(backend) => backend.poses().get(&id).copied(),
            BackendLink::Threaded(handle) => handle.poses().get(&id).copied(),
        };
        optimised.unwrap_or(self.keyframes[id].world_from_keyframe)
    }

    /// Tracking failed: try the current and the most recent keyframes. On success the frame
    /// becomes a new keyframe whose depth is propagated from the keyframe it relocalised
    /// against; otherwise it is reported lost.
    fn lost_or_relocalised(&mut self, frame: &Arc<Frame>) -> Result<Vec<Event>> {
        // The motion since the last good frame is unknown.
        self.velocity = None;
        // Relocalise against the newest keyframe, once it is made.
        self.switch_to_pending_keyframe(true)?;
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
        let guess = |id: KeyframeId| {
            if id == current_id {
                self.last_frame_from_keyframe
            } else {
                SE3::identity()
            }
        };
        let refs: Vec<(&TrackingReference, SE3)> = candidates
            .iter()
            .map(|&id| (self.keyframes[id].reference.as_ref(), guess(id)))
            .collect();
        if let Some((i, result)) = self.tracker.try_relocalise(&refs, frame) {
            let kf = candidates[i];
            self.lost = false;
            let t0 = std::time::Instant::now();
            let propagated = match self.current {
                Some(current) if current == kf => self.mapper.with_filter(|filter| {
                    filter.propagate_to(frame.clone(), &result.frame_from_keyframe)
                })?,
                _ => DepthFilter::from_depth_map(
                    self.keyframes[kf].frame.clone(),
                    &self.keyframes[kf].depth,
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
            return self.new_keyframe(candidate, propagated, None);
        }
        self.lost = true;
        self.stats.frames_lost += 1;
        let keyframe_from_frame = self.last_frame_from_keyframe.inverse();
        self.frames.push(FrameRecord {
            timestamp: frame.timestamp,
            keyframe: current_id,
            keyframe_from_frame,
            lost: true,
        });
        Ok(vec![Event::Pose(PoseEvent {
            frame_id: frame.id,
            timestamp: frame.timestamp,
            world_from_camera: self.keyframes[current_id].world_from_keyframe
                * Sim3::from_se3(&keyframe_from_frame, 1.0),
            state: TrackingState::Lost,
            keyframe_id: current_id,
            is_keyframe: false,
        })])
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
) -> crate::tracking::TrackingResult {
    if let Some(v) = velocity {
        let result = tracker.track(reference, frame, &(v * *last_frame_from_keyframe));
        if result.good {
            return result;
        }
    }
    tracker.track(reference, frame, last_frame_from_keyframe)
}

/// Σ of a pose from its information matrix; zero (no uncertainty propagated) when the
/// information is singular.
fn covariance(information: &Matrix7) -> Matrix7 {
    information.try_inverse().unwrap_or_else(Matrix7::zeros)
}

/// Scales a relative inverse-depth map so that its mean over positive pixels is 1 (the
/// keyframe scale gauge), leaving non-positive pixels at 0 ("no prediction").
fn normalise_mean(idepth: &ImageF32) -> Result<ImageF32> {
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
    ImageF32::from_vec(idepth.width, idepth.height, data)
}
