//! The fusion of one session: keyframe depths integrated into the sparse TSDF at their current
//! poses, re-integrated when the pose graph moves them, and meshed block by block into
//! [`MeshDelta`]s (paper §III-F).
//!
//! Re-integration follows BundleFusion's de-integration: a moved keyframe is integrated again
//! with weight −w at the pose it went in with, then with +w at its new pose, so the volume
//! always equals the fusion of every kept keyframe at its latest pose (exactly, while voxel
//! weights stay under the cap). The inputs needed for that are kept within
//! `fusion.keyframe_memory_mb`; a keyframe whose input was dropped stays where it was fused.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;

use crate::dense::DenseCompute;
use crate::geometry::Sim3;
use crate::gpu::GpuContext;
use crate::graph::KeyframeId;
use crate::{Error, Result};

use super::block::{BLOCK_SIDE, BlockIndex, BlockTable, UPPER_NEIGHBOURS};
use super::config::FusionConfig;
use super::gpu_marching::GpuMarching;
use super::gpu_volume::GpuVoxels;
use super::input::FusionInput;
use super::integrate::{DepthView, IntegrateParams, integrate_cpu, touched_blocks};
use super::marching::{MeshParams, extract_blocks};
use super::mesh::{BlockMesh, Mesh};
use super::voxels::{BYTES_PER_VOXEL, CpuVoxels};

/// The blocks whose triangles changed since the previous delta (a `MeshUpdate`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshDelta {
    /// Increases by one per delta; a subscriber that sees a gap must re-fetch the whole map.
    pub revision: u64,
    /// Edge of a block in map units.
    pub block_size: f32,
    /// New triangles of changed or new blocks (replace what the subscriber has).
    pub changed: Vec<BlockMesh>,
    /// Blocks with no surface any more.
    pub removed: Vec<BlockIndex>,
}

/// Counters and timings of a session's fusion.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FusionStats {
    pub keyframes_fused: usize,
    /// De-integrations + re-integrations after pose-graph moves.
    pub reintegrations: usize,
    /// Keyframes whose input was dropped for the memory budget (they can no longer move).
    pub inputs_dropped: usize,
    /// Blocks that could not be allocated (pool full).
    pub blocks_refused: usize,
    pub blocks: usize,
    pub voxel_size: f64,
    pub truncation: f64,
    /// Bytes of the voxel pool (GPU buffers or CPU arrays).
    pub pool_bytes: u64,
    pub mesh_revision: u64,
    pub triangles: usize,
    /// Total wall times (ms).
    pub integrate_ms: f64,
    pub mesh_ms: f64,
    /// `"gpu"` or `"cpu"`.
    pub compute: &'static str,
}

/// The voxel pool and its kernels.
enum Store {
    Cpu(CpuVoxels),
    Gpu {
        voxels: Box<GpuVoxels>,
        marching: GpuMarching,
    },
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Store::Cpu(_) => "Store::Cpu",
            Store::Gpu { .. } => "Store::Gpu",
        })
    }
}

impl Store {
    fn open(config: &FusionConfig, ctx: Option<Arc<GpuContext>>) -> Self {
        if config.compute == DenseCompute::Cpu {
            return Store::Cpu(CpuVoxels::default());
        }
        let ctx = match ctx.map_or_else(crate::gpu::shared_context, Ok) {
            Ok(ctx) => ctx,
            Err(e) => {
                tracing::warn!(error = %e, "no GPU for fusion: using the CPU reference");
                return Store::Cpu(CpuVoxels::default());
            }
        };
        let opened = GpuVoxels::new(ctx.clone(), 1024)
            .and_then(|voxels| Ok((voxels, GpuMarching::new(ctx)?)));
        match opened {
            Ok((voxels, marching)) => Store::Gpu {
                voxels: Box::new(voxels),
                marching,
            },
            Err(e) => {
                tracing::warn!(error = %e, "fusion kernels unavailable: using the CPU reference");
                Store::Cpu(CpuVoxels::default())
            }
        }
    }

