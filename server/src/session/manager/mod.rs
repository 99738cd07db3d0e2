//! [`SessionManager`]: creates, finds, lists and deletes sessions; admission control; the
//! durable upload path; restart recovery; graceful shutdown.
//!
//! Admission ([`super::admission`]): at most `limits.max_sessions` sessions process at once.
//! A live session beyond that is refused (503: a live stream cannot wait), an upload is
//! acknowledged and queued (state `queued`, at most `limits.max_queued_uploads`) and starts
//! when a slot frees. Each owner's sessions, uploads and bytes are bounded by `[quotas]`; each
//! session's map by its share of the memory budget ([`crate::memory`]).
//!
//! Recovery at start ([`SessionManager::open`]): every `sessions/<id>/meta.json` is read.
//! Finished and failed sessions come back read-only (their results stay downloadable);
//! unfinished uploads re-run from scratch with their stored configuration (deterministic, so
//! the re-run gives the result the interrupted run would have); unfinished live sessions are
//! marked failed (their client is gone), keeping their last checkpoint. Folders without
//! `meta.json` are uploads that were never acknowledged and are removed.
//!
//! A session worker that panics fails its session and gives its slot back; the server goes on.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock, RwLockReadGuard, RwLockWriteGuard, Weak};
use std::time::{Duration, Instant};

use relfusion_proto::http::{MapMode, MapStart};
use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::odometry::memory::memory_bound;
use relfusion_slam::pipeline::{Config as SlamConfig, Frontend};

use super::admission::{
    Admission, NewSession, OwnerHoldings, SharedAdmission, UploadTicket, check_quota,
    lock as lock_admission, under_active_quota,
};
use super::handle::{Session, SessionSpec};
use super::persist::{META_VERSION, SessionMeta, meta_key, session_prefix, upload_key};
use super::prior::SharedModel;
use super::types::{
    FramePolicy, Owner, SessionId, SessionInfo, SessionKind, SessionRequest, SessionState,
};
use super::upload::{ArchiveKind, ExtractLimits, stage_upload};
use super::worker::{self, Outcome, WorkerEnv};
use crate::config::Config;
use crate::gpu_pool::{GpuPool, device_count};
use crate::maps::MapStore;
use crate::memory::{MapShape, MemoryPlan, SessionCost, resident_bytes};
use crate::metrics::Metrics;
use crate::storage::ObjectStore;
use crate::{ApiError, ServerError};

mod health;
mod recover;
mod retention;
#[cfg(test)]
mod tests;
mod uploads;

pub use uploads::NewUpload;

/// Every session of this node.
pub struct SessionManager {
    me: Weak<SessionManager>,
    config: Config,
    store: Arc<dyn ObjectStore>,
    /// Saved maps (`/v1/maps`), in the same store.
    maps: MapStore,
    metrics: Arc<Metrics>,
    pool: GpuPool,
    model: Option<SharedModel>,
    memory: MemoryPlan,
    sessions: RwLock<HashMap<SessionId, Arc<Session>>>,
    /// Sessions whose data expired (`[retention]`): their ids answer 410 to their owner.
    expired: RwLock<HashMap<SessionId, Owner>>,
    admission: SharedAdmission,
    shutting_down: AtomicBool,
    temp_dir: PathBuf,
    /// When the store last proved writable (health checks probe it at most every 10 s).
    store_probe: Mutex<Option<(Instant, Result<(), String>)>>,
    /// The ROS 2 side, once the Zenoh side is up with `[ros2]` on.
    ros2: std::sync::OnceLock<Arc<crate::ros2_api::Ros2Bridge>>,
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

pub(crate) use crate::storage::now_unix;

/// A fresh unguessable id: `s-` and 24 hex digits (96 bits) from the thread's CSPRNG.
fn new_id() -> SessionId {
    format!("s-{:024x}", rand::random::<u128>() & ((1u128 << 96) - 1))
}

impl SessionManager {
    /// Opens the store in `config.data_dir`, loads the depth model, starts the GPU pool and
    /// recovers the sessions of a previous run (see the module docs).
    pub fn open(config: &Config, metrics: Arc<Metrics>) -> Result<Arc<Self>, ServerError> {
        let store = crate::storage::open(config)?;
        let temp_dir = config.data_dir.join("tmp");
        let _ = std::fs::remove_dir_all(&temp_dir);
        std::fs::create_dir_all(&temp_dir)
            .map_err(|e| ServerError::Startup(format!("creating {}: {e}", temp_dir.display())))?;
        let model = SharedModel::load(&config.model)?;
        let devices = device_count();
        let workers = match config.pool.workers {
            0 => devices,
            n => n,
        };
        let pool = GpuPool::new(
            workers,
            devices,
            config.limits.pool_job_queue,
            Some(metrics.clone()),
        );
        tracing::info!(
            workers,
            devices = pool.devices(),
            model = model.as_ref().map_or("none", |m| m.name()),
            "GPU pool started"
        );
        let manager = Arc::new_cyclic(|me| Self {
            me: me.clone(),
            config: config.clone(),
            maps: MapStore::new(store.clone(), config.quotas.max_maps),
            store,
            metrics,
            pool,
            model,
            memory: MemoryPlan::new(&config.limits),
            sessions: RwLock::new(HashMap::new()),
            expired: RwLock::new(HashMap::new()),
            admission: Arc::new(Mutex::new(Admission::default())),
            shutting_down: AtomicBool::new(false),
            temp_dir,
            store_probe: Mutex::new(None),
            ros2: std::sync::OnceLock::new(),
        });
        tracing::info!(
            budget_mb = manager.memory.budget >> 20,
            share_mb = manager.memory.share >> 20,
            "memory budget"
        );
        manager.recover()?;
        Ok(manager)
    }

