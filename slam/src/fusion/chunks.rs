//! TSDF blocks spilled to the session's store (issue 37, item 3: bounded fusion).
//!
//! A session that keeps exploring touches new blocks for as long as it runs, and every block
//! costs 6 KiB of pool plus its mesh. As nvblox and voxblox do, blocks far from where the
//! camera works leave memory: they are grouped into chunks of 4×4×4 blocks (a spatial unit,
//! so a revisit loads a neighbourhood in one read, not block by block), and once the pool holds
//! more than `fusion.resident_blocks`, the chunks used least recently go to the session's store
//! with their voxels and meshes, LZ4-compressed ([`crate::spill`]). Whatever reads or writes a
//! spilled chunk's voxels — a keyframe integrated there, a moved keyframe de-integrated,
//! marching cubes on a neighbour — loads it back first, bit-identical, so spilling changes
//! where the volume lives, never the volume or the mesh.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet, VecDeque};
use std::sync::Arc;

use crate::Result;
use crate::spill::{Reader, Spillable, Stored, Writer};

use super::block::{BLOCK_VOXELS, BlockIndex};
use super::mesh::{BlockMesh, EdgeKey};
use super::voxels::CpuVoxels;
use super::weld::BlockSource;

/// Blocks along one edge of a chunk.
pub const CHUNK_SIDE: i32 = 4;

/// Newest keyframes whose chunks stay in the pool (while they fill at most half of
/// `fusion.resident_blocks`; the newest always): the next keyframes integrate where these
/// did, and evicting them would bring them straight back.
const PROTECTED_KEYFRAMES: usize = 8;

/// Integer coordinates of a chunk: blocks `4c … 4c + 3` along each axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ChunkIndex([i32; 3]);

impl ChunkIndex {
    /// The chunk holding block `b`.
    pub fn of(b: &BlockIndex) -> Self {
        Self([b.x, b.y, b.z].map(|v| v.div_euclid(CHUNK_SIDE)))
    }
}

/// One chunk as spilled: its blocks (sorted), their voxels (block `k` in slot `k`) and their
/// meshes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChunkData {
    pub blocks: Vec<BlockIndex>,
    pub voxels: CpuVoxels,
    pub meshes: Vec<BlockMesh>,
}

impl Spillable for ChunkData {
    fn encode(&self, out: &mut Writer) {
        out.u32s(&self.blocks.iter().flat_map(block_words).collect::<Vec<_>>());
        out.f32s(&self.voxels.tsdf);
        out.f32s(&self.voxels.weight);
        out.u32s(&self.voxels.color);
        out.u64(self.meshes.len() as u64);
        for m in &self.meshes {
            out.u32s(&block_words(&m.index));
            out.f32s(m.positions.as_flattened());
            out.f32s(m.normals.as_flattened());
            out.bytes(m.colors.as_flattened());
            out.u32s(&m.indices);
            let keys: Vec<u32> = m
                .edge_keys
                .iter()
                .flat_map(|k| [k.voxel[0], k.voxel[1], k.voxel[2], i32::from(k.axis)])
                .map(|v| v as u32)
                .collect();
            out.u32s(&keys);
        }
    }

