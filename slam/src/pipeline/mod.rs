//! The SLAM pipeline: frames in, events out (`Pipeline::push`).
//!
//! A thin orchestration over the components, in LSD-SLAM's order (Engel et al. ECCV 2014,
//! Fig. 3): each frame is tracked against the current keyframe (SE(3) direct alignment); a good
//! frame refines the keyframe's semi-dense depth (epipolar stereo + filtering); when the camera
//! has moved far enough, the frame becomes the next keyframe (depth propagated, scale
//! normalised) and the finished keyframe goes to the back end (Sim(3) constraints, pose graph).
//! Each finished keyframe also goes to the dense layer (DeepRelativeFusion §III-B..E), whose
//! two-view consistent depth comes back to refine the keyframe's constraints, and densified
//! keyframes are fused into the TSDF at their current poses and meshed ([`crate::fusion`]);
//! pose-graph moves re-integrate them. The back end, the dense layer and the fusion run as
//! background services ([`crate::background::Link`]): in step when `pipeline.deterministic`,
//! on their own threads otherwise.
//!
//! - [`frames`]: one frame: undistortion, tracking, mapping or keyframe choice, relocalisation;
//! - [`keyframes`]: a keyframe's life: start, propagation into the next, prior hole filling,
//!   hand-over to the back end and the dense layer;
//! - [`layers`]: the dense layer's and the fusion's results coming back;
//! - [`export`]: trajectories and point clouds at the current poses;
//! - [`extend`]: a pipeline that starts from a saved map and extends it;
//! - [`reactivate`]: an old keyframe made current again instead of a new one (revisits);
//! - [`mapper`]: the current keyframe's depth mapping, in step or on its own thread;
//! - [`odometry_front`]: the pipeline driven by the DSO-class odometry instead of LSD's
//!   tracking (`pipeline.frontend = "dso"`);
//! - [`user_config`]: the few settings a user should ever touch, and who may set them.

pub mod config;
pub mod engine;
pub mod events;
mod export;
mod extend;
mod frames;
mod keyframes;
mod layers;
mod mapper;
#[cfg(test)]
mod metric_tests;
mod odometry_front;
#[cfg(test)]
mod odometry_front_tests;
mod reactivate;
#[cfg(test)]
mod reactivate_tests;
#[cfg(test)]
mod tests;
pub mod user_config;

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

pub use config::{Config, DepthInit, Frontend, PipelineConfig};
pub use engine::{Engine, Start, Trajectories};
pub use events::{Event, KeyframeEvent, KeyframePose, PoseEvent, TrackingState};
pub use export::SemidenseSnapshot;
pub use extend::ExtendConfig;
pub use user_config::{Scope, USER_SETTINGS, UserConfig, UserConfigError};

use crate::Result;
use crate::background::{Link, Priority, WorkerSpec};
use crate::dense::DenseKeyframe;
use crate::dense::layer::{DenseLayer, SharedPrior};
use crate::dense::prior::DepthPrior;
use crate::frame::CompactFrame;
use crate::frame_log::FrameLog;
use crate::fusion::weld::WeldCounts;
use crate::fusion::worker::FusionLink;
use crate::fusion::{FusionStats, Mesh};
use crate::geometry::{PinholeCamera, SE3, Sim3, UndistortMap};
use crate::gpu::GpuContext;
use crate::graph::{Backend, BackendLink, KeyframeId};
use crate::image::ImageF32;
use crate::mapping::DepthMap;
use crate::spill::{Spill, Stored};
use crate::tracking::SE3Tracker;
use extend::MapOrigin;
use keyframes::{FrameRecord, KeyframeRecord};
use mapper::KeyframeMapper;

