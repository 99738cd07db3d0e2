//! Folders of files (a saved map, `docs/map-format.md`) through the object-store interface:
//! the map reader and writer work on a local folder, the store on keys.
//!
//! A filesystem store lends its own folder ([`ObjectStore::local_path`]): nothing is copied. Any
//! other store is read into, or written from, a private temporary folder, one object per file
//! under the folder's key prefix. Relative names are checked both ways: a key that would leave
//! the temporary folder is refused, and only plain files are uploaded.

use std::path::{Component, Path, PathBuf};

use crate::storage::ObjectStore;

/// A folder of the store on local disk: the store's own, or a temporary copy removed on drop.
#[derive(Debug)]
pub struct LocalFolder {
    path: PathBuf,
    _temp: Option<tempfile::TempDir>,
}

impl LocalFolder {
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// The folder under `prefix` (no trailing `/`) on local disk.
pub fn fetch(store: &dyn ObjectStore, prefix: &str) -> Result<LocalFolder, String> {
    if let Some(path) = store.local_path(prefix) {
        return Ok(LocalFolder { path, _temp: None });
    }
    let temp = tempfile::tempdir().map_err(|e| format!("a temporary folder: {e}"))?;
    let root = temp.path().join("folder");
    let keys = store
        .list(&format!("{prefix}/"))
        .map_err(|e| e.to_string())?;
    for key in keys {
        let rel = key
            .strip_prefix(prefix)
            .and_then(|r| r.strip_prefix('/'))
            .filter(|r| plain_relative(r))
            .ok_or_else(|| format!("stored key {key:?} is not a file of {prefix}/"))?;
        let bytes = store
            .get(&key)
            .map_err(|e| e.to_string())?
            .ok_or_else(|| format!("{key} vanished while it was read"))?;
        let path = root.join(rel);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| format!("{}: {e}", parent.display()))?;
        }
        std::fs::write(&path, bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    }
    Ok(LocalFolder {
        path: root,
        _temp: Some(temp),
    })
}

/// Writes the folder under `prefix` with `write` (given a local folder to create); returns the
/// bytes stored.
pub fn store(
    store: &dyn ObjectStore,
    prefix: &str,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<u64, String> {
    if let Some(path) = store.local_path(prefix) {
        write(&path)?;
        return Ok(folder_bytes(&path));
    }
    let temp = tempfile::tempdir().map_err(|e| format!("a temporary folder: {e}"))?;
    let root = temp.path().join("folder");
    write(&root)?;
    let mut total = 0;
    for (rel, path) in files(&root)? {
        let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        store
            .put(&format!("{prefix}/{rel}"), &bytes)
            .map_err(|e| e.to_string())?;
        total += bytes.len() as u64;
    }
    Ok(total)
}

/// Bytes of the plain files under `dir` (0 when it cannot be read: the figure is for quotas).
pub fn folder_bytes(dir: &Path) -> u64 {
    files(dir).map_or(0, |files| {
        files
            .iter()
            .filter_map(|(_, p)| std::fs::metadata(p).ok())
            .map(|m| m.len())
            .sum()
    })
}

/// Every plain file under `dir` with its `/`-separated relative name, sorted.
fn files(dir: &Path) -> Result<Vec<(String, PathBuf)>, String> {
    let mut out = Vec::new();
    let mut stack = vec![(String::new(), dir.to_path_buf())];
    while let Some((prefix, folder)) = stack.pop() {
        let entries =
            std::fs::read_dir(&folder).map_err(|e| format!("{}: {e}", folder.display()))?;
        for entry in entries {
            let entry = entry.map_err(|e| format!("{}: {e}", folder.display()))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let rel = if prefix.is_empty() {
                name
            } else {
                format!("{prefix}/{name}")
            };
            let kind = entry
                .file_type()
                .map_err(|e| format!("{}: {e}", entry.path().display()))?;
            if kind.is_dir() {
                stack.push((rel, entry.path()));
            } else if kind.is_file() {
                out.push((rel, entry.path()));
            }
        }
    }
    out.sort();
    Ok(out)
}

/// A relative name of plain components only (no `..`, no root, not empty).
fn plain_relative(rel: &str) -> bool {
    !rel.is_empty()
        && Path::new(rel)
            .components()
            .all(|c| matches!(c, Component::Normal(_)))
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::sync::Mutex;

    use super::*;
    use crate::storage::StoreError;

    /// A store without local paths: what a remote (S3-like) store looks like to this module.
    #[derive(Debug, Default)]
    struct KeysOnly(Mutex<BTreeMap<String, Vec<u8>>>);

    impl ObjectStore for KeysOnly {
        fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError> {
            self.0
                .lock()
                .expect("lock")
                .insert(key.into(), bytes.to_vec());
            Ok(())
        }
        fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
            Ok(self.0.lock().expect("lock").get(key).cloned())
        }
        fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
            Ok(self
                .0
                .lock()
                .expect("lock")
                .keys()
                .filter(|k| k.starts_with(prefix))
                .cloned()
                .collect())
        }
        fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError> {
            self.0
                .lock()
                .expect("lock")
                .retain(|k, _| !k.starts_with(prefix));
            Ok(())
        }
        fn local_path(&self, _key: &str) -> Option<PathBuf> {
            None
        }
    }

    fn write_tree(dir: &Path) -> Result<(), String> {
        std::fs::create_dir_all(dir.join("keyframes/000001")).map_err(|e| e.to_string())?;
        std::fs::write(dir.join("manifest.json"), b"{}").map_err(|e| e.to_string())?;
        std::fs::write(dir.join("keyframes/000001/image.png"), [1u8, 2, 3])
            .map_err(|e| e.to_string())
    }

    #[test]
    fn a_folder_round_trips_through_a_store_without_local_paths() {
        let store = KeysOnly::default();
        let bytes = super::store(&store, "maps/m-1/map", write_tree).expect("store");
        assert_eq!(bytes, 5);
        assert_eq!(
            store.list("maps/").expect("list"),
            [
                "maps/m-1/map/keyframes/000001/image.png",
                "maps/m-1/map/manifest.json"
            ]
        );
        let local = fetch(&store, "maps/m-1/map").expect("fetch");
        assert_eq!(
            std::fs::read(local.path().join("keyframes/000001/image.png")).expect("read"),
            [1, 2, 3]
        );
        assert_eq!(folder_bytes(local.path()), 5);
        let temp = local.path().to_path_buf();
        drop(local);
        assert!(!temp.exists(), "the temporary copy is removed");
    }

    #[test]
    fn stored_keys_that_would_leave_the_folder_are_refused() {
        let store = KeysOnly::default();
        store.put("maps/m-1/map/../../evil", b"x").expect("put");
        let err = fetch(&store, "maps/m-1/map").expect_err("refused");
        assert!(err.contains("not a file"), "{err}");
    }
}