    fn decode(input: &mut Reader<'_>) -> Result<Self> {
        let bad = |what: &str| crate::Error::Spill(format!("a spilled TSDF chunk {what}"));
        let blocks: Vec<BlockIndex> = input
            .u32s()?
            .chunks(3)
            .map(block_of_words)
            .collect::<Option<_>>()
            .ok_or_else(|| bad("has a partial block index"))?;
        let voxels = CpuVoxels {
            tsdf: input.f32s()?,
            weight: input.f32s()?,
            color: input.u32s()?,
        };
        let n = blocks.len() * BLOCK_VOXELS;
        if [voxels.tsdf.len(), voxels.weight.len(), voxels.color.len()] != [n; 3] {
            return Err(bad("holds voxels of the wrong count"));
        }
        let count = input.usize()?;
        let mut meshes = Vec::with_capacity(count.min(blocks.len()));
        for _ in 0..count {
            let index = block_of_words(&input.u32s()?).ok_or_else(|| bad("mesh has no block"))?;
            let triples = |v: Vec<f32>| -> Option<Vec<[f32; 3]>> {
                v.len()
                    .is_multiple_of(3)
                    .then(|| v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
            };
            let positions = triples(input.f32s()?).ok_or_else(|| bad("mesh has bad positions"))?;
            let normals = triples(input.f32s()?).ok_or_else(|| bad("mesh has bad normals"))?;
            let colors = input.bytes()?;
            let indices = input.u32s()?;
            let keys = input.u32s()?;
            let vertices = positions.len();
            if normals.len() != vertices
                || colors.len() != 3 * vertices
                || keys.len() != 4 * vertices
                || !indices.len().is_multiple_of(3)
                || indices.iter().any(|&i| i as usize >= vertices)
            {
                return Err(bad("mesh has inconsistent arrays"));
            }
            meshes.push(BlockMesh {
                index,
                positions,
                normals,
                colors: colors.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
                indices,
                edge_keys: keys
                    .chunks_exact(4)
                    .map(|k| EdgeKey {
                        voxel: [k[0] as i32, k[1] as i32, k[2] as i32],
                        axis: k[3] as u8,
                    })
                    .collect(),
            });
        }
        Ok(Self {
            blocks,
            voxels,
            meshes,
        })
    }

    fn heap_bytes(&self) -> usize {
        let mesh = |m: &BlockMesh| m.positions.len() * (12 + 12 + 3 + 16) + m.indices.len() * 4;
        self.blocks.len() * (12 + 12 * BLOCK_VOXELS) + self.meshes.iter().map(mesh).sum::<usize>()
    }
}

fn block_words(b: &BlockIndex) -> [u32; 3] {
    [b.x as u32, b.y as u32, b.z as u32]
}

fn block_of_words(w: &[u32]) -> Option<BlockIndex> {
    match w {
        [x, y, z] => Some(BlockIndex::new(*x as i32, *y as i32, *z as i32)),
        _ => None,
    }
}

/// Which chunks are in the pool and when each was last integrated into (in fusion steps), and
/// which are in the store. Only integration counts as use: a chunk brought back to mesh a
/// neighbour keeps its age and leaves again at the next eviction.
#[derive(Debug, Default)]
pub struct Residency {
    step: u64,
    used: HashMap<ChunkIndex, u64>,
    /// The chunks each of the newest keyframes went into, oldest first.
    newest: VecDeque<Vec<ChunkIndex>>,
    spilled: BTreeMap<ChunkIndex, Spilled>,
    loads: usize,
}

/// What [`Residency::figures`] reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SpilledFigures {
    pub blocks: usize,
    pub chunks: usize,
    pub triangles: usize,
    pub loads: usize,
}

/// A chunk in the store: the stored value, its block and triangle counts and when it was
/// last used.
#[derive(Debug)]
struct Spilled {
    stored: Arc<Stored<ChunkData>>,
    blocks: usize,
    triangles: usize,
    used: u64,
}

impl Residency {
    /// A new fusion step (a keyframe added or moved): chunks it uses are the most recent.
    pub fn advance(&mut self) {
        self.step += 1;
    }

    /// A new keyframe went into `blocks`: their chunks are where the camera works now.
    pub fn keyframe_added(&mut self, blocks: &[BlockIndex]) {
        let mut chunks: Vec<ChunkIndex> = blocks.iter().map(ChunkIndex::of).collect();
        chunks.sort_unstable();
        chunks.dedup();
        self.newest.push_back(chunks);
        if self.newest.len() > PROTECTED_KEYFRAMES {
            self.newest.pop_front();
        }
    }

