//! What a session has produced so far, as its subscribers have it: the poses reported (the
//! live trajectory), the keyframes with their latest poses, and the fused mesh with every
//! `MeshUpdate` applied; and the result files served from it while the session runs (from the
//! store once it has ended).

use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::sync::{Mutex, MutexGuard};

use relfusion_slam::dataset::trajectory::{StampedPose, format_tum_trajectory, stamped_se3};
use relfusion_slam::export::{mesh_glb_bytes, mesh_ply_bytes};
use relfusion_slam::fusion::{BlockIndex, BlockMesh, Mesh, MeshDelta};
use relfusion_slam::geometry::Sim3;

use super::handle::Session;
use super::persist::result_key;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The poses reported so far (the live trajectory, before the final optimisation).
#[derive(Debug, Default)]
pub(crate) struct Track {
    /// Every processed frame: timestamp, pose at tracking time, lost.
    frames: Vec<(f64, Sim3, bool)>,
    /// Keyframe id → (timestamp, latest pose).
    keyframes: BTreeMap<u64, (f64, Sim3)>,
    /// The fused mesh as the subscribers have it: every delta applied.
    mesh: MeshState,
}

/// The session's fused mesh, block by block (what `MeshUpdate`s describe).
#[derive(Debug, Default)]
pub(crate) struct MeshState {
    pub blocks: BTreeMap<BlockIndex, BlockMesh>,
    pub revision: u64,
    pub block_size: f32,
}

impl MeshState {
    /// Replaces the changed blocks and drops the removed ones.
    pub(super) fn apply(&mut self, delta: &MeshDelta) {
        for b in &delta.removed {
            self.blocks.remove(b);
        }
        for m in &delta.changed {
            self.blocks.insert(m.index, m.clone());
        }
        self.revision = delta.revision;
        self.block_size = delta.block_size;
    }

    pub(super) fn triangles(&self) -> u64 {
        self.blocks
            .values()
            .map(|m| m.triangle_count() as u64)
            .sum()
    }
}

/// A session's poses: the stored file once it has ended (final, optimised), else the poses
/// reported so far as stamped SE(3) (the scale acts on the map, not on the camera centre).
#[derive(Clone, Debug)]
pub enum Poses {
    Stored(String),
    Live(Vec<StampedPose>),
}

impl Poses {
    /// The TUM text, exactly as `relfusion run` writes it.
    pub fn into_tum(self) -> String {
        match self {
            Poses::Stored(text) => text,
            Poses::Live(poses) => format_tum_trajectory(&poses),
        }
    }
}

impl Session {
    /// The trajectory: final (optimised) once finished, else the poses as tracked so far.
    pub fn trajectory(&self) -> Poses {
        if let Some(text) = self.stored_text("trajectory.txt") {
            return Poses::Stored(text);
        }
        let track = lock(&self.track);
        let poses: Vec<(f64, Sim3)> = track
            .frames
            .iter()
            .filter(|(_, _, lost)| !lost)
            .map(|(t, p, _)| (*t, *p))
            .collect();
        Poses::Live(stamped_se3(&poses))
    }

    /// The keyframe poses (final once finished).
    pub fn keyframes(&self) -> Poses {
        if let Some(text) = self.stored_text("keyframes.txt") {
            return Poses::Stored(text);
        }
        let track = lock(&self.track);
        let poses: Vec<(f64, Sim3)> = track.keyframes.values().copied().collect();
        Poses::Live(stamped_se3(&poses))
    }

    /// [`Session::trajectory`] in TUM format.
    pub fn trajectory_tum(&self) -> String {
        self.trajectory().into_tum()
    }

    /// [`Session::keyframes`] in TUM format.
    pub fn keyframes_tum(&self) -> String {
        self.keyframes().into_tum()
    }

    /// The semi-dense point cloud (PLY): final once finished, else the last checkpoint
    /// (an empty cloud before the first one).
    pub fn pointcloud_ply(&self) -> Vec<u8> {
        match self.store.get(&result_key(self.id(), "pointcloud.ply")) {
            Ok(Some(bytes)) => bytes,
            _ => crate::convert::points_ply(&[]),
        }
    }

