//! The GPU worker pool: sessions are placed on the node's GPUs, and worker threads run their
//! pool jobs (the depth-prior inference) fairly.
//!
//! Placement: each session ([`PoolClient`]) is given the device with the fewest sessions when
//! it is created; its pipeline's kernels (dense layer, fusion) run on that device's context
//! ([`PoolClient::gpu`]), and its pool jobs run on the workers of that device (worker `i`
//! serves device `i mod devices`). A node without a real GPU has one device: the CPU fallback.
//!
//! Fairness: each session ([`PoolClient`]) has its own bounded job queue, and workers serve
//! the sessions with waiting jobs in round robin, one job at a time. A session that submits a
//! burst of keyframes therefore delays another session by at most one job per turn instead of
//! its whole burst. A full per-session queue blocks the submitting (pipeline) thread: that is
//! the backpressure from the GPU onto a session's own tracking, never onto other sessions.

use std::collections::{HashMap, VecDeque};
use std::panic::AssertUnwindSafe;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, mpsc};
use std::thread::JoinHandle;

use relfusion_slam::gpu::GpuContext;

use crate::metrics::Metrics;

type Job = Box<dyn FnOnce() + Send>;

/// Why a job did not produce a result.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PoolError {
    #[error("the GPU pool is shutting down")]
    Closed,
    #[error("the GPU job panicked")]
    Panicked,
}

#[derive(Default)]
struct PoolState {
    /// Waiting jobs per client.
    queues: HashMap<u64, VecDeque<Job>>,
    /// Per device: its clients with waiting jobs, in the order they will be served.
    rotation: Vec<VecDeque<u64>>,
    /// Per device: its live clients.
    clients: Vec<usize>,
    next_client: u64,
    queued: usize,
    completed: u64,
    closed: bool,
}

struct Shared {
    state: Mutex<PoolState>,
    /// Signalled when a job is queued (workers wait on it).
    work: Condvar,
    /// Signalled when a job leaves a queue (full submitters wait on it).
    space: Condvar,
    job_queue: usize,
    metrics: Option<Arc<Metrics>>,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, PoolState> {
        // A panicking job runs outside the lock, so a poisoned lock still holds consistent
        // state.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn set_gauge(&self, queued: usize) {
        if let Some(m) = &self.metrics {
            m.gpu_queue_depth.set(queued as i64);
        }
    }
}

/// The pool. Dropping it (or [`GpuPool::shutdown`]) lets the workers finish the queued jobs and
/// joins them.
pub struct GpuPool {
    shared: Arc<Shared>,
    workers: Mutex<Vec<JoinHandle<()>>>,
    count: usize,
    devices: usize,
}

impl std::fmt::Debug for GpuPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuPool")
            .field("workers", &self.count)
            .field("devices", &self.devices)
            .field("queued", &self.queued())
            .finish()
    }
}

impl GpuPool {
    /// A pool of `workers` threads (at least one) over `devices` devices (at least one, at
    /// most one per worker) with `job_queue` waiting jobs per client.
    pub fn new(
        workers: usize,
        devices: usize,
        job_queue: usize,
        metrics: Option<Arc<Metrics>>,
    ) -> Self {
        let count = workers.max(1);
        let devices = devices.clamp(1, count);
        let shared = Arc::new(Shared {
            state: Mutex::new(PoolState {
                rotation: vec![VecDeque::new(); devices],
                clients: vec![0; devices],
                ..PoolState::default()
            }),
            work: Condvar::new(),
            space: Condvar::new(),
            job_queue: job_queue.max(1),
            metrics,
        });
        let handles = (0..count)
            .filter_map(|i| {
                let shared = shared.clone();
                std::thread::Builder::new()
                    .name(format!("gpu-worker-{i}"))
                    .spawn(move || worker_loop(&shared, i % devices))
                    .map_err(|e| tracing::error!("cannot start GPU worker {i}: {e}"))
                    .ok()
            })
            .collect();
        Self {
            shared,
            workers: Mutex::new(handles),
            count,
            devices,
        }
    }

    /// Number of devices sessions are placed on.
    pub fn devices(&self) -> usize {
        self.devices
    }

    /// Number of worker threads.
    pub fn workers(&self) -> usize {
        self.count
    }

    /// Worker threads still running (fewer than [`Self::workers`] means one died: health).
    pub fn alive_workers(&self) -> usize {
        self.workers
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .filter(|h| !h.is_finished())
            .count()
    }

    /// Jobs waiting now (all clients).
    pub fn queued(&self) -> usize {
        self.shared.lock().queued
    }

    /// Jobs completed since start.
    pub fn completed(&self) -> u64 {
        self.shared.lock().completed
    }

    /// A new client (one per session) with its own queue, placed on the device with the
    /// fewest clients (the lowest index among equals).
    pub fn client(&self) -> PoolClient {
        let mut state = self.shared.lock();
        let id = state.next_client;
        state.next_client += 1;
        state.queues.insert(id, VecDeque::new());
        let device = (0..state.clients.len())
            .min_by_key(|&d| (state.clients[d], d))
            .unwrap_or(0);
        state.clients[device] += 1;
        PoolClient {
            shared: self.shared.clone(),
            id,
            device,
        }
    }