    fn prepare(&mut self, table: &BlockTable, fresh: &[u32]) -> Result<()> {
        match self {
            Store::Cpu(v) => {
                v.ensure_capacity(table.high_water());
                v.reset_slots(fresh);
                Ok(())
            }
            Store::Gpu { voxels, .. } => {
                voxels.ensure_capacity(table.high_water())?;
                voxels.reset_slots(fresh)
            }
        }
    }

    fn integrate(
        &mut self,
        blocks: &[(BlockIndex, u32)],
        view: &DepthView,
        p: &IntegrateParams,
        sign: f32,
    ) -> Result<()> {
        match self {
            Store::Cpu(v) => {
                integrate_cpu(v, blocks, view, p, sign);
                Ok(())
            }
            Store::Gpu { voxels, .. } => voxels.integrate(blocks, view, p, sign),
        }
    }

    fn max_weights(&self, slots: &[u32]) -> Result<Vec<f32>> {
        match self {
            Store::Cpu(v) => Ok(v.max_weights(slots)),
            Store::Gpu { voxels, .. } => voxels.max_weights(slots),
        }
    }

    fn extract(
        &self,
        table: &BlockTable,
        blocks: &[BlockIndex],
        p: &MeshParams,
    ) -> Result<Vec<BlockMesh>> {
        let jobs: Vec<_> = blocks.iter().filter_map(|b| table.mesh_job(*b)).collect();
        match self {
            Store::Cpu(v) => Ok(extract_blocks(v, &jobs, p)),
            Store::Gpu { voxels, marching } => marching.extract(voxels.buffers(), &jobs, p),
        }
    }

    fn bytes(&self) -> u64 {
        match self {
            Store::Cpu(v) => (v.tsdf.len() * BYTES_PER_VOXEL) as u64,
            Store::Gpu { voxels, .. } => voxels.bytes(),
        }
    }

    fn name(&self) -> &'static str {
        match self {
            Store::Cpu(_) => "cpu",
            Store::Gpu { .. } => "gpu",
        }
    }
}

/// A fused keyframe: where it went in, and its input while the budget keeps it.
#[derive(Debug)]
struct Fused {
    pose: Sim3,
    blocks: Vec<BlockIndex>,
    input: Option<Arc<FusionInput>>,
}

/// TSDF volume, block table, keyframe records and the current block meshes of one session.
#[derive(Debug)]
pub struct Fuser {
    config: FusionConfig,
    store: Store,
    table: BlockTable,
    /// Set by the first keyframe unless configured.
    voxel_size: Option<f32>,
    fused: BTreeMap<KeyframeId, Fused>,
    /// Keyframes holding an input, oldest first (eviction order).
    kept: VecDeque<KeyframeId>,
    kept_bytes: usize,
    dirty: BTreeSet<BlockIndex>,
    meshes: BTreeMap<BlockIndex, BlockMesh>,
    revision: u64,
    stats: FusionStats,
}

impl Fuser {
    /// A fuser on `ctx` (the process-wide context when `None`) or on the CPU reference, as
    /// `config.compute` says; falls back to the CPU with a warning when the GPU cannot be used.
    pub fn new(config: FusionConfig, ctx: Option<Arc<GpuContext>>) -> Result<Self> {
        config.validate()?;
        let store = Store::open(&config, ctx);
        let voxel_size = config.voxel_size.map(|v| v as f32);
        Ok(Self {
            table: BlockTable::new(config.max_blocks),
            stats: FusionStats {
                compute: store.name(),
                ..FusionStats::default()
            },
            store,
            voxel_size,
            config,
            fused: BTreeMap::new(),
            kept: VecDeque::new(),
            kept_bytes: 0,
            dirty: BTreeSet::new(),
            meshes: BTreeMap::new(),
            revision: 0,
        })
    }

