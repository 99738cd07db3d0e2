//! Keyframes spilled to the session's store (issue 37, item 2: sessions of an hour in bounded
//! memory).
//!
//! A keyframe older than the working set keeps a compact form (its colour image and its depth
//! by its estimates, about 2.7 MB at 640×480); a session of an hour makes thousands. When the
//! session has a store ([`Spill::attach`]: the service's object store, filesystem or S3, or a
//! folder for `relfusion run --spill`), the compact data of keyframes older than the newest
//! `backend.resident_keyframes + backend.held_keyframes` is written there, LZ4-compressed, and
//! dropped from memory; whoever needs it again (a loop-closure candidate, relocalisation, a
//! depth update, the exports) reads it back, bit-identical. The pose graph, the descriptors and
//! every figure the candidate search reads stay in memory: they are small. Spilling changes
//! where data lives, never a result.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::geometry::{Distortion, PinholeCamera, SO3, Sim3};
use crate::image::ImageF32;
use crate::{Error, Result};

/// Where spilled keyframes go: a key-value store private to one session.
pub trait SpillStore: Send + Sync + fmt::Debug {
    /// Stores `bytes` under `key` (replacing an older object).
    fn put(&self, key: &str, bytes: &[u8]) -> std::result::Result<(), String>;
    /// The object under `key`.
    fn get(&self, key: &str) -> std::result::Result<Vec<u8>, String>;
    /// Removes the object under `key` (a value replaced or dropped: a refined depth map
    /// supersedes the one spilled before).
    fn remove(&self, key: &str) -> std::result::Result<(), String>;
}

/// A folder as a [`SpillStore`] (`relfusion run --spill DIR`, tests). Nothing here needs to
/// survive a crash, so files are written without syncing.
#[derive(Debug)]
pub struct FolderStore {
    dir: PathBuf,
}

impl FolderStore {
    /// Spills into `dir`, created when missing.
    pub fn new(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|source| Error::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        Ok(Self {
            dir: dir.to_path_buf(),
        })
    }
}

impl SpillStore for FolderStore {
    fn put(&self, key: &str, bytes: &[u8]) -> std::result::Result<(), String> {
        std::fs::write(self.dir.join(key), bytes).map_err(|e| format!("{key}: {e}"))
    }

    fn get(&self, key: &str) -> std::result::Result<Vec<u8>, String> {
        std::fs::read(self.dir.join(key)).map_err(|e| format!("{key}: {e}"))
    }

    fn remove(&self, key: &str) -> std::result::Result<(), String> {
        std::fs::remove_file(self.dir.join(key)).map_err(|e| format!("{key}: {e}"))
    }
}

/// One session's spilling: the store once attached, key numbering and figures. Cloning shares
/// it; every [`Stored`] value made with it spills to the store attached later.
#[derive(Clone, Debug, Default)]
pub struct Spill {
    shared: Arc<Shared>,
}

#[derive(Debug, Default)]
struct Shared {
    store: OnceLock<Arc<dyn SpillStore>>,
    next_key: AtomicU64,
    spilled: AtomicUsize,
    spilled_bytes: AtomicU64,
    loads: AtomicUsize,
    /// Why the store refused a value: spilling stops there (keyframes stay in memory) and the
    /// session says so ([`Spill::failure`]).
    failure: OnceLock<String>,
}

/// What a session has spilled ([`Spill::figures`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct SpillFigures {
    /// Values written to the store (an image and a depth map per keyframe).
    pub spilled: usize,
    /// Bytes written, compressed.
    pub spilled_bytes: u64,
    /// Values read back.
    pub loads: usize,
    /// The store refused a value and spilling stopped ([`Spill::failure`] says why).
    pub failed: bool,
}

impl Spill {
    /// Spilling goes to `store` from now on (values made before attach spill there too). A
    /// second store is refused.
    pub fn attach(&self, store: Arc<dyn SpillStore>) -> Result<()> {
        self.shared
            .store
            .set(store)
            .map_err(|_| Error::Spill("a store is already attached".into()))
    }

