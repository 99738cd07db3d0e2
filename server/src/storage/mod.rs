//! Durable storage of uploads, session metadata, results and saved maps behind a small
//! object-store interface: the local filesystem by default ([`FsStore`]), or an S3-compatible
//! bucket shared by the nodes of a cluster ([`s3::S3Store`], `[storage] backend = "s3"`).
//!
//! Keys are `/`-separated relative paths (`sessions/<id>/meta.json`). Layout:
//! `sessions/<id>/meta.json`, `sessions/<id>/upload/…` (the extracted dataset),
//! `sessions/<id>/results/{trajectory.txt,keyframes.txt,pointcloud.ply,summary.json}`.
//!
//! Durability contract: when [`ObjectStore::put`] returns, the object survives a `kill -9` or
//! a power cut, and a reader never sees a half-written object (write to a temporary file,
//! fsync it, rename over the key, fsync the folder; S3 PUTs are atomic and durable).

pub mod s3;

use std::fs::File;
use std::io::Write;
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A storage failure (the disk, not the request).
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("invalid storage key {0:?}")]
    BadKey(String),
    #[error("object storage: {0}")]
    Remote(String),
    #[error("storage {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Where sessions keep their data.
pub trait ObjectStore: Send + Sync + std::fmt::Debug {
    /// Stores `bytes` under `key` atomically and durably (see the module docs).
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError>;
    /// The object, or `None` when there is none.
    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError>;
    /// Every key that starts with `prefix`, sorted.
    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError>;
    /// Removes every object under `prefix` (a folder-like prefix ending in `/`).
    fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError>;
    /// A local path for `key` when the store is a filesystem (the pipeline reads uploaded
    /// images straight from it); `None` for remote stores.
    fn local_path(&self, key: &str) -> Option<PathBuf>;
    /// Whether other nodes see the same objects (a cluster's bucket): then a node may take
    /// over another's sessions.
    fn shared(&self) -> bool {
        false
    }
}

/// The store `config` names: files below `data_dir`, or the S3 bucket of `[storage.s3]`.
pub fn open(config: &crate::config::Config) -> Result<std::sync::Arc<dyn ObjectStore>, StoreError> {
    use crate::config::StorageBackend;
    Ok(match config.storage.backend {
        StorageBackend::Fs => std::sync::Arc::new(FsStore::open(&config.data_dir)?),
        StorageBackend::S3 => std::sync::Arc::new(s3::S3Store::open(&config.storage.s3)?),
    })
}

/// Refuses keys that are empty or would leave the store's root (`..`, absolute, `.`).
pub(crate) fn check_key(key: &str) -> Result<(), StoreError> {
    let ok = !key.is_empty()
        && !key.contains('\\')
        && Path::new(key)
            .components()
            .all(|c| matches!(c, Component::Normal(_)));
    if ok {
        Ok(())
    } else {
        Err(StoreError::BadKey(key.to_string()))
    }
}

/// The local-filesystem store rooted at the data directory.
#[derive(Debug)]
pub struct FsStore {
    root: PathBuf,
}

/// Names temporary files uniquely within the process (several threads may put the same key).
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

impl FsStore {
    /// A store rooted at `root` (created if missing).
    pub fn open(root: &Path) -> Result<Self, StoreError> {
        std::fs::create_dir_all(root).map_err(io(root))?;
        Ok(Self {
            root: root.to_path_buf(),
        })
    }

    /// The root folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The path of `key`, refusing keys that would leave the root.
    fn path(&self, key: &str) -> Result<PathBuf, StoreError> {
        check_key(key)?;
        Ok(self.root.join(key))
    }
}

/// fsyncs a folder so that renames and new entries in it are durable.
pub fn sync_dir(dir: &Path) -> Result<(), StoreError> {
    File::open(dir).and_then(|f| f.sync_all()).map_err(io(dir))
}

/// Creates `dir` and its missing parents, fsyncing the parent of each folder it creates, so
/// that a new session folder (and what is renamed into it) survives a power cut.
pub fn create_dirs_durably(dir: &Path) -> Result<(), StoreError> {
    if dir.is_dir() {
        return Ok(());
    }
    if let Some(parent) = dir.parent()
        && !parent.as_os_str().is_empty()
    {
        create_dirs_durably(parent)?;
    }
    match std::fs::create_dir(dir) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => return Ok(()),
        Err(e) => return Err(io(dir)(e)),
    }
    match dir.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => sync_dir(parent),
        _ => Ok(()),
    }
}

