//! A session's checkpoints, made and stored on a thread of their own.
//!
//! Every `limits.checkpoint_keyframes` keyframes a session stores its results so far
//! (trajectory, keyframes, mesh, summary) and its metadata, so that a crash loses little. Done
//! in line on the session's worker, a 640×480 live session stopped taking frames for a median
//! 102 ms a checkpoint in its first 3000 frames and 197 ms after 20 000, longer as it grew:
//! every pose formatted, the mesh encoded twice, five files written and synced, the heap
//! trimmed (docs/tuning.md, issue 37). The worker now takes what the files are made of — the
//! poses as numbers and a [`MeshSnapshot`], no formatting, no I/O — and a thread at the dense
//! layer's low priority makes and stores them. A checkpoint that falls due while the last one
//! is still being written waits for a later keyframe. The final results wait for the
//! checkpoint in flight and are then written in line.

use std::sync::Arc;
use std::thread::JoinHandle;

use relfusion_slam::background::{Priority, lower_current_thread_priority};
use relfusion_slam::pipeline::Trajectories;

use super::handle::Session;
use super::mesh_state::MeshSnapshot;
use super::persist::Results;

/// What a checkpoint's files are made of, taken on the worker.
pub(super) struct Checkpoint {
    /// Every exported frame's and keyframe's pose of a mapping run; `None` for a localiser,
    /// whose trajectory is the poses it reported (read from the session by the writer).
    pub poses: Option<Trajectories>,
    /// The session's mesh (`None` before its first update).
    pub mesh: Option<MeshSnapshot>,
    pub summary: serde_json::Value,
    /// Bytes of the stored point cloud (`super::pointcloud` writes it).
    pub cloud_bytes: u64,
}

impl Checkpoint {
    /// Makes the files and stores them for `session`, with its metadata and the bytes its
    /// results take. Writes nothing for a deleted session.
    fn write(self, session: &Session) -> Result<(), String> {
        let (trajectory, keyframes) = match &self.poses {
            Some(t) => t.tum(),
            None => (session.trajectory_tum()?, String::new()),
        };
        let mesh = self.mesh.as_ref().and_then(|m| session.mesh_files_of(m));
        // Deleted meanwhile: its data is gone and must not be written again.
        if session.lifecycle.is_deleted() {
            return Err("the session was deleted".into());
        }
        let results = Results {
            trajectory,
            keyframes,
            pointcloud: None,
            mesh,
            summary: self.summary,
        };
        let bytes = results
            .save(session.store.as_ref(), session.id())
            .map_err(|e| e.to_string())?;
        session.set_results_bytes(bytes + self.cloud_bytes);
        session.persist_meta();
        crate::memory::release_free_memory();
        Ok(())
    }
}

/// The checkpoint being written, if any.
#[derive(Default)]
pub(super) struct CheckpointWriter {
    job: Job,
}

impl CheckpointWriter {
    /// Whether no checkpoint is being written.
    pub fn idle(&self) -> bool {
        self.job.idle()
    }

    /// Writes `checkpoint` for `session` on a thread of its own (after the one in flight). A
    /// failed write leaves the stored results as they were, with an error in the log.
    pub fn start(&mut self, session: &Arc<Session>, checkpoint: Checkpoint) {
        let session = Arc::clone(session);
        self.job.spawn("checkpoint", move || {
            lower_current_thread_priority(Priority::Dense);
            if let Err(e) = checkpoint.write(&session) {
                tracing::error!(session = %session.id(), "checkpoint: {e}");
            }
        });
    }

    /// Waits for the checkpoint in flight, if any.
    pub fn wait(&mut self) {
        self.job.wait();
    }
}

/// One background write of a session's results (a checkpoint, a point cloud): spawned when
/// the last has finished, waited for before the final results, joined when its owner goes —
/// the session's store is not written once its worker is gone.
#[derive(Default)]
pub(super) struct Job {
    handle: Option<(&'static str, JoinHandle<()>)>,
}

impl Job {
    /// Whether nothing is running.
    pub fn idle(&self) -> bool {
        self.handle.as_ref().is_none_or(|(_, h)| h.is_finished())
    }

    /// Runs `work` on a thread named `name`, after waiting for the one before; `false` (with
    /// a warning) when no thread could be started.
    pub fn spawn(&mut self, name: &'static str, work: impl FnOnce() + Send + 'static) -> bool {
        self.wait();
        match std::thread::Builder::new().name(name.into()).spawn(work) {
            Ok(handle) => {
                self.handle = Some((name, handle));
                true
            }
            Err(e) => {
                tracing::warn!("{name}: no thread: {e}");
                false
            }
        }
    }

    /// Waits for the running work, if any.
    pub fn wait(&mut self) {
        if let Some((name, handle)) = self.handle.take()
            && handle.join().is_err()
        {
            tracing::error!("{name}: the write panicked");
        }
    }
}

impl Drop for Job {
    fn drop(&mut self) {
        self.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_job_runs_one_write_at_a_time_and_is_joined_when_dropped() {
        let mut job = Job::default();
        assert!(job.idle());
        let (go, wait) = std::sync::mpsc::channel::<()>();
        let (done, finished) = std::sync::mpsc::channel::<u32>();
        let first = done.clone();
        assert!(job.spawn("test", move || {
            let _ = wait.recv();
            let _ = first.send(1);
        }));
        assert!(!job.idle(), "the first write waits");
        // The second starts only once the first has finished.
        let release = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(50));
            let _ = go.send(());
        });
        let second = done.clone();
        assert!(job.spawn("test", move || {
            let _ = second.send(2);
        }));
        drop(job);
        drop(done);
        assert_eq!(finished.iter().collect::<Vec<_>>(), vec![1, 2]);
        release.join().expect("release");
    }
}