/// One input frame: a colour image (distorted as the camera delivers it) and its time.
#[derive(Clone, Debug)]
pub struct FrameInput {
    /// The caller's id of this frame (a client's), echoed as `frame_id` in the frame's events
    /// and in those of the keyframe made from it, so no caller keeps a map back to its ids;
    /// `None`: the pipeline's own count (0, 1, 2, ... in arrival order).
    pub frame_id: Option<u64>,
    pub timestamp: f64,
    pub rgb: ::image::RgbImage,
    /// Metric depth registered to `rgb` (same size, distorted alike; metres, 0 = none), from
    /// an RGB-D dataset: used only by the ground-truth refinement baseline
    /// (`dense.two_view.ground_truth_depth`) and dropped otherwise.
    pub depth: Option<ImageF32>,
}

/// Summary counters of a run.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Stats {
    pub frames: usize,
    pub keyframes: usize,
    pub frames_lost: usize,
    /// Map fragments begun after tracking stayed lost (`pipeline.new_fragment_after_lost_s`).
    pub fragments: usize,
    /// Of the map's fragments, those still apart from the first at the end of the run (no
    /// constraint joined them); set by [`Pipeline::finish`].
    pub fragments_apart: usize,
    /// Accumulated wall time of tracking, mapping and keyframe creation (seconds).
    pub tracking_s: f64,
    pub mapping_s: f64,
    /// Frames the mapping thread observed in a batch with earlier ones because it was busy
    /// (`pipeline.mapping_thread`; always 0 in step). No tracked frame goes unobserved.
    pub frames_batched: usize,
    /// Keyframes the dense layer finished.
    pub keyframes_densified: usize,
    /// Keyframes it skipped (queue full) or failed on (reason logged).
    pub keyframes_not_densified: usize,
    /// `"prior"`, or `"no_model"` when no depth model is loaded (the dense layer then densifies
    /// from the semi-dense depth alone); `"off"` when the dense layer is disabled.
    pub dense_mode: &'static str,
    /// `"metric"` when a metric depth prior anchors the map's scale (the world's unit is the
    /// metre: `backend.metric_scale`), `"arbitrary"` otherwise (a monocular map's unit).
    pub scale: &'static str,
    /// Dense keyframes whose two-view consistent depth went to the back end (§III-E).
    pub depth_refinements: usize,
    /// Dense keyframes fused into the TSDF.
    pub keyframes_fused: usize,
    /// Dense keyframes the fusion skipped (queue full) or failed on (reason logged).
    pub keyframes_not_fused: usize,
    /// Revision of the last mesh update.
    pub mesh_revision: u64,
    /// Times an old keyframe became the current one again instead of a new keyframe being
    /// made (`pipeline.reactivation_candidates`).
    pub keyframes_reactivated: usize,
}

/// A keyframe's image and semi-dense depth ([`Pipeline::keyframe_depths`]).
pub type KeyframeDepth = (KeyframeId, Arc<CompactFrame>, Arc<DepthMap>);

/// What a session's keyframes hold ([`Pipeline::keyframe_memory`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct KeyframeMemory {
    pub keyframes: usize,
    /// Keyframes whose full frame and tracking reference the pipeline holds (the
    /// `backend.resident_keyframes` newest).
    pub resident: usize,
    /// Bytes of the compact images and depth maps held in memory.
    pub compact_bytes: usize,
    /// Keyframes whose compact image and depth are spilled to the session's store.
    pub spilled: usize,
    /// What was written to and read from the store.
    pub spill: crate::spill::SpillFigures,
    /// Bytes the full frames and tracking references held add.
    pub resident_bytes: usize,
    /// Bytes of the dense keyframes' maps held in memory (depth and variance; the stages when
    /// kept).
    pub dense_bytes: usize,
    /// Dense keyframes whose maps are spilled to the session's store.
    pub dense_spilled: usize,
    /// The back end's figures (as of its latest batch while it runs on its thread).
    pub backend: Option<crate::graph::backend::KeyframeMemory>,
}