    /// Whether values spill: a store is attached and has not failed.
    pub fn enabled(&self) -> bool {
        self.shared.store.get().is_some() && self.shared.failure.get().is_none()
    }

    /// Why the store refused a value, once it has: from then on nothing more is spilled (what
    /// is spilled already is still read back), so a full or broken store costs memory, never
    /// data.
    pub fn failure(&self) -> Option<&str> {
        self.shared.failure.get().map(String::as_str)
    }

    /// Figures so far.
    pub fn figures(&self) -> SpillFigures {
        SpillFigures {
            spilled: self.shared.spilled.load(Ordering::Relaxed),
            spilled_bytes: self.shared.spilled_bytes.load(Ordering::Relaxed),
            loads: self.shared.loads.load(Ordering::Relaxed),
            failed: self.shared.failure.get().is_some(),
        }
    }
}

/// A value that can be spilled: written to bytes and read back equal.
pub trait Spillable: Send + Sync + Sized + 'static {
    fn encode(&self, out: &mut Writer);
    fn decode(input: &mut Reader<'_>) -> Result<Self>;
    /// Bytes the value holds in memory.
    fn heap_bytes(&self) -> usize;
}

/// A value held in memory, or spilled to its session's store and read back on each use.
pub struct Stored<T> {
    spill: Spill,
    key: String,
    held: Mutex<Option<Arc<T>>>,
}

impl<T> fmt::Debug for Stored<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Stored")
            .field("key", &self.key)
            .field("held", &self.is_held())
            .finish()
    }
}

impl<T: Spillable> Stored<T> {
    /// `value`, held until [`Stored::spill`].
    pub fn new(spill: &Spill, value: Arc<T>) -> Arc<Self> {
        let n = spill.shared.next_key.fetch_add(1, Ordering::Relaxed);
        Arc::new(Self {
            spill: spill.clone(),
            key: format!("{n:08}"),
            held: Mutex::new(Some(value)),
        })
    }

    /// Another value of the same session (a keyframe's refined depth beside its image).
    pub fn sibling<U: Spillable>(&self, value: Arc<U>) -> Arc<Stored<U>> {
        Stored::new(&self.spill, value)
    }

    /// The value: the held one, or read back from the store.
    pub fn get(&self) -> Result<Arc<T>> {
        if let Some(value) = self.lock().as_ref() {
            return Ok(Arc::clone(value));
        }
        let store = self.store()?;
        let bytes = store.get(&self.key).map_err(Error::Spill)?;
        let raw = lz4_flex::decompress_size_prepended(&bytes)
            .map_err(|e| Error::Spill(format!("{}: {e}", self.key)))?;
        let mut reader = Reader::new(&raw);
        let value = T::decode(&mut reader)?;
        reader.finish()?;
        self.spill.shared.loads.fetch_add(1, Ordering::Relaxed);
        Ok(Arc::new(value))
    }

    /// Writes the value to the store and drops it from memory; nothing happens without a store,
    /// after the store failed once, or when the value is spilled already. The first failure is
    /// returned and stops all spilling of the session ([`Spill::failure`]).
    pub fn spill(&self) -> Result<()> {
        let shared = &self.spill.shared;
        let Some(store) = shared.store.get() else {
            return Ok(());
        };
        if shared.failure.get().is_some() {
            return Ok(());
        }
        let mut held = self.lock();
        let Some(value) = held.as_ref() else {
            return Ok(());
        };
        let mut writer = Writer::default();
        value.encode(&mut writer);
        let bytes = lz4_flex::compress_prepend_size(&writer.bytes);
        if let Err(e) = store.put(&self.key, &bytes) {
            let _ = shared.failure.set(e.clone());
            return Err(Error::Spill(e));
        }
        *held = None;
        shared.spilled.fetch_add(1, Ordering::Relaxed);
        shared
            .spilled_bytes
            .fetch_add(bytes.len() as u64, Ordering::Relaxed);
        Ok(())
    }

    /// Bytes held in memory (0 once spilled).
    pub fn held_bytes(&self) -> usize {
        self.lock().as_ref().map_or(0, |v| v.heap_bytes())
    }

