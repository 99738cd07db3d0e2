//! The worker thread of a session: owns its `slam::Pipeline`, feeds it from the frame queue
//! (live) or the uploaded dataset, turns pipeline events into session events, checkpoints
//! results every few keyframes and persists the final ones.
//!
//! Tracking is CPU work, so each session gets a plain thread (not a tokio task: a 50 ms
//! tracking step would stall the async runtime that serves `/healthz`). The pipeline's kernels
//! run on the GPU the pool placed the session on ([`PoolClient::gpu`]); its depth-prior
//! inference is a job on that device's pool workers ([`super::prior::PooledPrior`]).
//!
//! Bounds: a live session that receives fewer than `limits.min_frame_rate` frames per second
//! over `limits.idle_timeout_s` ends as idle; a session whose map reaches its keyframe limit
//! (its memory share) ends there, its results saved. Both say why in the session's notice.
//! Results that cannot be stored (a full disk) are retried until they can be, or until the
//! server shuts down (an upload then re-runs on restart): acknowledged work is not lost.

use std::cell::RefCell;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use relfusion_proto::http::SessionMemory;
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dense::DepthPrior;
use relfusion_slam::pipeline::{
    Engine, Event, FrameInput, KeyframeEvent, PoseEvent, Stats, TrackingState,
};
use serde_json::json;

use super::checkpoint::{Checkpoint, CheckpointWriter};
use super::events::SessionEvent;
use super::handle::Session;
use super::persist::Results;
use super::pointcloud::PointcloudWriter;
use super::prior::SharedModel;
use super::queue::Pop;
use super::recording::{Recorder, RecordingSummary};
use super::types::{QueuedFrame, SessionKind, SessionState};
use crate::gpu_pool::PoolClient;
use crate::metrics::{Metrics, Stage};

/// How long a live session's results (dense keyframes, mesh updates, moved keyframe poses)
/// may wait while its camera pauses: the worker polls the pipeline this often without frames.
const POLL_INTERVAL: Duration = Duration::from_millis(250);

/// What a worker needs besides its session.
#[derive(Debug)]
pub(crate) struct WorkerEnv {
    pub model: Option<SharedModel>,
    pub pool: Arc<PoolClient>,
    pub metrics: Arc<Metrics>,
    pub checkpoint_keyframes: usize,
    /// `limits.max_recording_mb` in bytes (0: no recording).
    pub max_recording_bytes: u64,
    pub idle_timeout: Duration,
    pub min_frame_rate: f64,
    /// What reading an uploaded dataset may cost (`limits`).
    pub sequence_limits: relfusion_slam::dataset::SequenceLimits,
}

/// How a worker ended.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Outcome {
    Finished,
    /// Deleted: nothing persisted.
    Cancelled,
    /// Server shutdown during an upload: left as is, it re-runs on restart.
    Stopped,
    Failed,
}

