//! A record per frame, spilled a chunk at a time (issue 37: an hour of video in bounded
//! memory).
//!
//! A session keeps one small record for every frame it tracked, twice (the pipeline's frame
//! poses, the session's reported poses): about 80 B each, 17 MB an hour at 30 fps, in `Vec`s
//! that double their capacity as they grow (heaptrack of `bench long`; docs/tuning.md). The
//! log keeps its newest [`CHUNK`] records in memory; each full chunk is sealed and spilled
//! through the session's [`Spill`] (held, as before, when there is no store), and read back,
//! bit-identical, when the whole log is read (the trajectory file, a download). Spilling
//! changes where records live, never what is read.

use std::sync::Arc;

use crate::Result;
use crate::spill::{Reader, Spill, Spillable, Stored, Writer};

/// Records per sealed chunk: 2.3 minutes at 30 fps, about 320 kB before compression.
pub const CHUNK: usize = 4096;

/// A fixed-size record that a [`FrameLog`] can spill.
pub trait LogRecord: Copy + Send + Sync + 'static {
    fn encode(&self, out: &mut Writer);
    fn decode(input: &mut Reader<'_>) -> Result<Self>;
}

/// A full chunk of records.
struct Chunk<T>(Vec<T>);

impl<T: LogRecord> Spillable for Chunk<T> {
    fn encode(&self, out: &mut Writer) {
        out.u64(self.0.len() as u64);
        for record in &self.0 {
            record.encode(out);
        }
    }

    fn decode(input: &mut Reader<'_>) -> Result<Self> {
        let n = input.usize()?.min(CHUNK);
        let mut records = Vec::with_capacity(n);
        for _ in 0..n {
            records.push(T::decode(input)?);
        }
        Ok(Chunk(records))
    }

    fn heap_bytes(&self) -> usize {
        self.0.capacity() * std::mem::size_of::<T>()
    }
}

/// An append-only log of per-frame records whose full chunks spill to the session's store.
pub struct FrameLog<T> {
    spill: Spill,
    chunk: usize,
    sealed: Vec<Arc<Stored<Chunk<T>>>>,
    tail: Vec<T>,
}

impl<T> std::fmt::Debug for FrameLog<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameLog")
            .field("sealed", &self.sealed.len())
            .field("tail", &self.tail.len())
            .finish()
    }
}

/// A copy to read outside a lock: the records in memory copied, the spilled chunks shared
/// (they stay in the store while a copy holds them).
impl<T: LogRecord> Clone for FrameLog<T> {
    fn clone(&self) -> Self {
        Self {
            spill: self.spill.clone(),
            chunk: self.chunk,
            sealed: self.sealed.clone(),
            tail: self.tail.clone(),
        }
    }
}

impl<T: LogRecord> Default for FrameLog<T> {
    /// A log that never spills (no store will be attached to its own [`Spill`]).
    fn default() -> Self {
        Self::new(&Spill::default())
    }
}

impl<T: LogRecord> FrameLog<T> {
    /// An empty log that spills through `spill` (once a store is attached to it).
    pub fn new(spill: &Spill) -> Self {
        Self::with_chunk(spill, CHUNK)
    }

    /// A log sealing every `chunk` records (tests spill a short sequence's records).
    pub fn with_chunk(spill: &Spill, chunk: usize) -> Self {
        let chunk = chunk.clamp(1, CHUNK);
        Self {
            spill: spill.clone(),
            chunk,
            sealed: Vec::new(),
            tail: Vec::with_capacity(chunk),
        }
    }

    /// Appends `record`. A full chunk is sealed and spilled, with any sealed before a store
    /// was attached; a store that refuses keeps the chunk in memory (the [`Spill`] records
    /// why and the session reports it).
    pub fn push(&mut self, record: T) {
        self.tail.push(record);
        if self.tail.len() < self.chunk {
            return;
        }
        let full = std::mem::replace(&mut self.tail, Vec::with_capacity(self.chunk));
        self.sealed
            .push(Stored::new(&self.spill, Arc::new(Chunk(full))));
        if !self.spill.enabled() {
            return;
        }
        for chunk in self.sealed.iter().rev().take_while(|c| c.is_held()) {
            if let Err(e) = chunk.spill() {
                tracing::warn!(error = %e, "a chunk of frame records stays in memory");
                return;
            }
        }
    }

    /// Records so far.
    pub fn len(&self) -> usize {
        self.sealed.len() * self.chunk + self.tail.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every record in order, spilled chunks read back one at a time.
    pub fn for_each(&self, mut f: impl FnMut(&T)) -> Result<()> {
        for chunk in &self.sealed {
            chunk.get()?.0.iter().for_each(&mut f);
        }
        self.tail.iter().for_each(f);
        Ok(())
    }

    /// Bytes of records held in memory.
    pub fn held_bytes(&self) -> usize {
        self.tail.capacity() * std::mem::size_of::<T>()
            + self.sealed.iter().map(|c| c.held_bytes()).sum::<usize>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spill::FolderStore;

    #[derive(Clone, Copy, Debug, PartialEq)]
    struct Rec(f64, u64);

    impl LogRecord for Rec {
        fn encode(&self, out: &mut Writer) {
            out.f64(self.0);
            out.u64(self.1);
        }
        fn decode(input: &mut Reader<'_>) -> Result<Self> {
            Ok(Rec(input.f64()?, input.u64()?))
        }
    }

    fn records(n: usize) -> Vec<Rec> {
        (0..n)
            .map(|i| Rec((i as f64).sqrt() * 1e-3 + 0.1, i as u64 * 7))
            .collect()
    }

    fn read(log: &FrameLog<Rec>) -> Vec<Rec> {
        let mut out = Vec::new();
        log.for_each(|r| out.push(*r)).expect("read back");
        out
    }

    #[test]
    fn spilled_chunks_read_back_the_records_and_leave_the_tail_in_memory() {
        let dir = std::env::temp_dir().join(format!("relfusion-frame-log-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let spill = Spill::default();
        let mut log = FrameLog::new(&spill);
        let all = records(3 * CHUNK + 17);
        // The first chunk is sealed before the store comes (a session attaches it after it
        // starts): it spills with the next one.
        for r in &all[..CHUNK + 5] {
            log.push(*r);
        }
        assert!(log.held_bytes() >= CHUNK * std::mem::size_of::<Rec>());
        spill
            .attach(Arc::new(FolderStore::new(&dir).expect("store")))
            .expect("attach");
        for r in &all[CHUNK + 5..] {
            log.push(*r);
        }
        assert_eq!(log.len(), all.len());
        assert_eq!(read(&log), all, "bit-identical, in order");
        let copy = log.clone();
        assert_eq!(spill.figures().spilled, 3);
        assert_eq!(std::fs::read_dir(&dir).expect("dir").count(), 3);
        // Only the tail is held: its capacity, never the spilled chunks.
        assert_eq!(log.held_bytes(), CHUNK * std::mem::size_of::<Rec>());
        drop(log);
        assert_eq!(
            read(&copy),
            all,
            "a copy keeps the spilled chunks it shares"
        );
        drop(copy);
        assert_eq!(
            std::fs::read_dir(&dir).expect("dir").count(),
            0,
            "a dropped log leaves the store"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn without_a_store_every_record_stays_in_memory() {
        let mut log = FrameLog::new(&Spill::default());
        let all = records(2 * CHUNK);
        for r in &all {
            log.push(*r);
        }
        assert_eq!(read(&log), all);
        assert!(log.held_bytes() >= all.len() * std::mem::size_of::<Rec>());
        assert!(FrameLog::<Rec>::new(&Spill::default()).is_empty());
    }
}
