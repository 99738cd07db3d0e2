//! The depth mapping of the current keyframe: in step with tracking, or on its own thread
//! (LSD-SLAM's mapping thread, Engel et al. ECCV 2014 §3).
//!
//! Stereo observation, regularisation and the rebuild of the tracking reference cost about
//! three times what tracking a frame does. On their own thread they never hold up tracking:
//! every frame gets its pose at tracking speed, and the mapping observes the newest tracked
//! frame whenever it is free. When it falls behind, a waiting frame is replaced by a newer one
//! (latest wins, counted as not mapped), so the queue cannot grow — LSD-SLAM likewise maps its
//! backlog of tracked frames in one update. Tracking always uses the latest published depth.
//! A new keyframe's depth is propagated on the thread as well
//! ([`KeyframeMapper::propagate_on_thread`]); tracking goes on against the previous keyframe
//! until it is ready.
//!
//! In step (deterministic mode, or `pipeline.mapping_thread = false`) every good frame is
//! observed before the next one is tracked.

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

/// One observation: stereo, regularisation, and the new published state.
fn map_one(
    filter: &mut DepthFilter,
    obs: &Observation,
    spare: Option<Arc<TrackingReference>>,
) -> Result<Published> {
    filter.observe_with_residual(&obs.frame, &obs.keyframe_from_frame, obs.residual)?;
    filter.regularize();
    Published::of(filter, spare)
}

/// The state shared with the mapping thread.
#[derive(Debug, Default)]
struct Slot {
    /// The current keyframe's filter; `None` while the thread maps with it, or between
    /// keyframes.
    filter: Option<DepthFilter>,
    /// The newest tracked frame waiting to be observed.
    pending: Option<Observation>,
    /// A frame to become the next keyframe, with its pose `frame_from_keyframe`: the filter is
    /// propagated into it on the thread (LSD-SLAM creates keyframes on its mapping thread).
    propagate: Option<(Arc<Frame>, SE3)>,
    /// The propagated filter, once the thread has it.
    propagated: Option<Result<DepthFilter>>,
    busy: bool,
    published: Option<Published>,
    /// The previously published reference, rebuilt in place next time when unshared.
    spare: Option<Arc<TrackingReference>>,
    mapping_s: f64,
    not_mapped: usize,
    error: Option<Error>,
    shutdown: bool,
}

impl Slot {
    /// The error the thread met since the last call, if any.
    fn check(&mut self) -> Result<()> {
        self.error.take().map_or(Ok(()), Err)
    }

    /// Drops the frame waiting to be observed (counted as not mapped).
    fn drop_pending(&mut self) {
        if self.pending.take().is_some() {
            self.not_mapped += 1;
        }
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

    /// Waits until the thread is not mapping; the pending observation is dropped (it belongs to
    /// a keyframe that is about to change) and counted.
    fn idle(&self) -> MutexGuard<'_, Slot> {
        let mut slot = self.lock();
        slot.drop_pending();
        while slot.busy {
            slot = self.changed.wait(slot).unwrap_or_else(|e| e.into_inner());
        }
        slot
    }