    pub fn stats(&self) -> FusionStats {
        let mut s = self.stats.clone();
        s.blocks = self.table.len();
        s.pool_bytes = self.store.bytes();
        s.mesh_revision = self.revision;
        s.triangles = self.meshes.values().map(BlockMesh::triangle_count).sum();
        s
    }

    /// Voxel edge in map units (`None` before the first keyframe when automatic).
    pub fn voxel_size(&self) -> Option<f32> {
        self.voxel_size
    }

    fn params(&self) -> IntegrateParams {
        let voxel_size = self
            .voxel_size
            .expect("voxel size set by the first keyframe");
        IntegrateParams {
            voxel_size,
            truncation: voxel_size * self.config.truncation_voxels as f32,
            max_weight: self.config.max_weight,
        }
    }

    /// Integrates a keyframe at `pose` (a keyframe fused before is first taken out at its
    /// old pose: a re-densified keyframe replaces its earlier depth).
    pub fn add_keyframe(&mut self, input: FusionInput, pose: Sim3) -> Result<()> {
        let id = input.keyframe_id;
        if self.voxel_size.is_none() {
            let median_world = f64::from(input.median_depth) * pose.scale;
            let v = median_world / self.config.voxels_per_median_depth;
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::Config(format!(
                    "fusion: cannot derive a voxel size from keyframe {id} (median depth {median_world})"
                )));
            }
            self.voxel_size = Some(v as f32);
            self.stats.voxel_size = v;
            self.stats.truncation = v * self.config.truncation_voxels;
            tracing::info!(voxel_size = v, "fusion volume");
        }
        if self.fused.contains_key(&id) {
            self.remove_keyframe(id)?;
        }
        let input = Arc::new(input);
        let blocks = self.integrate(&input, &pose)?;
        self.stats.keyframes_fused += 1;
        self.fused.insert(
            id,
            Fused {
                pose,
                blocks,
                input: Some(input.clone()),
            },
        );
        self.kept.push_back(id);
        self.kept_bytes += input.bytes();
        self.enforce_budget();
        Ok(())
    }

    /// Moves fused keyframes to their new poses: every keyframe whose points (at its median
    /// depth) moved by more than `reintegrate_voxels` voxels is de-integrated at its old pose
    /// and integrated at the new one. Returns how many were.
    pub fn update_poses(&mut self, poses: &[(KeyframeId, Sim3)]) -> Result<usize> {
        let Some(voxel) = self.voxel_size else {
            return Ok(0);
        };
        let limit = self.config.reintegrate_voxels * f64::from(voxel);
        let mut moved = 0;
        for (id, pose) in poses {
            let Some(f) = self.fused.get(id) else {
                continue;
            };
            let Some(input) = f.input.clone() else {
                continue;
            };
            if displacement(&f.pose, pose, &input) <= limit {
                continue;
            }
            let (old, old_blocks) = (f.pose, f.blocks.clone());
            self.deintegrate(&input, &old, &old_blocks)?;
            let blocks = self.integrate(&input, pose)?;
            let f = self.fused.get_mut(id).expect("checked above");
            f.pose = *pose;
            f.blocks = blocks;
            moved += 1;
        }
        self.stats.reintegrations += moved;
        if moved > 0 {
            self.free_empty_blocks()?;
        }
        Ok(moved)
    }

    /// De-integrates a keyframe (kept input only) and forgets it.
    fn remove_keyframe(&mut self, id: KeyframeId) -> Result<()> {
        let Some(f) = self.fused.remove(&id) else {
            return Ok(());
        };
        if let Some(input) = &f.input {
            self.deintegrate(input, &f.pose, &f.blocks)?;
            self.kept.retain(|k| *k != id);
            self.kept_bytes -= input.bytes();
            self.free_empty_blocks()?;
        }
        Ok(())
    }

    /// Integrates one input at `pose` into the blocks it touches (allocating them); returns
    /// those that received an observation (what [`Fuser::deintegrate`] needs to undo it).
    fn integrate(&mut self, input: &FusionInput, pose: &Sim3) -> Result<Vec<BlockIndex>> {
        let t = Instant::now();
        let params = self.params();
        let view = input_view(input, pose)?;
        let mut blocks = Vec::new();
        let mut fresh = Vec::new();
        for b in touched_blocks(&view, &params) {
            match self.table.get_or_alloc(b) {
                Ok((slot, new)) => {
                    if new {
                        fresh.push(slot);
                    }
                    blocks.push((b, slot));
                }
                Err(e) => {
                    if self.stats.blocks_refused == 0 {
                        tracing::warn!(error = %e, "fusion: blocks dropped");
                    }
                    self.stats.blocks_refused += 1;
                }
            }
        }
        self.store.prepare(&self.table, &fresh)?;
        self.store.integrate(&blocks, &view, &params, 1.0)?;
        if !fresh.is_empty() {
            // `touched_blocks` errs on the side of coverage (about 1.7× the blocks that get a
            // voxel in the truncation band): give back the new blocks that stayed empty.
            let weights = self.store.max_weights(&fresh)?;
            let empty: std::collections::HashSet<u32> = fresh
                .iter()
                .zip(weights)
                .filter(|(_, w)| *w <= 0.0)
                .map(|(s, _)| *s)
                .collect();
            blocks.retain(|(b, s)| {
                let keep = !empty.contains(s);
                if !keep {
                    self.table.free(b);
                }
                keep
            });
        }
        self.dirty.extend(blocks.iter().map(|(b, _)| *b));
        self.stats.integrate_ms += t.elapsed().as_secs_f64() * 1e3;
        Ok(blocks.into_iter().map(|(b, _)| b).collect())
    }

    /// Takes one input out again at the pose it went in at, over the blocks it went into
    /// (those freed since hold none of it).
    fn deintegrate(
        &mut self,
        input: &FusionInput,
        pose: &Sim3,
        blocks: &[BlockIndex],
    ) -> Result<()> {
        let t = Instant::now();
        let params = self.params();
        let view = input_view(input, pose)?;
        let blocks: Vec<(BlockIndex, u32)> = blocks
            .iter()
            .filter_map(|b| self.table.get(b).map(|s| (*b, s)))
            .collect();
        self.store.integrate(&blocks, &view, &params, -1.0)?;
        self.dirty.extend(blocks.iter().map(|(b, _)| *b));
        self.stats.integrate_ms += t.elapsed().as_secs_f64() * 1e3;
        Ok(())
    }

    /// Frees dirty blocks left without any observation (after de-integration).
    fn free_empty_blocks(&mut self) -> Result<()> {
        let candidates: Vec<(BlockIndex, u32)> = self
            .dirty
            .iter()
            .filter_map(|b| self.table.get(b).map(|s| (*b, s)))
            .collect();
        let slots: Vec<u32> = candidates.iter().map(|(_, s)| *s).collect();
        let weights = self.store.max_weights(&slots)?;
        for ((b, _), w) in candidates.iter().zip(weights) {
            if w <= 0.0 {
                self.table.free(b);
            }
        }
        Ok(())
    }

    /// Drops the oldest inputs past the memory budget (never the newest keyframe's).
    fn enforce_budget(&mut self) {
        let budget = (self.config.keyframe_memory_mb * 1024.0 * 1024.0) as usize;
        while self.kept_bytes > budget && self.kept.len() > 1 {
            let id = self.kept.pop_front().expect("len > 1");
            if let Some(input) = self.fused.get_mut(&id).and_then(|f| f.input.take()) {
                self.kept_bytes -= input.bytes();
                self.stats.inputs_dropped += 1;
            }
        }
    }

    /// Meshes every block whose voxels (or upper neighbours' voxels) changed since the last
    /// call; `None` when nothing changed.
    pub fn take_delta(&mut self) -> Result<Option<MeshDelta>> {
        if self.dirty.is_empty() {
            return Ok(None);
        }
        let t = Instant::now();
        let mut todo = BTreeSet::new();
        for b in std::mem::take(&mut self.dirty) {
            todo.insert(b);
            for d in UPPER_NEIGHBOURS {
                // The block below-behind reaches into `b` with its last cells.
                todo.insert(b.offset([-d[0], -d[1], -d[2]]));
            }
        }
        let (live, gone): (Vec<BlockIndex>, Vec<BlockIndex>) =
            todo.into_iter().partition(|b| self.table.get(b).is_some());
        let voxel_size = self.voxel_size.expect("dirty blocks imply a voxel size");
        let params = MeshParams {
            voxel_size,
            min_weight: self.config.min_mesh_weight,
        };
        let meshes = self.store.extract(&self.table, &live, &params)?;
        let mut delta = MeshDelta {
            revision: 0,
            block_size: voxel_size * BLOCK_SIDE as f32,
            changed: Vec::new(),
            removed: Vec::new(),
        };
        for b in gone {
            if self.meshes.remove(&b).is_some() {
                delta.removed.push(b);
            }
        }
        for m in meshes {
            if m.is_empty() {
                if self.meshes.remove(&m.index).is_some() {
                    delta.removed.push(m.index);
                }
            } else if self.meshes.get(&m.index) != Some(&m) {
                self.meshes.insert(m.index, m.clone());
                delta.changed.push(m);
            }
        }
        self.stats.mesh_ms += t.elapsed().as_secs_f64() * 1e3;
        if delta.changed.is_empty() && delta.removed.is_empty() {
            return Ok(None);
        }
        self.revision += 1;
        delta.revision = self.revision;
        Ok(Some(delta))
    }

    /// The current block meshes (what a subscriber holds after applying every delta).
    pub fn block_meshes(&self) -> impl Iterator<Item = &BlockMesh> {
        self.meshes.values()
    }

    /// The whole surface, welded (meshes pending changes first).
    pub fn mesh(&mut self) -> Result<Mesh> {
        self.take_delta()?;
        Ok(Mesh::from_blocks(self.meshes.values()))
    }

    /// The keyframes fused so far with the pose each is fused at.
    pub fn fused_poses(&self) -> Vec<(KeyframeId, Sim3)> {
        self.fused.iter().map(|(id, f)| (*id, f.pose)).collect()
    }
}