    /// Marks the chunks of `blocks` used now.
    pub fn touch<'a>(&mut self, blocks: impl IntoIterator<Item = &'a BlockIndex>) {
        for b in blocks {
            self.used.insert(ChunkIndex::of(b), self.step);
        }
    }

    /// Whether any chunk is in the store (nothing to load otherwise).
    pub fn any_spilled(&self) -> bool {
        !self.spilled.is_empty()
    }

    pub fn is_spilled(&self, b: &BlockIndex) -> bool {
        self.spilled.contains_key(&ChunkIndex::of(b))
    }

    /// The spilled chunk `c` (it stays listed until [`Residency::loaded`]).
    pub fn stored(&self, c: &ChunkIndex) -> Option<Arc<Stored<ChunkData>>> {
        self.spilled.get(c).map(|s| Arc::clone(&s.stored))
    }

    /// Chunk `c` is back in the pool, as old as when it left; its stored copy is dropped (and
    /// so removed from the store: the pool's copy is the one that changes from now on).
    pub fn loaded(&mut self, c: ChunkIndex) {
        if let Some(s) = self.spilled.remove(&c) {
            self.loads += 1;
            self.used.insert(c, s.used);
        }
    }

    /// Chunk `c` left the pool for `stored`, which holds `data`.
    pub fn spilled(&mut self, c: ChunkIndex, stored: Arc<Stored<ChunkData>>, data: &ChunkData) {
        let used = self.used.remove(&c).unwrap_or(0);
        self.spilled.insert(
            c,
            Spilled {
                stored,
                blocks: data.blocks.len(),
                triangles: data.meshes.iter().map(BlockMesh::triangle_count).sum(),
                used,
            },
        );
    }

    /// Resident chunks (with their block counts) that may leave the pool, least recently used
    /// first: every one but those of the newest keyframes, newest first, while their blocks
    /// stay within `protect_blocks` (the newest keyframe's always).
    pub fn eviction_order(
        &self,
        resident: &BTreeMap<ChunkIndex, usize>,
        protect_blocks: usize,
    ) -> Vec<ChunkIndex> {
        let mut protected = HashSet::new();
        let mut blocks = 0;
        for (k, chunks) in self.newest.iter().rev().enumerate() {
            let more: usize = chunks
                .iter()
                .filter(|c| !protected.contains(*c))
                .map(|c| resident.get(c).copied().unwrap_or(0))
                .sum();
            if k > 0 && blocks + more > protect_blocks {
                break;
            }
            blocks += more;
            protected.extend(chunks.iter().copied());
        }
        let mut order: Vec<(u64, ChunkIndex)> = resident
            .keys()
            .filter(|c| !protected.contains(*c))
            .map(|c| (self.used.get(c).copied().unwrap_or(0), *c))
            .collect();
        order.sort_unstable();
        order.into_iter().map(|(_, c)| c).collect()
    }

    /// The whole surface: `resident` block meshes and the spilled chunks' meshes.
    pub fn surface<'a>(&self, resident: &'a BTreeMap<BlockIndex, BlockMesh>) -> Surface<'a> {
        Surface::new(
            resident,
            self.spilled
                .iter()
                .map(|(c, s)| (*c, Arc::clone(&s.stored))),
        )
    }

    /// Blocks, chunks and mesh triangles in the store, and chunk loads so far.
    pub fn figures(&self) -> SpilledFigures {
        SpilledFigures {
            blocks: self.spilled.values().map(|s| s.blocks).sum(),
            chunks: self.spilled.len(),
            triangles: self.spilled.values().map(|s| s.triangles).sum(),
            loads: self.loads,
        }
    }
}

/// A whole surface as a [`BlockSource`]: block meshes in memory and chunks of them spilled
/// to the store (a fuser's, or a session's copy of it), read back a slab of chunks (one chunk
/// x) at a time and dropped after, so walking the surface holds one slab of what is spilled.
#[derive(Debug)]
pub struct Surface<'a> {
    resident: &'a BTreeMap<BlockIndex, BlockMesh>,
    /// Sorted by chunk.
    spilled: Vec<(ChunkIndex, Arc<Stored<ChunkData>>)>,
}

impl<'a> Surface<'a> {
    /// `resident` and the `spilled` chunks' meshes (no block in both).
    pub fn new(
        resident: &'a BTreeMap<BlockIndex, BlockMesh>,
        spilled: impl IntoIterator<Item = (ChunkIndex, Arc<Stored<ChunkData>>)>,
    ) -> Self {
        let mut spilled: Vec<_> = spilled.into_iter().collect();
        spilled.sort_by_key(|(c, _)| *c);
        Self { resident, spilled }
    }
}

