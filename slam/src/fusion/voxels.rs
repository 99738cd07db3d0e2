//! Voxel storage: the CPU pool ([`CpuVoxels`], the reference every kernel is tested against)
//! and the borrowed view of the GPU pool's buffers ([`VoxelBuffers`]). Both use the same
//! layout: three flat arrays indexed `slot · 512 + voxel_linear(x, y, z)`.
//!
//! Per voxel: truncated signed distance in units of the truncation distance (`[-1, 1]`,
//! positive in front of the surface), the accumulated weight (0 = never observed), and the
//! weighted mean colour packed as `r | g << 8 | b << 16` — 12 bytes per voxel.

use super::block::BLOCK_VOXELS;

/// Bytes of one voxel in either pool (f32 tsdf, f32 weight, u32 colour).
pub const BYTES_PER_VOXEL: usize = 12;

/// The CPU voxel pool.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CpuVoxels {
    pub tsdf: Vec<f32>,
    pub weight: Vec<f32>,
    pub color: Vec<u32>,
}

impl CpuVoxels {
    /// Slots the pool holds.
    pub fn capacity(&self) -> u32 {
        (self.tsdf.len() / BLOCK_VOXELS) as u32
    }

    /// Grows the pool to at least `slots` slots (new voxels unobserved).
    pub fn ensure_capacity(&mut self, slots: u32) {
        let n = slots as usize * BLOCK_VOXELS;
        if n > self.tsdf.len() {
            self.tsdf.resize(n, 0.0);
            self.weight.resize(n, 0.0);
            self.color.resize(n, 0);
        }
    }

    /// Marks every voxel of the slots unobserved (a freshly allocated or reused slot).
    pub fn reset_slots(&mut self, slots: &[u32]) {
        for &s in slots {
            let r = s as usize * BLOCK_VOXELS..(s as usize + 1) * BLOCK_VOXELS;
            self.tsdf[r.clone()].fill(0.0);
            self.weight[r.clone()].fill(0.0);
            self.color[r].fill(0);
        }
    }

    /// Range of pool entries of one slot.
    pub fn slot_range(slot: u32) -> std::ops::Range<usize> {
        slot as usize * BLOCK_VOXELS..(slot as usize + 1) * BLOCK_VOXELS
    }

    /// The voxels of `slots`, slot `slots[k]` as slot `k` of the result (a chunk of blocks
    /// leaving the pool for the session's store).
    pub fn read_slots(&self, slots: &[u32]) -> CpuVoxels {
        let mut out = CpuVoxels::default();
        for &s in slots {
            let r = Self::slot_range(s);
            out.tsdf.extend_from_slice(&self.tsdf[r.clone()]);
            out.weight.extend_from_slice(&self.weight[r.clone()]);
            out.color.extend_from_slice(&self.color[r]);
        }
        out
    }

    /// Writes slot `k` of `data` into slot `slots[k]` (the inverse of [`Self::read_slots`]).
    /// Panics when `data` holds fewer slots or a slot is beyond the capacity.
    pub fn write_slots(&mut self, slots: &[u32], data: &CpuVoxels) {
        for (k, &s) in slots.iter().enumerate() {
            let (to, from) = (Self::slot_range(s), Self::slot_range(k as u32));
            self.tsdf[to.clone()].copy_from_slice(&data.tsdf[from.clone()]);
            self.weight[to.clone()].copy_from_slice(&data.weight[from.clone()]);
            self.color[to].copy_from_slice(&data.color[from]);
        }
    }

    /// Largest weight in each slot (0 = the block holds no observation any more).
    pub fn max_weights(&self, slots: &[u32]) -> Vec<f32> {
        slots
            .iter()
            .map(|&s| {
                self.weight[Self::slot_range(s)]
                    .iter()
                    .fold(0f32, |m, &w| m.max(w))
            })
            .collect()
    }
}

/// The GPU pool's three storage buffers (same layout as [`CpuVoxels`]).
#[derive(Clone, Copy, Debug)]
pub struct VoxelBuffers<'a> {
    pub tsdf: &'a wgpu::Buffer,
    pub weight: &'a wgpu::Buffer,
    pub color: &'a wgpu::Buffer,
    /// Slots the buffers hold.
    pub capacity: u32,
}