    fn run(&self) {
        loop {
            let (mut filter, work) = {
                let mut slot = self.lock();
                while !slot.shutdown
                    && (slot.filter.is_none()
                        || (slot.pending.is_none() && slot.propagate.is_none()))
                {
                    slot = self.changed.wait(slot).unwrap_or_else(|e| e.into_inner());
                }
                if slot.shutdown {
                    return;
                }
                slot.busy = true;
                let Some(filter) = slot.filter.take() else {
                    unreachable!("waited for a filter");
                };
                let work = match slot.propagate.take() {
                    Some(job) => Err(job),
                    None => Ok(slot.pending.take().map(|obs| (obs, slot.spare.take()))),
                };
                (filter, work)
            };
            let t0 = Instant::now();
            let result = match work {
                Ok(Some((obs, spare))) => Ok(Some(map_one(&mut filter, &obs, spare))),
                Ok(None) => Ok(None),
                Err((frame, frame_from_keyframe)) => {
                    Err(filter.propagate_to(frame, &frame_from_keyframe))
                }
            };
            let mut slot = self.lock();
            slot.mapping_s += t0.elapsed().as_secs_f64();
            slot.busy = false;
            slot.filter = Some(filter);
            match result {
                Ok(Some(Ok(published))) => {
                    slot.spare = slot.published.replace(published).map(|p| p.reference);
                }
                Ok(Some(Err(e))) => slot.error = Some(e),
                Ok(None) => {}
                Err(propagated) => slot.propagated = Some(propagated),
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
    /// In step with tracking, or on its own thread when `threaded`.
    pub fn new(threaded: bool) -> Result<Self> {
        let mode = if threaded {
            let shared = Arc::new(Shared::default());
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

    /// Observes a tracked frame into the current keyframe: at once in step, else when the
    /// thread is free (replacing a frame still waiting).
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
                *published = Some(map_one(filter, &obs, spare)?);
                *mapping_s += t0.elapsed().as_secs_f64();
                Ok(())
            }
            Mode::Threaded { shared, .. } => {
                let mut slot = shared.lock();
                slot.check()?;
                if slot.pending.replace(obs).is_some() {
                    slot.not_mapped += 1;
                }
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

    /// Whether the mapping runs on its own thread.
    pub fn is_threaded(&self) -> bool {
        matches!(self.mode, Mode::Threaded { .. })
    }

    /// On the thread: starts propagating the current keyframe's depth into `frame` (the next
    /// keyframe, at `frame_from_keyframe`), after the observation in progress; the waiting one
    /// is dropped. [`Self::take_propagated`] collects the result. In step there is nothing to
    /// overlap: use [`Self::with_filter`].
    pub fn propagate_on_thread(&mut self, frame: Arc<Frame>, frame_from_keyframe: SE3) {
        if let Mode::Threaded { shared, .. } = &self.mode {
            let mut slot = shared.lock();
            slot.drop_pending();
            slot.propagated = None;
            slot.propagate = Some((frame, frame_from_keyframe));
            shared.changed.notify_all();
        }
    }

    /// The filter [`Self::propagate_on_thread`] produced: `None` while it is not ready (with
    /// `wait`, it waits for it; `None` then means nothing was asked).
    pub fn take_propagated(&mut self, wait: bool) -> Option<Result<DepthFilter>> {
        let Mode::Threaded { shared, .. } = &self.mode else {
            return None;
        };
        let mut slot = shared.lock();
        while wait && slot.propagated.is_none() && (slot.propagate.is_some() || slot.busy) {
            slot = shared.changed.wait(slot).unwrap_or_else(|e| e.into_inner());
        }
        slot.propagated.take()
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

    /// Runs `f` on the current keyframe's filter once the thread is idle (a waiting frame is
    /// dropped: the keyframe is about to change).
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

    /// Seconds spent observing frames, and frames left unobserved because the mapping was busy.
    pub fn counters(&self) -> (f64, usize) {
        match &self.mode {
            Mode::InStep { mapping_s, .. } => (*mapping_s, 0),
            Mode::Threaded { shared, .. } => {
                let slot = shared.lock();
                (slot.mapping_s, slot.not_mapped)
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
        let mut in_step = KeyframeMapper::new(false).expect("in step");
        let mut threaded = KeyframeMapper::new(true).expect("thread");
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
        assert_eq!(threaded.counters().1, 0, "nothing skipped");
        assert!(
            a.depth.num_estimates() > 1000,
            "the filter mapped something"
        );
        assert_eq!(*a.depth, *b.depth, "same depth from the thread");
        assert!(threaded.published().is_err(), "no keyframe after finish");
    }

    #[test]
    fn a_busy_mapping_thread_skips_frames_instead_of_queueing_them() {
        let mut threaded = KeyframeMapper::new(true).expect("thread");
        threaded.begin(filter()).expect("begin");
        let n = 30;
        // Back to back, far faster than one stereo pass over the keyframe.
        for i in 1..=n {
            threaded.observe(observation(i)).expect("observe");
        }
        let done = threaded.finish().expect("finish").expect("a keyframe");
        let (_, skipped) = threaded.counters();
        assert_eq!(
            done.frames_mapped + skipped,
            n,
            "every frame is either mapped or counted as skipped"
        );
        assert!(skipped > n / 2, "only {skipped} of {n} skipped");
    }
}