/// Runs the session to its end (called on the session's own thread).
pub(crate) fn run(session: &Arc<Session>, env: WorkerEnv) -> Outcome {
    session.set_state(SessionState::Running, None);
    let ended_before_start = session.has_ended();
    if ended_before_start && session.kind() == SessionKind::Live {
        session.set_state(SessionState::Finishing, None);
    }
    let prior: Option<Box<dyn DepthPrior>> = env
        .model
        .as_ref()
        .map(|m| Box::new(m.pooled(env.pool.clone(), env.metrics.clone())) as Box<dyn DepthPrior>);
    let engine = match super::engine::start(
        &session.config,
        session.camera(),
        prior,
        env.pool.gpu(),
        session.map.as_ref(),
        session.store.as_ref(),
    ) {
        Ok(engine) => engine,
        Err(e) => return fail(session, None, e),
    };
    *super::handle::lock(&session.scale) = Some(engine.stats().scale.to_string());
    // Old keyframes spill to the session's store: its memory stays bounded however long it
    // runs (issue 37).
    let spill = super::spill::SessionSpill::open(session.store.clone(), session.id())
        .map_err(|e| format!("opening the session's spill area: {e}"))
        .and_then(|spill| {
            engine
                .attach_spill(Arc::new(spill))
                .map_err(|e| format!("spilling: {e}"))
        });
    if let Err(e) = spill {
        return fail(session, None, e);
    }
    // The session's copy of the mesh and its poses spill with it (the mesh past the fusion's
    // own bound).
    if let Some(spill) = engine.spill().cloned() {
        session.bound_memory(spill, session.config.fusion.resident_blocks as usize);
    }
    // An extended map's keyframes are the session's too: listed with their poses, counted
    // towards its keyframe limit.
    for (id, (timestamp, pose)) in engine.map_keyframes().into_iter().enumerate() {
        session.record_keyframe(id as u64, timestamp, pose);
        session.counters.keyframes.fetch_add(1, Ordering::Relaxed);
    }
    // A recording that cannot start (no temporary space) costs the session nothing else.
    let recorder = (env.max_recording_bytes > 0)
        .then(|| Recorder::open(session.camera(), env.max_recording_bytes))
        .and_then(|r| {
            r.map_err(|e| tracing::warn!(session = %session.id(), "no recording: {e}"))
                .ok()
        });
    let mut runner = Runner {
        session,
        env: &env,
        recorder: RefCell::new(recorder),
        recorded: RefCell::new(None),
        engine,
        last_stats: Stats::default(),
        since_checkpoint: 0,
        tracked_keyframe: None,
        pointcloud: RefCell::default(),
        checkpoints: RefCell::default(),
        mapping_ended: false,
    };
    let fed = match session.kind() {
        SessionKind::Live => runner.feed_live(),
        SessionKind::Upload => runner.feed_upload(),
    };
    match fed {
        Ok(Outcome::Finished) => runner.finish(),
        Ok(other) => other,
        Err(message) => fail(session, Some(&runner), message),
    }
}

/// Marks the session failed, saving what results there are.
fn fail(session: &Session, runner: Option<&Runner<'_>>, message: String) -> Outcome {
    tracing::warn!(session = %session.id(), "session failed: {message}");
    if let Some(runner) = runner {
        if let Err(e) = runner.checkpoint() {
            tracing::error!(session = %session.id(), "saving results: {e}");
        }
        runner.checkpoints.borrow_mut().wait();
    }
    session.conclude(SessionState::Failed, Some(message));
    Outcome::Failed
}

struct Runner<'a> {
    session: &'a Arc<Session>,
    env: &'a WorkerEnv,
    engine: Engine,
    last_stats: Stats,
    since_checkpoint: usize,
    /// The keyframe the last pose was tracked against: a change (a new keyframe, or an old one
    /// re-activated, which adds none) counts towards the next checkpoint and refreshes the
    /// memory figures.
    tracked_keyframe: Option<u64>,
    /// The checkpoints' point cloud, rebuilt off this thread when the keyframes have doubled
    /// (`super::pointcloud`).
    pointcloud: RefCell<PointcloudWriter>,
    /// The checkpoint being written off this thread (`super::checkpoint`).
    checkpoints: RefCell<CheckpointWriter>,
    /// Mapping ended early (the map limit, or a store that refused spilled keyframes): no more
    /// frames go in.
    mapping_ended: bool,
    /// The session's recording while it is written (`super::recording`), then what the
    /// stored one came to.
    recorder: RefCell<Option<Recorder>>,
    recorded: RefCell<Option<RecordingSummary>>,
}

