//! Background work: the back end, the dense layer and the fusion each run as a [`Service`] —
//! on its own thread behind a bounded queue ([`Worker`]), or in step with the frames
//! (deterministic runs) — through one [`Link`] that the pipeline drives the same way in both
//! modes: submit a job, poll the replies, finish.
//!
//! Background threads give way to the frame path. Bounded queues make sure tracking never
//! *waits* for the dense layer ("the depth prior never blocks tracking"), but on a machine with
//! few cores the network, the lavapipe kernels, the fusion and the back end's constraint work
//! still take CPU time from it. Linux nice values order them: the frame path (tracking,
//! mapping) at normal priority, the back end (keyframe constraints, pose graph) at
//! [`Priority::Graph`], and the dense layer, the network and the fusion at [`Priority::Dense`],
//! the lowest, so that a keyframe's constraints are ready before its densification competes
//! with them (docs/tuning.md, "Background priorities"). A dense layer that falls too far
//! behind skips keyframes through its bounded queue (counted); it never delays frames.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use crate::{Error, Result};

/// Work that runs in the background: jobs in, replies out.
pub trait Service: Send + 'static {
    type Job: Send + 'static;
    type Reply: Send + 'static;
    /// Whether the jobs queued while one batch was handled are handed over together (the back
    /// end processes its commands in batches, as LSD-SLAM's constraint thread does).
    const BATCH: bool = false;
    /// Handles `jobs` (at least one), in order, sending replies through `reply`. An error is
    /// the caller's in step and logged (and kept as [`Worker::last_error`]) on a thread.
    fn handle(&mut self, jobs: Vec<Self::Job>, reply: &mut dyn FnMut(Self::Reply)) -> Result<()>;
    /// After the last job, once the queue has closed.
    fn close(&mut self, _reply: &mut dyn FnMut(Self::Reply)) -> Result<()> {
        Ok(())
    }
    /// The reply to a job when the service could not be built on its thread (`None`: none).
    fn unavailable(_job: Self::Job, _error: &str) -> Option<Self::Reply> {
        None
    }
}

/// How a [`Worker`]'s thread is set up.
#[derive(Clone, Copy, Debug)]
pub struct WorkerSpec {
    /// Thread name.
    pub name: &'static str,
    pub priority: Priority,
    /// Jobs waiting at most; [`Worker::submit`] refuses beyond, [`Worker::send`] waits.
    pub queue: usize,
}

/// What a worker's thread shares with its handle.
#[derive(Debug, Default)]
struct Status {
    queued: AtomicU64,
    handled: AtomicU64,
    last_error: Mutex<Option<String>>,
}

/// A [`Service`] on its own thread behind a bounded queue. Dropping it closes the queue and
/// joins the thread (the jobs already queued are handled first).
#[derive(Debug)]
pub struct Worker<S: Service> {
    jobs: Option<SyncSender<S::Job>>,
    replies: Receiver<S::Reply>,
    status: Arc<Status>,
    thread: Option<JoinHandle<Option<S>>>,
    name: &'static str,
}

impl<S: Service> Worker<S> {
    /// Starts the thread; `make` builds the service there (opening a GPU or a network can
    /// take a while, and must not hold up the caller). If it fails, every job gets
    /// [`Service::unavailable`]'s reply.
    pub fn spawn(
        spec: WorkerSpec,
        make: impl FnOnce() -> Result<S> + Send + 'static,
    ) -> Result<Self> {
        let (jobs, job_rx) = std::sync::mpsc::sync_channel::<S::Job>(spec.queue.max(1));
        let (reply_tx, replies) = std::sync::mpsc::channel::<S::Reply>();
        let status = Arc::new(Status::default());
        let thread_status = status.clone();
        let name = spec.name;
        let thread = std::thread::Builder::new()
            .name(format!("relfusion-{name}"))
            .spawn(move || {
                lower_current_thread_priority(spec.priority);
                run(make, &job_rx, &reply_tx, &thread_status, name)
            })
            .map_err(|e| Error::Config(format!("cannot start the {name} thread: {e}")))?;
        Ok(Self {
            jobs: Some(jobs),
            replies,
            status,
            thread: Some(thread),
            name,
        })
    }

    fn stopped(&self) -> Error {
        Error::Config(format!("the {} thread has stopped", self.name))
    }

    /// Queues a job without waiting; `false` when the queue is full (the job is dropped).
    pub fn submit(&self, job: S::Job) -> Result<bool> {
        let jobs = self.jobs.as_ref().ok_or_else(|| self.stopped())?;
        // Counted before it is queued, so that `handled` never runs ahead of it.
        self.status.queued.fetch_add(1, Ordering::SeqCst);
        let sent = jobs.try_send(job);
        if sent.is_err() {
            self.status.queued.fetch_sub(1, Ordering::SeqCst);
        }
        match sent {
            Ok(()) => Ok(true),
            Err(TrySendError::Full(_)) => Ok(false),
            Err(TrySendError::Disconnected(_)) => Err(self.stopped()),
        }
    }

