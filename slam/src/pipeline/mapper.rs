//! The depth mapping of the current keyframe: in step with tracking, or on its own thread
//! (LSD-SLAM's mapping thread, Engel et al. ECCV 2014 §3).
//!
//! Stereo observation, regularisation and the rebuild of the tracking reference cost about
//! three times what tracking a frame does. On their own thread they overlap with tracking:
//! tracked frames wait in a bounded queue, and the thread maps its whole backlog in one batch
//! — every frame observed, then one regularisation and one published reference — as LSD-SLAM
//! maps its `unmappedTrackedFrames` in one `updateKeyframe`. No observation is dropped (each
//! one holds the map's scale; skipping them under load made the result swing 3-5× with spare
//! CPU, issue 22): when the queue is full, tracking waits for room, so a slow machine runs
//! slower rather than worse. Tracking always uses the latest published depth. A new keyframe
//! waits for the queue to be mapped before the depth is propagated into it: propagating on the
//! thread while tracking went on against the old keyframe left those frames unmapped and gave
//! fewer keyframes and more drift (docs/tuning.md, "Mapping thread").
//!
//! In step (deterministic mode, or `pipeline.mapping_thread = false`) every good frame is
//! observed before the next one is tracked.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Instant;

use crate::frame::Frame;
use crate::geometry::SE3;
use crate::mapping::{DepthFilter, DepthMap};
use crate::tracking::TrackingReference;
use crate::{Error, Result};

/// A tracked frame for the current keyframe's depth filter.
#[derive(Clone, Debug)]
pub(super) struct Observation {
    pub frame: Arc<Frame>,
    pub keyframe_from_frame: SE3,
    /// The tracking residual (LSD's `initialTrackedResidual`, scales the geometric error).
    pub residual: f32,
}

/// What tracking and keyframe selection read of the keyframe being mapped.
#[derive(Clone, Debug)]
pub(super) struct Published {
    pub reference: Arc<TrackingReference>,
    pub depth: Arc<DepthMap>,
    /// Mean inverse depth of the filter (keyframe distance is measured in it).
    pub mean_idepth: Option<f64>,
    /// Frames observed into this keyframe (LSD replaces a keyframe only after a few).
    pub frames_mapped: usize,
}

impl Published {
    fn of(filter: &DepthFilter, spare: Option<Arc<TrackingReference>>) -> Result<Self> {
        let depth = filter.depth_map();
        let reference = match spare {
            Some(mut spare) => match Arc::get_mut(&mut spare) {
                // Unshared (tracking let go of it): rebuild reusing its buffers.
                Some(reference) => {
                    reference.rebuild(filter.keyframe(), &depth)?;
                    spare
                }
                None => Arc::new(TrackingReference::new(filter.keyframe(), &depth)?),
            },
            None => Arc::new(TrackingReference::new(filter.keyframe(), &depth)?),
        };
        Ok(Self {
            reference,
            depth: Arc::new(depth),
            mean_idepth: filter.mean_idepth(),
            frames_mapped: filter.frames_observed(),
        })
    }
}

/// Observations in order (stereo each), then one regularisation and the new published state.
fn map_batch(
    filter: &mut DepthFilter,
    batch: &[Observation],
    spare: Option<Arc<TrackingReference>>,
) -> Result<Published> {
    for obs in batch {
        filter.observe_with_residual(&obs.frame, &obs.keyframe_from_frame, obs.residual)?;
    }
    filter.regularize();
    Published::of(filter, spare)
}

/// The state shared with the mapping thread.
#[derive(Debug, Default)]
struct Slot {
    /// The current keyframe's filter; `None` while the thread maps with it, or between
    /// keyframes.
    filter: Option<DepthFilter>,
    /// Tracked frames waiting to be observed, oldest first.
    pending: VecDeque<Observation>,
    /// Most frames `pending` holds before tracking waits for room.
    capacity: usize,
    busy: bool,
    published: Option<Published>,
    /// The previously published reference, rebuilt in place next time when unshared.
    spare: Option<Arc<TrackingReference>>,
    mapping_s: f64,
    /// Observations mapped in one batch with others (the backlog of a busy thread).
    batched: usize,
    error: Option<Error>,
    shutdown: bool,
}

impl Slot {
    /// The error the thread met since the last call, if any.
    fn check(&mut self) -> Result<()> {
        self.error.take().map_or(Ok(()), Err)
    }
}

/// Asked for the keyframe's state when none is being mapped.
fn no_keyframe() -> Error {
    Error::Config("no keyframe being mapped".into())
}

#[derive(Debug, Default)]
struct Shared {
    slot: Mutex<Slot>,
    changed: Condvar,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Slot> {
        self.slot.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Waits until the thread has mapped every queued observation and is not busy.
    fn idle(&self) -> MutexGuard<'_, Slot> {
        let mut slot = self.lock();
        while slot.busy
            || (!slot.pending.is_empty() && slot.filter.is_some() && slot.error.is_none())
        {
            slot = self.changed.wait(slot).unwrap_or_else(|e| e.into_inner());
        }
        slot
    }

