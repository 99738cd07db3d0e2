//! Saved maps (issue 24, item 3): a finished session's map kept beyond the session, owned by
//! the token that saved it, listed, described, deleted, and started from by new sessions.
//!
//! Keys: `maps/<id>/meta.json` (who owns it, where it came from, its camera) and
//! `maps/<id>/map/` (the map in the format of `docs/map-format.md`), through the object-store
//! interface ([`crate::folders`]). A map is copied there from the session's `results/map/` by
//! reading it whole (every part checked) and writing it again; its metadata is written last and
//! removed first, so a map without metadata is never listed and a crash in between leaves at
//! worst an unlisted folder.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use relfusion_proto::http::{MapInfo, MapStart};
use relfusion_slam::geometry::PinholeCamera;
use serde::{Deserialize, Serialize};

use crate::ApiError;
use crate::auth::Owner;
use crate::convert::camera_json;
use crate::storage::ObjectStore;

/// Version of `meta.json`.
const META_VERSION: u32 = 1;
/// Longest map name.
pub const MAX_NAME_CHARS: usize = 128;

/// A map's metadata as stored.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct MapMeta {
    version: u32,
    id: String,
    owner: Owner,
    name: Option<String>,
    session: String,
    created_unix: u64,
    keyframes: u64,
    #[serde(with = "crate::convert::camera_as_json")]
    camera: PinholeCamera,
    bytes: u64,
    format_version: u32,
    /// The map's unit is the metre (absent in metadata written before map format 2).
    #[serde(default)]
    metric: bool,
}

impl MapMeta {
    fn info(&self) -> MapInfo {
        MapInfo {
            id: self.id.clone(),
            name: self.name.clone(),
            session: self.session.clone(),
            created_unix: self.created_unix,
            keyframes: self.keyframes,
            camera: camera_json(&self.camera),
            bytes: self.bytes,
            format_version: self.format_version,
            scale: relfusion_slam::pipeline::scale_name(self.metric).into(),
        }
    }
}

/// A map a session may start from.
#[derive(Clone, Debug)]
pub struct MapSource {
    pub camera: PinholeCamera,
}

/// Key prefix of map `id`'s files.
pub fn map_prefix(id: &str) -> String {
    format!("maps/{id}/map")
}

/// The saved maps of every owner.
#[derive(Debug)]
pub struct MapStore {
    store: Arc<dyn ObjectStore>,
    /// Maps one owner may keep (`quotas.max_maps`).
    max_per_owner: usize,
    /// Saves in progress per owner: counted with the stored maps under one lock, so that
    /// concurrent saves cannot all pass the quota check (issue 34, item 8).
    saving: Mutex<HashMap<Owner, usize>>,
}

/// One save's place under its owner's quota, given back when dropped (the saved map, if any,
/// is listed by then).
struct QuotaPlace<'a> {
    maps: &'a MapStore,
    owner: Owner,
}

impl Drop for QuotaPlace<'_> {
    fn drop(&mut self) {
        let mut saving = self.maps.saving.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = saving.get_mut(&self.owner) {
            *n -= 1;
            if *n == 0 {
                saving.remove(&self.owner);
            }
        }
    }
}

fn meta_key(id: &str) -> String {
    format!("maps/{id}/meta.json")
}

fn new_id() -> String {
    format!("m-{:024x}", rand::random::<u128>() & ((1u128 << 96) - 1))
}

