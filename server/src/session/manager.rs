//! [`SessionManager`]: creates, finds, lists and deletes sessions; admission control; the
//! durable upload path; restart recovery; graceful shutdown.
//!
//! Admission: at most `limits.max_sessions` sessions process at once. A live session beyond
//! that is refused (503: a live stream cannot wait), an upload is acknowledged and queued
//! (state `queued`, at most `limits.max_queued_uploads`) and starts when a slot frees.
//!
//! Recovery at start ([`SessionManager::open`]): every `sessions/<id>/meta.json` is read.
//! Finished and failed sessions come back read-only (their results stay downloadable);
//! unfinished uploads re-run from scratch with their stored configuration (deterministic, so
//! the re-run gives the result the interrupted run would have); unfinished live sessions are
//! marked failed (their client is gone), keeping their last checkpoint. Folders without
//! `meta.json` are uploads that were never acknowledged and are removed.

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock, Weak};
use std::time::Duration;

use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::pipeline::Config as SlamConfig;

use super::handle::{Session, SessionSpec};
use super::overrides::merge_config;
use super::persist::{META_VERSION, SessionMeta, meta_key, session_prefix, upload_key};
use super::prior::SharedModel;
use super::types::{
    CameraJson, CreateSession, FramePolicy, Owner, SessionId, SessionInfo, SessionKind,
    SessionState,
};
use super::upload::{ArchiveKind, ExtractLimits, stage_upload};
use super::worker::{self, Outcome, WorkerEnv};
use crate::config::Config;
use crate::gpu_pool::{GpuPool, adapter_count};
use crate::metrics::Metrics;
use crate::storage::{FsStore, ObjectStore};
use crate::{ApiError, ServerError};

#[derive(Debug, Default)]
struct Admission {
    active: usize,
    queued: VecDeque<Arc<Session>>,
}

/// Every session of this node.
pub struct SessionManager {
    me: Weak<SessionManager>,
    config: Config,
    store: Arc<dyn ObjectStore>,
    metrics: Arc<Metrics>,
    pool: GpuPool,
    model: Option<SharedModel>,
    sessions: RwLock<HashMap<SessionId, Arc<Session>>>,
    admission: Mutex<Admission>,
    shutting_down: AtomicBool,
    temp_dir: PathBuf,
}

impl std::fmt::Debug for SessionManager {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SessionManager")
            .field("data_dir", &self.config.data_dir)
            .field("pool", &self.pool)
            .finish_non_exhaustive()
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

fn now_unix() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// A fresh unguessable id: `s-` and 12 hex digits from the thread's CSPRNG.
fn new_id() -> SessionId {
    format!("s-{:012x}", rand::random::<u64>() & 0xffff_ffff_ffff)
}

impl SessionManager {
    /// Opens the store in `config.data_dir`, loads the depth model, starts the GPU pool and
    /// recovers the sessions of a previous run (see the module docs).
    pub fn open(config: &Config, metrics: Arc<Metrics>) -> Result<Arc<Self>, ServerError> {
        let store: Arc<dyn ObjectStore> = Arc::new(FsStore::open(&config.data_dir)?);
        let temp_dir = config.data_dir.join("tmp");
        let _ = std::fs::remove_dir_all(&temp_dir);
        std::fs::create_dir_all(&temp_dir)
            .map_err(|e| ServerError::Startup(format!("creating {}: {e}", temp_dir.display())))?;
        let model = SharedModel::load(&config.model)?;
        let workers = match config.pool.workers {
            0 => adapter_count(),
            n => n,
        };
        let pool = GpuPool::new(workers, config.limits.pool_job_queue, Some(metrics.clone()));
        tracing::info!(
            workers,
            model = model.as_ref().map_or("none", |m| m.name()),
            "GPU pool started"
        );
        let manager = Arc::new_cyclic(|me| Self {
            me: me.clone(),
            config: config.clone(),
            store,
            metrics,
            pool,
            model,
            sessions: RwLock::new(HashMap::new()),
            admission: Mutex::new(Admission::default()),
            shutting_down: AtomicBool::new(false),
            temp_dir,
        });
        manager.recover()?;
        Ok(manager)
    }

