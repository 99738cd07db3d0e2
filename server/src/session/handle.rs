//! [`Session`]: the shared handle of one session. Request handlers push frames into it and
//! read its state and results; its worker thread ([`super::worker`]) runs the pipeline and
//! reports back through it.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;

use relfusion_proto::http::{MapStart, SessionMemory};
use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::pipeline::Config as SlamConfig;
use tokio::sync::broadcast;

use super::events::SessionEvent;
use super::lifecycle::{Lifecycle, Stop};
use super::persist::{CounterSnapshot, SessionMeta};
use super::queue::FrameQueue;
use super::types::QueuedFrame;
use super::types::camera_json;
use super::types::{
    FramePolicy, Owner, Progress, SessionId, SessionInfo, SessionKind, SessionState,
};
use crate::metrics::Metrics;
use crate::storage::ObjectStore;

/// Live counters of a session.
#[derive(Debug, Default)]
pub(crate) struct Counters {
    pub received: AtomicU64,
    pub processed: AtomicU64,
    pub dropped: AtomicU64,
    pub lost: AtomicU64,
    pub keyframes: AtomicU64,
    pub densified: AtomicU64,
    pub mesh_revision: AtomicU64,
    pub mesh_triangles: AtomicU64,
}

impl Counters {
    pub fn snapshot(&self) -> CounterSnapshot {
        CounterSnapshot {
            received: self.received.load(Ordering::Relaxed),
            processed: self.processed.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
            lost: self.lost.load(Ordering::Relaxed),
            keyframes: self.keyframes.load(Ordering::Relaxed),
            densified: self.densified.load(Ordering::Relaxed),
            mesh_revision: self.mesh_revision.load(Ordering::Relaxed),
            mesh_triangles: self.mesh_triangles.load(Ordering::Relaxed),
        }
    }

    fn restore(snapshot: &CounterSnapshot) -> Self {
        Self {
            received: snapshot.received.into(),
            processed: snapshot.processed.into(),
            dropped: snapshot.dropped.into(),
            lost: snapshot.lost.into(),
            keyframes: snapshot.keyframes.into(),
            densified: snapshot.densified.into(),
            mesh_revision: snapshot.mesh_revision.into(),
            mesh_triangles: snapshot.mesh_triangles.into(),
        }
    }
}

/// One session. Shared (`Arc`) by the manager, request handlers and its worker thread.
pub struct Session {
    pub(super) id: SessionId,
    owner: Owner,
    pub(super) kind: SessionKind,
    pub(super) camera: PinholeCamera,
    model: String,
    pub(super) policy: FramePolicy,
    created_unix: u64,
    /// The resolved pipeline configuration.
    pub(crate) config: SlamConfig,
    /// Uploads: the dataset folder below the session's key.
    pub(crate) dataset: Option<String>,
    /// The saved map it works in (`None`: it maps from nothing).
    pub(crate) map: Option<MapStart>,
    /// The node it runs on.
    pub(crate) node: String,
    total_frames: Option<u64>,
    pub(crate) counters: Counters,
    /// Where the running pipeline's keyframes live (set by the worker at each keyframe).
    pub(crate) memory: Mutex<Option<SessionMemory>>,
    /// The unit of its map, `"metric"` or `"arbitrary"` (set by the worker when the pipeline
    /// starts; kept in the metadata).
    pub(crate) scale: Mutex<Option<String>>,
    /// Live sessions: frames waiting for the pipeline.
    pub(crate) queue: Option<FrameQueue<QueuedFrame>>,
    /// Serialises pushes so frames enter the queue in id order; holds the last frame's id
    /// and timestamp.
    pub(super) push_order: tokio::sync::Mutex<Option<(u64, f64)>>,
    /// Largest step between consecutive timestamps (`limits.max_timestamp_step_s`).
    pub(super) max_timestamp_step: f64,
    /// Most keyframes its map may hold (memory share, `limits.max_keyframes`).
    pub(crate) max_keyframes: usize,
    /// Bytes of its extracted upload and of its last saved results.
    upload_bytes: AtomicU64,
    results_bytes: AtomicU64,
    /// When it ended (seconds since the epoch; 0 while it runs).
    ended_unix: AtomicU64,
    /// Holds one of the `limits.max_sessions` slots (released once, by delete or worker end).
    pub(crate) holds_slot: AtomicBool,
    /// State, input, stop signal: the only writer of the session's status.
    pub(crate) lifecycle: Lifecycle,
    events: broadcast::Sender<SessionEvent>,
    pub(super) track: Mutex<super::track::Track>,
    pub(crate) store: Arc<dyn ObjectStore>,
    pub(crate) metrics: Arc<Metrics>,
    pub(super) max_frame_bytes: u64,
    /// Serialises metadata writes with deletion (a deleted session is never re-written).
    meta_lock: Mutex<()>,
    pub(crate) worker: Mutex<Option<JoinHandle<()>>>,
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Session")
            .field("id", &self.id)
            .field("kind", &self.kind)
            .field("state", &self.lifecycle.state())
            .finish_non_exhaustive()
    }
}

pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Everything needed to build a session.
#[derive(Debug)]
pub(crate) struct SessionSpec {
    pub meta: SessionMeta,
    pub frame_queue: usize,
    pub event_buffer: usize,
    pub max_frame_bytes: u64,
    pub max_timestamp_step: f64,
    pub max_keyframes: usize,
}

impl Session {
    /// A session from its (saved) metadata. Live, non-terminal sessions get a frame queue.
    pub(crate) fn new(
        spec: SessionSpec,
        store: Arc<dyn ObjectStore>,
        metrics: Arc<Metrics>,
    ) -> Self {
        let meta = spec.meta;
        let queue = (meta.kind == SessionKind::Live && !meta.state.is_terminal())
            .then(|| FrameQueue::new(spec.frame_queue));
        let (events, _) = broadcast::channel(spec.event_buffer.max(1));
        let lifecycle = Lifecycle::new(meta.state, meta.error.clone(), meta.notice.clone());
        Self {
            id: meta.id,
            owner: meta.owner,
            kind: meta.kind,
            camera: meta.camera,
            model: meta.model,
            policy: meta.policy,
            created_unix: meta.created_unix,
            config: meta.config,
            dataset: meta.dataset,
            map: meta.map,
            node: meta.node.unwrap_or_default(),
            total_frames: meta.total_frames,
            counters: Counters::restore(&meta.counters),
            memory: Mutex::new(None),
            scale: Mutex::new(meta.scale),
            queue,
            push_order: tokio::sync::Mutex::new(None),
            max_timestamp_step: spec.max_timestamp_step,
            max_keyframes: spec.max_keyframes,
            upload_bytes: meta.upload_bytes.into(),
            results_bytes: meta.results_bytes.into(),
            ended_unix: meta.ended_unix.unwrap_or(0).into(),
            holds_slot: AtomicBool::new(false),
            lifecycle,
            events,
            track: Mutex::new(Default::default()),
            store,
            metrics,
            max_frame_bytes: spec.max_frame_bytes,
            meta_lock: Mutex::new(()),
            worker: Mutex::new(None),
        }
    }

    pub fn id(&self) -> &str {
        &self.id
    }

    pub fn owner(&self) -> &Owner {
        &self.owner
    }

    pub fn kind(&self) -> SessionKind {
        self.kind
    }

    /// The session's camera (as given, with its distortion).
    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    pub fn policy(&self) -> FramePolicy {
        self.policy
    }

    /// The current state.
    pub fn state(&self) -> SessionState {
        self.lifecycle.state()
    }

    /// Everything reported about the session now.
    pub fn info(&self) -> SessionInfo {
        let status = self.lifecycle.status();
        let c = self.counters.snapshot();
        SessionInfo {
            id: self.id.clone(),
            kind: self.kind,
            state: status.state,
            frames_received: c.received,
            frames_processed: c.processed,
            frames_dropped: c.dropped,
            frames_lost: c.lost,
            keyframes: c.keyframes,
            keyframes_densified: c.densified,
            mesh_revision: c.mesh_revision,
            mesh_triangles: c.mesh_triangles,
            dense_mode: super::types::dense_mode(&self.config, &self.model),
            progress: Progress {
                processed: c.processed,
                total: self.total_frames,
            },
            created_unix: self.created_unix,
            camera: camera_json(&self.camera),
            model: self.model.clone(),
            error: status.error,
            notice: status.notice,
            max_keyframes: Some(self.max_keyframes as u64),
            map: self.map.clone(),
            node: (!self.node.is_empty()).then(|| self.node.clone()),
            memory: *lock(&self.memory),
            scale: lock(&self.scale).clone(),
        }
    }

    /// Bytes its upload and results take on disk.
    pub fn disk_bytes(&self) -> u64 {
        self.upload_bytes.load(Ordering::Relaxed) + self.results_bytes.load(Ordering::Relaxed)
    }

    /// When it finished or failed (seconds since the epoch), if it has.
    pub fn ended_unix(&self) -> Option<u64> {
        Some(self.ended_unix.load(Ordering::Relaxed)).filter(|&t| t > 0)
    }

    /// End of stream: the worker processes the frames already queued, finishes the map,
    /// persists the results and reports `Finished`. Idempotent; no-op for uploads.
    pub fn end_of_stream(&self) {
        if self.kind != SessionKind::Live || !self.lifecycle.end_of_stream() {
            return;
        }
        if let Some(queue) = &self.queue {
            queue.close();
        }
    }

    /// Whether it takes no more frames (end of stream received, or its worker ended).
    pub fn has_ended(&self) -> bool {
        self.lifecycle.input_closed()
    }