    fn run(&self) {
        loop {
            let (mut filter, batch, spare) = {
                let mut slot = self.lock();
                while !slot.shutdown && (slot.filter.is_none() || slot.pending.is_empty()) {
                    slot = self.changed.wait(slot).unwrap_or_else(|e| e.into_inner());
                }
                if slot.shutdown {
                    return;
                }
                slot.busy = true;
                let Some(filter) = slot.filter.take() else {
                    unreachable!("waited for a filter");
                };
                let batch: Vec<Observation> = slot.pending.drain(..).collect();
                slot.batched += batch.len().saturating_sub(1);
                (filter, batch, slot.spare.take())
            };
            let t0 = Instant::now();
            let result = map_batch(&mut filter, &batch, spare);
            let mut slot = self.lock();
            slot.mapping_s += t0.elapsed().as_secs_f64();
            slot.busy = false;
            slot.filter = Some(filter);
            match result {
                Ok(published) => {
                    slot.spare = slot.published.replace(published).map(|p| p.reference);
                }
                Err(e) => slot.error = Some(e),
            }
            self.changed.notify_all();
        }
    }
}

/// Where the current keyframe is mapped.
#[derive(Debug)]
enum Mode {
    InStep {
        filter: Box<Option<DepthFilter>>,
        published: Option<Published>,
        mapping_s: f64,
    },
    Threaded {
        shared: Arc<Shared>,
        thread: Option<std::thread::JoinHandle<()>>,
    },
}

/// The depth mapping of the current keyframe (see the module docs).
#[derive(Debug)]
pub(super) struct KeyframeMapper {
    mode: Mode,
}

impl KeyframeMapper {
    /// In step with tracking, or on its own thread when `threaded`, with at most `queue`
    /// tracked frames waiting for it.
    pub fn new(threaded: bool, queue: usize) -> Result<Self> {
        let mode = if threaded {
            let shared = Arc::new(Shared::default());
            shared.lock().capacity = queue.max(1);
            let worker = shared.clone();
            let thread = std::thread::Builder::new()
                .name("relfusion-mapping".into())
                .spawn(move || worker.run())
                .map_err(|e| Error::Config(format!("cannot start the mapping thread: {e}")))?;
            Mode::Threaded {
                shared,
                thread: Some(thread),
            }
        } else {
            Mode::InStep {
                filter: Box::new(None),
                published: None,
                mapping_s: 0.0,
            }
        };
        Ok(Self { mode })
    }

    /// Starts mapping a new keyframe with `filter` (its initial or propagated depth); returns
    /// what was published for it (its depth and tracking reference).
    pub fn begin(&mut self, filter: DepthFilter) -> Result<Published> {
        match &mut self.mode {
            Mode::InStep {
                filter: slot,
                published,
                ..
            } => {
                let spare = published.take().map(|p| p.reference);
                let new = Published::of(&filter, spare)?;
                **slot = Some(filter);
                *published = Some(new.clone());
                Ok(new)
            }
            Mode::Threaded { shared, .. } => {
                let mut slot = shared.idle();
                let spare = slot.published.take().map(|p| p.reference);
                let new = Published::of(&filter, spare)?;
                slot.filter = Some(filter);
                slot.published = Some(new.clone());
                Ok(new)
            }
        }
    }

    /// Observes a tracked frame into the current keyframe: at once in step, else queued for the
    /// thread (waiting for room while the queue is full).
    pub fn observe(&mut self, obs: Observation) -> Result<()> {
        match &mut self.mode {
            Mode::InStep {
                filter,
                published,
                mapping_s,
            } => {
                let filter = (**filter).as_mut().ok_or_else(no_keyframe)?;
                let t0 = Instant::now();
                let spare = published.take().map(|p| p.reference);
                *published = Some(map_batch(filter, std::slice::from_ref(&obs), spare)?);
                *mapping_s += t0.elapsed().as_secs_f64();
                Ok(())
            }
            Mode::Threaded { shared, .. } => {
                let mut slot = shared.lock();
                slot.check()?;
                while slot.pending.len() >= slot.capacity && slot.error.is_none() {
                    slot = shared.changed.wait(slot).unwrap_or_else(|e| e.into_inner());
                }
                slot.check()?;
                slot.pending.push_back(obs);
                shared.changed.notify_all();
                Ok(())
            }
        }
    }

    /// The latest published state of the current keyframe.
    pub fn published(&self) -> Result<Published> {
        let published = match &self.mode {
            Mode::InStep { published, .. } => published.clone(),
            Mode::Threaded { shared, .. } => {
                let mut slot = shared.lock();
                slot.check()?;
                slot.published.clone()
            }
        };
        published.ok_or_else(no_keyframe)
    }