    /// Queues a job, waiting while the queue is full.
    pub fn send(&self, job: S::Job) -> Result<()> {
        let jobs = self.jobs.as_ref().ok_or_else(|| self.stopped())?;
        self.status.queued.fetch_add(1, Ordering::SeqCst);
        jobs.send(job).map_err(|_| {
            self.status.queued.fetch_sub(1, Ordering::SeqCst);
            self.stopped()
        })
    }

    /// Replies ready now, without waiting.
    pub fn poll(&self) -> Vec<S::Reply> {
        self.replies.try_iter().collect()
    }

    /// Jobs handled so far.
    pub fn handled(&self) -> u64 {
        self.status.handled.load(Ordering::SeqCst)
    }

    /// Jobs queued and not yet handled (those of the batch in hand included): what a service
    /// fallen behind holds.
    pub fn waiting(&self) -> u64 {
        let handled = self.handled();
        self.status
            .queued
            .load(Ordering::SeqCst)
            .saturating_sub(handled)
    }

    /// The last error a job met on the thread, if any.
    pub fn last_error(&self) -> Option<String> {
        self.status.last_error.lock().ok().and_then(|e| e.clone())
    }

    /// Closes the queue, lets the thread handle what is queued and [`Service::close`], joins
    /// it, and returns the remaining replies with the service (`None` if it never started or
    /// the thread panicked).
    pub fn finish(&mut self) -> (Vec<S::Reply>, Option<S>) {
        self.jobs = None;
        let service = match self.thread.take().map(JoinHandle::join) {
            Some(Ok(service)) => service,
            Some(Err(_)) => {
                tracing::error!("the {} thread panicked", self.name);
                None
            }
            None => None,
        };
        (self.replies.try_iter().collect(), service)
    }
}

impl<S: Service> Drop for Worker<S> {
    fn drop(&mut self) {
        self.jobs = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// The thread body: builds the service, hands it the jobs (in batches if it wants them) until
/// the queue closes, then closes it and returns it.
fn run<S: Service>(
    make: impl FnOnce() -> Result<S>,
    jobs: &Receiver<S::Job>,
    replies: &std::sync::mpsc::Sender<S::Reply>,
    status: &Status,
    name: &str,
) -> Option<S> {
    let record = |e: &Error| {
        tracing::error!(error = %e, "{name}");
        if let Ok(mut slot) = status.last_error.lock() {
            *slot = Some(e.to_string());
        }
    };
    let mut service = match make() {
        Ok(service) => service,
        Err(e) => {
            record(&e);
            let error = e.to_string();
            for job in jobs {
                if let Some(reply) = S::unavailable(job, &error)
                    && replies.send(reply).is_err()
                {
                    break;
                }
            }
            return None;
        }
    };
    let mut send = |reply: S::Reply| {
        let _ = replies.send(reply);
    };
    while let Ok(first) = jobs.recv() {
        let mut batch = vec![first];
        if S::BATCH {
            batch.extend(jobs.try_iter());
        }
        let n = batch.len() as u64;
        if let Err(e) = service.handle(batch, &mut send) {
            record(&e);
        }
        status.handled.fetch_add(n, Ordering::SeqCst);
    }
    if let Err(e) = service.close(&mut send) {
        record(&e);
    }
    Some(service)
}

/// A [`Service`] driven the same way whether it runs in step with the caller (deterministic
/// runs: a job is handled inside [`Link::submit`]) or on a [`Worker`].
pub struct Link<S: Service> {
    mode: Mode<S>,
    /// Replies of jobs handled in step, until polled.
    pending: Vec<S::Reply>,
}

enum Mode<S: Service> {
    InStep(S),
    Threaded(Worker<S>),
    /// After [`Link::finish`]: the service, for what it still answers (final mesh, poses).
    Finished(Option<S>),
}

impl<S: Service> std::fmt::Debug for Link<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mode = match &self.mode {
            Mode::InStep(_) => "in step",
            Mode::Threaded(worker) => worker.name,
            Mode::Finished(_) => "finished",
        };
        f.debug_struct("Link")
            .field("mode", &mode)
            .field("pending", &self.pending.len())
            .finish()
    }
}

impl<S: Service> Link<S> {
    /// A link to a service run in step (`threaded` false, built now) or on its own thread.
    pub fn new(
        threaded: bool,
        spec: WorkerSpec,
        make: impl FnOnce() -> Result<S> + Send + 'static,
    ) -> Result<Self> {
        let mode = if threaded {
            Mode::Threaded(Worker::spawn(spec, make)?)
        } else {
            Mode::InStep(make()?)
        };
        Ok(Self {
            mode,
            pending: Vec::new(),
        })
    }

    /// Hands over a job: handled now in step (its error is returned), queued on a thread
    /// without waiting (`false` when the queue is full: the job is dropped).
    pub fn submit(&mut self, job: S::Job) -> Result<bool> {
        match &mut self.mode {
            Mode::InStep(service) => {
                let pending = &mut self.pending;
                service.handle(vec![job], &mut |r| pending.push(r))?;
                Ok(true)
            }
            Mode::Threaded(worker) => worker.submit(job),
            Mode::Finished(_) => Err(Error::Config("the link has finished".into())),
        }
    }