    /// Where the HTTP layer writes incoming upload archives before [`Self::create_upload`]
    /// (inside the data directory, so the rename-free extraction stays on one filesystem;
    /// emptied at every start).
    pub fn temp_dir(&self) -> &Path {
        &self.temp_dir
    }

    /// Whether this node runs (or keeps) the session `id`, whoever owns it (cluster routing;
    /// the owner check comes with the request).
    pub fn holds(&self, id: &str) -> bool {
        self.read_sessions().contains_key(id)
    }

    /// This node's name (`[zenoh] node`).
    pub fn node(&self) -> &str {
        &self.config.zenoh.node
    }

    /// The configuration in force.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// The ROS 2 side (`[ros2]`), once it is up.
    pub fn ros2(&self) -> Option<&Arc<crate::ros2_api::Ros2Bridge>> {
        self.ros2.get()
    }

    /// Called once by the Zenoh side when it starts with `[ros2]` on.
    pub(crate) fn set_ros2(&self, bridge: Arc<crate::ros2_api::Ros2Bridge>) {
        let _ = self.ros2.set(bridge);
    }

    /// The saved maps.
    pub fn maps(&self) -> &MapStore {
        &self.maps
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
            lock_admission(&self.admission).active,
            self.config.limits.max_sessions,
        )
    }

    /// The memory budget in force.
    pub fn memory(&self) -> &MemoryPlan {
        &self.memory
    }

