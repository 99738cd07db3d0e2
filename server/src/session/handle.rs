//! [`Session`]: the shared handle of one session. Request handlers push frames into it and
//! read its state and results; its worker thread ([`super::worker`]) runs the pipeline and
//! reports back through it.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Instant;

use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::pipeline::Config as SlamConfig;
use tokio::sync::{broadcast, watch};

use super::decode::decode_frame;
use super::events::SessionEvent;
use super::persist::{CounterSnapshot, SessionMeta};
use super::queue::FrameQueue;
use super::types::{
    CameraJson, FrameData, FramePolicy, Owner, Progress, SessionId, SessionInfo, SessionKind,
    SessionState,
};
use crate::ApiError;
use crate::metrics::{Metrics, Stage};
use crate::storage::ObjectStore;

/// Largest timestamp magnitude accepted, in seconds (year ~5000 as Unix time): trajectories
/// print timestamps with six decimals, which `f64` keeps exactly up to about here.
const MAX_TIMESTAMP: f64 = 1e11;

/// A decoded frame waiting for the pipeline.
#[derive(Debug)]
pub struct QueuedFrame {
    /// The client's frame id (pose events carry it).
    pub frame_id: u64,
    pub timestamp: f64,
    pub rgb: image::RgbImage,
    /// When the server accepted it (frame-to-pose latency).
    pub received: Instant,
}

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

/// State and error, published through a watch channel so that waiters wake up.
#[derive(Clone, Debug)]
pub(crate) struct Status {
    pub state: SessionState,
    pub error: Option<String>,
    /// Why it ended without failing, or what it waits for (`SessionInfo::notice`).
    pub notice: Option<String>,
}

/// One session. Shared (`Arc`) by the manager, request handlers and its worker thread.
pub struct Session {
    id: SessionId,
    owner: Owner,
    kind: SessionKind,
    camera: PinholeCamera,
    camera_json: CameraJson,
    model: String,
    policy: FramePolicy,
    created_unix: u64,
    /// The resolved pipeline configuration.
    pub(crate) config: SlamConfig,
    /// Uploads: the dataset folder below the session's key.
    pub(crate) dataset: Option<String>,
    total_frames: Option<u64>,
    pub(crate) counters: Counters,
    /// Live sessions: frames waiting for the pipeline.
    pub(crate) queue: Option<FrameQueue<QueuedFrame>>,
    /// Serialises pushes so frames enter the queue in id order; holds the last frame's id
    /// and timestamp.
    push_order: tokio::sync::Mutex<Option<(u64, f64)>>,
    /// Largest step between consecutive timestamps (`limits.max_timestamp_step_s`).
    max_timestamp_step: f64,
    /// Most keyframes its map may hold (memory share, `limits.max_keyframes`).
    pub(crate) max_keyframes: usize,
    /// Bytes of its extracted upload and of its last saved results.
    upload_bytes: AtomicU64,
    results_bytes: AtomicU64,
    /// When it ended (seconds since the epoch; 0 while it runs).
    ended_unix: AtomicU64,
    ended: AtomicBool,
    /// Deleted: the worker stops and discards everything.
    pub(crate) cancelled: AtomicBool,
    /// Server shutdown: an upload stops where it is (it re-runs on restart).
    pub(crate) stop: AtomicBool,
    /// Holds one of the `limits.max_sessions` slots (released once, by delete or worker end).
    pub(crate) holds_slot: AtomicBool,
    status: watch::Sender<Status>,
    events: broadcast::Sender<SessionEvent>,
    pub(super) track: Mutex<super::track::Track>,
    pub(crate) store: Arc<dyn ObjectStore>,
    pub(crate) metrics: Arc<Metrics>,
    max_frame_bytes: u64,
    /// Serialises metadata writes with deletion (a deleted session is never re-written).
    meta_lock: Mutex<()>,
    pub(crate) worker: Mutex<Option<JoinHandle<()>>>,
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Session")
            .field("id", &self.id)
            .field("kind", &self.kind)
            .field("state", &self.status.borrow().state)
            .finish_non_exhaustive()
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Everything needed to build a session.
#[derive(Debug)]
pub(crate) struct SessionSpec {
    pub meta: SessionMeta,
    pub camera: PinholeCamera,
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
        let (status, _) = watch::channel(Status {
            state: meta.state,
            error: meta.error.clone(),
            notice: meta.notice.clone(),
        });
        Self {
            id: meta.id,
            owner: meta.owner,
            kind: meta.kind,
            camera: spec.camera,
            camera_json: meta.camera,
            model: meta.model,
            policy: meta.policy,
            created_unix: meta.created_unix,
            config: meta.config,
            dataset: meta.dataset,
            total_frames: meta.total_frames,
            counters: Counters::restore(&meta.counters),
            queue,
            push_order: tokio::sync::Mutex::new(None),
            max_timestamp_step: spec.max_timestamp_step,
            max_keyframes: spec.max_keyframes,
            upload_bytes: meta.upload_bytes.into(),
            results_bytes: meta.results_bytes.into(),
            ended_unix: meta.ended_unix.unwrap_or(0).into(),
            ended: AtomicBool::new(meta.state.is_terminal()),
            cancelled: AtomicBool::new(false),
            stop: AtomicBool::new(false),
            holds_slot: AtomicBool::new(false),
            status,
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
        self.status.borrow().state
    }