    /// A new subscriber to the session's events (bounded by `limits.event_buffer`; a
    /// subscriber that falls behind gets `RecvError::Lagged` and misses the oldest events, the
    /// pipeline never waits).
    pub fn subscribe(&self) -> broadcast::Receiver<SessionEvent> {
        self.events.subscribe()
    }

    /// Waits until the session is finished or failed; returns its final info.
    pub async fn wait_finished(&self) -> SessionInfo {
        self.lifecycle.terminal().await;
        self.info()
    }

    /// Resolves once the session is deleted: its tasks select on this to stop.
    pub async fn deleted(&self) {
        self.lifecycle.deleted().await;
    }

    // ---- used by the worker and the manager ----

    /// Sends an event to every subscriber (none listening is fine).
    pub(crate) fn emit(&self, event: SessionEvent) {
        let _ = self.events.send(event);
    }

    /// Sets the notice (why it ends, what it waits for), persisting the metadata.
    pub(crate) fn set_notice(&self, notice: Option<String>) {
        self.lifecycle.set_notice(notice);
        self.persist_meta();
    }

    /// Records the bytes its saved results take on disk.
    pub(crate) fn set_results_bytes(&self, bytes: u64) {
        self.results_bytes.store(bytes, Ordering::Relaxed);
    }

    /// Changes the state (and error), persisting the metadata.
    pub(crate) fn set_state(&self, state: SessionState, error: Option<String>) {
        self.lifecycle.set_state(state, error);
        self.persist_meta();
    }

    /// Ends the session in `state` (finished or failed): the state is visible and persisted
    /// first, then the last event goes out, then `wait_finished` callers wake — so a waiter
    /// that subscribes afterwards finds the results, and a subscriber sees the last event
    /// before anyone is told the session is over.
    pub(crate) fn conclude(&self, state: SessionState, error: Option<String>) {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(1, |d| d.as_secs().max(1));
        self.ended_unix.store(now, Ordering::Relaxed);
        self.lifecycle.record_end(state, error.clone());
        self.persist_meta();
        let event = match (state, error) {
            (SessionState::Failed, Some(message)) => SessionEvent::Failed { message },
            _ => SessionEvent::Finished {
                info: Box::new(self.info()),
            },
        };
        self.emit(event);
        self.lifecycle.announce();
    }

    /// The metadata as it stands.
    pub(crate) fn meta(&self) -> SessionMeta {
        let status = self.lifecycle.status();
        SessionMeta {
            version: super::persist::META_VERSION,
            id: self.id.clone(),
            owner: self.owner.clone(),
            kind: self.kind,
            state: status.state,
            camera: self.camera,
            config: self.config.clone(),
            model: self.model.clone(),
            policy: self.policy,
            created_unix: self.created_unix,
            error: status.error,
            dataset: self.dataset.clone(),
            total_frames: self.total_frames,
            counters: self.counters.snapshot(),
            ended_unix: self.ended_unix(),
            notice: status.notice,
            upload_bytes: self.upload_bytes.load(Ordering::Relaxed),
            results_bytes: self.results_bytes.load(Ordering::Relaxed),
            map: self.map.clone(),
            node: Some(self.node.clone()),
            scale: lock(&self.scale).clone(),
        }
    }

    /// Writes `meta.json` unless the session was deleted.
    pub(crate) fn persist_meta(&self) {
        let _guard = lock(&self.meta_lock);
        if self.lifecycle.is_deleted() {
            return;
        }
        if let Err(e) = self.meta().save(self.store.as_ref()) {
            tracing::error!(session = %self.id, "persisting metadata: {e}");
        }
    }

    /// The worker has ended: no more frames are accepted, and any still queued (a failed
    /// pipeline leaves some) are discarded so that waiting producers are released.
    pub(crate) fn close_input(&self) {
        self.lifecycle.close_input();
        if let Some(queue) = &self.queue {
            let n = queue.close_and_clear();
            self.metrics.frame_queue_depth.dec_by(n as i64);
        }
    }

    /// Marks the session deleted (its metadata is never written again) and stops its
    /// producers and worker.
    pub(crate) fn cancel(&self) {
        {
            let _guard = lock(&self.meta_lock);
            self.lifecycle.stop(Stop::Deleted);
        }
        self.close_input();
    }

    /// Server shutdown: a live session ends its stream (its queued frames are processed and
    /// its results persisted); an upload stops where it is and re-runs on restart, and its
    /// subscribers are told so.
    pub(crate) fn shut_down(&self) {
        match self.kind {
            SessionKind::Live => self.end_of_stream(),
            SessionKind::Upload => {
                self.lifecycle.stop(Stop::Shutdown);
                if !self.state().is_terminal() {
                    self.emit(SessionEvent::Failed {
                        message:
                            "the server is shutting down; this upload re-runs when it restarts"
                                .into(),
                    });
                }
            }
        }
    }
}
