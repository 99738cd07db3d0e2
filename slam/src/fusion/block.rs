//! Sparse voxel blocks: block coordinates, the block table that maps a block to its slot in the
//! voxel pool, and the meshing jobs handed to marching cubes.
//!
//! Why a table on the CPU and a flat pool on the GPU: the set of blocks a keyframe touches is
//! computed on the CPU from its depth map anyway (a few thousand blocks), so allocation is a
//! hash-map insert there; the GPU then only sees dense slot arrays, which keeps every kernel
//! free of hashing and atomics (the same split as the "CPU hash, GPU pool" voxel-hashing
//! variants).
//!
//! Geometry: voxel `v` (global integer coordinates) is a *sample point* at `v · voxel_size` in
//! the world frame; block `b` holds the voxels `8b … 8b + 7` along each axis, so its minimum
//! corner is `b · block_size` with `block_size = 8 · voxel_size` (the proto's `BlockIndex`).
//! Inside a block, voxel `(x, y, z)` is stored at `x + 8y + 64z`, and slot `s` occupies pool
//! entries `s · 512 … s · 512 + 511`.

use std::collections::HashMap;

use serde::Serialize;

/// Voxels along one edge of a block.
pub const BLOCK_SIDE: i32 = 8;
/// Voxels in one block.
pub const BLOCK_VOXELS: usize = 512;

/// Integer coordinates of a block (see the module doc for the geometry).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
pub struct BlockIndex {
    pub x: i32,
    pub y: i32,
    pub z: i32,
}

impl BlockIndex {
    pub const fn new(x: i32, y: i32, z: i32) -> Self {
        Self { x, y, z }
    }

    /// The block holding global voxel `v`.
    pub fn of_voxel(v: [i32; 3]) -> Self {
        Self::new(
            v[0].div_euclid(BLOCK_SIDE),
            v[1].div_euclid(BLOCK_SIDE),
            v[2].div_euclid(BLOCK_SIDE),
        )
    }

    /// The block whose cube contains world point `p` (sample points `8b … 8b + 7` and the
    /// cells between them).
    pub fn of_point(p: [f32; 3], voxel_size: f32) -> Self {
        let v = |c: f32| (c / voxel_size).floor() as i32;
        Self::of_voxel([v(p[0]), v(p[1]), v(p[2])])
    }

    /// Global coordinates of this block's voxel `local` (each component in `0..8`).
    pub fn voxel(&self, local: [i32; 3]) -> [i32; 3] {
        [
            self.x * BLOCK_SIDE + local[0],
            self.y * BLOCK_SIDE + local[1],
            self.z * BLOCK_SIDE + local[2],
        ]
    }

    pub fn offset(&self, d: [i32; 3]) -> Self {
        Self::new(self.x + d[0], self.y + d[1], self.z + d[2])
    }
}

/// Storage index of voxel `(x, y, z)` inside its block.
pub const fn voxel_linear(x: i32, y: i32, z: i32) -> usize {
    (x + BLOCK_SIDE * y + BLOCK_SIDE * BLOCK_SIDE * z) as usize
}

/// Offsets of the seven "upper" neighbours a block's cells reach into, in the order of
/// [`MeshJob::neighbours`]: neighbour `n - 1` is offset `(n & 1, (n >> 1) & 1, (n >> 2) & 1)`
/// for `n = 1 … 7`.
pub const UPPER_NEIGHBOURS: [[i32; 3]; 7] = [
    [1, 0, 0],
    [0, 1, 0],
    [1, 1, 0],
    [0, 0, 1],
    [1, 0, 1],
    [0, 1, 1],
    [1, 1, 1],
];

/// Why a block could not be allocated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the voxel pool is full ({capacity} blocks, fusion.max_blocks)")]
pub struct PoolFull {
    pub capacity: u32,
}

/// Block → slot map with a free list; slots are reused after [`BlockTable::free`].
#[derive(Debug, Clone)]
pub struct BlockTable {
    slots: HashMap<BlockIndex, u32>,
    free: Vec<u32>,
    /// Slots ever handed out (the pool's high-water mark).
    high_water: u32,
    max_blocks: u32,
}

impl BlockTable {
    pub fn new(max_blocks: u32) -> Self {
        Self {
            slots: HashMap::new(),
            free: Vec::new(),
            high_water: 0,
            max_blocks,
        }
    }