    /// The current keyframe's latest published depth, if any (errors are left for the next
    /// call that reports them).
    pub fn latest_depth(&self) -> Option<Arc<DepthMap>> {
        match &self.mode {
            Mode::InStep { published, .. } => published.as_ref().map(|p| p.depth.clone()),
            Mode::Threaded { shared, .. } => {
                shared.lock().published.as_ref().map(|p| p.depth.clone())
            }
        }
    }

    /// Runs `f` on the current keyframe's filter once the thread has mapped its queue.
    pub fn with_filter<R>(&mut self, f: impl FnOnce(&DepthFilter) -> Result<R>) -> Result<R> {
        match &mut self.mode {
            Mode::InStep { filter, .. } => f((**filter).as_ref().ok_or_else(no_keyframe)?),
            Mode::Threaded { shared, .. } => {
                let mut slot = shared.idle();
                slot.check()?;
                f(slot.filter.as_ref().ok_or_else(no_keyframe)?)
            }
        }
    }

    /// Ends the current keyframe once the thread is idle: what was published of its filter
    /// last, which is its final depth (`None` when no keyframe is being mapped).
    pub fn finish(&mut self) -> Result<Option<Published>> {
        match &mut self.mode {
            Mode::InStep {
                filter, published, ..
            } => Ok(filter.take().and(published.take())),
            Mode::Threaded { shared, .. } => {
                let mut slot = shared.idle();
                slot.check()?;
                Ok(slot.filter.take().and(slot.published.take()))
            }
        }
    }

    /// Seconds spent observing frames, and observations mapped in a batch with earlier ones
    /// (how often the thread fell behind).
    pub fn counters(&self) -> (f64, usize) {
        match &self.mode {
            Mode::InStep { mapping_s, .. } => (*mapping_s, 0),
            Mode::Threaded { shared, .. } => {
                let slot = shared.lock();
                (slot.mapping_s, slot.batched)
            }
        }
    }
}

impl Drop for KeyframeMapper {
    fn drop(&mut self) {
        if let Mode::Threaded { shared, thread } = &mut self.mode {
            shared.lock().shutdown = true;
            shared.changed.notify_all();
            if let Some(thread) = thread.take() {
                let _ = thread.join();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::mapping::MappingConfig;
    use crate::mapping::test_scene::orbit_320;

    fn filter() -> DepthFilter {
        let scene = orbit_320();
        let mut filter =
            DepthFilter::new(scene.frames[0].clone(), MappingConfig::default()).expect("filter");
        filter.init_random(7);
        filter
    }

    fn observation(i: usize) -> Observation {
        let scene = orbit_320();
        Observation {
            frame: scene.frames[i].clone(),
            keyframe_from_frame: scene.relative(0, i),
            residual: 0.0,
        }
    }

    #[test]
    fn mapping_thread_computes_what_in_step_mapping_does() {
        let mut in_step = KeyframeMapper::new(false, 8).expect("in step");
        let mut threaded = KeyframeMapper::new(true, 8).expect("thread");
        in_step.begin(filter()).expect("begin");
        threaded.begin(filter()).expect("begin");
        let n = 12;
        for i in 1..=n {
            in_step.observe(observation(i)).expect("observe");
            threaded.observe(observation(i)).expect("observe");
            // Wait for the thread to publish this frame, so that none is skipped.
            let t0 = Instant::now();
            while threaded.published().expect("published").frames_mapped < i {
                assert!(
                    t0.elapsed() < Duration::from_secs(60),
                    "mapping thread stalled"
                );
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        let a = in_step.finish().expect("finish").expect("a keyframe");
        let b = threaded.finish().expect("finish").expect("a keyframe");
        assert_eq!((a.frames_mapped, b.frames_mapped), (n, n));
        assert_eq!(threaded.counters().1, 0, "nothing batched");
        assert!(
            a.depth.num_estimates() > 1000,
            "the filter mapped something"
        );
        assert_eq!(*a.depth, *b.depth, "same depth from the thread");
        assert!(threaded.published().is_err(), "no keyframe after finish");
    }

    #[test]
    fn a_busy_mapping_thread_batches_its_backlog_and_loses_no_frame() {
        let queue = 4;
        let mut threaded = KeyframeMapper::new(true, queue).expect("thread");
        threaded.begin(filter()).expect("begin");
        let n = 30;
        // Back to back, far faster than one stereo pass over the keyframe: the queue fills
        // and tracking waits for room instead of dropping frames.
        for i in 1..=n {
            threaded.observe(observation(i)).expect("observe");
            let waiting = match &threaded.mode {
                Mode::Threaded { shared, .. } => shared.lock().pending.len(),
                Mode::InStep { .. } => 0,
            };
            assert!(waiting <= queue, "{waiting} frames queued, bound {queue}");
        }
        let done = threaded.finish().expect("finish").expect("a keyframe");
        let (_, batched) = threaded.counters();
        assert_eq!(done.frames_mapped, n, "every frame observed");
        assert!(batched > 0, "a busy thread maps its backlog in batches");
    }
}
