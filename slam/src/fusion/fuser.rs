//! The fusion of one session: keyframe depths integrated into the sparse TSDF at their current
//! poses, re-integrated when the pose graph moves them, and meshed block by block into
//! [`MeshDelta`]s (paper §III-F).
//!
//! Re-integration follows BundleFusion's de-integration: a moved keyframe is integrated again
//! with weight −w at the pose it went in with, then with +w at its new pose, so the volume
//! always equals the fusion of every kept keyframe at its latest pose (exactly, while voxel
//! weights stay under the cap). The inputs needed for that are held within
//! `fusion.keyframe_memory_mb`; past it, older inputs spill to the session's store (issue 37)
//! and are read back when their keyframe moves, or, without a store, are dropped and their
//! keyframe stays where it was fused.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;

use crate::geometry::{PinholeCamera, Sim3};
use crate::gpu::GpuContext;
use crate::graph::KeyframeId;
use crate::spill::{Spill, Stored};
use crate::{Error, Result};

use super::block::{BLOCK_SIDE, BlockIndex, BlockTable, UPPER_NEIGHBOURS};
use super::block_list::BlockList;
use super::chunks::{ChunkData, ChunkIndex, Residency, Surface};
use super::config::FusionConfig;
use super::input::FusionInput;
use super::integrate::{DepthView, IntegrateParams, touched_blocks};
use super::marching::MeshParams;
use super::mesh::{BlockMesh, Mesh};
use super::pool::Pool;
use super::weld::weld;

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
    /// Keyframes whose input was dropped for the memory budget (no store: they can no longer
    /// move).
    pub inputs_dropped: usize,
    /// Keyframes whose input went to the session's store for the memory budget (read back
    /// when they move).
    pub inputs_spilled: usize,
    /// Blocks that could not be allocated (pool full).
    pub blocks_refused: usize,
    /// Blocks in the pool.
    pub blocks: usize,
    /// Block indices the fused keyframes remember (to take them out again when they move),
    /// and the bytes those lists hold.
    pub keyframe_blocks: usize,
    pub keyframe_block_bytes: usize,
    /// Blocks spilled to the session's store with their chunks (`fusion.resident_blocks`),
    /// and the chunks they form.
    pub blocks_spilled: usize,
    pub chunks_spilled: usize,
    /// Spilled chunks read back into the pool (a revisit, a moved keyframe, a neighbour meshed).
    pub chunk_loads: usize,
    pub voxel_size: f64,
    pub truncation: f64,
    /// Bytes of the voxel pool (GPU buffers or CPU arrays).
    pub pool_bytes: u64,
    pub mesh_revision: u64,
    /// Triangles of the whole mesh (spilled chunks' too).
    pub triangles: usize,
    /// Total wall times (ms).
    pub integrate_ms: f64,
    pub mesh_ms: f64,
    /// `"gpu"` or `"cpu"`.
    pub compute: &'static str,
}

/// A fused keyframe: where it went in, and its input (held, spilled, or dropped without a
/// store). Camera and median depth stay for the pose-change test.
#[derive(Debug)]
struct Fused {
    pose: Sim3,
    blocks: BlockList,
    camera: PinholeCamera,
    median_depth: f32,
    input: Option<Arc<Stored<FusionInput>>>,
}

/// TSDF volume, block table, keyframe records and the current block meshes of one session.
#[derive(Debug)]
pub struct Fuser {
    config: FusionConfig,
    pool: Pool,
    table: BlockTable,
    /// Set by the first keyframe unless configured.
    voxel_size: Option<f32>,
    fused: BTreeMap<KeyframeId, Fused>,
    /// Keyframes holding an input in memory, oldest first (eviction order).
    kept: VecDeque<KeyframeId>,
    /// Where inputs past the budget go (`crate::spill`; dropped when no store is attached).
    spill: Spill,
    kept_bytes: usize,
    dirty: BTreeSet<BlockIndex>,
    meshes: BTreeMap<BlockIndex, BlockMesh>,
    revision: u64,
    /// Which chunks of blocks are in the pool and which in the store (`super::chunks`).
    residency: Residency,
    stats: FusionStats,
}