    /// Stops taking jobs, lets the workers drain what is queued, and joins them.
    pub fn shutdown(&self) {
        self.shared.lock().closed = true;
        self.shared.work.notify_all();
        self.shared.space.notify_all();
        let handles = std::mem::take(&mut *self.workers.lock().unwrap_or_else(|e| e.into_inner()));
        for h in handles {
            let _ = h.join();
        }
    }
}

impl Drop for GpuPool {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn worker_loop(shared: &Shared, device: usize) {
    loop {
        let job = {
            let mut state = shared.lock();
            loop {
                if let Some(job) = next_job(&mut state, device) {
                    break job;
                }
                if state.closed {
                    return;
                }
                state = shared.work.wait(state).unwrap_or_else(|e| e.into_inner());
            }
        };
        shared.space.notify_all();
        // A panicking job must not take the worker (and every session's GPU work) down; its
        // submitter sees `PoolError::Panicked` through the dropped result channel.
        let _ = std::panic::catch_unwind(AssertUnwindSafe(job));
        let queued = {
            let mut state = shared.lock();
            state.completed += 1;
            state.queued
        };
        if let Some(m) = &shared.metrics {
            m.gpu_jobs.inc();
        }
        shared.set_gauge(queued);
    }
}

/// Round robin on `device`: the next client in its rotation gives one job and goes to the back
/// if it has more.
fn next_job(state: &mut PoolState, device: usize) -> Option<Job> {
    while let Some(id) = state.rotation[device].pop_front() {
        let Some(queue) = state.queues.get_mut(&id) else {
            continue;
        };
        let Some(job) = queue.pop_front() else {
            continue;
        };
        if !queue.is_empty() {
            state.rotation[device].push_back(id);
        }
        state.queued -= 1;
        return Some(job);
    }
    None
}

/// One session's handle on the pool. Dropping it discards its waiting jobs (their handles
/// report [`PoolError::Closed`]).
pub struct PoolClient {
    shared: Arc<Shared>,
    id: u64,
    device: usize,
}

impl std::fmt::Debug for PoolClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PoolClient")
            .field("id", &self.id)
            .field("device", &self.device)
            .finish()
    }
}

/// The result of a submitted job.
#[derive(Debug)]
pub struct JobHandle<R>(mpsc::Receiver<R>);

impl<R> JobHandle<R> {
    /// Blocks until the job ran.
    pub fn wait(self) -> Result<R, PoolError> {
        self.0.recv().map_err(|_| PoolError::Panicked)
    }
}

impl PoolClient {
    /// The device the session is placed on.
    pub fn device(&self) -> usize {
        self.device
    }

    /// The GPU context of the session's device, for its pipeline's kernels (`None` when it
    /// cannot be opened: the pipeline then falls back as it would without a pool).
    pub fn gpu(&self) -> Option<Arc<GpuContext>> {
        relfusion_slam::gpu::context_for(self.device)
            .map_err(|e| tracing::warn!(device = self.device, "no GPU context: {e}"))
            .ok()
    }

    /// Queues `job`, blocking while this client already has `pool_job_queue` jobs waiting.
    pub fn submit<R, F>(&self, job: F) -> Result<JobHandle<R>, PoolError>
    where
        R: Send + 'static,
        F: FnOnce() -> R + Send + 'static,
    {
        let (tx, rx) = mpsc::sync_channel(1);
        let boxed: Job = Box::new(move || {
            let _ = tx.send(job());
        });
        let mut state = self.shared.lock();
        loop {
            if state.closed {
                return Err(PoolError::Closed);
            }
            let len = state.queues.get(&self.id).map_or(0, VecDeque::len);
            if len < self.shared.job_queue {
                break;
            }
            state = self
                .shared
                .space
                .wait(state)
                .unwrap_or_else(|e| e.into_inner());
        }
        let queue = state.queues.entry(self.id).or_default();
        queue.push_back(boxed);
        if queue.len() == 1 {
            state.rotation[self.device].push_back(self.id);
        }
        state.queued += 1;
        let queued = state.queued;
        drop(state);
        self.shared.set_gauge(queued);
        // Every worker wakes: only those of this client's device can take the job.
        self.shared.work.notify_all();
        Ok(JobHandle(rx))
    }

    /// Submits `job` and waits for its result.
    pub fn run<R, F>(&self, job: F) -> Result<R, PoolError>
    where
        R: Send + 'static,
        F: FnOnce() -> R + Send + 'static,
    {
        self.submit(job)?.wait()
    }
}

impl Drop for PoolClient {
    fn drop(&mut self) {
        let mut state = self.shared.lock();
        if let Some(queue) = state.queues.remove(&self.id) {
            state.queued -= queue.len();
        }
        state.rotation[self.device].retain(|&id| id != self.id);
        state.clients[self.device] -= 1;
        let queued = state.queued;
        drop(state);
        self.shared.set_gauge(queued);
        self.shared.space.notify_all();
    }
}