    /// Everything reported about the session now.
    pub fn info(&self) -> SessionInfo {
        let status = self.status.borrow().clone();
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
            camera: self.camera_json.clone(),
            model: self.model.clone(),
            error: status.error,
            notice: status.notice,
            max_keyframes: Some(self.max_keyframes as u64),
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

    /// [`Session::push_frame`] for a protobuf `Frame` (WebSocket, Zenoh): the frame may
    /// repeat the session camera but not change it (the pipeline has one camera), and every
    /// error names the frame.
    pub async fn push_proto_frame(
        &self,
        frame: relfusion_proto::v1::Frame,
    ) -> Result<u64, ApiError> {
        let frame_id = frame.frame_id;
        let result = match &frame.camera {
            Some(camera) => self.check_same_camera(camera),
            None => Ok(()),
        };
        let result = match result {
            Ok(()) => {
                self.push_frame(FrameData {
                    frame_id: Some(frame_id),
                    timestamp: frame.timestamp,
                    bytes: frame.image.into(),
                })
                .await
            }
            Err(e) => Err(e),
        };
        result.map_err(|e| ApiError {
            message: format!("frame {frame_id}: {}", e.message),
            ..e
        })
    }

    fn check_same_camera(&self, camera: &relfusion_proto::v1::Camera) -> Result<(), ApiError> {
        let own = &self.camera;
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * a.abs().max(1.0);
        let same = camera.width == own.width
            && camera.height == own.height
            && close(camera.fx, own.fx)
            && close(camera.fy, own.fy)
            && close(camera.cx, own.cx)
            && close(camera.cy, own.cy);
        if same {
            return Ok(());
        }
        Err(ApiError::bad_request(format!(
            "the frame's camera ({}x{}, fx {} fy {} cx {} cy {}) differs from the session's \
             ({}x{}, fx {} fy {} cx {} cy {}); open a new session for another camera",
            camera.width,
            camera.height,
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            own.width,
            own.height,
            own.fx,
            own.fy,
            own.cx,
            own.cy
        )))
    }

    /// Decodes and checks one frame now (400 for a corrupt image or a size that does not match
    /// the camera, 413 beyond `limits.max_frame_bytes`), then queues it for the pipeline:
    /// with `drop_oldest` a full queue loses its oldest frame (counted), with `wait` the call
    /// waits for room. Returns the frame's id. 409 after end of stream.
    pub async fn push_frame(&self, frame: FrameData) -> Result<u64, ApiError> {
        let Some(queue) = &self.queue else {
            return Err(self.not_accepting());
        };
        if self.ended.load(Ordering::SeqCst) {
            return Err(self.not_accepting());
        }
        if frame.bytes.len() as u64 > self.max_frame_bytes {
            return Err(ApiError::payload_too_large(format!(
                "frame of {} bytes exceeds limits.max_frame_bytes = {}",
                frame.bytes.len(),
                self.max_frame_bytes
            )));
        }
        if !(frame.timestamp.is_finite() && frame.timestamp.abs() <= MAX_TIMESTAMP) {
            return Err(ApiError::bad_request(format!(
                "timestamp must be a finite number of seconds within ±{MAX_TIMESTAMP:e}, got {}",
                frame.timestamp
            )));
        }
        let mut last = self.push_order.lock().await;
        let frame_id = match (frame.frame_id, *last) {
            (Some(id), Some((prev, _))) if id <= prev => {
                return Err(ApiError::bad_request(format!(
                    "frame_id {id} is not greater than the previous frame_id {prev}; \
                     frame ids must strictly increase"
                )));
            }
            (Some(id), _) => id,
            (None, Some((prev, _))) => prev.checked_add(1).ok_or_else(|| {
                ApiError::bad_request(format!(
                    "frame ids are used up: the previous frame_id is {prev}; open a new session"
                ))
            })?,
            (None, None) => 0,
        };
        if let Some((_, prev_t)) = *last {
            let step = frame.timestamp - prev_t;
            if !(step > 0.0 && step <= self.max_timestamp_step) {
                return Err(ApiError::bad_request(format!(
                    "timestamp {} follows {prev_t}: timestamps must increase, by at most {} s \
                     per frame (limits.max_timestamp_step_s)",
                    frame.timestamp, self.max_timestamp_step
                )));
            }
        }
        let start = Instant::now();
        let (w, h) = (self.camera.width, self.camera.height);
        let bytes = frame.bytes;
        let rgb = tokio::task::spawn_blocking(move || decode_frame(&bytes, w, h))
            .await
            .map_err(|e| ApiError::internal(format!("decoding task failed: {e}")))??;
        self.metrics
            .observe_stage(Stage::Decode, start.elapsed().as_secs_f64());
        let queued = QueuedFrame {
            frame_id,
            timestamp: frame.timestamp,
            rgb,
            received: Instant::now(),
        };
        match self.policy {
            FramePolicy::DropOldest => {
                let dropped = queue
                    .push_drop_oldest(queued)
                    .map_err(|_| self.not_accepting())?;
                self.metrics.frame_queue_depth.inc();
                if dropped.is_some() {
                    self.metrics.frame_queue_depth.dec();
                    let total = self.counters.dropped.fetch_add(1, Ordering::Relaxed) + 1;
                    self.metrics.frames_dropped.inc();
                    self.emit(SessionEvent::Dropped {
                        frames_dropped: total,
                    });
                }
            }
            FramePolicy::Wait => {
                queue
                    .push_wait(queued)
                    .await
                    .map_err(|_| self.not_accepting())?;
                self.metrics.frame_queue_depth.inc();
            }
        }
        *last = Some((frame_id, frame.timestamp));
        self.counters.received.fetch_add(1, Ordering::Relaxed);
        self.metrics.frames_received.inc();
        Ok(frame_id)
    }

    fn not_accepting(&self) -> ApiError {
        let status = self.status.borrow().clone();
        if status.state == SessionState::Failed {
            return ApiError::conflict(format!(
                "session {} failed ({}); it takes no more frames",
                self.id,
                status.error.as_deref().unwrap_or("no reason recorded")
            ));
        }
        match self.kind {
            SessionKind::Upload => ApiError::conflict(format!(
                "session {} is an upload; it takes no frames",
                self.id
            )),
            SessionKind::Live => ApiError::conflict(format!(
                "session {} has ended (end of stream); it takes no more frames",
                self.id
            )),
        }
    }

    /// End of stream: the worker processes the frames already queued, finishes the map,
    /// persists the results and reports `Finished`. Idempotent; no-op for uploads.
    pub fn end_of_stream(&self) {
        if self.kind != SessionKind::Live || self.ended.swap(true, Ordering::SeqCst) {
            return;
        }
        if let Some(queue) = &self.queue {
            queue.close();
        }
        self.status.send_if_modified(|s| {
            let running = s.state == SessionState::Running;
            if running {
                s.state = SessionState::Finishing;
            }
            running
        });
    }

    /// Whether end of stream was received.
    pub fn has_ended(&self) -> bool {
        self.ended.load(Ordering::SeqCst)
    }

    /// A new subscriber to the session's events (bounded by `limits.event_buffer`; a
    /// subscriber that falls behind gets `RecvError::Lagged` and misses the oldest events, the
    /// pipeline never waits).
    pub fn subscribe(&self) -> broadcast::Receiver<SessionEvent> {
        self.events.subscribe()
    }

    /// Waits until the session is finished or failed; returns its final info.
    pub async fn wait_finished(&self) -> SessionInfo {
        let mut rx = self.status.subscribe();
        let _ = rx.wait_for(|s| s.state.is_terminal()).await;
        self.info()
    }

    // ---- used by the worker and the manager ----

    /// Sends an event to every subscriber (none listening is fine).
    pub(crate) fn emit(&self, event: SessionEvent) {
        let _ = self.events.send(event);
    }

    /// Sets the notice (why it ends, what it waits for), persisting the metadata.
    pub(crate) fn set_notice(&self, notice: Option<String>) {
        self.status.send_modify(|s| s.notice = notice);
        self.persist_meta();
    }

    /// Records the bytes its saved results take on disk.
    pub(crate) fn set_results_bytes(&self, bytes: u64) {
        self.results_bytes.store(bytes, Ordering::Relaxed);
    }

    /// Changes the state (and error), persisting the metadata.
    pub(crate) fn set_state(&self, state: SessionState, error: Option<String>) {
        self.status.send_modify(|s| {
            s.state = state;
            s.error = error;
        });
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
        self.status.send_if_modified(|s| {
            s.state = state;
            s.error = error.clone();
            false
        });
        self.persist_meta();
        let event = match (state, error) {
            (SessionState::Failed, Some(message)) => SessionEvent::Failed { message },
            _ => SessionEvent::Finished {
                info: Box::new(self.info()),
            },
        };
        self.emit(event);
        self.status.send_modify(|_| {});
    }

    /// The metadata as it stands.
    pub(crate) fn meta(&self) -> SessionMeta {
        let status = self.status.borrow().clone();
        SessionMeta {
            version: super::persist::META_VERSION,
            id: self.id.clone(),
            owner: self.owner.clone(),
            kind: self.kind,
            state: status.state,
            camera: self.camera_json.clone(),
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
        }
    }

    /// Writes `meta.json` unless the session was deleted.
    pub(crate) fn persist_meta(&self) {
        let _guard = lock(&self.meta_lock);
        if self.cancelled.load(Ordering::SeqCst) {
            return;
        }
        if let Err(e) = self.meta().save(self.store.as_ref()) {
            tracing::error!(session = %self.id, "persisting metadata: {e}");
        }
    }

    /// The worker has ended: no more frames are accepted, and any still queued (a failed
    /// pipeline leaves some) are discarded so that waiting producers are released.
    pub(crate) fn close_input(&self) {
        self.ended.store(true, Ordering::SeqCst);
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
            self.cancelled.store(true, Ordering::SeqCst);
        }
        self.close_input();
    }
}