/// `m-` and 24 lowercase hex digits: checked before an id goes anywhere near a path.
fn is_map_id(id: &str) -> bool {
    id.len() == 26
        && id.starts_with("m-")
        && id[2..]
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

fn not_found(id: &str) -> ApiError {
    ApiError::not_found(format!("no map {id:?}; GET /v1/maps lists yours"))
}

impl MapStore {
    pub fn new(store: Arc<dyn ObjectStore>, max_per_owner: usize) -> Self {
        Self {
            store,
            max_per_owner,
            saving: Mutex::new(HashMap::new()),
        }
    }

    /// Checks and reserves one map of `owner`'s quota at once (429 when it is used up).
    fn reserve(&self, owner: &Owner) -> Result<QuotaPlace<'_>, ApiError> {
        let mut saving = self.saving.lock().unwrap_or_else(|e| e.into_inner());
        let in_progress = saving.get(owner).copied().unwrap_or(0);
        let held = self.list(owner)?.len() + in_progress;
        if held >= self.max_per_owner {
            return Err(ApiError::quota(format!(
                "this token keeps {held} maps (saved or being saved), the most quotas.max_maps \
                 allows: delete one first"
            )));
        }
        *saving.entry(owner.clone()).or_default() += 1;
        Ok(QuotaPlace {
            maps: self,
            owner: owner.clone(),
        })
    }

    fn read_meta(&self, id: &str) -> Result<Option<MapMeta>, ApiError> {
        let Some(bytes) = self
            .store
            .get(&meta_key(id))
            .map_err(|e| ApiError::internal(e.to_string()))?
        else {
            return Ok(None);
        };
        serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| ApiError::internal(format!("{}: {e}", meta_key(id))))
    }

    /// The caller's map `id`; 404 for a malformed id, a missing map or another owner's.
    fn owned(&self, id: &str, owner: &Owner) -> Result<MapMeta, ApiError> {
        if !is_map_id(id) {
            return Err(not_found(id));
        }
        match self.read_meta(id)? {
            Some(meta) if meta.owner == *owner => Ok(meta),
            _ => Err(not_found(id)),
        }
    }

    /// Every map of `owner`, oldest first.
    pub fn list(&self, owner: &Owner) -> Result<Vec<MapInfo>, ApiError> {
        let keys = self
            .store
            .list("maps/")
            .map_err(|e| ApiError::internal(e.to_string()))?;
        let mut maps: Vec<MapMeta> = keys
            .iter()
            .filter_map(|k| k.strip_prefix("maps/")?.strip_suffix("/meta.json"))
            .filter(|id| is_map_id(id))
            .filter_map(|id| self.read_meta(id).ok().flatten())
            .filter(|m| m.owner == *owner)
            .collect();
        maps.sort_by(|a, b| (a.created_unix, &a.id).cmp(&(b.created_unix, &b.id)));
        Ok(maps.iter().map(MapMeta::info).collect())
    }

    /// The caller's map `id`.
    pub fn get(&self, id: &str, owner: &Owner) -> Result<MapInfo, ApiError> {
        Ok(self.owned(id, owner)?.info())
    }

    /// Where a session of `owner` starting from `start` finds the map (404 when not theirs).
    pub fn source(&self, start: &MapStart, owner: &Owner) -> Result<MapSource, ApiError> {
        let meta = self.owned(&start.id, owner)?;
        Ok(MapSource {
            camera: meta.camera,
        })
    }

    /// Keeps the map of finished session `session` (its `results/map/`) as a new map of
    /// `owner`. Blocking (reads and writes the whole map): call it off the async runtime.
    pub fn save(
        &self,
        owner: &Owner,
        session: &str,
        name: Option<String>,
    ) -> Result<MapInfo, ApiError> {
        if let Some(name) = &name
            && (name.chars().count() > MAX_NAME_CHARS || name.chars().any(char::is_control))
        {
            return Err(ApiError::bad_request(format!(
                "name: at most {MAX_NAME_CHARS} characters, no control characters"
            )));
        }
        let _place = self.reserve(owner)?;
        let source = crate::folders::fetch(
            self.store.as_ref(),
            &crate::storage::result_key(session, "map"),
        )
        .map_err(|e| ApiError::internal(format!("reading session {session}'s map: {e}")))?;
        let map = relfusion_slam::map::read_map(source.path(), None)
            .map_err(|e| ApiError::conflict(format!("session {session} has no usable map: {e}")))?;
        let id = new_id();
        let bytes = crate::folders::store(self.store.as_ref(), &map_prefix(&id), |dir| {
            relfusion_slam::map::write_map(dir, &map).map_err(|e| e.to_string())
        })
        .map_err(|e| {
            let _ = self.store.delete_prefix(&format!("maps/{id}/"));
            ApiError::internal(format!("writing the map: {e}"))
        })?;
        let meta = MapMeta {
            version: META_VERSION,
            id: id.clone(),
            owner: owner.clone(),
            name,
            session: session.to_string(),
            created_unix: crate::storage::now_unix(),
            keyframes: map.keyframes.len() as u64,
            camera: map.camera,
            bytes,
            format_version: relfusion_slam::map::FORMAT_VERSION,
            metric: map.metric,
        };
        let bytes = serde_json::to_vec_pretty(&meta).unwrap_or_default();
        if let Err(e) = self.store.put(&meta_key(&id), &bytes) {
            let _ = self.store.delete_prefix(&format!("maps/{id}/"));
            return Err(ApiError::internal(e.to_string()));
        }
        Ok(meta.info())
    }

    /// Deletes the caller's map `id` (its metadata first: it is gone from listings at once).
    pub fn delete(&self, id: &str, owner: &Owner) -> Result<(), ApiError> {
        self.owned(id, owner)?;
        self.store
            .delete_prefix(&meta_key(id))
            .and_then(|()| self.store.delete_prefix(&format!("maps/{id}/")))
            .map_err(|e| ApiError::internal(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_ids_are_checked_before_use() {
        assert!(is_map_id(&new_id()));
        for bad in [
            "",
            "m-",
            "m-../../etc/passwd",
            "s-0123456789abcdef01234567",
            "m-0123456789ABCDEF01234567",
        ] {
            assert!(!is_map_id(bad), "{bad}");
        }
    }
}