/// The pipeline of one session.
#[derive(Debug)]
pub struct Pipeline {
    config: Config,
    /// The camera as given (possibly distorted).
    camera: PinholeCamera,
    undistort: Option<UndistortMap>,
    prior: Option<SharedPrior>,
    /// The prior is metric and anchors the scale: keyframes observe their scale in it.
    metric: bool,
    /// The world's unit is the metre (`Stats::scale`): `metric`, or the extended map was
    /// made in metres.
    metres: bool,
    tracker: SE3Tracker,
    /// The DSO-class odometry when it is the front end (`pipeline.frontend = "dso"`).
    odometry: Option<Box<odometry_front::OdometryFront>>,
    backend: BackendLink,
    dense: Option<Link<DenseLayer>>,
    fusion: Option<FusionLink>,
    /// The latest dense result of each keyframe, by keyframe id.
    /// Dense results, spilled with their keyframe's compact data (`retire_keyframes`).
    dense_keyframes: BTreeMap<KeyframeId, Arc<Stored<DenseKeyframe>>>,
    /// Events produced outside a frame's own processing (dense results, pose-graph updates),
    /// returned with the next [`Pipeline::push`] or by
    /// [`Pipeline::take_events`].
    pending_events: Vec<Event>,
    keyframes: Vec<KeyframeRecord>,
    /// The keyframe being mapped; its depth filter is in `mapper`.
    current: Option<KeyframeId>,
    /// The current keyframe when it is an old one re-activated (`reactivate`).
    reactivated: Option<reactivate::Reactivated>,
    mapper: KeyframeMapper,
    /// Seconds spent creating keyframes (propagation); the mapper adds its own.
    keyframe_creation_s: f64,
    /// Where every frame ended up; full chunks spill with `spill` (`crate::frame_log`).
    frames: FrameLog<FrameRecord>,
    /// Pose of the last good frame relative to the current keyframe (the tracking prior).
    last_frame_from_keyframe: SE3,
    /// Motion of the camera between the last two good frames, `last_from_previous`, in the
    /// current keyframe's scale (the constant-velocity model of the tracking guess).
    velocity: Option<SE3>,
    lost: bool,
    /// Timestamp of the first frame of the current run of lost frames.
    lost_since: Option<f64>,
    next_frame_id: u64,
    stats: Stats,
    /// The keyframe poses last reported in an [`Event::KeyframePoses`].
    reported_poses: HashMap<KeyframeId, Sim3>,
    /// The saved map this pipeline extends, if any ([`Pipeline::extending`]).
    map: Option<MapOrigin>,
    /// Where old keyframes' compact data goes (`crate::spill`).
    spill: Spill,
}

/// `Stats::scale` of a world in metres or not.
pub fn scale_name(metres: bool) -> &'static str {
    if metres { "metric" } else { "arbitrary" }
}

impl Pipeline {
    /// A pipeline for frames of `camera` (with its distortion, if any). `prior` initialises the
    /// first keyframe's depth when `config.pipeline.init` is `Prior`. The dense layer's and the
    /// fusion's kernels run on the process's shared GPU context.
    pub fn new(
        config: Config,
        camera: PinholeCamera,
        prior: Option<Box<dyn DepthPrior>>,
    ) -> Result<Self> {
        Self::with_gpu(config, camera, prior, None)
    }

    /// [`Pipeline::new`] with the kernels on `gpu` (a service gives each session the context
    /// of the GPU its pool worker owns).
    pub fn with_gpu(
        config: Config,
        camera: PinholeCamera,
        prior: Option<Box<dyn DepthPrior>>,
        gpu: Option<Arc<GpuContext>>,
    ) -> Result<Self> {
        Self::build(config, camera, prior, gpu, None, Spill::default())
    }