/// The devices of this node: its real GPUs (discrete, integrated, virtual) of the preferred
/// kind, or 1 when there is none (lavapipe or no adapter at all: the kernels then run on the
/// CPU fallback, and the depth prior still one job at a time). Also the worker count for
/// `pool.workers = 0`.
pub fn device_count() -> usize {
    relfusion_slam::gpu::gpu_adapter_count(&relfusion_slam::gpu::GpuConfig::default()).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, Ordering};

    #[test]
    fn two_sessions_are_served_round_robin() {
        let pool = GpuPool::new(1, 1, 4, None);
        let a = pool.client();
        let b = pool.client();
        // Hold the only worker so both queues fill before anything runs.
        let gate = Arc::new((Mutex::new(false), Condvar::new()));
        let g = gate.clone();
        let blocker = a
            .submit(move || {
                let (lock, cv) = &*g;
                let mut open = lock.lock().expect("gate");
                while !*open {
                    open = cv.wait(open).expect("gate");
                }
            })
            .expect("submit");
        // Wait until the worker holds the blocker (so it is not counted in a's queue).
        while pool.queued() > 0 {
            std::thread::yield_now();
        }
        let order = Arc::new(Mutex::new(Vec::new()));
        let mut handles = Vec::new();
        for i in 0..4 {
            let o = order.clone();
            handles.push(
                a.submit(move || o.lock().expect("order").push(format!("a{i}")))
                    .expect("a"),
            );
        }
        for i in 0..3 {
            let o = order.clone();
            handles.push(
                b.submit(move || o.lock().expect("order").push(format!("b{i}")))
                    .expect("b"),
            );
        }
        assert_eq!(pool.queued(), 7);
        {
            let (lock, cv) = &*gate;
            *lock.lock().expect("gate") = true;
            cv.notify_all();
        }
        blocker.wait().expect("blocker");
        for h in handles {
            h.wait().expect("job");
        }
        // a's burst was queued first, yet b gets every other turn.
        assert_eq!(
            *order.lock().expect("order"),
            ["a0", "b0", "a1", "b1", "a2", "b2", "a3"]
        );
        // The worker counts a job after handing its result over, so the count may trail the
        // last `wait` by a moment.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while pool.completed() < 8 && std::time::Instant::now() < deadline {
            std::thread::yield_now();
        }
        assert_eq!(pool.completed(), 8);
    }

    #[test]
    fn a_full_queue_blocks_only_its_own_session() {
        let pool = GpuPool::new(1, 1, 1, None);
        let a = pool.client();
        let b = pool.client();
        let release = Arc::new(AtomicBool::new(false));
        let r = release.clone();
        let busy = a
            .submit(move || {
                while !r.load(Ordering::SeqCst) {
                    std::thread::sleep(std::time::Duration::from_millis(1));
                }
            })
            .expect("submit");
        while pool.queued() > 0 {
            std::thread::yield_now();
        }
        let _queued_a = a.submit(|| ()).expect("fills a's queue of one");
        // b still has room although a is full.
        let b_job = b.submit(|| 7).expect("b not blocked by a");
        let blocked = std::thread::scope(|s| {
            let t = s.spawn(|| a.submit(|| ()).map(|_| ()));
            std::thread::sleep(std::time::Duration::from_millis(50));
            let still_blocked = !t.is_finished();
            release.store(true, Ordering::SeqCst);
            t.join().expect("join").expect("submitted after room");
            still_blocked
        });
        assert!(blocked, "a third job of a must wait for room");
        busy.wait().expect("busy");
        assert_eq!(b_job.wait(), Ok(7));
    }

    #[test]
    fn sessions_are_spread_over_devices_and_run_on_their_own() {
        let pool = GpuPool::new(4, 2, 2, None);
        assert_eq!(pool.devices(), 2);
        let clients: Vec<PoolClient> = (0..3).map(|_| pool.client()).collect();
        let devices: Vec<usize> = clients.iter().map(PoolClient::device).collect();
        assert_eq!(devices, [0, 1, 0], "the least loaded device first");
        for c in &clients {
            for _ in 0..4 {
                let worker = c
                    .run(|| std::thread::current().name().map(String::from))
                    .expect("job")
                    .expect("named worker");
                let index: usize = worker
                    .strip_prefix("gpu-worker-")
                    .and_then(|i| i.parse().ok())
                    .expect("worker index");
                assert_eq!(
                    index % 2,
                    c.device(),
                    "{worker} ran a job of device {}",
                    c.device()
                );
            }
        }
        // A departed session frees its place.
        drop(clients);
        assert_eq!(pool.client().device(), 0);
        assert_eq!(
            GpuPool::new(1, 8, 1, None).devices(),
            1,
            "a device needs a worker"
        );
    }

    #[test]
    fn panicking_job_reports_and_worker_survives() {
        let pool = GpuPool::new(1, 1, 2, None);
        let c = pool.client();
        let r: Result<(), _> = c.run(|| panic!("boom"));
        assert_eq!(r, Err(PoolError::Panicked));
        assert_eq!(c.run(|| 5), Ok(5));
        pool.shutdown();
        assert_eq!(c.run(|| 5), Err(PoolError::Closed));
    }
}