impl Fuser {
    /// A fuser on `ctx` (the process-wide context when `None`) or on the CPU reference, as
    /// `config.compute` says; falls back to the CPU with a warning when the GPU cannot be used.
    pub fn new(config: FusionConfig, ctx: Option<Arc<GpuContext>>) -> Result<Self> {
        config.validate()?;
        let pool = Pool::open(&config, ctx);
        let voxel_size = config.voxel_size.map(|v| v as f32);
        Ok(Self {
            table: BlockTable::new(config.max_blocks),
            stats: FusionStats {
                compute: pool.name(),
                ..FusionStats::default()
            },
            pool,
            voxel_size,
            config,
            fused: BTreeMap::new(),
            kept: VecDeque::new(),
            spill: Spill::default(),
            kept_bytes: 0,
            dirty: BTreeSet::new(),
            meshes: BTreeMap::new(),
            revision: 0,
            residency: Residency::default(),
        })
    }

    /// Inputs past the memory budget spill to `spill`'s store (once one is attached) instead
    /// of being dropped.
    pub fn with_spill(mut self, spill: Spill) -> Self {
        self.spill = spill;
        self
    }

    pub fn stats(&self) -> FusionStats {
        let mut s = self.stats.clone();
        s.blocks = self.table.len();
        s.keyframe_blocks = self.fused.values().map(|f| f.blocks.len()).sum();
        s.keyframe_block_bytes = self.fused.values().map(|f| f.blocks.heap_bytes()).sum();
        let spilled = self.residency.figures();
        (s.blocks_spilled, s.chunks_spilled, s.chunk_loads) =
            (spilled.blocks, spilled.chunks, spilled.loads);
        s.pool_bytes = self.pool.bytes();
        s.mesh_revision = self.revision;
        s.triangles = spilled.triangles
            + self
                .meshes
                .values()
                .map(BlockMesh::triangle_count)
                .sum::<usize>();
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
        self.residency.advance();
        if self.fused.contains_key(&id) {
            self.remove_keyframe(id)?;
        }
        let blocks = self.integrate(&input, &pose)?;
        self.residency.keyframe_added(&blocks);
        self.stats.keyframes_fused += 1;
        self.kept.push_back(id);
        self.kept_bytes += input.bytes();
        self.fused.insert(
            id,
            Fused {
                pose,
                blocks: BlockList::new(&blocks),
                camera: input.camera,
                median_depth: input.median_depth,
                input: Some(Stored::new(&self.spill, Arc::new(input))),
            },
        );
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
            let Some(stored) = &f.input else {
                continue;
            };
            if displacement(&f.pose, pose, &f.camera, f.median_depth) <= limit {
                continue;
            }
            // Read back when spilled; it stays in the store.
            let input = stored.get()?;
            let (old, old_blocks) = (f.pose, f.blocks.to_vec());
            self.residency.advance();
            self.deintegrate(&input, &old, &old_blocks)?;
            let blocks = self.integrate(&input, pose)?;
            let f = self.fused.get_mut(id).expect("checked above");
            f.pose = *pose;
            f.blocks = BlockList::new(&blocks);
            moved += 1;
            if self.table.len() > 2 * self.config.resident_blocks as usize {
                // A loop closure can move every keyframe of an hour: the chunks the moves
                // brought back leave again as the pass goes on (past twice the budget, so
                // that neighbouring keyframes do not hand chunks back and forth).
                self.free_empty_blocks()?;
                self.evict()?;
            }
        }
        self.stats.reintegrations += moved;
        if moved > 0 {
            self.free_empty_blocks()?;
        }
        Ok(moved)
    }

    /// De-integrates a keyframe (one whose input was dropped for the memory budget stays in
    /// the volume) and forgets it.
    pub fn remove_keyframe(&mut self, id: KeyframeId) -> Result<()> {
        let Some(f) = self.fused.remove(&id) else {
            return Ok(());
        };
        if let Some(stored) = &f.input {
            let input = stored.get()?;
            self.deintegrate(&input, &f.pose, &f.blocks.to_vec())?;
            if stored.is_held() {
                self.kept.retain(|k| *k != id);
                self.kept_bytes -= input.bytes();
            }
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
        let touched = touched_blocks(&view, &params);
        self.load_chunks(touched.iter().copied())?;
        let mut blocks = Vec::new();
        let mut fresh = Vec::new();
        for b in touched {
            if self.residency.is_spilled(&b) {
                // Its chunk could not come back (pool full): a new block here would hide it.
                self.stats.blocks_refused += 1;
                continue;
            }
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
        self.pool.prepare(&self.table, &fresh)?;
        self.pool.integrate(&blocks, &view, &params, 1.0)?;
        if !fresh.is_empty() {
            // `touched_blocks` errs on the side of coverage (about 1.7× the blocks that get a
            // voxel in the truncation band): give back the new blocks that stayed empty.
            let weights = self.pool.max_weights(&fresh)?;
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
        self.residency.touch(blocks.iter().map(|(b, _)| b));
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
        self.load_chunks(blocks.iter().copied())?;
        let blocks: Vec<(BlockIndex, u32)> = blocks
            .iter()
            .filter_map(|b| self.table.get(b).map(|s| (*b, s)))
            .collect();
        self.pool.integrate(&blocks, &view, &params, -1.0)?;
        self.dirty.extend(blocks.iter().map(|(b, _)| *b));
        self.residency.touch(blocks.iter().map(|(b, _)| b));
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
        let weights = self.pool.max_weights(&slots)?;
        for ((b, _), w) in candidates.iter().zip(weights) {
            if w <= 0.0 {
                self.table.free(b);
            }
        }
        Ok(())
    }

    /// Spills (or, without a store, drops) the oldest inputs past the memory budget (never the
    /// newest keyframe's).
    fn enforce_budget(&mut self) {
        let budget = (self.config.keyframe_memory_mb * 1024.0 * 1024.0) as usize;
        while self.kept_bytes > budget && self.kept.len() > 1 {
            let id = self.kept.pop_front().expect("len > 1");
            let Some(f) = self.fused.get_mut(&id) else {
                continue;
            };
            let Some(bytes) = f.input.as_ref().and_then(|s| s.held()).map(|i| i.bytes()) else {
                continue;
            };
            self.kept_bytes -= bytes;
            let spilled = self.spill.enabled()
                && f.input.as_ref().is_some_and(|s| match s.spill() {
                    Ok(()) => !s.is_held(),
                    Err(e) => {
                        tracing::warn!(keyframe = id, error = %e, "fusion input dropped: spilling failed");
                        false
                    }
                });
            if spilled {
                self.stats.inputs_spilled += 1;
            } else {
                f.input = None;
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
        // Marching cubes reads each block and its upper neighbours: spilled ones come back.
        self.load_chunks(
            todo.iter()
                .flat_map(|b| std::iter::once(*b).chain(UPPER_NEIGHBOURS.map(|d| b.offset(d)))),
        )?;
        // A block whose chunk stayed in the store (pool full) keeps its stored mesh.
        todo.retain(|b| !self.residency.is_spilled(b));
        let (live, gone): (Vec<BlockIndex>, Vec<BlockIndex>) =
            todo.into_iter().partition(|b| self.table.get(b).is_some());
        let voxel_size = self.voxel_size.expect("dirty blocks imply a voxel size");
        let params = MeshParams {
            voxel_size,
            min_weight: self.config.min_mesh_weight,
        };
        let meshes = self.pool.extract(&self.table, &live, &params)?;
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
        self.evict()?;
        if delta.changed.is_empty() && delta.removed.is_empty() {
            return Ok(None);
        }
        self.revision += 1;
        delta.revision = self.revision;
        Ok(Some(delta))
    }

    /// The current meshes of the blocks in the pool (what a subscriber holds after applying
    /// every delta, less the chunks spilled to the store).
    pub fn block_meshes(&self) -> impl Iterator<Item = &BlockMesh> {
        self.meshes.values()
    }

    /// The whole surface, welded (meshes pending changes first; spilled chunks' meshes are
    /// read back from the store, not into the pool).
    pub fn mesh(&mut self) -> Result<Mesh> {
        let mut mesh = Mesh::default();
        weld(&mut self.surface()?, &mut mesh)?;
        Ok(mesh)
    }

    /// The whole surface as blocks to weld or write a slab at a time (meshes pending changes
    /// first): what the exports of a long session stream from (`export::write_mesh_ply_from`).
    pub fn surface(&mut self) -> Result<Surface<'_>> {
        self.take_delta()?;
        Ok(self.residency.surface(&self.meshes))
    }

    /// Brings back into the pool every spilled chunk holding one of `blocks`. A chunk whose
    /// blocks do not all fit in the pool (`fusion.max_blocks`) stays in the store; callers
    /// leave its blocks alone.
    fn load_chunks(&mut self, blocks: impl IntoIterator<Item = BlockIndex>) -> Result<()> {
        if !self.residency.any_spilled() {
            return Ok(());
        }
        let chunks: BTreeSet<ChunkIndex> = blocks
            .into_iter()
            .filter(|b| self.residency.is_spilled(b))
            .map(|b| ChunkIndex::of(&b))
            .collect();
        for c in chunks {
            let Some(stored) = self.residency.stored(&c) else {
                continue;
            };
            let data = stored.get()?;
            let mut slots = Vec::with_capacity(data.blocks.len());
            for b in &data.blocks {
                match self.table.get_or_alloc(*b) {
                    Ok((slot, _)) => slots.push(slot),
                    Err(e) => {
                        tracing::warn!(error = %e, "fusion: a spilled chunk cannot come back");
                        for b in &data.blocks[..slots.len()] {
                            self.table.free(b);
                        }
                        slots.clear();
                        break;
                    }
                }
            }
            if slots.len() != data.blocks.len() {
                self.stats.blocks_refused += data.blocks.len();
                continue;
            }
            self.pool.prepare(&self.table, &[])?;
            self.pool.write_slots(&slots, &data.voxels)?;
            for m in &data.meshes {
                self.meshes.insert(m.index, m.clone());
            }
            self.residency.loaded(c);
        }
        Ok(())
    }

    /// Past `fusion.resident_blocks` (and with a store attached), moves the least recently
    /// used chunks to the store until a quarter of the budget is free again (so a session
    /// exploring new ground spills every few keyframes, not after each), keeping the newest
    /// keyframes' chunks ([`Residency::eviction_order`]). Called after meshing and during
    /// long re-integration passes; a block evicted before its mesh comes back for it.
    fn evict(&mut self) -> Result<()> {
        let limit = self.config.resident_blocks as usize;
        if self.table.len() <= limit || !self.spill.enabled() {
            return Ok(());
        }
        let target = limit - limit / 4;
        let mut by_chunk: BTreeMap<ChunkIndex, Vec<(BlockIndex, u32)>> = BTreeMap::new();
        for (b, slot) in self.table.iter() {
            by_chunk
                .entry(ChunkIndex::of(&b))
                .or_default()
                .push((b, slot));
        }
        let counts = by_chunk.iter().map(|(c, b)| (*c, b.len())).collect();
        // The chunks that leave, then their voxels in one read-back (one wait for the GPU).
        let mut left = self.table.len();
        let mut victims = Vec::new();
        for c in self.residency.eviction_order(&counts, limit / 2) {
            if left <= target {
                break;
            }
            let mut blocks = by_chunk.remove(&c).unwrap_or_default();
            blocks.sort_unstable();
            left -= blocks.len();
            victims.push((c, blocks));
        }
        let slots: Vec<u32> = victims
            .iter()
            .flat_map(|(_, blocks)| blocks.iter().map(|(_, s)| *s))
            .collect();
        let voxels = self.pool.read_slots(&slots)?;
        let mut first = 0;
        for (c, blocks) in victims {
            let slots = first as u32..(first + blocks.len()) as u32;
            first += blocks.len();
            let data = Arc::new(ChunkData {
                voxels: voxels.read_slots(&slots.collect::<Vec<_>>()),
                meshes: blocks
                    .iter()
                    .filter_map(|(b, _)| self.meshes.get(b).cloned())
                    .collect(),
                blocks: blocks.iter().map(|(b, _)| *b).collect(),
            });
            let stored = Stored::new(&self.spill, Arc::clone(&data));
            if let Err(e) = stored.spill() {
                // The session's spilling stops there; the chunk stays in the pool.
                tracing::warn!(error = %e, "fusion: TSDF chunks stay in memory");
                return Ok(());
            }
            for (b, _) in &blocks {
                self.table.free(b);
                self.meshes.remove(b);
            }
            self.residency.spilled(c, stored, &data);
        }
        Ok(())
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
fn displacement(old: &Sim3, new: &Sim3, c: &PinholeCamera, median_depth: f32) -> f64 {
    let d = f64::from(median_depth);
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
#[path = "fuser_tests.rs"]
mod tests;