    fn read_sessions(&self) -> RwLockReadGuard<'_, HashMap<SessionId, Arc<Session>>> {
        self.sessions.read().unwrap_or_else(|e| e.into_inner())
    }

    fn write_sessions(&self) -> RwLockWriteGuard<'_, HashMap<SessionId, Arc<Session>>> {
        self.sessions.write().unwrap_or_else(|e| e.into_inner())
    }

    /// Whether [`Self::shutdown`] has begun (readiness turns 503).
    pub fn is_shutting_down(&self) -> bool {
        self.shutting_down.load(Ordering::SeqCst)
    }

    /// Whether new sessions and uploads are accepted (`/readyz`).
    pub fn is_accepting(&self) -> bool {
        !self.is_shutting_down()
    }

    /// The session of `meta`, run by the node it names (this one when it names none).
    fn build(&self, mut meta: SessionMeta, max_keyframes: usize) -> Session {
        meta.node
            .get_or_insert_with(|| self.config.zenoh.node.clone());
        Session::new(
            SessionSpec {
                meta,
                frame_queue: self.config.limits.frame_queue,
                event_buffer: self.config.limits.event_buffer,
                max_frame_bytes: self.config.limits.max_frame_bytes,
                max_timestamp_step: self.config.limits.max_timestamp_step_s,
                max_keyframes,
            },
            self.store.clone(),
            self.metrics.clone(),
        )
    }

    /// 400 for a camera over `limits.max_image_pixels`.
    fn check_image_size(&self, camera: &PinholeCamera) -> Result<(), ApiError> {
        let pixels = u64::from(camera.width) * u64::from(camera.height);
        let max = self.config.limits.max_image_pixels;
        if pixels > max {
            return Err(ApiError::bad_request(format!(
                "a {}x{} camera has {pixels} pixels; this server takes at most {max} \
                 (limits.max_image_pixels): send smaller images",
                camera.width, camera.height
            )));
        }
        Ok(())
    }

    /// `config` with the operator's pipeline settings (`[pipeline]`); a session that extends
    /// a saved map keeps the LSD front end, the one that can extend one.
    pub(crate) fn with_operator_settings(
        &self,
        mut config: SlamConfig,
        map: Option<&MapStart>,
    ) -> SlamConfig {
        let extends = map.is_some_and(|m| m.mode == MapMode::Extend);
        if !extends {
            config.pipeline.frontend = self.config.pipeline.frontend;
        }
        config
    }

    /// How many keyframes a session of `camera` and `config` may map in its memory share
    /// (400 when too few fit: the image is too large for this server).
    fn map_limit(&self, camera: &PinholeCamera, config: &SlamConfig) -> Result<usize, ApiError> {
        self.check_image_size(camera)?;
        let pixels = u64::from(camera.width) * u64::from(camera.height);
        let dense = &config.dense;
        let dense_pixels = dense.enabled.then(|| (dense.width * dense.height) as u64);
        self.memory
            .keyframes_for(SessionCost::estimate(MapShape {
                pixels,
                dense_pixels,
                resident: config.backend.resident_keyframes,
                held: config.backend.held_keyframes,
                fusion_inputs: config
                    .fusion
                    .enabled
                    .then_some((config.fusion.keyframe_memory_mb * 1024.0 * 1024.0) as u64),
                fusion_blocks: u64::from(config.fusion.resident_blocks),
                odometry: (config.pipeline.frontend == Frontend::Dso).then(|| {
                    memory_bound(
                        &config.odometry,
                        camera.width as usize,
                        camera.height as usize,
                    )
                }),
            }))
            .map_err(ApiError::bad_request)
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
    pub fn create(&self, req: SessionRequest, owner: &Owner) -> Result<Arc<Session>, ApiError> {
        self.refuse_if_shutting_down()?;
        let SessionRequest {
            camera,
            config,
            model,
            policy,
            map,
        } = req;
        self.check_image_size(&camera)?;
        if let Some(start) = &map {
            let source = self.maps.source(start, owner)?;
            if source.camera != camera {
                return Err(ApiError::bad_request(format!(
                    "map {} serves the camera {:?}, not this session's {:?}",
                    start.id,
                    crate::session::types::camera_json(&source.camera),
                    crate::session::types::camera_json(&camera)
                )));
            }
        }
        let model = self.resolve_model(model.as_deref())?;
        let config = self.with_operator_settings(config, map.as_ref());
        let max_keyframes = self.map_limit(&camera, &config)?;
        let meta = SessionMeta {
            version: META_VERSION,
            id: new_id(),
            owner: owner.clone(),
            kind: SessionKind::Live,
            state: SessionState::Running,
            camera,
            config,
            model: model
                .as_ref()
                .map_or("none".into(), |m| m.name().to_string()),
            policy,
            created_unix: now_unix(),
            error: None,
            dataset: None,
            total_frames: None,
            counters: Default::default(),
            ended_unix: None,
            notice: None,
            upload_bytes: 0,
            results_bytes: 0,
            map,
            node: None,
            scale: None,
        };
        let session = {
            // Quota, slot and registration under one lock: racing creates cannot both pass.
            let mut admission = lock_admission(&self.admission);
            let max = self.config.limits.max_sessions;
            if admission.active >= max {
                return Err(ApiError::unavailable(format!(
                    "at capacity: {max} sessions are processing (limits.max_sessions); retry later"
                )));
            }
            let holdings = OwnerHoldings::of(owner, self.read_sessions().values());
            check_quota(
                &self.config,
                &admission,
                owner,
                holdings,
                NewSession::Live,
                0,
            )?;
            admission.active += 1;
            self.metrics.sessions_active.set(admission.active as i64);
            let session = Arc::new(self.build(meta, max_keyframes));
            self.write_sessions()
                .insert(session.id().to_string(), session.clone());
            session
        };
        if let Err(e) = self.start(&session, model) {
            self.release(&session);
            return Err(e);
        }
        Ok(session)
    }

    /// The session `id` if `owner` may see it; 404 otherwise (another owner's session does
    /// not exist for this caller).
    /// An expired session of `owner` is 410.
    pub fn get(&self, id: &str, owner: &Owner) -> Result<Arc<Session>, ApiError> {
        if let Some(session) = self.read_sessions().get(id).filter(|s| s.owner() == owner) {
            return Ok(session.clone());
        }
        let expired = self.expired.read().unwrap_or_else(|e| e.into_inner());
        if expired.get(id) == Some(owner) {
            return Err(ApiError::gone(format!(
                "session {id:?} has expired: finished sessions are kept {} s \
                 (retention.finished_ttl_s)",
                self.config.retention.finished_ttl_s
            )));
        }
        Err(ApiError::not_found(format!("no session {id:?}")))
    }

    /// The sessions of `owner`, oldest first.
    pub fn list(&self, owner: &Owner) -> Vec<SessionInfo> {
        let mut infos: Vec<SessionInfo> = self
            .read_sessions()
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
        self.write_sessions().remove(id);
        // A queued upload holds no slot: dropping it from the queue is all it takes.
        lock_admission(&self.admission)
            .queued
            .retain(|s| s.id() != id);
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

    /// Reserves an upload of `owner` before its body is read: a place in the upload queue
    /// and in the owner's quotas (`declared` bytes, or the largest allowed upload when none
    /// is declared). 503 when the queue is full, 429 over a quota.
    pub fn reserve_upload(
        &self,
        owner: &Owner,
        declared: Option<u64>,
    ) -> Result<UploadTicket, ApiError> {
        self.refuse_if_shutting_down()?;
        let adding = declared.unwrap_or(self.config.limits.max_upload_bytes);
        UploadTicket::reserve(&self.admission, &self.config, owner, |admission| {
            let holdings = OwnerHoldings::of(owner, self.read_sessions().values());
            check_quota(
                &self.config,
                admission,
                owner,
                holdings,
                NewSession::Upload,
                adding,
            )
        })
    }

    /// Gives an upload a slot now (`true`: the caller starts it) if one is free, else queues
    /// it.
    fn queue_or_slot(&self, admission: &mut Admission, session: &Arc<Session>) -> bool {
        if admission.active < self.config.limits.max_sessions
            && !self.is_shutting_down()
            && self.may_start(session)
        {
            admission.active += 1;
            self.metrics.sessions_active.set(admission.active as i64);
            true
        } else {
            admission.queued.push_back(session.clone());
            false
        }
    }

    /// Whether `session`'s owner holds fewer slots than its quota (an upload of an owner at
    /// its quota waits for one of the owner's own sessions to end).
    fn may_start(&self, session: &Session) -> bool {
        let holdings = OwnerHoldings::of(session.owner(), self.read_sessions().values());
        under_active_quota(&self.config, holdings)
    }

    /// `session` gives its slot back (its worker ended, or it was deleted; whichever comes
    /// first): the slot goes to the oldest queued upload whose owner is under its quota.
    fn release(&self, session: &Session) {
        if !session.holds_slot.swap(false, Ordering::SeqCst) {
            return;
        }
        let next = {
            let mut admission = lock_admission(&self.admission);
            admission.active = admission.active.saturating_sub(1);
            let next = if self.is_shutting_down() {
                None
            } else {
                let pos = admission.queued.iter().position(|s| self.may_start(s));
                pos.and_then(|i| admission.queued.remove(i))
            };
            if next.is_some() {
                admission.active += 1;
            }
            self.metrics.sessions_active.set(admission.active as i64);
            next
        };
        if let Some(session) = next {
            self.start_or_release(&session, self.model.clone());
        }
    }

    fn start_or_release(&self, session: &Arc<Session>, model: Option<SharedModel>) {
        if let Err(e) = self.start(session, model) {
            tracing::error!(session = %session.id(), "cannot start: {}", e.message);
            self.release(session);
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
            max_recording_bytes: self.config.limits.max_recording_mb << 20,
            idle_timeout: Duration::from_secs(self.config.limits.idle_timeout_s),
            min_frame_rate: self.config.limits.min_frame_rate,
            sequence_limits: self.config.limits.sequence_limits(),
        };
        let s = session.clone();
        let handle = std::thread::Builder::new()
            .name(format!("session-{}", session.id()))
            // The pipeline's recursive steps are shallow, but image pyramids of big frames
            // live on the heap anyway; 16 MiB matches a main thread with room to spare.
            .stack_size(16 << 20)
            .spawn(move || {
                // A bug in one session's pipeline fails that session, never the server, and
                // its slot is given back below either way.
                let run = std::panic::AssertUnwindSafe(|| worker::run(&s, env));
                let outcome = std::panic::catch_unwind(run).unwrap_or_else(|panic| {
                    let what = panic
                        .downcast_ref::<&str>()
                        .map(|m| (*m).to_string())
                        .or_else(|| panic.downcast_ref::<String>().cloned())
                        .unwrap_or_else(|| "unknown panic".into());
                    tracing::error!(session = %s.id(), "session worker panicked: {what}");
                    s.conclude(
                        SessionState::Failed,
                        Some(format!("internal error in the session's pipeline: {what}")),
                    );
                    Outcome::Failed
                });
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
        let sessions: Vec<Arc<Session>> = self.read_sessions().values().cloned().collect();
        for s in &sessions {
            s.shut_down();
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