    /// Where the HTTP layer writes incoming upload archives before [`Self::create_upload`]
    /// (inside the data directory, so the rename-free extraction stays on one filesystem;
    /// emptied at every start).
    pub fn temp_dir(&self) -> &Path {
        &self.temp_dir
    }

    /// The configuration in force.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// The shared metrics.
    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    /// Worker threads of the GPU pool.
    pub fn gpu_workers(&self) -> usize {
        self.pool.workers()
    }

    /// Sessions processing now and the limit (for node status and readiness).
    pub fn load(&self) -> (usize, usize) {
        (
            lock(&self.admission).active,
            self.config.limits.max_sessions,
        )
    }

    /// Whether [`Self::shutdown`] has begun (readiness turns 503).
    pub fn is_shutting_down(&self) -> bool {
        self.shutting_down.load(Ordering::SeqCst)
    }

    /// Whether new sessions and uploads are accepted (`/readyz`).
    pub fn is_accepting(&self) -> bool {
        !self.is_shutting_down()
    }

    fn recover(&self) -> Result<(), ServerError> {
        let keys = self.store.list("sessions/")?;
        let mut ids: Vec<String> = keys
            .iter()
            .filter_map(|k| k.strip_prefix("sessions/")?.split('/').next())
            .map(String::from)
            .collect();
        ids.dedup();
        let mut resumed = Vec::new();
        for id in ids {
            let meta = match SessionMeta::load(self.store.as_ref(), &id) {
                Ok(Some(meta)) => meta,
                Ok(None) => {
                    tracing::info!(session = %id, "removing an unacknowledged upload");
                    self.store.delete_prefix(&session_prefix(&id))?;
                    continue;
                }
                Err(e) => {
                    tracing::error!(session = %id, "unreadable metadata, skipped: {e}");
                    continue;
                }
            };
            let camera = match meta.camera.to_camera() {
                Ok(c) => c,
                Err(e) => {
                    tracing::error!(session = %id, "stored camera invalid, skipped: {e}");
                    continue;
                }
            };
            let mut meta = meta;
            let mut resume = false;
            if !meta.state.is_terminal() {
                match meta.kind {
                    SessionKind::Upload => {
                        // Re-run from scratch: progress restarts at zero.
                        meta.state = SessionState::Queued;
                        meta.counters = Default::default();
                        resume = true;
                    }
                    SessionKind::Live => {
                        meta.state = SessionState::Failed;
                        meta.error = Some(
                            "interrupted: the server stopped while this live session ran; \
                             results up to the last checkpoint are kept"
                                .into(),
                        );
                        meta.save(self.store.as_ref())?;
                    }
                }
            }
            let session = Arc::new(self.build(meta, camera));
            if resume {
                tracing::info!(session = %id, "re-running an unfinished upload");
                resumed.push(session.clone());
            }
            self.sessions
                .write()
                .unwrap_or_else(|e| e.into_inner())
                .insert(id, session);
        }
        resumed.sort_by_key(|s| s.info().created_unix);
        for session in resumed {
            self.admit_upload(session);
        }
        Ok(())
    }

    fn build(&self, meta: SessionMeta, camera: PinholeCamera) -> Session {
        Session::new(
            SessionSpec {
                meta,
                camera,
                frame_queue: self.config.limits.frame_queue,
                event_buffer: self.config.limits.event_buffer,
                max_frame_bytes: self.config.limits.max_frame_bytes,
            },
            self.store.clone(),
            self.metrics.clone(),
        )
    }

    /// The model a request names: absent or `"default"` = the server's model (if any),
    /// `"none"` = no model, else it must be the server model's name.
    fn resolve_model(&self, requested: Option<&str>) -> Result<Option<SharedModel>, ApiError> {
        match requested {
            None | Some("") | Some("default") => Ok(self.model.clone()),
            Some("none") => Ok(None),
            Some(name) => {
                match &self.model {
                    Some(m) if m.name() == name => Ok(Some(m.clone())),
                    _ => Err(ApiError::bad_request(format!(
                        "unknown model {name:?}: this server has {}",
                        self.model.as_ref().map_or(
                            "no model (use \"none\")".to_string(),
                            |m| format!("\"{}\" (or \"none\")", m.name())
                        )
                    ))),
                }
            }
        }
    }

