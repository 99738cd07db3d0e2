//! The fusion on its own thread behind a bounded queue, so that integration and meshing never
//! hold up tracking (the dense layer's pattern, `dense::layer::DenseWorker`).
//!
//! Pose-graph moves are not queued: the pipeline posts the latest keyframe poses into a
//! latest-wins slot that the thread applies before each keyframe and when finishing, so a
//! burst of optimisations costs one re-integration pass, not one per optimisation.

use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};

use ::image::RgbImage;

use crate::dense::DenseKeyframe;
use crate::dense::resample::box_downsample_rgb;
use crate::geometry::Sim3;
use crate::graph::KeyframeId;
use crate::{Error, Result};

use super::config::FusionConfig;
use super::fuser::{Fuser, MeshDelta};
use super::input::FusionInput;

/// One densified keyframe to fuse, with the frame's colour image (if it had one).
#[derive(Clone, Debug)]
pub struct FusionJob {
    pub keyframe: Arc<DenseKeyframe>,
    pub rgb: Option<Arc<RgbImage>>,
    pub pose: Sim3,
}

/// Fuses one job into `fuser` after applying `poses`, and meshes what changed.
pub fn process(
    fuser: &mut Fuser,
    config: &FusionConfig,
    job: Option<FusionJob>,
    poses: Option<Vec<(KeyframeId, Sim3)>>,
) -> Result<Option<MeshDelta>> {
    if let Some(poses) = poses {
        fuser.update_poses(&poses)?;
    }
    if let Some(job) = job {
        let kf = &job.keyframe;
        let colors = match &job.rgb {
            Some(rgb) => Some(box_downsample_rgb(rgb, kf.idepth.width, kf.idepth.height)?),
            None => None,
        };
        let input = FusionInput::from_dense(kf, colors.as_deref(), config)?;
        fuser.add_keyframe(input, job.pose)?;
    }
    fuser.take_delta()
}

/// One reply of the thread: whether the job carried a keyframe, and the delta it produced.
pub type FusionReply = (bool, Result<Option<MeshDelta>>);

/// The latest-wins slot of keyframe poses shared with the thread.
type LatestPoses = Arc<Mutex<Option<Vec<(KeyframeId, Sim3)>>>>;

/// [`Fuser`] on its own thread.
#[derive(Debug)]
pub struct FusionWorker {
    jobs: Option<SyncSender<FusionJob>>,
    poses: LatestPoses,
    replies: Receiver<FusionReply>,
    thread: Option<std::thread::JoinHandle<Option<Fuser>>>,
}

impl FusionWorker {
    /// Starts the thread; the fuser (and its GPU pool) is built there.
    pub fn spawn(config: FusionConfig) -> Result<Self> {
        config.validate()?;
        let (jobs, job_rx) = std::sync::mpsc::sync_channel::<FusionJob>(config.queue);
        let (reply_tx, replies) = std::sync::mpsc::channel::<FusionReply>();
        let poses = LatestPoses::default();
        let latest = poses.clone();
        let thread = std::thread::Builder::new()
            .name("relfusion-fusion".into())
            .spawn(move || {
                crate::background::lower_current_thread_priority(
                    crate::background::Priority::Dense,
                );
                let mut fuser = match Fuser::new(config.clone(), None) {
                    Ok(f) => f,
                    Err(e) => {
                        let _ = reply_tx.send((false, Err(e)));
                        return None;
                    }
                };
                let take_poses = || latest.lock().map(|mut p| p.take()).unwrap_or(None);
                for job in job_rx {
                    let reply = process(&mut fuser, &config, Some(job), take_poses());
                    if reply_tx.send((true, reply)).is_err() {
                        return None;
                    }
                }
                // The queue closed: apply the final poses.
                let _ = reply_tx.send((false, process(&mut fuser, &config, None, take_poses())));
                Some(fuser)
            })
            .map_err(|e| Error::Config(format!("cannot start the fusion worker: {e}")))?;
        Ok(Self {
            jobs: Some(jobs),
            poses,
            replies,
            thread: Some(thread),
        })
    }

    /// Queues a keyframe; `false` when the queue is full (the keyframe is not fused).
    pub fn submit(&self, job: FusionJob) -> Result<bool> {
        let jobs = self
            .jobs
            .as_ref()
            .ok_or_else(|| Error::Config("fusion worker already finished".into()))?;
        match jobs.try_send(job) {
            Ok(()) => Ok(true),
            Err(TrySendError::Full(_)) => Ok(false),
            Err(TrySendError::Disconnected(_)) => {
                Err(Error::Config("the fusion worker stopped".into()))
            }
        }
    }

    /// Posts the latest keyframe poses (replacing any not yet applied).
    pub fn post_poses(&self, poses: Vec<(KeyframeId, Sim3)>) {
        if let Ok(mut slot) = self.poses.lock() {
            *slot = Some(poses);
        }
    }

    /// Deltas ready now, without waiting.
    pub fn poll(&self) -> Vec<FusionReply> {
        self.replies.try_iter().collect()
    }

    /// Fuses what is queued, applies the posted poses, stops the thread and returns the
    /// remaining deltas with the fuser (for the final mesh).
    pub fn finish(&mut self) -> (Vec<FusionReply>, Option<Fuser>) {
        self.jobs = None;
        let fuser = match self.thread.take().map(|t| t.join()) {
            Some(Ok(fuser)) => fuser,
            Some(Err(_)) => {
                tracing::error!("the fusion worker panicked");
                None
            }
            None => None,
        };
        (self.replies.try_iter().collect(), fuser)
    }
}

impl Drop for FusionWorker {
    fn drop(&mut self) {
        self.jobs = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