    fn store(&self) -> Result<&Arc<dyn SpillStore>> {
        self.spill.shared.store.get().ok_or_else(|| {
            Error::Spill(format!("{} is spilled but no store is attached", self.key))
        })
    }
}

impl<T> Drop for Stored<T> {
    /// A spilled value nobody holds any more leaves the store too.
    fn drop(&mut self) {
        let spilled = self.lock().is_none();
        if let (true, Some(store)) = (spilled, self.spill.shared.store.get())
            && let Err(e) = store.remove(&self.key)
        {
            tracing::debug!(key = %self.key, error = %e, "a dropped spilled value stays in the store");
        }
    }
}

impl<T> Stored<T> {
    /// The value when it is held (not spilled).
    pub fn held(&self) -> Option<Arc<T>> {
        self.lock().clone()
    }

    /// Whether the value is in memory.
    pub fn is_held(&self) -> bool {
        self.lock().is_some()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Option<Arc<T>>> {
        // A panic while holding the lock leaves the value as it was: use it.
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Little-endian encoding of spilled values.
#[derive(Debug, Default)]
pub struct Writer {
    bytes: Vec<u8>,
}

impl Writer {
    pub fn u8(&mut self, v: u8) {
        self.bytes.push(v);
    }
    pub fn u64(&mut self, v: u64) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f64(&mut self, v: f64) {
        self.u64(v.to_bits());
    }
    /// A length-prefixed byte slice.
    pub fn bytes(&mut self, v: &[u8]) {
        self.u64(v.len() as u64);
        self.bytes.extend_from_slice(v);
    }
    /// A length-prefixed slice of `f32` (bit patterns kept).
    pub fn f32s(&mut self, v: &[f32]) {
        self.bytes(bytemuck::cast_slice(v));
    }
    pub fn u32s(&mut self, v: &[u32]) {
        self.bytes(bytemuck::cast_slice(v));
    }
    pub fn str(&mut self, v: &str) {
        self.bytes(v.as_bytes());
    }
    /// A pinhole camera with its distortion, if any.
    pub fn camera(&mut self, c: &PinholeCamera) {
        for v in [c.fx, c.fy, c.cx, c.cy] {
            self.f64(v);
        }
        self.u64(u64::from(c.width));
        self.u64(u64::from(c.height));
        match &c.distortion {
            Some(d) => {
                self.u8(1);
                for v in [d.k1, d.k2, d.p1, d.p2, d.k3] {
                    self.f64(v);
                }
            }
            None => self.u8(0),
        }
    }
    /// A similarity (quaternion, translation, scale; bit patterns kept).
    pub fn sim3(&mut self, p: &Sim3) {
        let q = p.rotation.quaternion();
        for v in [q.w, q.i, q.j, q.k] {
            self.f64(v);
        }
        for v in p.translation.iter() {
            self.f64(*v);
        }
        self.f64(p.scale);
    }
    pub fn image(&mut self, image: &ImageF32) {
        self.u64(image.width as u64);
        self.u64(image.height as u64);
        self.f32s(&image.data);
    }
    pub fn opt_image(&mut self, image: Option<&ImageF32>) {
        match image {
            Some(image) => {
                self.u8(1);
                self.image(image);
            }
            None => self.u8(0),
        }
    }
}

/// Reads what a [`Writer`] wrote; any shortfall or excess is an error, never a panic.
#[derive(Debug)]
pub struct Reader<'a> {
    rest: &'a [u8],
}

impl<'a> Reader<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        Self { rest: bytes }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if self.rest.len() < n {
            return Err(Error::Spill("a spilled value is truncated".into()));
        }
        let (head, rest) = self.rest.split_at(n);
        self.rest = rest;
        Ok(head)
    }

    pub fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    pub fn u64(&mut self) -> Result<u64> {
        let mut b = [0u8; 8];
        b.copy_from_slice(self.take(8)?);
        Ok(u64::from_le_bytes(b))
    }
    pub fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_bits(self.u64()?))
    }
    pub fn usize(&mut self) -> Result<usize> {
        usize::try_from(self.u64()?).map_err(|_| Error::Spill("a length does not fit".into()))
    }
    pub fn bytes(&mut self) -> Result<&'a [u8]> {
        let n = self.usize()?;
        self.take(n)
    }
    pub fn f32s(&mut self) -> Result<Vec<f32>> {
        let raw = self.bytes()?;
        if raw.len() % 4 != 0 {
            return Err(Error::Spill("a float array has a partial element".into()));
        }
        Ok(raw
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }
    pub fn u32s(&mut self) -> Result<Vec<u32>> {
        Ok(self.f32s()?.into_iter().map(f32::to_bits).collect())
    }
    pub fn string(&mut self) -> Result<String> {
        String::from_utf8(self.bytes()?.to_vec())
            .map_err(|_| Error::Spill("a spilled text is not UTF-8".into()))
    }
    /// A camera, through [`PinholeCamera`]'s own checks: a damaged object is an error, not a
    /// bad camera.
    pub fn camera(&mut self) -> Result<PinholeCamera> {
        let (fx, fy, cx, cy) = (self.f64()?, self.f64()?, self.f64()?, self.f64()?);
        let dim = |v: u64| u32::try_from(v).map_err(|_| Error::Spill("a size does not fit".into()));
        let (width, height) = (dim(self.u64()?)?, dim(self.u64()?)?);
        let camera = PinholeCamera::new(fx, fy, cx, cy, width, height)?;
        Ok(match self.u8()? {
            0 => camera,
            _ => camera.with_distortion(Distortion {
                k1: self.f64()?,
                k2: self.f64()?,
                p1: self.f64()?,
                p2: self.f64()?,
                k3: self.f64()?,
            })?,
        })
    }
    pub fn sim3(&mut self) -> Result<Sim3> {
        let (w, i, j, k) = (self.f64()?, self.f64()?, self.f64()?, self.f64()?);
        let t = Vector3::new(self.f64()?, self.f64()?, self.f64()?);
        let scale = self.f64()?;
        let q = UnitQuaternion::new_unchecked(Quaternion::new(w, i, j, k));
        Ok(Sim3::new(SO3::from_quaternion(q), t, scale))
    }
    pub fn image(&mut self) -> Result<ImageF32> {
        let (width, height) = (self.usize()?, self.usize()?);
        let data = self.f32s()?;
        if width.checked_mul(height) != Some(data.len()) {
            return Err(Error::Spill("a spilled image has the wrong size".into()));
        }
        Ok(ImageF32 {
            width,
            height,
            data,
        })
    }
    pub fn opt_image(&mut self) -> Result<Option<ImageF32>> {
        match self.u8()? {
            0 => Ok(None),
            _ => self.image().map(Some),
        }
    }
    /// Everything was read.
    pub fn finish(&self) -> Result<()> {
        if self.rest.is_empty() {
            Ok(())
        } else {
            Err(Error::Spill("a spilled value has trailing bytes".into()))
        }
    }
}

