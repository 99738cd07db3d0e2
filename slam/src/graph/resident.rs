//! Working sets of keyframes (issue 37: sessions of an hour in bounded memory).
//!
//! Every keyframe stays in the back end as a [`CompactKeyframe`] (colour image, depth map by
//! its estimates, descriptor: about a tenth of the full one at 640×480). The full
//! [`Keyframe`] — pyramid with gradients and the per-level points the Sim(3) alignment reads —
//! is kept for the `capacity` most recently used keyframes and rebuilt, identical, when an
//! older one is needed again (a loop-closure candidate, a depth update); a
//! [`crate::map::Localizer`] keeps its keyframes' tracking references the same way. Which
//! keyframes are resident changes where data lives and how long a rebuild takes, never a
//! result.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

use super::KeyframeId;
use super::search::{CompactKeyframe, Keyframe};
use crate::Result;

/// A least-recently-used set of values built from keyframes (full keyframes by default).
#[derive(Debug)]
pub struct Resident<V = Keyframe> {
    capacity: usize,
    full: HashMap<KeyframeId, Arc<V>>,
    /// Least recently used first.
    order: VecDeque<KeyframeId>,
    rebuilds: usize,
}

impl Resident<Keyframe> {
    /// The full form of `kept`, rebuilt when it is not resident; it becomes the most recently
    /// used.
    pub fn get(&mut self, kept: &CompactKeyframe) -> Result<Arc<Keyframe>> {
        self.get_or_build(kept.id, || kept.rebuild())
    }

    /// Makes `keyframe` the resident form of its id (replacing an older one) and evicts the
    /// least recently used beyond the capacity.
    pub fn insert(&mut self, keyframe: Keyframe) -> Arc<Keyframe> {
        self.insert_as(keyframe.id, keyframe)
    }

    /// Bytes the resident full forms add to their compact forms.
    pub fn heap_bytes(&self) -> usize {
        self.full.values().map(|k| k.heap_bytes()).sum()
    }
}

impl<V> Resident<V> {
    /// At most `capacity` values (0: every use builds).
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity,
            full: HashMap::new(),
            order: VecDeque::new(),
            rebuilds: 0,
        }
    }

    /// The value of `id`, built by `build` when it is not resident; it becomes the most
    /// recently used.
    pub fn get_or_build(
        &mut self,
        id: KeyframeId,
        build: impl FnOnce() -> Result<V>,
    ) -> Result<Arc<V>> {
        if let Some(full) = self.full.get(&id) {
            let full = Arc::clone(full);
            self.touch(id);
            return Ok(full);
        }
        self.rebuilds += 1;
        Ok(self.insert_as(id, build()?))
    }

    /// Makes `value` the resident one of `id` (replacing an older one) and evicts the least
    /// recently used beyond the capacity.
    pub fn insert_as(&mut self, id: KeyframeId, value: V) -> Arc<V> {
        let full = Arc::new(value);
        if self.capacity == 0 {
            self.remove(id);
            return full;
        }
        self.full.insert(id, Arc::clone(&full));
        self.touch(id);
        while self.order.len() > self.capacity {
            if let Some(old) = self.order.pop_front() {
                self.full.remove(&old);
            }
        }
        full
    }

    /// Forgets the resident form of `id`, if any.
    pub fn remove(&mut self, id: KeyframeId) {
        self.full.remove(&id);
        self.order.retain(|&k| k != id);
    }

    fn touch(&mut self, id: KeyframeId) {
        self.order.retain(|&k| k != id);
        self.order.push_back(id);
    }

    /// Values held.
    pub fn len(&self) -> usize {
        self.full.len()
    }

    /// Whether no value is held.
    pub fn is_empty(&self) -> bool {
        self.full.is_empty()
    }

    /// Values built because they were not resident, so far.
    pub fn rebuilds(&self) -> usize {
        self.rebuilds
    }
}
