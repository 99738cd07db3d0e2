//! A session's checkpointed `pointcloud.ply`, built on a thread of its own.
//!
//! Building the semi-dense cloud reads every spilled keyframe back. Done in line on the
//! session's worker, a live 640×480 session of 1280 keyframes stopped taking frames for 19 s:
//! the live policy dropped them, tracking was lost and a new map fragment began (issue 37). The
//! worker now takes a [`SemidenseSnapshot`] (poses and handles, no reading) and this thread,
//! at the dense layer's low priority, builds and stores the cloud. A checkpoint rebuilds it
//! only when the map's keyframes have doubled since the last one, so a session reads its
//! keyframes back O(log n) times; the final results build it in line, after waiting for a
//! build in flight so that an older cloud cannot overwrite them.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use relfusion_slam::background::{Priority, lower_current_thread_priority};
use relfusion_slam::pipeline::SemidenseSnapshot;

use super::checkpoint::Job;
use super::engine::POINTCLOUD_MAX_POINTS;
use super::handle::Session;
use super::persist::result_key;

/// The checkpoints' point cloud: when it was taken, what it weighs, the build in flight.
#[derive(Default)]
pub(super) struct PointcloudWriter {
    /// The map's keyframes when the stored (or building) cloud was taken; 0 before any.
    taken_at: u64,
    /// Bytes of the stored cloud, set by the build that stored it.
    bytes: Arc<AtomicU64>,
    job: Job,
}

impl PointcloudWriter {
    /// Whether a checkpoint of a map of `keyframes` rebuilds the cloud: none was taken yet, or
    /// the keyframes have doubled since, and no build is in flight.
    pub fn due(&self, keyframes: u64) -> bool {
        self.job.idle() && (self.taken_at == 0 || keyframes >= 2 * self.taken_at)
    }

    /// Bytes of the stored cloud.
    pub fn bytes(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }

    /// A cloud of `keyframes` stored in line (the final results).
    pub fn stored(&mut self, keyframes: u64, bytes: u64) {
        self.taken_at = keyframes;
        self.bytes.store(bytes, Ordering::Relaxed);
    }

    /// Builds the cloud of `snapshot` (a map of `keyframes`) and stores it for `session`, on a
    /// thread of its own. A failed build leaves the stored cloud as it was, with a warning.
    pub fn start(&mut self, session: &Arc<Session>, snapshot: SemidenseSnapshot, keyframes: u64) {
        let session = Arc::clone(session);
        let bytes = Arc::clone(&self.bytes);
        let build = move || {
            lower_current_thread_priority(Priority::Dense);
            let stored = snapshot
                .points(POINTCLOUD_MAX_POINTS)
                .map_err(|e| e.to_string())
                .and_then(|points| {
                    let ply = crate::convert::points_ply(&points);
                    // Deleted meanwhile: its data is gone and must not be written again.
                    if session.lifecycle.is_deleted() {
                        return Err("the session was deleted".into());
                    }
                    let key = result_key(session.id(), "pointcloud.ply");
                    session.store.put(&key, &ply).map_err(|e| e.to_string())?;
                    Ok(ply.len() as u64)
                });
            match stored {
                Ok(n) => bytes.store(n, Ordering::Relaxed),
                Err(e) => tracing::warn!(session = %session.id(), "checkpoint point cloud: {e}"),
            }
        };
        if self.job.spawn("pointcloud", build) {
            self.taken_at = keyframes;
        }
    }

    /// Waits for the build in flight, if any.
    pub fn wait(&mut self) {
        self.job.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cloud_is_rebuilt_when_the_keyframes_have_doubled_and_none_is_building() {
        let mut writer = PointcloudWriter::default();
        assert!(writer.due(1), "the first checkpoint builds one");
        writer.stored(10, 1234);
        assert_eq!(writer.bytes(), 1234);
        assert!(!writer.due(19));
        assert!(writer.due(20));
        // A build in flight holds the next one back until it has finished.
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        writer.job.spawn("test", move || {
            let _ = rx.recv();
        });
        assert!(!writer.due(40));
        tx.send(()).expect("the build waits");
        writer.wait();
        assert!(writer.due(40));
    }
}