/// `value` written and read back (tests of the [`Spillable`] implementations).
#[cfg(test)]
pub(crate) fn round_trip<T: Spillable>(value: &T) -> Result<T> {
    let mut writer = Writer::default();
    value.encode(&mut writer);
    let mut reader = Reader::new(&writer.bytes);
    let back = T::decode(&mut reader)?;
    reader.finish()?;
    // A truncated value is refused.
    let short = &writer.bytes[..writer.bytes.len() - 1];
    assert!(T::decode(&mut Reader::new(short)).is_err());
    Ok(back)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq)]
    struct Pair(u64, Vec<f32>);

    impl Spillable for Pair {
        fn encode(&self, out: &mut Writer) {
            out.u64(self.0);
            out.f32s(&self.1);
        }
        fn decode(input: &mut Reader<'_>) -> Result<Self> {
            Ok(Pair(input.u64()?, input.f32s()?))
        }
        fn heap_bytes(&self) -> usize {
            4 * self.1.len()
        }
    }

    fn temp(tag: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("relfusion-spill-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn a_spilled_value_reads_back_equal_and_leaves_memory() {
        let dir = temp("roundtrip");
        let spill = Spill::default();
        let value = Pair(7, vec![1.5, f32::NAN, -0.0, f32::MIN_POSITIVE]);
        let stored = Stored::new(&spill, Arc::new(Pair(7, value.1.clone())));
        // Without a store nothing spills.
        stored.spill().expect("no store: no-op");
        assert!(stored.is_held());
        spill
            .attach(Arc::new(FolderStore::new(&dir).expect("dir")))
            .expect("attach");
        assert!(
            spill
                .attach(Arc::new(FolderStore::new(&dir).expect("dir")))
                .is_err()
        );
        stored.spill().expect("spill");
        assert!(!stored.is_held());
        stored.spill().expect("twice: no-op");
        let back = stored.get().expect("load");
        assert_eq!(back.0, 7);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back.1), bits(&value.1));
        let figures = spill.figures();
        assert_eq!((figures.spilled, figures.loads), (1, 1));
        assert!(figures.spilled_bytes > 0);
        // A damaged object is an error, not a panic or a wrong value.
        let path = std::fs::read_dir(&dir)
            .expect("dir")
            .next()
            .expect("a file")
            .expect("entry")
            .path();
        let mut bytes = std::fs::read(&path).expect("read");
        bytes.truncate(bytes.len() - 3);
        std::fs::write(&path, &bytes).expect("write");
        assert!(stored.get().is_err());
        // Dropping a spilled value removes its object.
        drop(stored);
        assert!(!path.exists());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A store that takes `room` values and then refuses, like a full disk or bucket.
    #[derive(Debug)]
    struct Full {
        room: usize,
        puts: AtomicUsize,
    }

    impl SpillStore for Full {
        fn put(&self, key: &str, _: &[u8]) -> std::result::Result<(), String> {
            let n = self.puts.fetch_add(1, Ordering::Relaxed);
            if n < self.room {
                Ok(())
            } else {
                Err(format!("{key}: no space left"))
            }
        }
        fn get(&self, key: &str) -> std::result::Result<Vec<u8>, String> {
            Err(format!("{key}: not kept"))
        }
        fn remove(&self, _: &str) -> std::result::Result<(), String> {
            Ok(())
        }
    }

    #[test]
    fn a_full_store_stops_spilling_and_keeps_values_in_memory() {
        let spill = Spill::default();
        let store = Arc::new(Full {
            room: 1,
            puts: AtomicUsize::new(0),
        });
        spill.attach(store.clone()).expect("attach");
        let values: Vec<_> = (0..4)
            .map(|i| Stored::new(&spill, Arc::new(Pair(i, vec![i as f32]))))
            .collect();
        values[0].spill().expect("room for one");
        let e = values[1].spill().expect_err("full");
        assert!(e.to_string().contains("no space left"), "{e}");
        assert!(spill.failure().is_some_and(|f| f.contains("no space")));
        assert!(!spill.enabled() && spill.figures().failed);
        // No further attempts: the rest stay in memory, readable.
        values[2].spill().expect("no-op after the failure");
        assert_eq!(store.puts.load(Ordering::Relaxed), 2);
        for v in &values[1..] {
            assert!(v.is_held());
            assert_eq!(v.get().expect("held").0, v.held().expect("held").0);
        }
        assert_eq!(spill.figures().spilled, 1);
    }

    #[test]
    fn readers_refuse_short_and_long_input() {
        let mut w = Writer::default();
        w.f32s(&[1.0, 2.0]);
        w.u8(3);
        let mut r = Reader::new(&w.bytes);
        assert_eq!(r.f32s().expect("floats"), vec![1.0, 2.0]);
        assert!(r.finish().is_err());
        assert_eq!(r.u8().expect("byte"), 3);
        r.finish().expect("all read");
        assert!(r.u64().is_err());
        let mut huge = Writer::default();
        huge.u64(u64::MAX);
        assert!(Reader::new(&huge.bytes).bytes().is_err());
    }
}
