//! A session's spilled keyframes in its store (issue 37): `sessions/<id>/spill/<n>/value`
//! (a folder per value, so that a superseded one is removed with `delete_prefix`), in the
//! same object store as its uploads and results (filesystem or S3), so they go with the
//! session when it is deleted or expires. They are a cache of the running pipeline: a session
//! that re-runs after a restart clears them first ([`SessionSpill::open`]).

use std::sync::Arc;

use relfusion_slam::spill::SpillStore;

use super::persist::session_prefix;
use crate::storage::{ObjectStore, StoreError};

/// Key prefix of a session's spilled keyframes (with the trailing `/`).
pub fn spill_prefix(id: &str) -> String {
    format!("{}spill/", session_prefix(id))
}

/// One session's spill area.
#[derive(Debug)]
pub(crate) struct SessionSpill {
    store: Arc<dyn ObjectStore>,
    prefix: String,
}

impl SessionSpill {
    /// The spill area of session `id`, emptied (what an earlier run of it left is stale).
    pub fn open(store: Arc<dyn ObjectStore>, id: &str) -> Result<Self, StoreError> {
        let prefix = spill_prefix(id);
        store.delete_prefix(&prefix)?;
        Ok(Self { store, prefix })
    }
}

impl SpillStore for SessionSpill {
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), String> {
        self.store
            .put(&format!("{}{key}/value", self.prefix), bytes)
            .map_err(|e| e.to_string())
    }

    fn get(&self, key: &str) -> Result<Vec<u8>, String> {
        match self.store.get(&format!("{}{key}/value", self.prefix)) {
            Ok(Some(bytes)) => Ok(bytes),
            Ok(None) => Err(format!("spilled keyframe data {key} is missing")),
            Err(e) => Err(e.to_string()),
        }
    }

    fn remove(&self, key: &str) -> Result<(), String> {
        self.store
            .delete_prefix(&format!("{}{key}/", self.prefix))
            .map_err(|e| e.to_string())
    }
}