    pub fn get(&self, b: &BlockIndex) -> Option<u32> {
        self.slots.get(b).copied()
    }

    /// The block's slot, allocating one if it has none; `true` when the slot is new (its
    /// voxels must be reset before use).
    pub fn get_or_alloc(&mut self, b: BlockIndex) -> Result<(u32, bool), PoolFull> {
        if let Some(&s) = self.slots.get(&b) {
            return Ok((s, false));
        }
        let slot = match self.free.pop() {
            Some(s) => s,
            None if self.high_water < self.max_blocks => {
                self.high_water += 1;
                self.high_water - 1
            }
            None => {
                return Err(PoolFull {
                    capacity: self.max_blocks,
                });
            }
        };
        self.slots.insert(b, slot);
        Ok((slot, true))
    }

    /// Releases a block's slot (its voxels are stale until reset on reuse).
    pub fn free(&mut self, b: &BlockIndex) -> Option<u32> {
        let s = self.slots.remove(b)?;
        self.free.push(s);
        Some(s)
    }

    /// Allocated blocks.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Slots the pool must hold (highest slot handed out + 1).
    pub fn high_water(&self) -> u32 {
        self.high_water
    }

    pub fn iter(&self) -> impl Iterator<Item = (BlockIndex, u32)> + '_ {
        self.slots.iter().map(|(b, s)| (*b, *s))
    }

    /// The meshing job of an allocated block (`None` if it has no slot).
    pub fn mesh_job(&self, b: BlockIndex) -> Option<MeshJob> {
        let slot = self.get(&b)?;
        let mut neighbours = [-1i32; 7];
        for (n, d) in UPPER_NEIGHBOURS.iter().enumerate() {
            neighbours[n] = self.get(&b.offset(*d)).map_or(-1, |s| s as i32);
        }
        Some(MeshJob {
            index: b,
            slot,
            neighbours,
        })
    }
}

/// One block to mesh: its slot and the slots of its seven upper neighbours (−1 = not
/// allocated; cells that reach into a missing neighbour produce no triangles).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MeshJob {
    pub index: BlockIndex,
    pub slot: u32,
    pub neighbours: [i32; 7],
}

/// Packs an 8-bit RGB colour as voxels and depth inputs store it: `r | g << 8 | b << 16`.
pub const fn pack_rgb(rgb: [u8; 3]) -> u32 {
    rgb[0] as u32 | (rgb[1] as u32) << 8 | (rgb[2] as u32) << 16
}

pub const fn unpack_rgb(c: u32) -> [u8; 3] {
    [c as u8, (c >> 8) as u8, (c >> 16) as u8]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxel_to_block_rounds_towards_negative_infinity() {
        assert_eq!(BlockIndex::of_voxel([0, 7, -1]), BlockIndex::new(0, 0, -1));
        assert_eq!(
            BlockIndex::of_voxel([8, -8, -9]),
            BlockIndex::new(1, -1, -2)
        );
        assert_eq!(
            BlockIndex::of_point([0.79, -0.01, 1.6], 0.1),
            BlockIndex::new(0, -1, 2)
        );
    }

    #[test]
    fn table_reuses_freed_slots_and_refuses_past_its_capacity() {
        let mut t = BlockTable::new(2);
        let a = BlockIndex::new(0, 0, 0);
        let b = BlockIndex::new(1, 0, 0);
        assert_eq!(t.get_or_alloc(a), Ok((0, true)));
        assert_eq!(t.get_or_alloc(a), Ok((0, false)));
        assert_eq!(t.get_or_alloc(b), Ok((1, true)));
        assert!(t.get_or_alloc(BlockIndex::new(2, 0, 0)).is_err());
        assert_eq!(t.free(&a), Some(0));
        assert_eq!(t.get_or_alloc(BlockIndex::new(2, 0, 0)), Ok((0, true)));
        let job = t.mesh_job(BlockIndex::new(1, 0, 0)).expect("allocated");
        assert_eq!(
            job.neighbours[0], 0,
            "+x neighbour is the block at (2, 0, 0)"
        );
        assert!(job.neighbours[1..].iter().all(|&n| n == -1));
    }

    #[test]
    fn colours_round_trip() {
        assert_eq!(unpack_rgb(pack_rgb([1, 200, 255])), [1, 200, 255]);
    }
}