impl BlockSource for Surface<'_> {
    fn runs(&mut self, each: &mut dyn FnMut(&[&BlockMesh]) -> Result<()>) -> Result<()> {
        let slabs: BTreeSet<i32> = self
            .resident
            .keys()
            .map(|b| ChunkIndex::of(b).0[0])
            .chain(self.spilled.iter().map(|(c, _)| c.0[0]))
            .collect();
        for cx in slabs {
            let from = self.spilled.partition_point(|(c, _)| c.0[0] < cx);
            let to = self.spilled.partition_point(|(c, _)| c.0[0] <= cx);
            let loaded = self.spilled[from..to]
                .iter()
                .map(|(_, s)| s.get())
                .collect::<Result<Vec<_>>>()?;
            let block = |x: i32| BlockIndex::new(x * CHUNK_SIDE, i32::MIN, i32::MIN);
            let mut blocks: Vec<&BlockMesh> = self
                .resident
                .range(block(cx)..block(cx + 1))
                .map(|(_, m)| m)
                .chain(loaded.iter().flat_map(|c| c.meshes.iter()))
                .collect();
            blocks.sort_by_key(|b| b.index);
            each(&blocks)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spill::{FolderStore, Spill};

    #[test]
    fn chunks_hold_four_blocks_a_side_rounding_down() {
        assert_eq!(
            ChunkIndex::of(&BlockIndex::new(0, 3, -1)),
            ChunkIndex([0, 0, -1])
        );
        assert_eq!(
            ChunkIndex::of(&BlockIndex::new(4, -4, -5)),
            ChunkIndex([1, -1, -2])
        );
    }

    #[test]
    fn a_chunk_round_trips_through_the_store_bit_identical() {
        let blocks = vec![BlockIndex::new(-1, 2, 3), BlockIndex::new(0, 2, 3)];
        let n = blocks.len() * BLOCK_VOXELS;
        let data = ChunkData {
            voxels: CpuVoxels {
                tsdf: (0..n).map(|i| (i as f32 * 0.37).sin()).collect(),
                weight: (0..n).map(|i| i as f32 * 0.5).collect(),
                color: (0..n).map(|i| i as u32 * 7919).collect(),
            },
            meshes: vec![BlockMesh {
                index: blocks[1],
                positions: vec![
                    [0.1, -0.2, 3.0],
                    [1.0, 2.0, f32::MIN_POSITIVE],
                    [5.0, 6.0, 7.0],
                ],
                normals: vec![[0.0, 0.0, 1.0]; 3],
                colors: vec![[1, 2, 3], [250, 0, 9], [7, 7, 7]],
                indices: vec![0, 1, 2],
                edge_keys: (0..3)
                    .map(|a| EdgeKey {
                        voxel: [-8, a, 17],
                        axis: a as u8,
                    })
                    .collect(),
            }],
            blocks,
        };
        let dir = std::env::temp_dir().join(format!("relfusion-chunks-{}", std::process::id()));
        let spill = Spill::default();
        spill
            .attach(Arc::new(FolderStore::new(&dir).expect("dir")))
            .expect("attach");
        let stored = Stored::new(&spill, Arc::new(data.clone()));
        stored.spill().expect("spill");
        assert!(!stored.is_held());
        assert_eq!(*stored.get().expect("read back"), data);
        drop(stored);
        assert_eq!(std::fs::read_dir(&dir).expect("dir").count(), 0);
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    #[test]
    fn eviction_keeps_the_newest_keyframes_chunks_and_takes_the_oldest_first() {
        let mut r = Residency::default();
        let blocks = [0, 4, 8, 12].map(|x| BlockIndex::new(x, 0, 0));
        let chunks = blocks.map(|b| ChunkIndex::of(&b));
        // Keyframes went into chunks 1, 0, 3 in that order; chunk 2 was last touched by a
        // keyframe moved (re-integrated) before them.
        r.advance();
        r.touch([&blocks[2]]);
        for k in [1, 0, 3] {
            r.advance();
            r.touch([&blocks[k]]);
            r.keyframe_added(&blocks[k..=k]);
        }
        let resident: BTreeMap<ChunkIndex, usize> = chunks.iter().map(|c| (*c, 10)).collect();
        // Room for the newest keyframe only: the rest leave, least recently used first.
        assert_eq!(
            r.eviction_order(&resident, 0),
            vec![chunks[2], chunks[1], chunks[0]]
        );
        // Room for two keyframes' chunks: the second newest stays too.
        assert_eq!(r.eviction_order(&resident, 20), vec![chunks[2], chunks[1]]);
    }
}
