//! What a session keeps in the store, and under which keys.
//!
//! `sessions/<id>/meta.json` ([`SessionMeta`]) is written when a session is acknowledged and
//! on every state change, atomically; its presence is what makes a session exist after a
//! restart (a folder without it is an unacknowledged upload and is removed).
//! `sessions/<id>/results/` holds the trajectory, keyframes, point cloud and a summary,
//! written on finish and every few keyframes while running.

use relfusion_proto::http::MapStart;
use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::pipeline::Config as SlamConfig;
use serde::{Deserialize, Serialize};

use super::types::{
    FramePolicy, Owner, Progress, SessionInfo, SessionKind, SessionState, camera_json, dense_mode,
};
use crate::storage::{ObjectStore, StoreError};

/// Format version of `meta.json`.
pub const META_VERSION: u32 = 1;

/// Key of a session's folder (with the trailing `/`).
pub fn session_prefix(id: &str) -> String {
    format!("sessions/{id}/")
}

/// Key of a session's metadata.
pub fn meta_key(id: &str) -> String {
    format!("sessions/{id}/meta.json")
}

pub use crate::storage::result_key;

/// Key of an upload's extracted archive.
pub fn upload_key(id: &str) -> String {
    format!("sessions/{id}/upload")
}

/// Running counters of a session (part of its info and of its metadata).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CounterSnapshot {
    pub received: u64,
    pub processed: u64,
    pub dropped: u64,
    pub lost: u64,
    pub keyframes: u64,
    /// Keyframes the dense layer finished.
    #[serde(default)]
    pub densified: u64,
    /// Revision of the last mesh update, and the mesh's triangles then.
    #[serde(default)]
    pub mesh_revision: u64,
    #[serde(default)]
    pub mesh_triangles: u64,
}

/// Everything needed to show a session after a restart, and to re-run an upload exactly.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SessionMeta {
    pub version: u32,
    pub id: String,
    pub owner: Owner,
    pub kind: SessionKind,
    pub state: SessionState,
    /// The resolved camera (for uploads: from the request, calibration.txt or a preset),
    /// stored in the API's camera JSON layout and checked again when read.
    #[serde(with = "super::types::camera_as_json")]
    pub camera: PinholeCamera,
    /// The resolved pipeline configuration; a re-run uses exactly this.
    pub config: SlamConfig,
    pub model: String,
    pub policy: FramePolicy,
    pub created_unix: u64,
    #[serde(default)]
    pub error: Option<String>,
    /// Uploads: the dataset folder's key below the session (`upload` or `upload/<folder>`).
    #[serde(default)]
    pub dataset: Option<String>,
    /// Uploads: frames in the dataset.
    #[serde(default)]
    pub total_frames: Option<u64>,
    #[serde(default)]
    pub counters: CounterSnapshot,
    /// When it finished or failed (seconds since the epoch); retention counts from here.
    #[serde(default)]
    pub ended_unix: Option<u64>,
    /// Why it ended, or what it waits for (`SessionInfo::notice`).
    #[serde(default)]
    pub notice: Option<String>,
    /// Bytes of its extracted upload and of its results on disk (owner quotas).
    #[serde(default)]
    pub upload_bytes: u64,
    #[serde(default)]
    pub results_bytes: u64,
    /// The saved map it started from (`None`: an empty one).
    #[serde(default)]
    pub map: Option<MapStart>,
    /// The node that runs it (`[zenoh] node`): with a shared store, a node recovers only its
    /// own sessions at start, and takes over those of a node that left (cluster failover).
    #[serde(default)]
    pub node: Option<String>,
    /// The unit of its map (`SessionInfo::scale`), once its pipeline has started.
    #[serde(default)]
    pub scale: Option<String>,
}

impl SessionMeta {
    /// Writes it (atomically, durably).
    pub fn save(&self, store: &dyn ObjectStore) -> Result<(), StoreError> {
        let bytes = serde_json::to_vec_pretty(self).unwrap_or_default();
        store.put(&meta_key(&self.id), &bytes)
    }

    /// Reads the metadata of session `id`; `Ok(None)` when absent, an error text when
    /// unreadable.
    pub fn load(store: &dyn ObjectStore, id: &str) -> Result<Option<Self>, String> {
        let Some(bytes) = store.get(&meta_key(id)).map_err(|e| e.to_string())? else {
            return Ok(None);
        };
        serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| format!("{}: {e}", meta_key(id)))
    }

    /// The info of a session known only from its metadata.
    pub fn info(&self) -> SessionInfo {
        SessionInfo {
            id: self.id.clone(),
            kind: self.kind,
            state: self.state,
            frames_received: self.counters.received,
            frames_processed: self.counters.processed,
            frames_dropped: self.counters.dropped,
            frames_lost: self.counters.lost,
            keyframes: self.counters.keyframes,
            keyframes_densified: self.counters.densified,
            mesh_revision: self.counters.mesh_revision,
            mesh_triangles: self.counters.mesh_triangles,
            dense_mode: dense_mode(&self.config, &self.model),
            progress: Progress {
                processed: self.counters.processed,
                total: self.total_frames,
            },
            created_unix: self.created_unix,
            camera: camera_json(&self.camera),
            model: self.model.clone(),
            error: self.error.clone(),
            notice: self.notice.clone(),
            max_keyframes: None,
            map: self.map.clone(),
            node: self.node.clone(),
            memory: None,
            scale: self.scale.clone(),
        }
    }
}

/// The result files of a session, as bytes.
#[derive(Clone, Debug, Default)]
pub struct Results {
    pub trajectory: String,
    pub keyframes: String,
    /// `None`: the stored point cloud is left as it is (a checkpoint that does not rebuild it).
    pub pointcloud: Option<Vec<u8>>,
    /// The fused mesh as PLY and GLB (absent until the first mesh update).
    pub mesh: Option<(Vec<u8>, Vec<u8>)>,
    pub summary: serde_json::Value,
}

impl Results {
    /// Writes every result file (each atomically); returns the bytes they take.
    pub fn save(&self, store: &dyn ObjectStore, id: &str) -> Result<u64, StoreError> {
        let summary = serde_json::to_vec_pretty(&self.summary).unwrap_or_default();
        let mut files: Vec<(&str, &[u8])> = vec![
            ("trajectory.txt", self.trajectory.as_bytes()),
            ("keyframes.txt", self.keyframes.as_bytes()),
        ];
        if let Some(ply) = &self.pointcloud {
            files.push(("pointcloud.ply", ply));
        }
        if let Some((ply, glb)) = &self.mesh {
            files.push(("mesh.ply", ply));
            files.push(("mesh.glb", glb));
        }
        files.push(("summary.json", &summary));
        let mut bytes = 0;
        for (name, data) in files {
            store.put(&result_key(id, name), data)?;
            bytes += data.len() as u64;
        }
        Ok(bytes)
    }
}