/// The integration view of an input at `pose`.
fn input_view<'a>(input: &'a FusionInput, pose: &Sim3) -> Result<DepthView<'a>> {
    DepthView::new(
        &input.camera,
        pose,
        &input.depth,
        &input.weight,
        &input.color,
    )
}

/// How far a keyframe's surface moves between two poses: the largest displacement of five
/// points at its median depth (image centre and corners), in world units. Scale changes count:
/// a Sim(3) scale change moves the surface even when the camera stays put.
fn displacement(old: &Sim3, new: &Sim3, input: &FusionInput) -> f64 {
    let c = &input.camera;
    let d = f64::from(input.median_depth);
    let (w, h) = (f64::from(c.width), f64::from(c.height));
    [(w / 2.0, h / 2.0), (0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .iter()
        .map(|&(u, v)| {
            let p = c.unproject(&nalgebra::Vector2::new(u, v), d);
            (old.act(&p) - new.act(&p)).norm()
        })
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use nalgebra::Vector3;

    use super::*;
    use crate::eval::mesh::{score_surface, transform_vertices};
    use crate::geometry::{PinholeCamera, SO3};
    use crate::image::ImageF32;

    /// A 96×72 view of a tilted wall with a spherical bump, in the keyframe's units.
    fn wall_input(id: KeyframeId, config: &FusionConfig) -> FusionInput {
        let camera = PinholeCamera::new(70.0, 70.0, 47.5, 35.5, 96, 72).expect("camera");
        let (w, h) = (96, 72);
        let mut depth = ImageF32::filled(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let ray = Vector3::new((x as f64 - 47.5) / 70.0, (y as f64 - 35.5) / 70.0, 1.0);
                // Plane z = 2 + 0.3·x (camera frame), plus a bump in the middle.
                let t = 2.0 / (ray.z - 0.3 * ray.x);
                let p = ray * t;
                let bump = 0.15 * (-(p.x * p.x + p.y * p.y) / 0.05).exp();
                *depth.at_mut(x, y) = (t * (1.0 - bump / p.z)) as f32;
            }
        }
        let colors: Vec<[u8; 3]> = (0..w * h).map(|i| [(i % 256) as u8, 90, 200]).collect();
        FusionInput::from_depth(id, id as f64, camera, &depth, Some(&colors), config)
            .expect("input")
    }

    fn pose(yaw: f64, x: f64, scale: f64) -> Sim3 {
        Sim3::new(
            SO3::exp(&Vector3::new(0.0, yaw, 0.02)),
            Vector3::new(x, 0.05, -0.1),
            scale,
        )
    }

    fn config(compute: DenseCompute) -> FusionConfig {
        FusionConfig {
            compute,
            voxels_per_median_depth: 64.0,
            ..FusionConfig::default()
        }
    }

    /// Both meshes have every vertex within `tol` of the other's (same surface).
    fn assert_same_surface(a: &Mesh, b: &Mesh, tol: f64) {
        let va = transform_vertices(a, &Sim3::identity());
        let vb = transform_vertices(b, &Sim3::identity());
        let s = score_surface(&va, &vb, tol);
        assert!(
            s.accuracy > 0.999 && s.completeness > 0.999,
            "{} vs {} vertices: {s:?}",
            va.len(),
            vb.len()
        );
    }

    #[test]
    fn a_moved_keyframe_ends_up_as_if_fused_at_its_new_pose() {
        let config = config(DenseCompute::Cpu);
        let (p0, p1, p1_moved) = (
            pose(0.0, 0.0, 1.0),
            pose(0.2, 0.3, 1.0),
            pose(0.25, 0.4, 1.3),
        );
        let mut moved = Fuser::new(config.clone(), None).expect("fuser");
        moved
            .add_keyframe(wall_input(0, &config), p0)
            .expect("kf 0");
        moved
            .add_keyframe(wall_input(1, &config), p1)
            .expect("kf 1");
        let before = moved.mesh().expect("mesh");
        assert_eq!(
            moved.update_poses(&[(0, p0), (1, p1_moved)]).expect("move"),
            1
        );
        let after = moved.mesh().expect("mesh");

        let mut direct = Fuser::new(config.clone(), None).expect("fuser");
        direct
            .add_keyframe(wall_input(0, &config), p0)
            .expect("kf 0");
        direct
            .add_keyframe(wall_input(1, &config), p1_moved)
            .expect("kf 1");
        let expected = direct.mesh().expect("mesh");
        let voxel = f64::from(moved.voxel_size().expect("voxel"));
        assert_same_surface(&after, &expected, 1e-3 * voxel);
        assert_eq!(
            moved.stats().blocks,
            direct.stats().blocks,
            "emptied blocks are freed"
        );
        // And the move did change the surface.
        let s = score_surface(
            &transform_vertices(&before, &Sim3::identity()),
            &transform_vertices(&after, &Sim3::identity()),
            voxel,
        );
        assert!(s.accuracy < 0.9, "{s:?}");
    }

    #[test]
    fn applying_every_delta_rebuilds_the_mesh() {
        let config = config(DenseCompute::Cpu);
        let mut fuser = Fuser::new(config.clone(), None).expect("fuser");
        let mut patched: BTreeMap<BlockIndex, BlockMesh> = BTreeMap::new();
        let mut revision = 0;
        let mut apply = |delta: MeshDelta| {
            assert_eq!(delta.revision, revision + 1);
            revision = delta.revision;
            for b in &delta.removed {
                assert!(
                    patched.remove(b).is_some(),
                    "removed block {b:?} was not there"
                );
            }
            for m in delta.changed {
                assert!(!m.is_empty());
                patched.insert(m.index, m);
            }
        };
        for (id, p) in [(0, pose(0.0, 0.0, 1.0)), (1, pose(0.3, 0.5, 1.1))] {
            fuser.add_keyframe(wall_input(id, &config), p).expect("add");
            apply(fuser.take_delta().expect("delta").expect("changed"));
        }
        assert!(
            fuser.take_delta().expect("delta").is_none(),
            "nothing changed since"
        );
        fuser
            .update_poses(&[(1, pose(0.6, 1.5, 1.1))])
            .expect("move");
        let delta = fuser.take_delta().expect("delta").expect("changed");
        assert!(
            !delta.removed.is_empty(),
            "moving a keyframe away empties blocks"
        );
        apply(delta);
        let current: BTreeMap<BlockIndex, BlockMesh> =
            fuser.block_meshes().map(|m| (m.index, m.clone())).collect();
        assert_eq!(patched, current);
        assert_eq!(fuser.stats().mesh_revision, revision);
    }

    #[test]
    fn inputs_past_the_memory_budget_stay_where_they_were_fused() {
        let one = wall_input(0, &FusionConfig::default()).bytes() as f64;
        let config = FusionConfig {
            keyframe_memory_mb: 1.5 * one / (1024.0 * 1024.0),
            ..config(DenseCompute::Cpu)
        };
        let mut fuser = Fuser::new(config.clone(), None).expect("fuser");
        for id in 0..3 {
            fuser
                .add_keyframe(wall_input(id, &config), pose(0.1 * id as f64, 0.0, 1.0))
                .expect("add");
        }
        assert_eq!(
            fuser.stats().inputs_dropped,
            2,
            "only the newest input fits"
        );
        let moved: Vec<_> = (0..3)
            .map(|id| (id, pose(0.1 * id as f64, 1.0, 1.0)))
            .collect();
        assert_eq!(fuser.update_poses(&moved).expect("move"), 1);
        assert_eq!(fuser.stats().reintegrations, 1);
    }

    #[test]
    fn small_moves_are_not_reintegrated_and_scale_changes_are() {
        let config = config(DenseCompute::Cpu);
        let mut fuser = Fuser::new(config.clone(), None).expect("fuser");
        fuser
            .add_keyframe(wall_input(0, &config), pose(0.0, 0.0, 1.0))
            .expect("add");
        let voxel = f64::from(fuser.voxel_size().expect("voxel"));
        assert_eq!(
            fuser
                .update_poses(&[(0, pose(0.0, 0.2 * voxel, 1.0))])
                .expect("tiny"),
            0
        );
        assert_eq!(
            fuser
                .update_poses(&[(0, pose(0.0, 0.0, 1.05))])
                .expect("scale"),
            1
        );
    }

    #[test]
    fn gpu_and_cpu_fusion_make_the_same_mesh() {
        let Ok(ctx) = crate::gpu::shared_context() else {
            eprintln!("SKIP: no GPU adapter (not even lavapipe)");
            return;
        };
        let mut meshes = Vec::new();
        for compute in [DenseCompute::Gpu, DenseCompute::Cpu] {
            let config = config(compute);
            let mut fuser = Fuser::new(config.clone(), Some(ctx.clone())).expect("fuser");
            assert_eq!(
                fuser.stats().compute,
                if compute == DenseCompute::Gpu {
                    "gpu"
                } else {
                    "cpu"
                }
            );
            fuser
                .add_keyframe(wall_input(0, &config), pose(0.0, 0.0, 1.0))
                .expect("kf 0");
            fuser
                .add_keyframe(wall_input(1, &config), pose(0.2, 0.3, 1.0))
                .expect("kf 1");
            fuser
                .update_poses(&[(1, pose(0.25, 0.4, 1.2))])
                .expect("move");
            meshes.push((
                fuser.mesh().expect("mesh"),
                fuser.voxel_size().expect("voxel"),
            ));
        }
        let tol = 1e-3 * f64::from(meshes[0].1);
        assert!(meshes[0].0.triangle_count() > 1000);
        assert_same_surface(&meshes[0].0, &meshes[1].0, tol);
    }
}
