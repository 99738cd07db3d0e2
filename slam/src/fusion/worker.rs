//! The fusion as a background [`Service`] ([`FusionLink`]): on its own thread behind a bounded
//! queue, so that integration and meshing never hold up tracking, or in step with the frames
//! in deterministic runs.
//!
//! Pose-graph moves are not queued: the pipeline posts the latest keyframe poses into a
//! latest-wins slot that the service applies before each keyframe and when finishing, so a
//! burst of optimisations costs one re-integration pass, not one per optimisation.

use std::sync::{Arc, Mutex};

use ::image::RgbImage;

use crate::Result;
use crate::background::{Link, Priority, Service, WorkerSpec};
use crate::dense::DenseKeyframe;
use crate::dense::resample::box_downsample_rgb;
use crate::geometry::Sim3;
use crate::gpu::GpuContext;
use crate::graph::KeyframeId;
use crate::spill::Spill;

use super::config::FusionConfig;
use super::fuser::{Fuser, FusionStats, MeshDelta};
use super::input::FusionInput;

/// One densified keyframe to fuse, with the frame's colour image (if it had one).
#[derive(Clone, Debug)]
pub struct FusionJob {
    pub keyframe: Arc<DenseKeyframe>,
    pub rgb: Option<Arc<RgbImage>>,
    pub pose: Sim3,
}

/// One reply: whether it came from a keyframe (rather than the final re-integration), and the
/// delta it produced.
pub type FusionReply = (bool, Result<Option<MeshDelta>>);

/// The latest-wins slot of keyframe poses shared with the service.
type LatestPoses = Arc<Mutex<Option<Vec<(KeyframeId, Sim3)>>>>;

/// The fuser as a service.
#[derive(Debug)]
pub struct FusionService {
    fuser: Fuser,
    config: FusionConfig,
    poses: LatestPoses,
    /// The fuser's figures after its latest step, readable while it runs on its thread.
    stats: Arc<Mutex<FusionStats>>,
}

impl FusionService {
    /// Applies the posted poses (if any), fuses `job` (if any) and meshes what changed.
    fn step(&mut self, job: Option<FusionJob>) -> Result<Option<MeshDelta>> {
        let poses = self.poses.lock().map(|mut p| p.take()).unwrap_or(None);
        if let Some(poses) = poses {
            self.fuser.update_poses(&poses)?;
        }
        if let Some(job) = job {
            let kf = &job.keyframe;
            let colors = match &job.rgb {
                Some(rgb) => Some(box_downsample_rgb(rgb, kf.idepth.width, kf.idepth.height)?),
                None => None,
            };
            let input = FusionInput::from_dense(kf, colors.as_deref(), &self.config)?;
            self.fuser.add_keyframe(input, job.pose)?;
        }
        let delta = self.fuser.take_delta();
        if let Ok(mut stats) = self.stats.lock() {
            *stats = self.fuser.stats();
        }
        delta
    }
}

impl Service for FusionService {
    type Job = FusionJob;
    type Reply = FusionReply;

    fn handle(&mut self, jobs: Vec<FusionJob>, reply: &mut dyn FnMut(FusionReply)) -> Result<()> {
        for job in jobs {
            reply((true, self.step(Some(job))));
        }
        Ok(())
    }

    /// The final poses: re-integrates what they moved.
    fn close(&mut self, reply: &mut dyn FnMut(FusionReply)) -> Result<()> {
        reply((false, self.step(None)));
        Ok(())
    }

    fn unavailable(_job: FusionJob, error: &str) -> Option<FusionReply> {
        Some((false, Err(crate::Error::Config(format!("fusion: {error}")))))
    }
}

/// The session's fusion, in step or on its thread (see the module docs).
#[derive(Debug)]
pub struct FusionLink {
    link: Link<FusionService>,
    poses: LatestPoses,
    stats: Arc<Mutex<FusionStats>>,
}

impl FusionLink {
    /// Starts the fusion; the fuser (and its GPU pool, on `gpu`, the session's GPU) is built on
    /// the thread when `threaded`.
    /// Inputs past `fusion.keyframe_memory_mb` spill to `spill`'s store.
    pub fn new(
        config: FusionConfig,
        threaded: bool,
        gpu: Option<Arc<GpuContext>>,
        spill: Spill,
    ) -> Result<Self> {
        config.validate()?;
        let poses = LatestPoses::default();
        let spec = WorkerSpec {
            name: "fusion",
            priority: Priority::Dense,
            queue: config.queue,
        };
        let service_poses = poses.clone();
        let stats = Arc::new(Mutex::new(FusionStats::default()));
        let service_stats = stats.clone();
        let link = Link::new(threaded, spec, move || {
            Ok(FusionService {
                fuser: Fuser::new(config.clone(), gpu)?.with_spill(spill),
                config,
                poses: service_poses,
                stats: service_stats,
            })
        })?;
        Ok(Self { link, poses, stats })
    }

    /// The fuser's figures as of its latest step (also while it runs on its thread).
    pub fn stats(&self) -> FusionStats {
        self.stats.lock().map(|s| s.clone()).unwrap_or_default()
    }

    /// Posts the latest keyframe poses (replacing any not yet applied).
    pub fn post_poses(&self, poses: Vec<(KeyframeId, Sim3)>) {
        if let Ok(mut slot) = self.poses.lock() {
            *slot = Some(poses);
        }
    }

    /// Hands a keyframe over; `false` when the queue is full (the keyframe is not fused).
    pub fn submit(&mut self, job: FusionJob) -> Result<bool> {
        self.link.submit(job)
    }

    /// Hands a keyframe over, waiting for queue room (a loaded map's keyframes, none of which
    /// may be dropped).
    pub fn send(&mut self, job: FusionJob) -> Result<()> {
        self.link.send(job)
    }

    /// Deltas ready now.
    pub fn poll(&mut self) -> Vec<FusionReply> {
        self.link.poll()
    }

    /// Fuses what is queued, applies the posted poses, stops the thread and returns the
    /// remaining deltas; the fuser stays for [`FusionLink::fuser`].
    pub fn finish(&mut self) -> Result<Vec<FusionReply>> {
        self.link.finish()
    }

    /// The fuser, when it is at hand (in step, or after [`FusionLink::finish`]).
    pub fn fuser(&mut self) -> Option<&mut Fuser> {
        self.link.service_mut().map(|s| &mut s.fuser)
    }

    /// [`FusionLink::fuser`], shared.
    pub fn fuser_ref(&self) -> Option<&Fuser> {
        self.link.service().map(|s| &s.fuser)
    }
}