    /// [`Pipeline::with_gpu`] with a back end that may already hold keyframes (a loaded map,
    /// whose compact data spills with `spill`).
    fn build(
        mut config: Config,
        camera: PinholeCamera,
        prior: Option<Box<dyn DepthPrior>>,
        gpu: Option<Arc<GpuContext>>,
        backend: Option<Backend>,
        spill: Spill,
    ) -> Result<Self> {
        config.validate()?;
        let threaded = !config.pipeline.deterministic;
        let mapping_thread = config.pipeline.maps_on_thread();
        if mapping_thread {
            config.mapping.threads = config.pipeline.mapping_thread_workers;
        }
        let undistort = camera
            .distortion
            .is_some()
            .then(|| UndistortMap::new(&camera));
        let tracker = SE3Tracker::new(config.tracking.clone())?;
        if config.pipeline.frontend == Frontend::Dso && backend.is_some() {
            return Err(crate::Error::Config(
                "extending a saved map needs pipeline.frontend = \"lsd\"".into(),
            ));
        }
        let backend = match backend {
            Some(backend) => BackendLink::with_backend(backend, threaded)?,
            None => BackendLink::new(config.backend.clone(), threaded)?,
        };
        let prior: Option<SharedPrior> = prior.map(|p| Arc::new(std::sync::Mutex::new(p)));
        let dense = if config.dense.enabled {
            config.dense.validate()?;
            let spec = WorkerSpec {
                name: "dense",
                priority: Priority::Dense,
                queue: config.dense.queue,
            };
            let (dense_config, dense_prior, dense_gpu) =
                (config.dense.clone(), prior.clone(), gpu.clone());
            Some(Link::new(threaded, spec, move || {
                DenseLayer::new(dense_config, dense_prior, dense_gpu)
            })?)
        } else {
            None
        };
        let fusion = (config.fusion.enabled && config.dense.enabled)
            .then(|| FusionLink::new(config.fusion.clone(), threaded, gpu, spill.clone()))
            .transpose()?;
        // Anchoring needs the first keyframe in metres, so its depth must come from the prior.
        let metric = config.backend.metric_scale.enabled
            && config.pipeline.init == DepthInit::Prior
            && prior.as_ref().is_some_and(crate::dense::layer::is_metric);
        let odometry = match config.pipeline.frontend {
            Frontend::Lsd => None,
            Frontend::Dso => {
                // The window runs the model on its keyframes only when it uses it.
                let in_window = metric && config.odometry.metric_prior_weight > 0.0;
                let model = prior.clone().filter(|_| in_window);
                Some(Box::new(odometry_front::OdometryFront::new(
                    &config, model,
                )?))
            }
        };
        let dense_mode = match (&dense, &prior) {
            (None, _) => "off",
            (Some(_), Some(_)) => "prior",
            (Some(_), None) => "no_model",
        };
        Ok(Self {
            camera,
            undistort,
            prior,
            metric,
            metres: metric,
            tracker,
            odometry,
            backend,
            dense,
            fusion,
            dense_keyframes: BTreeMap::new(),
            pending_events: Vec::new(),
            keyframes: Vec::new(),
            current: None,
            reactivated: None,
            mapper: KeyframeMapper::new(mapping_thread, config.pipeline.mapping_queue)?,
            keyframe_creation_s: 0.0,
            frames: FrameLog::new(&spill),
            last_frame_from_keyframe: SE3::identity(),
            velocity: None,
            lost: false,
            lost_since: None,
            next_frame_id: 0,
            stats: Stats {
                dense_mode,
                scale: scale_name(metric),
                ..Stats::default()
            },
            reported_poses: HashMap::new(),
            map: None,
            spill,
            config,
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

    /// What the keyframes hold in memory now (issue 37).
    pub fn keyframe_memory(&self) -> KeyframeMemory {
        let held = self.keyframes.iter().filter(|k| k.frame.is_some());
        KeyframeMemory {
            keyframes: self.keyframes.len(),
            resident: held.clone().count(),
            compact_bytes: self.keyframes.iter().map(|k| k.data.held_bytes()).sum(),
            spilled: self.keyframes.iter().filter(|k| !k.data.is_held()).count(),
            spill: self.spill.figures(),
            resident_bytes: held
                .map(|k| {
                    k.frame.as_ref().map_or(0, |f| f.heap_bytes())
                        + k.depth.as_ref().map_or(0, |d| d.heap_bytes())
                        + k.reference.as_ref().map_or(0, |r| r.heap_bytes())
                })
                .sum(),
            dense_bytes: self.dense_keyframes.values().map(|d| d.held_bytes()).sum(),
            dense_spilled: self
                .dense_keyframes
                .values()
                .filter(|d| !d.is_held())
                .count(),
            backend: Some(self.backend.memory()),
        }
    }

    /// Processes one frame and returns what happened: a pose event always; keyframe events
    /// when one was made; dense keyframes and mesh updates as the layers finish them; the
    /// keyframe poses whenever the pose graph moved them.
    pub fn push(&mut self, input: FrameInput) -> Result<Vec<Event>> {
        let mut events = self.push_frame(input)?;
        events.append(&mut self.poll()?);
        Ok(events)
    }

    /// What the threads beside tracking finished since the last call, without a frame: dense
    /// keyframes, mesh updates and moved keyframe poses. A live caller polls while the camera
    /// pauses, so that results do not wait for the next frame.
    pub fn poll(&mut self) -> Result<Vec<Event>> {
        self.poll_dense()?;
        self.poll_fusion();
        self.report_keyframe_poses();
        self.update_mapping_stats();
        Ok(std::mem::take(&mut self.pending_events))
    }

    /// Events produced since the last [`Pipeline::push`] outside a frame's processing: the
    /// dense keyframes and the mesh [`Pipeline::finish`] waited for.
    pub fn take_events(&mut self) -> Vec<Event> {
        std::mem::take(&mut self.pending_events)
    }

    /// Ends the session: finishes the last keyframe, runs the final pose-graph optimisation,
    /// re-integrates the fusion at the final poses and returns the optimised pose of every
    /// keyframe.
    pub fn finish(&mut self) -> Result<Vec<(KeyframeId, Sim3)>> {
        if let Some(front) = &mut self.odometry {
            front.finish()?;
        }
        self.finish_current()?;
        self.update_mapping_stats();
        if let Some(dense) = &mut self.dense {
            let replies = dense.finish()?;
            self.apply_dense(replies)?;
        }
        self.backend.finish()?;
        if let Some(backend) = self.backend.backend() {
            let fragments: std::collections::BTreeSet<KeyframeId> =
                backend.fragments().into_values().collect();
            self.stats.fragments_apart = fragments.len().saturating_sub(1);
        }
        let poses = self.keyframe_poses();
        self.finish_fusion(&poses)?;
        Ok(poses)
    }

    fn update_mapping_stats(&mut self) {
        let (mapping_s, batched) = self.mapper.counters();
        self.stats.mapping_s = self.keyframe_creation_s + mapping_s;
        self.stats.frames_batched = batched;
    }

    /// Reports the keyframe poses when the pose graph moved any since the last report (in
    /// step after every keyframe; on the back end's thread whenever it published a batch).
    fn report_keyframe_poses(&mut self) {
        let optimised = self.backend.poses();
        if optimised.len() < 2 || optimised == self.reported_poses {
            return;
        }
        let poses = self.with_frames(self.keyframe_poses_from(&optimised));
        self.pending_events.push(Event::KeyframePoses { poses });
        self.reported_poses = optimised;
    }

    /// Keyframe `poses` with the caller's frame id and the timestamp of each (what
    /// [`Event::KeyframePoses`] carries).
    pub fn with_frames(&self, poses: Vec<(KeyframeId, Sim3)>) -> Vec<KeyframePose> {
        poses
            .into_iter()
            .map(|(id, pose)| KeyframePose {
                keyframe_id: id,
                frame_id: self.keyframes[id].frame_id,
                timestamp: self.keyframes[id].timestamp,
                world_from_keyframe: pose,
            })
            .collect()
    }

    /// Current pose of every keyframe: optimised where the back end has one, else the front
    /// end's estimate.
    pub fn keyframe_poses(&self) -> Vec<(KeyframeId, Sim3)> {
        self.keyframe_poses_from(&self.backend.poses())
    }

    fn keyframe_poses_from(
        &self,
        optimised: &HashMap<KeyframeId, Sim3>,
    ) -> Vec<(KeyframeId, Sim3)> {
        (0..self.keyframes.len())
            .map(|id| {
                let front_end = self.keyframes[id].world_from_keyframe;
                (id, optimised.get(&id).copied().unwrap_or(front_end))
            })
            .collect()
    }

    /// Every keyframe's image and semi-dense inverse depth as last published (final once the
    /// keyframe is finished), in the keyframe's own scale: what the depth probes of
    /// `relfusion bench accuracy` compare with the sensor's depth.
    /// Spilled keyframes are read back.
    pub fn keyframe_depths(&self) -> Result<Vec<KeyframeDepth>> {
        self.keyframes
            .iter()
            .enumerate()
            .map(|(id, k)| Ok((id, k.data.image.get()?, self.keyframe_depth(id)?)))
            .collect()
    }

    /// The session's spilling (`crate::spill`): attach a store before the first frame to keep
    /// only the newest keyframes' compact data in memory.
    pub fn spill(&self) -> &Spill {
        &self.spill
    }

    /// The best current estimate of a keyframe's pose: the back end's once it has one.
    fn current_pose(&self, id: KeyframeId) -> Sim3 {
        self.backend
            .poses()
            .get(&id)
            .copied()
            .unwrap_or(self.keyframes[id].world_from_keyframe)
    }

    /// The latest dense result of every densified keyframe with its current pose (optimised
    /// after [`Pipeline::finish`]); spilled ones are read back.
    pub fn dense_keyframes(&self) -> Result<Vec<(Arc<DenseKeyframe>, Sim3)>> {
        let poses = self.keyframe_poses();
        self.dense_keyframes
            .iter()
            .map(|(id, kf)| Ok((kf.get()?, poses[*id].1)))
            .collect()
    }

    /// The fused mesh (at the optimised poses after [`Pipeline::finish`]); `None` without
    /// fusion, while it runs on its thread, or before any surface.
    pub fn mesh(&mut self) -> Result<Option<Mesh>> {
        let Some(fuser) = self.fusion.as_mut().and_then(FusionLink::fuser) else {
            return Ok(None);
        };
        let mesh = fuser.mesh()?;
        Ok((!mesh.is_empty()).then_some(mesh))
    }

    /// Writes the fused mesh (as [`Pipeline::mesh`]) as `mesh.ply` and `mesh.glb` in `dir`, a
    /// block at a time: a long session's spilled chunks are read back a slab at a time, so
    /// the whole surface is never in memory (issue 37). `None`, and nothing written, when
    /// [`Pipeline::mesh`] would be `None`.
    pub fn write_mesh(&mut self, dir: &std::path::Path) -> Result<Option<WeldCounts>> {
        let Some(fuser) = self.fusion.as_mut().and_then(FusionLink::fuser) else {
            return Ok(None);
        };
        let mut surface = fuser.surface()?;
        // The PLY's counting pass tells whether there is a surface at all.
        let ply = dir.join("mesh.ply");
        let counts = crate::export::write_mesh_ply_from(&ply, &mut surface)?;
        if counts.triangles == 0 {
            std::fs::remove_file(&ply).map_err(|e| crate::Error::io(&ply, e))?;
            return Ok(None);
        }
        crate::export::write_mesh_glb_from(&dir.join("mesh.glb"), &mut surface)?;
        Ok(Some(counts))
    }

    /// The fusion's figures (voxel size, blocks, timings): current when the fuser is at hand
    /// (in step, or after [`Pipeline::finish`]), as of its latest keyframe while it runs on
    /// its thread; `None` without fusion.
    pub fn fusion_stats(&self) -> Option<FusionStats> {
        let fusion = self.fusion.as_ref()?;
        Some(
            fusion
                .fuser_ref()
                .map_or_else(|| fusion.stats(), |f| f.stats()),
        )
    }
}