    /// Hands over a job, waiting for queue room on a thread.
    pub fn send(&mut self, job: S::Job) -> Result<()> {
        match &mut self.mode {
            Mode::Threaded(worker) => worker.send(job),
            _ => self.submit(job).map(|_| ()),
        }
    }

    /// Replies ready now.
    pub fn poll(&mut self) -> Vec<S::Reply> {
        let mut replies = std::mem::take(&mut self.pending);
        if let Mode::Threaded(worker) = &self.mode {
            replies.extend(worker.poll());
        }
        replies
    }

    /// Ends the service (the queue is drained and [`Service::close`] runs) and returns the
    /// remaining replies; the service stays reachable through [`Link::service`].
    pub fn finish(&mut self) -> Result<Vec<S::Reply>> {
        let mut replies = std::mem::take(&mut self.pending);
        let mode = std::mem::replace(&mut self.mode, Mode::Finished(None));
        let service = match mode {
            Mode::InStep(mut service) => {
                service.close(&mut |r| replies.push(r))?;
                Some(service)
            }
            Mode::Threaded(mut worker) => {
                let (rest, service) = worker.finish();
                replies.extend(rest);
                service
            }
            Mode::Finished(service) => service,
        };
        self.mode = Mode::Finished(service);
        Ok(replies)
    }

    /// Whether it runs on its own thread.
    pub fn is_threaded(&self) -> bool {
        matches!(self.mode, Mode::Threaded(_))
    }

    /// The service itself, when it is at hand: in step, or after [`Link::finish`].
    pub fn service(&self) -> Option<&S> {
        match &self.mode {
            Mode::InStep(service) | Mode::Finished(Some(service)) => Some(service),
            _ => None,
        }
    }

    /// [`Link::service`], mutably.
    pub fn service_mut(&mut self) -> Option<&mut S> {
        match &mut self.mode {
            Mode::InStep(service) | Mode::Finished(Some(service)) => Some(service),
            _ => None,
        }
    }

    /// The worker, when it runs on a thread.
    pub fn worker(&self) -> Option<&Worker<S>> {
        match &self.mode {
            Mode::Threaded(worker) => Some(worker),
            _ => None,
        }
    }
}

/// How far a background thread steps back from the frame path.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Priority {
    /// Part of the frame path, beside tracking: the odometry's window (keeps the priority of
    /// the thread that starts it).
    Frame,
    /// The back end: asynchronous, but its poses and loop closures are wanted within a few
    /// keyframes (nice 10).
    Graph,
    /// The dense layer, the depth network and the fusion: the lowest priority (nice 19).
    Dense,
}

impl Priority {
    fn nice(self) -> i32 {
        match self {
            Self::Frame => 0,
            Self::Graph => 10,
            Self::Dense => 19,
        }
    }
}

/// Lowers the calling thread's scheduling priority (and that of threads it starts later). Where
/// that is not possible the thread keeps its priority; that is logged, not an error.
pub fn lower_current_thread_priority(priority: Priority) {
    if priority == Priority::Frame {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        // On Linux `setpriority(PRIO_PROCESS, 0, …)` sets the nice value of the calling thread
        // only: threads are scheduled entities with their own nice value (setpriority(2),
        // BUGS), and threads they create inherit it.
        #[allow(unsafe_code)]
        // SAFETY: a system call with integer arguments only; no memory is passed or shared.
        let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, priority.nice()) };
        if rc != 0 {
            tracing::debug!(
                error = %std::io::Error::last_os_error(),
                "background thread keeps its priority"
            );
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = priority;
}

#[cfg(test)]
#[path = "background_tests.rs"]
mod worker_tests;

#[cfg(all(test, target_os = "linux"))]
mod tests {
    #[test]
    fn background_threads_run_at_their_priority_and_others_do_not() {
        let nice = |path: &str| -> i64 {
            // Field 19 of /proc/…/stat is the nice value; the command name (field 2) is in
            // parentheses and may hold spaces, so count from the last ')'.
            let stat = std::fs::read_to_string(path).expect("stat");
            let rest = &stat[stat.rfind(')').expect("comm") + 2..];
            rest.split(' ')
                .nth(16)
                .expect("nice")
                .parse()
                .expect("number")
        };
        let before = nice("/proc/thread-self/stat");
        for (priority, expected) in [(super::Priority::Graph, 10), (super::Priority::Dense, 19)] {
            let inside = std::thread::spawn(move || {
                super::lower_current_thread_priority(priority);
                let own = nice("/proc/thread-self/stat");
                let child = std::thread::spawn(move || nice("/proc/thread-self/stat"))
                    .join()
                    .expect("child");
                (own, child)
            })
            .join()
            .expect("thread");
            assert_eq!(
                inside,
                (expected, expected),
                "{priority:?}: lowered, and inherited by its threads"
            );
        }
        assert_eq!(
            nice("/proc/thread-self/stat"),
            before,
            "the caller is untouched"
        );
    }
}
