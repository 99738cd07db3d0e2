//! A session's outputs: recorded into its [`super::track::Track`] as the worker produces them, and read
//! back as result files (poses, point cloud, mesh, recording) while it runs, or from the store
//! once it has ended.

use std::sync::atomic::Ordering;
use std::sync::{Mutex, MutexGuard};

use relfusion_slam::dataset::trajectory::{StampedPose, format_tum_trajectory, stamped_se3};
use relfusion_slam::export::{mesh_glb_bytes_from, mesh_ply_bytes_from};
use relfusion_slam::frame_log::FrameLog;
use relfusion_slam::fusion::weld::BlockSource;
use relfusion_slam::fusion::{BlockMesh, MeshDelta};
use relfusion_slam::geometry::Sim3;
use relfusion_slam::pipeline::KeyframePose;
use relfusion_slam::spill::Spill;

use super::handle::Session;
use super::mesh_state::MeshSnapshot;
use super::persist::result_key;
use super::track::Reported;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
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
    /// The trajectory: final (optimised) once finished, else the poses as tracked so far
    /// (spilled ones read back; `Err` when the store cannot give them).
    pub fn trajectory(&self) -> Result<Poses, String> {
        if let Some(text) = self.stored_text("trajectory.txt") {
            return Ok(Poses::Stored(text));
        }
        // Copied under the lock (the newest chunk; the spilled ones shared), read outside it:
        // recording a frame's pose never waits for the store.
        let frames = lock(&self.track).frames.clone();
        let mut poses = Vec::with_capacity(frames.len());
        frames
            .for_each(|r| {
                if !r.lost {
                    poses.push((r.timestamp, r.pose));
                }
            })
            .map_err(|e| format!("reading the session's poses back: {e}"))?;
        Ok(Poses::Live(stamped_se3(&poses)))
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
    pub fn trajectory_tum(&self) -> Result<String, String> {
        self.trajectory().map(Poses::into_tum)
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
        self.mesh_file("mesh.ply", mesh_ply_bytes_from)
    }

    /// The fused mesh as glTF binary (like [`Session::mesh_ply`]).
    pub fn mesh_glb(&self) -> Option<Vec<u8>> {
        self.mesh_file("mesh.glb", mesh_glb_bytes_from)
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

    fn mesh_file(&self, name: &str, encode: MeshEncoder) -> Option<Vec<u8>> {
        if self.state().is_terminal()
            && let Ok(Some(bytes)) = self.store.get(&result_key(self.id(), name))
        {
            return Some(bytes);
        }
        self.encode_mesh(&self.mesh_snapshot()?, encode)
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
        lock(&self.track).frames.push(Reported {
            timestamp,
            pose,
            lost,
        });
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

    /// The map snapshot's mesh: each block in index order to `each` (spilled chunks read
    /// back a slab at a time, outside the session's lock), then the revision and block size
    /// they are at. `Err` when the store cannot give a spilled chunk back.
    pub(crate) fn each_mesh_block(
        &self,
        each: &mut dyn FnMut(&BlockMesh),
    ) -> Result<(u64, f32), String> {
        let (snapshot, revision, block_size) = {
            let track = lock(&self.track);
            let m = &track.mesh;
            (m.snapshot(), m.revision, m.block_size)
        };
        snapshot
            .surface()
            .runs(&mut |blocks| {
                blocks.iter().for_each(|b| each(b));
                Ok(())
            })
            .map_err(|e| format!("reading the mesh back: {e}"))?;
        Ok((revision, block_size))
    }

    /// The current mesh as PLY and GLB (`None` before the first mesh update), encoded a slab
    /// of blocks at a time: the welded mesh is never built.
    pub(crate) fn mesh_files(&self) -> Option<(Vec<u8>, Vec<u8>)> {
        self.mesh_files_of(&self.mesh_snapshot()?)
    }

    /// [`Session::mesh_files`] of a snapshot taken before (a checkpoint's, encoded on its
    /// writer's thread).
    pub(super) fn mesh_files_of(&self, snapshot: &MeshSnapshot) -> Option<(Vec<u8>, Vec<u8>)> {
        Some((
            self.encode_mesh(snapshot, mesh_ply_bytes_from)?,
            self.encode_mesh(snapshot, mesh_glb_bytes_from)?,
        ))
    }

    /// The mesh as it stands, to encode outside the session's lock (frames go on being
    /// recorded meanwhile); `None` before the first mesh update.
    pub(super) fn mesh_snapshot(&self) -> Option<MeshSnapshot> {
        let track = lock(&self.track);
        (!track.mesh.is_empty()).then(|| track.mesh.snapshot())
    }

    fn encode_mesh(&self, snapshot: &MeshSnapshot, encode: MeshEncoder) -> Option<Vec<u8>> {
        encode(&mut snapshot.surface())
            .inspect_err(|e| tracing::error!(session = %self.id(), "encoding the mesh: {e}"))
            .ok()
    }

    /// The session's records spill through `spill` (issue 37): its copy of the mesh past
    /// `resident_blocks` blocks, its poses a chunk at a time. Called before the first frame.
    pub(crate) fn bound_memory(&self, spill: Spill, resident_blocks: usize) {
        let mut track = lock(&self.track);
        debug_assert!(track.frames.is_empty(), "bound before the first frame");
        track.frames = FrameLog::new(&spill);
        track.mesh.bound(spill, resident_blocks);
    }

    /// Mesh blocks held in memory and spilled.
    pub(crate) fn mesh_block_counts(&self) -> (usize, usize) {
        lock(&self.track).mesh.block_counts()
    }

    /// The keyframes' poses after a pose-graph optimisation.
    pub(crate) fn update_keyframe_poses(&self, poses: &[KeyframePose]) {
        let mut track = lock(&self.track);
        for p in poses {
            if let Some(entry) = track.keyframes.get_mut(&(p.keyframe_id as u64)) {
                entry.1 = p.world_from_keyframe;
            }
        }
    }
}

/// An encoder of a whole surface (PLY or GLB).
type MeshEncoder = fn(&mut dyn BlockSource) -> relfusion_slam::Result<Vec<u8>>;

/// A stored result, as the download reads it.
#[derive(Debug)]
pub enum Stored {
    /// A file of a filesystem store.
    File(std::path::PathBuf),
    /// An object of a remote store.
    Bytes(Vec<u8>),
}