    /// The fused mesh as PLY: the stored result once finished, the current mesh while
    /// running; `None` before the first mesh update.
    pub fn mesh_ply(&self) -> Option<Vec<u8>> {
        self.mesh_file("mesh.ply", mesh_ply_bytes)
    }

    /// The fused mesh as glTF binary (like [`Session::mesh_ply`]).
    pub fn mesh_glb(&self) -> Option<Vec<u8>> {
        self.mesh_file("mesh.glb", mesh_glb_bytes)
    }

    /// Where the session's recording (`recording.mcap`) is read from: a file of a filesystem
    /// store, streamed; an object of another store, in one piece (bounded by
    /// `limits.max_recording_mb`); `None` while the session runs or when it has none.
    pub fn recording(&self) -> Result<Option<Stored>, crate::storage::StoreError> {
        if !self.state().is_terminal() {
            return Ok(None);
        }
        let key = result_key(self.id(), super::recording::RECORDING);
        if let Some(path) = self.store.local_path(&key) {
            return Ok(path.is_file().then_some(Stored::File(path)));
        }
        Ok(self.store.get(&key)?.map(Stored::Bytes))
    }

    fn mesh_file(&self, name: &str, encode: fn(&Mesh) -> Vec<u8>) -> Option<Vec<u8>> {
        if self.state().is_terminal()
            && let Ok(Some(bytes)) = self.store.get(&result_key(self.id(), name))
        {
            return Some(bytes);
        }
        self.current_mesh().map(|m| encode(&m))
    }

    /// A stored result of a finished (or failed) session.
    fn stored_text(&self, name: &str) -> Option<String> {
        if !self.state().is_terminal() {
            return None;
        }
        let bytes = self
            .store
            .get(&result_key(self.id(), name))
            .ok()
            .flatten()?;
        String::from_utf8(bytes).ok()
    }

    // ---- used by the worker ----

    pub(crate) fn record_pose(&self, timestamp: f64, pose: Sim3, lost: bool) {
        lock(&self.track).frames.push((timestamp, pose, lost));
    }

    pub(crate) fn record_keyframe(&self, id: u64, timestamp: f64, pose: Sim3) {
        lock(&self.track).keyframes.insert(id, (timestamp, pose));
    }

    pub(crate) fn apply_mesh_delta(&self, delta: &MeshDelta) {
        let mut track = lock(&self.track);
        track.mesh.apply(delta);
        let c = &self.counters;
        c.mesh_revision.store(delta.revision, Ordering::Relaxed);
        c.mesh_triangles
            .store(track.mesh.triangles(), Ordering::Relaxed);
    }

    /// The mesh blocks with their revision and block size (the map snapshot's mesh).
    pub(crate) fn mesh_blocks(&self) -> (Vec<BlockMesh>, u64, f32) {
        let track = lock(&self.track);
        let m = &track.mesh;
        (
            m.blocks.values().cloned().collect(),
            m.revision,
            m.block_size,
        )
    }

    /// The whole current mesh, welded (`None` before the first mesh update).
    pub(crate) fn current_mesh(&self) -> Option<Mesh> {
        let track = lock(&self.track);
        (!track.mesh.blocks.is_empty()).then(|| Mesh::from_blocks(track.mesh.blocks.values()))
    }

    pub(crate) fn update_keyframe_poses(&self, poses: &[(usize, Sim3)]) {
        let mut track = lock(&self.track);
        for (id, pose) in poses {
            if let Some(entry) = track.keyframes.get_mut(&(*id as u64)) {
                entry.1 = *pose;
            }
        }
    }
}

/// A stored result, as the download reads it.
#[derive(Debug)]
pub enum Stored {
    /// A file of a filesystem store.
    File(std::path::PathBuf),
    /// An object of a remote store.
    Bytes(Vec<u8>),
}