    fn refuse_if_shutting_down(&self) -> Result<(), ApiError> {
        if self.is_shutting_down() {
            return Err(ApiError::unavailable(
                "the server is shutting down; retry on another node",
            ));
        }
        Ok(())
    }

    /// Creates a live session and starts its worker. 400 for invalid intrinsics, config or
    /// model; 503 at capacity.
    pub fn create(&self, req: CreateSession, owner: &Owner) -> Result<Arc<Session>, ApiError> {
        self.refuse_if_shutting_down()?;
        let camera = req.camera.to_camera()?;
        let mut base = SlamConfig::default();
        // A live camera does not wait: tracking gives every frame its pose at frame rate and
        // the mapping thread observes the frames it has time for (skipped, never queued). A
        // replay that waits for room loses nothing, and maps every frame in step.
        base.pipeline.mapping_thread = req.policy == FramePolicy::DropOldest;
        let config = merge_config(&base, &req.config)?;
        let model = self.resolve_model(req.model.as_deref())?;
        {
            let mut admission = lock(&self.admission);
            let max = self.config.limits.max_sessions;
            if admission.active >= max {
                return Err(ApiError::unavailable(format!(
                    "at capacity: {max} sessions are processing (limits.max_sessions); retry later"
                )));
            }
            admission.active += 1;
            self.metrics.sessions_active.set(admission.active as i64);
        }
        let meta = SessionMeta {
            version: META_VERSION,
            id: new_id(),
            owner: owner.clone(),
            kind: SessionKind::Live,
            state: SessionState::Running,
            camera: CameraJson::from_camera(&camera),
            config,
            model: model
                .as_ref()
                .map_or("none".into(), |m| m.name().to_string()),
            policy: req.policy,
            created_unix: now_unix(),
            error: None,
            dataset: None,
            total_frames: None,
            counters: Default::default(),
        };
        let session = Arc::new(self.build(meta, camera));
        self.sessions
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(session.id().to_string(), session.clone());
        if let Err(e) = self.start(&session, model) {
            self.release(&session);
            return Err(e);
        }
        Ok(session)
    }

    /// The session `id` if `owner` may see it; 404 otherwise (another owner's session does
    /// not exist for this caller).
    pub fn get(&self, id: &str, owner: &Owner) -> Result<Arc<Session>, ApiError> {
        self.sessions
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .get(id)
            .filter(|s| s.owner() == owner)
            .cloned()
            .ok_or_else(|| ApiError::not_found(format!("no session {id:?}")))
    }

    /// The sessions of `owner`, oldest first.
    pub fn list(&self, owner: &Owner) -> Vec<SessionInfo> {
        let mut infos: Vec<SessionInfo> = self
            .sessions
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .values()
            .filter(|s| s.owner() == owner)
            .map(|s| s.info())
            .collect();
        infos.sort_by(|a, b| (a.created_unix, &a.id).cmp(&(b.created_unix, &b.id)));
        infos
    }

    /// Stops the session (its queued frames are discarded) and removes all its data.
    pub fn delete(&self, id: &str, owner: &Owner) -> Result<(), ApiError> {
        let session = self.get(id, owner)?;
        session.cancel();
        // The slot is free now, even if the worker still finishes its current frame.
        self.release(&session);
        self.sessions
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id);
        // A queued upload holds no slot: dropping it from the queue is all it takes.
        lock(&self.admission).queued.retain(|s| s.id() != id);
        // meta.json first: once it is gone the session cannot come back after a crash.
        self.store
            .delete_prefix(&meta_key(id))
            .map_err(|e| ApiError::internal(e.to_string()))?;
        let worker = lock(&session.worker).take();
        let store = self.store.clone();
        let prefix = session_prefix(id);
        // The worker may be inside a pipeline step; the folder goes once it has stopped.
        std::thread::Builder::new()
            .name(format!("delete-{id}"))
            .spawn(move || {
                if let Some(worker) = worker {
                    let _ = worker.join();
                }
                if let Err(e) = store.delete_prefix(&prefix) {
                    tracing::error!("deleting {prefix}: {e}");
                }
            })
            .map_err(|e| ApiError::internal(format!("starting the cleanup: {e}")))?;
        Ok(())
    }