impl Runner<'_> {
    /// Tells the session's subscribers, and the recording.
    fn emit(&self, event: SessionEvent) {
        if let Some(recorder) = self.recorder.borrow_mut().as_mut() {
            recorder.record(&event);
        }
        self.session.emit(event);
    }

    /// Reports what the threads beside tracking produced: moved keyframe poses, dense
    /// keyframes and mesh updates. They come with a frame, from a poll while the camera
    /// pauses, or from the final optimisation. Frame events cannot come without a frame.
    fn emit_background(&self, event: Event) {
        let s = self.session;
        match event {
            Event::KeyframePoses { mut poses } => {
                s.update_keyframe_poses(&poses);
                // Subscribers hear of the keyframes of the session's own frames (a saved
                // map's keyframes, which an extending session starts from, have none).
                poses.retain(|p| p.frame_id.is_some());
                self.emit(SessionEvent::Pipeline(Event::KeyframePoses { poses }));
            }
            Event::KeyframeDensified { .. } => {
                s.counters.densified.fetch_add(1, Ordering::Relaxed);
                self.emit(SessionEvent::Pipeline(event));
            }
            Event::MeshUpdated { ref delta, .. } => {
                s.apply_mesh_delta(delta);
                self.emit(SessionEvent::Pipeline(event));
            }
            Event::Pose(_) | Event::Keyframe(_) => {}
        }
    }

    fn feed_live(&mut self) -> Result<Outcome, String> {
        let Some(queue) = &self.session.queue else {
            return Err("live session without a frame queue".into());
        };
        let window = self.env.idle_timeout;
        let needed = ((self.env.min_frame_rate * window.as_secs_f64()).ceil() as u64).max(1);
        let mut window_start = Instant::now();
        let mut in_window = 0u64;
        loop {
            if self.session.lifecycle.is_deleted() {
                return Ok(Outcome::Cancelled);
            }
            match queue.pop_timeout(window.min(POLL_INTERVAL)) {
                Pop::Item(frame) => {
                    self.env.metrics.frame_queue_depth.dec();
                    in_window += 1;
                    self.process(frame)?;
                    if self.mapping_ended {
                        self.session.close_input();
                        return Ok(Outcome::Finished);
                    }
                }
                Pop::TimedOut => self.poll()?,
                Pop::Closed => {
                    return Ok(if self.session.lifecycle.is_deleted() {
                        Outcome::Cancelled
                    } else {
                        Outcome::Finished
                    });
                }
            }
            if window_start.elapsed() >= window {
                if in_window < needed && !self.session.has_ended() {
                    let notice = format!(
                        "ended as idle: {in_window} frames in the last {} s, fewer than the \
                         {needed} that limits.min_frame_rate × limits.idle_timeout_s ask",
                        window.as_secs()
                    );
                    tracing::info!(session = %self.session.id(), "{notice}");
                    self.session.set_notice(Some(notice));
                    self.session.end_of_stream();
                }
                window_start = Instant::now();
                in_window = 0;
            }
        }
    }

    fn feed_upload(&mut self) -> Result<Outcome, String> {
        let dataset = self
            .session
            .dataset
            .as_deref()
            .ok_or("upload without a dataset")?;
        let key = format!("sessions/{}/{dataset}", self.session.id());
        // A remote store's dataset is copied to a private folder for the run (removed after).
        let folder = crate::folders::fetch(self.session.store.as_ref(), &key)
            .map_err(|e| format!("reading the uploaded dataset: {e}"))?;
        let camera = *self.session.camera();
        let mut seq =
            TumSequence::open_bounded(folder.path(), Some(camera), self.env.sequence_limits)
                .map_err(|e| format!("reading the uploaded dataset: {e}"))?;
        seq.camera = camera;
        for i in 0..seq.len() {
            if self.session.lifecycle.is_deleted() {
                return Ok(Outcome::Cancelled);
            }
            if self.session.lifecycle.is_stopped() {
                return Ok(Outcome::Stopped);
            }
            let rgb = seq.load_rgb(i).map_err(|e| format!("frame {i}: {e}"))?;
            self.session
                .counters
                .received
                .fetch_add(1, Ordering::Relaxed);
            self.process(QueuedFrame {
                frame_id: i as u64,
                timestamp: seq.frames[i].timestamp,
                rgb,
                received: Instant::now(),
            })?;
            if self.mapping_ended {
                break;
            }
        }
        self.session.set_state(SessionState::Finishing, None);
        Ok(Outcome::Finished)
    }

    /// While the camera pauses: what the pipeline's threads finished since the last frame
    /// goes out now instead of with the next frame.
    fn poll(&mut self) -> Result<(), String> {
        let events = self.engine.poll().map_err(|e| format!("pipeline: {e}"))?;
        for event in events {
            self.emit_background(event);
        }
        Ok(())
    }

    /// One frame through the pipeline; its events go to the subscribers.
    fn process(&mut self, frame: QueuedFrame) -> Result<(), String> {
        #[cfg(debug_assertions)]
        fault::maybe_panic(frame.frame_id);
        let (frame_id, received) = (frame.frame_id, frame.received);
        let events = self
            .engine
            .push(FrameInput {
                frame_id: Some(frame_id),
                timestamp: frame.timestamp,
                rgb: frame.rgb,
                depth: None,
            })
            .map_err(|e| format!("pipeline, frame {frame_id}: {e}"))?;
        self.observe_stages();
        self.session
            .counters
            .processed
            .fetch_add(1, Ordering::Relaxed);
        self.env.metrics.frames_processed.inc();
        for event in events {
            match event {
                Event::Pose(p) => self.pose(received, p),
                Event::Keyframe(k) => self.keyframe(k),
                event => self.emit_background(event),
            }
        }
        self.end_mapping_when_bounded(frame_id);
        // Due, and the last one written: one checkpoint at a time, the next at a later keyframe.
        if self.since_checkpoint >= self.env.checkpoint_keyframes
            && self.checkpoints.borrow().idle()
        {
            self.since_checkpoint = 0;
            // Timed: this is the part that stays on the frame path.
            let started = Instant::now();
            if let Err(e) = self.checkpoint() {
                tracing::error!(session = %self.session.id(), "checkpoint: {e}");
            }
            tracing::debug!(session = %self.session.id(), frames = self.engine.stats().frames,
                ms = started.elapsed().as_secs_f64() * 1e3, "checkpoint taken");
        }
        Ok(())
    }

    /// The time the pipeline's stages took since the last frame, into the metrics.
    fn observe_stages(&mut self) {
        let stats = self.engine.stats().clone();
        let metrics = &self.env.metrics;
        metrics.observe_stage(
            Stage::Tracking,
            stats.tracking_s - self.last_stats.tracking_s,
        );
        metrics.observe_stage(Stage::Mapping, stats.mapping_s - self.last_stats.mapping_s);
        self.last_stats = stats;
    }

    /// A frame's pose: recorded, counted, sent; a new tracking keyframe refreshes the memory
    /// figures and counts towards the next checkpoint.
    fn pose(&mut self, received: Instant, p: PoseEvent) {
        let s = self.session;
        let lost = p.state == TrackingState::Lost;
        if lost {
            s.counters.lost.fetch_add(1, Ordering::Relaxed);
        }
        s.record_pose(p.timestamp, p.world_from_camera, lost);
        let keyframe = p.keyframe_id as u64;
        if self.tracked_keyframe.replace(keyframe) != Some(keyframe) {
            self.since_checkpoint += 1;
            let (held, spilled) = s.mesh_block_counts();
            *super::handle::lock(&s.memory) =
                super::engine::memory(&self.engine).map(|m| SessionMemory {
                    mesh_blocks: held as u64,
                    mesh_blocks_spilled: spilled as u64,
                    ..m
                });
        }
        self.env
            .metrics
            .observe_stage(Stage::FrameToPose, received.elapsed().as_secs_f64());
        self.emit(SessionEvent::Pipeline(Event::Pose(p)));
    }

    /// A new keyframe: counted, recorded, sent.
    fn keyframe(&mut self, k: KeyframeEvent) {
        let s = self.session;
        s.counters.keyframes.fetch_add(1, Ordering::Relaxed);
        s.record_keyframe(k.keyframe_id as u64, k.timestamp, k.world_from_keyframe);
        self.emit(SessionEvent::Pipeline(Event::Keyframe(k)));
    }

    /// Mapping ends, with a notice, when the store refuses spilled keyframes (the memory
    /// model counts on old keyframes leaving memory; issue 37, item 4) or at the map limit.
    fn end_mapping_when_bounded(&mut self, frame_id: u64) {
        if self.mapping_ended {
            return;
        }
        let s = self.session;
        let keyframes = s.counters.keyframes.load(Ordering::Relaxed);
        let notice = if let Some(e) = self.engine.spill().and_then(|s| s.failure()) {
            format!(
                "ended: the session's store refused its spilled keyframes ({e}); results up \
                 to frame {frame_id} are kept, later frames were not processed"
            )
        } else if keyframes >= s.max_keyframes as u64 {
            format!(
                "ended at the map limit: {keyframes} keyframes, what this session's share of \
                 the server's memory holds (limits.memory_budget_mb, limits.max_keyframes); \
                 frames after {frame_id} were not processed"
            )
        } else {
            return;
        };
        self.mapping_ended = true;
        tracing::warn!(session = %s.id(), "{notice}");
        s.set_notice(Some(notice));
    }

    /// Starts a checkpoint: what its files are made of is taken here, and they are made and
    /// stored off this thread (`super::checkpoint`); the point cloud too when it is due.
    fn checkpoint(&self) -> Result<(), String> {
        let s = self.session;
        if s.lifecycle.is_deleted() {
            return Err("the session was deleted".into());
        }
        let keyframe_count = s.counters.keyframes.load(Ordering::Relaxed);
        let mut cloud = self.pointcloud.borrow_mut();
        if cloud.due(keyframe_count)
            && let Some(snapshot) = self.engine.semidense_snapshot()
        {
            cloud.start(s, snapshot, keyframe_count);
        }
        let checkpoint = Checkpoint {
            poses: self
                .engine
                .trajectories()
                .map_err(|e| format!("the trajectory: {e}"))?,
            mesh: s.mesh_snapshot(),
            summary: self.summary(false, None),
            cloud_bytes: cloud.bytes(),
        };
        self.checkpoints.borrow_mut().start(s, checkpoint);
        Ok(())
    }

    /// Writes the final results and the map, in line, once the checkpoint and the point
    /// cloud in flight are stored.
    fn save_results(&self) -> Result<(), String> {
        let s = self.session;
        self.checkpoints.borrow_mut().wait();
        self.pointcloud.borrow_mut().wait();
        if s.lifecycle.is_deleted() {
            return Err("the session was deleted".into());
        }
        let recording = self.store_recording()?;
        // A localising session's trajectory is the poses it reported, in the map's frame.
        let (trajectory, keyframes, pointcloud) = match super::engine::result_files(&self.engine)? {
            Some(files) => files,
            None => (
                s.trajectory_tum()?,
                String::new(),
                crate::convert::points_ply(&[]),
            ),
        };
        let keyframe_count = s.counters.keyframes.load(Ordering::Relaxed);
        self.pointcloud
            .borrow_mut()
            .stored(keyframe_count, pointcloud.len() as u64);
        let results = Results {
            trajectory,
            keyframes,
            pointcloud: Some(pointcloud),
            mesh: s.mesh_files(),
            summary: self.summary(true, recording.as_ref()),
        };
        let mut bytes = recording.as_ref().map_or(0, |r| r.bytes)
            + results
                .save(s.store.as_ref(), s.id())
                .map_err(|e| e.to_string())?;
        // The map, to keep with `POST /v1/maps` (docs/map-format.md).
        let key = super::persist::result_key(s.id(), "map");
        bytes += super::engine::write_map(&self.engine, s.store.as_ref(), &key)
            .map_err(|e| format!("saving the map: {e}"))?;
        s.set_results_bytes(bytes);
        Ok(())
    }

    /// `summary.json`: the session's info and the pipeline's figures.
    fn summary(&self, final_: bool, recording: Option<&RecordingSummary>) -> serde_json::Value {
        let stats = self.engine.stats();
        json!({
            "final": final_,
            "info": self.session.info(),
            "frames": stats.frames,
            "keyframes": stats.keyframes,
            "keyframes_reactivated": stats.keyframes_reactivated,
            "frames_lost": stats.frames_lost,
            "tracking_s": stats.tracking_s,
            "mapping_s": stats.mapping_s,
            "frames_batched": stats.frames_batched,
            "keyframes_densified": stats.keyframes_densified,
            "keyframes_not_densified": stats.keyframes_not_densified,
            "dense_mode": stats.dense_mode,
            "scale": stats.scale,
            "keyframes_fused": stats.keyframes_fused,
            "mesh_revision": stats.mesh_revision,
            // Keyframes held in full, compact and spilled, and their bytes (issue 37).
            "keyframe_memory": self.engine.keyframe_memory(),
            "recording": recording,
        })
    }

    /// Closes the recording and stores it with the results (`None` without one). Kept until
    /// stored, so a retry of the final save stores it then.
    fn store_recording(&self) -> Result<Option<RecordingSummary>, String> {
        let mut recorder = self.recorder.borrow_mut();
        if let Some(r) = recorder.as_mut() {
            let summary = r.finish(self.session.store.as_ref(), self.session.id())?;
            *self.recorded.borrow_mut() = Some(summary);
            *recorder = None;
        }
        Ok(self.recorded.borrow().clone())
    }

    /// Saves the final results, retrying (1 s, doubling to 30 s) while the store refuses them
    /// (a full disk) until it takes them, the session is deleted, or the server shuts down.
    /// Returns whether it had to wait (it said so in the notice).
    fn save_final(&self) -> Result<bool, Outcome> {
        let s = self.session;
        let mut delay = Duration::from_secs(1);
        let mut waited = false;
        loop {
            let error = match self.save_results() {
                Ok(()) => return Ok(waited),
                Err(e) => e,
            };
            if s.lifecycle.is_deleted() {
                return Err(Outcome::Cancelled);
            }
            if s.lifecycle.is_stopped() {
                // Shutdown: the upload re-runs on restart; a live session cannot.
                return Err(match s.kind() {
                    SessionKind::Upload => Outcome::Stopped,
                    SessionKind::Live => fail(
                        s,
                        None,
                        format!("the server shut down before the results could be stored: {error}"),
                    ),
                });
            }
            tracing::warn!(session = %s.id(), "storing the results failed, retrying in {delay:?}: {error}");
            s.set_notice(Some(format!(
                "waiting to store the results (retrying every {} s): {error}",
                delay.as_secs()
            )));
            waited = true;
            s.lifecycle.sleep_unless_stopped(delay);
            // Deleted while waiting: its data is gone and must not be written again.
            if s.lifecycle.is_deleted() {
                return Err(Outcome::Cancelled);
            }
            delay = (delay * 2).min(Duration::from_secs(30));
        }
    }

    /// End of the frames: final optimisation, final results, `Finished`.
    fn finish(mut self) -> Outcome {
        let s = self.session;
        if s.kind() == SessionKind::Live {
            s.set_state(SessionState::Finishing, None);
        }
        let t0 = std::time::Instant::now();
        let (poses, events) = match self.engine.finish() {
            Ok(finished) => finished,
            Err(e) => return fail(s, Some(&self), format!("final optimisation: {e}")),
        };
        // Keyframes the dense layer finished and fused while the session was finishing, and
        // the final mesh at the optimised poses.
        for event in events {
            self.emit_background(event);
        }
        self.emit_background(Event::KeyframePoses { poses });
        if s.lifecycle.is_deleted() {
            return Outcome::Cancelled;
        }
        let optimise_s = t0.elapsed().as_secs_f64();
        match self.save_final() {
            Ok(true) => s.set_notice(None),
            Ok(false) => {}
            Err(outcome) => return outcome,
        }
        tracing::info!(
            session = %s.id(),
            optimise_s,
            save_s = t0.elapsed().as_secs_f64() - optimise_s,
            "finished"
        );
        // The pipeline goes before the session is reported finished: what it spilled leaves
        // the store with it.
        drop(self);
        s.conclude(SessionState::Finished, None);
        Outcome::Finished
    }
}

/// Fault injection for the failure tests (debug builds only): `RELFUSIOND_FAULT_PANIC_AT_FRAME=N`
/// makes a session's worker panic on its frame `N`, as a bug in the pipeline would.
#[cfg(debug_assertions)]
mod fault {
    use std::sync::OnceLock;

    pub fn maybe_panic(frame_id: u64) {
        static AT: OnceLock<Option<u64>> = OnceLock::new();
        let at = AT.get_or_init(|| {
            std::env::var("RELFUSIOND_FAULT_PANIC_AT_FRAME")
                .ok()
                .and_then(|v| v.parse().ok())
        });
        if *at == Some(frame_id) {
            panic!("fault injection: RELFUSIOND_FAULT_PANIC_AT_FRAME={frame_id}");
        }
    }
}