impl ObjectStore for FsStore {
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError> {
        let path = self.path(key)?;
        let dir = path.parent().unwrap_or(&self.root).to_path_buf();
        create_dirs_durably(&dir)?;
        let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
        let tmp = dir.join(format!(".tmp-{}-{n}", std::process::id()));
        let write = || -> std::io::Result<()> {
            let mut f = File::create(&tmp)?;
            f.write_all(bytes)?;
            f.sync_all()
        };
        if let Err(e) = write() {
            let _ = std::fs::remove_file(&tmp);
            return Err(io(&tmp)(e));
        }
        std::fs::rename(&tmp, &path).map_err(io(&path))?;
        sync_dir(&dir)
    }

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let path = self.path(key)?;
        match std::fs::read(&path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(io(&path)(e)),
        }
    }

    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        // Walk the deepest folder the prefix names fully, then filter by the whole prefix.
        let folder = match prefix.rfind('/') {
            Some(i) => &prefix[..i],
            None => "",
        };
        let start = if folder.is_empty() {
            self.root.clone()
        } else {
            self.path(folder)?
        };
        let mut keys = Vec::new();
        let mut stack = vec![start];
        while let Some(dir) = stack.pop() {
            let entries = match std::fs::read_dir(&dir) {
                Ok(entries) => entries,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(io(&dir)(e)),
            };
            for entry in entries {
                let entry = entry.map_err(io(&dir))?;
                let path = entry.path();
                let kind = entry.file_type().map_err(io(&path))?;
                if kind.is_dir() {
                    stack.push(path);
                } else if kind.is_file() {
                    let Ok(rel) = path.strip_prefix(&self.root) else {
                        continue;
                    };
                    let key = rel
                        .components()
                        .map(|c| c.as_os_str().to_string_lossy())
                        .collect::<Vec<_>>()
                        .join("/");
                    let temp = path
                        .file_name()
                        .is_some_and(|n| n.to_string_lossy().starts_with(".tmp-"));
                    if key.starts_with(prefix) && !temp {
                        keys.push(key);
                    }
                }
            }
        }
        keys.sort();
        Ok(keys)
    }

    fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError> {
        let trimmed = prefix.trim_end_matches('/');
        let path = self.path(trimmed)?;
        let result = if prefix.ends_with('/') || path.is_dir() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        match result {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(io(&path)(e)),
        }
        if let Some(parent) = path.parent() {
            sync_dir(parent)?;
        }
        Ok(())
    }

    fn local_path(&self, key: &str) -> Option<PathBuf> {
        if key.is_empty() {
            return Some(self.root.clone());
        }
        self.path(key).ok()
    }
}

/// The key of a session's result `name` (`sessions/<id>/results/<name>`).
pub fn result_key(id: &str, name: &str) -> String {
    format!("sessions/{id}/results/{name}")
}

/// Seconds since the epoch: the clock of stored metadata (creation and end times).
pub fn now_unix() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_store(tag: &str) -> (FsStore, PathBuf) {
        let dir =
            std::env::temp_dir().join(format!("relfusion-store-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        (FsStore::open(&dir).expect("open"), dir)
    }

    #[test]
    fn put_get_list_delete() {
        let (store, dir) = temp_store("basic");
        store.put("sessions/a/meta.json", b"{}").expect("put");
        store.put("sessions/a/results/t.txt", b"x").expect("put");
        store.put("sessions/b/meta.json", b"[]").expect("put");
        assert_eq!(
            store.get("sessions/a/meta.json").expect("get").as_deref(),
            Some(&b"{}"[..])
        );
        assert_eq!(store.get("sessions/zz/meta.json").expect("get"), None);
        assert_eq!(
            store.list("sessions/a/").expect("list"),
            vec!["sessions/a/meta.json", "sessions/a/results/t.txt"]
        );
        assert_eq!(store.list("sessions/").expect("list").len(), 3);
        store.delete_prefix("sessions/a/").expect("delete");
        assert_eq!(
            store.list("sessions/").expect("list"),
            vec!["sessions/b/meta.json"]
        );
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn keys_cannot_escape_the_root() {
        let (store, dir) = temp_store("escape");
        assert!(store.put("../evil", b"x").is_err());
        assert!(store.put("/etc/evil", b"x").is_err());
        assert!(store.put("a/../../evil", b"x").is_err());
        assert!(store.get("").is_err());
        let _ = std::fs::remove_dir_all(dir);
    }

    #[test]
    fn put_replaces_atomically_and_leaves_no_temp_files() {
        let (store, dir) = temp_store("atomic");
        store.put("k/v", &vec![1u8; 1 << 20]).expect("put");
        // Readers racing with a writer see the old or the new object, never a mix.
        std::thread::scope(|s| {
            s.spawn(|| {
                for i in 0..20u8 {
                    store.put("k/v", &vec![i; 1 << 20]).expect("put");
                }
            });
            for _ in 0..200 {
                let v = store.get("k/v").expect("get").expect("present");
                assert_eq!(v.len(), 1 << 20);
                assert!(v.iter().all(|&b| b == v[0]), "torn read");
            }
        });
        let names: Vec<_> = std::fs::read_dir(dir.join("k"))
            .expect("read dir")
            .map(|e| e.expect("entry").file_name())
            .collect();
        assert_eq!(names.len(), 1, "temporary files left: {names:?}");
        let _ = std::fs::remove_dir_all(dir);
    }
}