    /// Accepts an uploaded dataset: extracts `archive` safely (400 for traversal, links,
    /// a broken archive or no TUM layout), resolves the camera (the given one, else
    /// `calibration.txt`, else a TUM preset from the folder name; 400 without any), stores it
    /// durably, and only then returns (the acknowledgement). Processing starts on the pool
    /// when a slot is free.
    pub async fn create_upload(
        &self,
        archive: &Path,
        kind: ArchiveKind,
        camera: Option<CameraJson>,
        config: serde_json::Value,
        owner: &Owner,
    ) -> Result<Arc<Session>, ApiError> {
        self.refuse_if_shutting_down()?;
        let camera = camera.map(|c| c.to_camera()).transpose()?;
        let mut base = SlamConfig::default();
        // Deterministic unless the client says otherwise: a re-run after a crash must give
        // the result the interrupted run would have given.
        base.pipeline.deterministic = true;
        let slam_config = merge_config(&base, &config)?;
        let model = self.resolve_model(None)?;
        {
            let admission = lock(&self.admission);
            if admission.queued.len() >= self.config.limits.max_queued_uploads {
                return Err(ApiError::unavailable(format!(
                    "{} uploads are already waiting (limits.max_queued_uploads); retry later",
                    admission.queued.len()
                )));
            }
        }
        let id = new_id();
        let staging_key = format!("sessions/{id}/upload.partial");
        let (Some(staging), Some(final_dir)) = (
            self.store.local_path(&staging_key),
            self.store.local_path(&upload_key(&id)),
        ) else {
            return Err(ApiError::internal("uploads need a filesystem store"));
        };
        let limits = ExtractLimits {
            max_bytes: self.config.limits.max_extracted_bytes,
            max_entries: self.config.limits.max_upload_entries,
        };
        let archive = archive.to_path_buf();
        let extracted = tokio::task::spawn_blocking(move || {
            stage_upload(&archive, kind, &staging, &final_dir, limits, camera)
        })
        .await
        .map_err(|e| ApiError::internal(format!("extraction task failed: {e}")));
        let (dataset_rel, camera, frames) = match extracted.and_then(|r| r) {
            Ok(v) => v,
            Err(e) => {
                let _ = self.store.delete_prefix(&session_prefix(&id));
                return Err(e);
            }
        };
        let camera_json = CameraJson::from_camera(&camera);
        if let Err(e) = camera_json.to_camera() {
            let _ = self.store.delete_prefix(&session_prefix(&id));
            return Err(e);
        }
        let mut dataset = String::from("upload");
        for part in dataset_rel.components() {
            dataset.push('/');
            dataset.push_str(&part.as_os_str().to_string_lossy());
        }
        let meta = SessionMeta {
            version: META_VERSION,
            id: id.clone(),
            owner: owner.clone(),
            kind: SessionKind::Upload,
            state: SessionState::Queued,
            camera: camera_json,
            config: slam_config,
            model: model
                .as_ref()
                .map_or("none".into(), |m| m.name().to_string()),
            policy: FramePolicy::Wait,
            created_unix: now_unix(),
            error: None,
            dataset: Some(dataset),
            total_frames: Some(frames as u64),
            counters: Default::default(),
        };
        // The acknowledgement point: once meta.json is durable, the upload exists.
        if let Err(e) = meta.save(self.store.as_ref()) {
            let _ = self.store.delete_prefix(&session_prefix(&id));
            return Err(ApiError::internal(format!("storing the upload: {e}")));
        }
        let session = Arc::new(self.build(meta, camera));
        self.sessions
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id, session.clone());
        self.admit_upload(session.clone());
        Ok(session)
    }

    /// Starts an upload now if a slot is free, else queues it.
    fn admit_upload(&self, session: Arc<Session>) {
        let start_now = {
            let mut admission = lock(&self.admission);
            if admission.active < self.config.limits.max_sessions && !self.is_shutting_down() {
                admission.active += 1;
                self.metrics.sessions_active.set(admission.active as i64);
                true
            } else {
                admission.queued.push_back(session.clone());
                false
            }
        };
        if start_now && let Err(e) = self.start(&session, self.model.clone()) {
            tracing::error!(session = %session.id(), "cannot start: {}", e.message);
            self.release(&session);
        }
    }

    /// `session` gives its slot back (its worker ended, or it was deleted; whichever comes
    /// first): the slot goes to the oldest queued upload.
    fn release(&self, session: &Session) {
        if !session.holds_slot.swap(false, Ordering::SeqCst) {
            return;
        }
        let next = {
            let mut admission = lock(&self.admission);
            admission.active = admission.active.saturating_sub(1);
            let next = if self.is_shutting_down() {
                None
            } else {
                admission.queued.pop_front()
            };
            if next.is_some() {
                admission.active += 1;
            }
            self.metrics.sessions_active.set(admission.active as i64);
            next
        };
        if let Some(session) = next
            && let Err(e) = self.start(&session, self.model.clone())
        {
            tracing::error!(session = %session.id(), "cannot start: {}", e.message);
            self.release(&session);
        }
    }

    /// Spawns the session's worker thread (it holds a slot until it ends).
    fn start(&self, session: &Arc<Session>, model: Option<SharedModel>) -> Result<(), ApiError> {
        session.holds_slot.store(true, Ordering::SeqCst);
        let manager = self
            .me
            .upgrade()
            .ok_or_else(|| ApiError::unavailable("the server is shutting down"))?;
        let env = WorkerEnv {
            model,
            pool: Arc::new(self.pool.client()),
            metrics: self.metrics.clone(),
            checkpoint_keyframes: self.config.limits.checkpoint_keyframes,
            idle_timeout: Duration::from_secs(self.config.limits.idle_timeout_s),
        };
        let s = session.clone();
        let handle = std::thread::Builder::new()
            .name(format!("session-{}", session.id()))
            // The pipeline's recursive steps are shallow, but image pyramids of big frames
            // live on the heap anyway; 16 MiB matches a main thread with room to spare.
            .stack_size(16 << 20)
            .spawn(move || {
                let outcome = worker::run(&s, env);
                s.close_input();
                tracing::info!(session = %s.id(), ?outcome, "session worker ended");
                if outcome == Outcome::Stopped {
                    tracing::info!(session = %s.id(), "upload interrupted by shutdown; it re-runs on restart");
                }
                manager.release(&s);
            })
            .map_err(|e| ApiError::internal(format!("starting the session thread: {e}")))?;
        *lock(&session.worker) = Some(handle);
        Ok(())
    }

    /// Graceful shutdown: refuses new sessions, ends every live session (its queued frames
    /// are processed and its results persisted), stops uploads where they are (they re-run on
    /// restart), and waits up to `limits.shutdown_grace_s` for the workers.
    pub async fn shutdown(&self) {
        if self.shutting_down.swap(true, Ordering::SeqCst) {
            return;
        }
        let sessions: Vec<Arc<Session>> = self
            .sessions
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .values()
            .cloned()
            .collect();
        for s in &sessions {
            match s.kind() {
                SessionKind::Live => s.end_of_stream(),
                SessionKind::Upload => {
                    s.stop.store(true, Ordering::SeqCst);
                    if !s.state().is_terminal() {
                        s.emit(super::events::SessionEvent::Failed {
                            message:
                                "the server is shutting down; this upload re-runs when it restarts"
                                    .into(),
                        });
                    }
                }
            }
        }
        let workers: Vec<_> = sessions
            .iter()
            .filter_map(|s| lock(&s.worker).take())
            .collect();
        let join = tokio::task::spawn_blocking(move || {
            for w in workers {
                let _ = w.join();
            }
        });
        let grace = Duration::from_secs(self.config.limits.shutdown_grace_s);
        if tokio::time::timeout(grace, join).await.is_err() {
            tracing::warn!("sessions did not finish within {grace:?}; exiting anyway");
        }
        self.pool.shutdown();
    }
}
