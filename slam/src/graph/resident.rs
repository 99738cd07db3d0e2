//! The back end's working set of keyframes (issue 37: sessions of an hour in bounded memory).
//!
//! Every keyframe stays in the back end as a [`CompactKeyframe`] (colour image, depth map,
//! descriptor: about a fifth of the full one at 640×480). The full [`Keyframe`] — pyramid with
//! gradients and the per-level points the Sim(3) alignment reads — is kept for the
//! `capacity` most recently used keyframes and rebuilt, identical, when an older one is needed
//! again (a loop-closure candidate, a depth update). Which keyframes are resident changes
//! where data lives and how long a rebuild takes, never a result.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

use super::KeyframeId;
use super::search::{CompactKeyframe, Keyframe};
use crate::Result;

/// A least-recently-used set of full keyframes.
#[derive(Debug, Default)]
pub struct Resident {
    capacity: usize,
    full: HashMap<KeyframeId, Arc<Keyframe>>,
    /// Least recently used first.
    order: VecDeque<KeyframeId>,
    rebuilds: usize,
}

impl Resident {
    /// At most `capacity` full keyframes (0: every use rebuilds).
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity,
            ..Self::default()
        }
    }

    /// The full form of `kept`, rebuilt when it is not resident; it becomes the most recently
    /// used.
    pub fn get(&mut self, kept: &CompactKeyframe) -> Result<Arc<Keyframe>> {
        if let Some(full) = self.full.get(&kept.id) {
            let full = Arc::clone(full);
            self.touch(kept.id);
            return Ok(full);
        }
        self.rebuilds += 1;
        Ok(self.insert(kept.rebuild()?))
    }

    /// Makes `keyframe` the resident form of its id (replacing an older one) and evicts the
    /// least recently used beyond the capacity.
    pub fn insert(&mut self, keyframe: Keyframe) -> Arc<Keyframe> {
        let id = keyframe.id;
        let full = Arc::new(keyframe);
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

    /// Keyframes held in full.
    pub fn len(&self) -> usize {
        self.full.len()
    }

    /// Whether no keyframe is held in full.
    pub fn is_empty(&self) -> bool {
        self.full.is_empty()
    }

    /// Full keyframes rebuilt from their compact form so far.
    pub fn rebuilds(&self) -> usize {
        self.rebuilds
    }

    /// Bytes the resident full keyframes add to their compact forms.
    pub fn heap_bytes(&self) -> usize {
        self.full.values().map(|k| k.heap_bytes()).sum()
    }
}
