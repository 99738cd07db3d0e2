//! The GPU voxel pool and the runner of the integration kernel (`tsdf_integrate.wgsl`).
//!
//! The pool is three flat storage buffers laid out like [`CpuVoxels`] (slot `s` = entries
//! `512 s … 512 s + 511`); the CPU block table decides slots, the GPU only sees the list of
//! (block, slot) pairs to update. The CPU twin, and the definition of what integration
//! computes, is [`super::integrate::integrate_cpu`].
//!
//! Nothing here waits for the GPU except the read-backs ([`GpuVoxels::download`],
//! [`GpuVoxels::max_weights`]): integration, resets and growth are queued, and wgpu orders them
//! with later submissions (marching cubes reads the pool in a later submission).

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};

use super::block::{BLOCK_VOXELS, BlockIndex};
use super::integrate::{DepthView, IntegrateParams};
use super::voxels::{CpuVoxels, VoxelBuffers};
use crate::gpu::GpuContext;
use crate::{Error, Result};

/// Invocations per workgroup (`@workgroup_size(64, 1, 1)` in the WGSL).
const WORKGROUP: u32 = 64;
/// Bytes of one slot in each of the three pool buffers (every voxel field is 4 bytes).
const SLOT_BYTES: u64 = 4 * BLOCK_VOXELS as u64;

/// Rust mirror of `IntegrateParams` in `tsdf_integrate.wgsl` (uniform, 96 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
struct IntegrateUniform {
    rows: [[f32; 4]; 3],
    /// fx, fy, cx, cy.
    intrinsics: [f32; 4],
    width: u32,
    height: u32,
    block_count: u32,
    scale: f32,
    voxel_size: f32,
    truncation: f32,
    max_weight: f32,
    sign: f32,
}
const _: () = assert!(std::mem::size_of::<IntegrateUniform>() == 96);

/// Per-pixel input buffers for one depth-map size (every keyframe has the working resolution,
/// so they are allocated once).
#[derive(Debug)]
struct PixelBuffers {
    pixels: usize,
    depth: wgpu::Buffer,
    weight: wgpu::Buffer,
    color: wgpu::Buffer,
}

/// The GPU voxel pool with the compiled integration kernel.
#[derive(Debug)]
pub struct GpuVoxels {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    tsdf: wgpu::Buffer,
    weight: wgpu::Buffer,
    color: wgpu::Buffer,
    /// Slots the pool buffers hold.
    capacity: u32,
    params: wgpu::Buffer,
    pixels: Option<PixelBuffers>,
    /// The (x, y, z, slot) list of the last integration; grows, never shrinks.
    blocks: Option<wgpu::Buffer>,
}

impl GpuVoxels {
    /// A pool of `initial_slots` unobserved slots (at least one: wgpu binds no empty buffer).
    pub fn new(ctx: Arc<GpuContext>, initial_slots: u32) -> Result<Self> {
        use relfusion_shaders::{ENTRY_POINT, TSDF_INTEGRATE};
        let pipeline = ctx.compute_pipeline("tsdf_integrate", TSDF_INTEGRATE, ENTRY_POINT)?;
        let capacity = initial_slots.max(1);
        check_slots(&ctx, capacity)?;
        let [tsdf, weight, color] = allocate_pool(&ctx, capacity);
        let params = ctx.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("tsdf_integrate params"),
            size: std::mem::size_of::<IntegrateUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Self {
            ctx,
            pipeline,
            tsdf,
            weight,
            color,
            capacity,
            params,
            pixels: None,
            blocks: None,
        })
    }

    /// Grows the pool to at least `slots` slots, doubling at least (amortised copies), within
    /// what one storage binding may hold; new voxels are unobserved (wgpu zero-fills new
    /// buffers), existing ones are copied. [`Error::Gpu`] if `slots` exceeds the device limit.
    pub fn ensure_capacity(&mut self, slots: u32) -> Result<()> {
        if slots <= self.capacity {
            return Ok(());
        }
        let max = check_slots(&self.ctx, slots)?;
        let capacity = slots.max(self.capacity.saturating_mul(2)).min(max);
        let new = allocate_pool(&self.ctx, capacity);
        let bytes = u64::from(self.capacity) * SLOT_BYTES;
        let device = self.ctx.device();
        self.ctx.checked("voxel pool growth", || {
            let mut encoder = device.create_command_encoder(&Default::default());
            for (old, new) in [&self.tsdf, &self.weight, &self.color]
                .into_iter()
                .zip(&new)
            {
                encoder.copy_buffer_to_buffer(old, 0, new, 0, bytes);
            }
            self.ctx.queue().submit([encoder.finish()]);
        })?;
        [self.tsdf, self.weight, self.color] = new;
        self.capacity = capacity;
        Ok(())
    }

    /// Marks every voxel of `slots` unobserved (freshly allocated or reused slots): one clear
    /// per run of consecutive slots and buffer.
    pub fn reset_slots(&mut self, slots: &[u32]) -> Result<()> {
        self.check_listed(slots.iter().copied())?;
        let mut sorted = slots.to_vec();
        sorted.sort_unstable();
        sorted.dedup();
        let device = self.ctx.device();
        self.ctx.checked("voxel slot reset", || {
            let mut encoder = device.create_command_encoder(&Default::default());
            for (first, count) in runs(&sorted) {
                for buffer in [&self.tsdf, &self.weight, &self.color] {
                    encoder.clear_buffer(
                        buffer,
                        u64::from(first) * SLOT_BYTES,
                        Some(u64::from(count) * SLOT_BYTES),
                    );
                }
            }
            self.ctx.queue().submit([encoder.finish()]);
        })
    }

    /// The pool's buffers (for the marching-cubes kernel).
    pub fn buffers(&self) -> VoxelBuffers<'_> {
        VoxelBuffers {
            tsdf: &self.tsdf,
            weight: &self.weight,
            color: &self.color,
            capacity: self.capacity,
        }
    }

    /// Largest weight in each slot (0 = the block holds no observation any more, e.g. after
    /// de-integration), in the order of `slots`. Copies the slots' weights back and waits.
    pub fn max_weights(&self, slots: &[u32]) -> Result<Vec<f32>> {
        self.check_listed(slots.iter().copied())?;
        if slots.is_empty() {
            return Ok(Vec::new());
        }
        let staging = self
            .ctx
            .staging_buffer("voxel max weights", slots.len() as u64 * SLOT_BYTES);
        let device = self.ctx.device();
        self.ctx.checked("voxel max weights", || {
            let mut encoder = device.create_command_encoder(&Default::default());
            for (k, &s) in slots.iter().enumerate() {
                encoder.copy_buffer_to_buffer(
                    &self.weight,
                    u64::from(s) * SLOT_BYTES,
                    &staging,
                    k as u64 * SLOT_BYTES,
                    SLOT_BYTES,
                );
            }
            self.ctx.queue().submit([encoder.finish()]);
        })?;
        self.ctx.read_mapped(&staging, |raw| {
            bytemuck::cast_slice::<u8, f32>(raw)
                .chunks_exact(BLOCK_VOXELS)
                .map(|w| w.iter().fold(0f32, |m, &x| m.max(x)))
                .collect()
        })
    }

    /// The voxels of `slots`, slot `slots[k]` as slot `k` of the result (a chunk of blocks
    /// leaving the pool for the session's store); one copy per run of consecutive slots and
    /// buffer; waits for the GPU.
    pub fn read_slots(&self, slots: &[u32]) -> Result<CpuVoxels> {
        self.check_listed(slots.iter().copied())?;
        if slots.is_empty() {
            return Ok(CpuVoxels::default());
        }
        let bytes = slots.len() as u64 * SLOT_BYTES;
        let staging = self.ctx.staging_buffer("voxel slots read", 3 * bytes);
        let device = self.ctx.device();
        self.ctx.checked("voxel slots read", || {
            let mut encoder = device.create_command_encoder(&Default::default());
            for (b, buffer) in [&self.tsdf, &self.weight, &self.color]
                .into_iter()
                .enumerate()
            {
                let mut k = 0u64;
                for (first, count) in runs(slots) {
                    encoder.copy_buffer_to_buffer(
                        buffer,
                        u64::from(first) * SLOT_BYTES,
                        &staging,
                        b as u64 * bytes + k * SLOT_BYTES,
                        u64::from(count) * SLOT_BYTES,
                    );
                    k += u64::from(count);
                }
            }
            self.ctx.queue().submit([encoder.finish()]);
        })?;
        let n = bytes as usize;
        self.ctx.read_mapped(&staging, |raw| CpuVoxels {
            tsdf: bytemuck::cast_slice(&raw[..n]).to_vec(),
            weight: bytemuck::cast_slice(&raw[n..2 * n]).to_vec(),
            color: bytemuck::cast_slice(&raw[2 * n..3 * n]).to_vec(),
        })
    }

    /// Writes slot `k` of `data` into slot `slots[k]` (a chunk read back from the store);
    /// queued like integration. [`Error::Shape`] when `data` does not hold `slots.len()`
    /// slots or a slot is beyond the capacity.
    pub fn write_slots(&mut self, slots: &[u32], data: &CpuVoxels) -> Result<()> {
        self.check_listed(slots.iter().copied())?;
        let n = slots.len() * BLOCK_VOXELS;
        if [data.tsdf.len(), data.weight.len(), data.color.len()] != [n; 3] {
            return Err(Error::Shape(format!(
                "{} voxel slots written from data of {} voxels",
                slots.len(),
                data.tsdf.len()
            )));
        }
        let queue = self.ctx.queue();
        self.ctx.checked("voxel slots write", || {
            for (k, &s) in slots.iter().enumerate() {
                let (at, r) = (u64::from(s) * SLOT_BYTES, CpuVoxels::slot_range(k as u32));
                queue.write_buffer(&self.tsdf, at, bytemuck::cast_slice(&data.tsdf[r.clone()]));
                queue.write_buffer(
                    &self.weight,
                    at,
                    bytemuck::cast_slice(&data.weight[r.clone()]),
                );
                queue.write_buffer(&self.color, at, bytemuck::cast_slice(&data.color[r]));
            }
        })
    }

    /// The whole pool copied back (tests, debugging); waits for the GPU.
    pub fn download(&self) -> Result<CpuVoxels> {
        self.read_slots(&(0..self.capacity).collect::<Vec<_>>())
    }

    /// Integrates (`sign > 0`) or de-integrates (`sign ≤ 0`) `view` into the voxels of
    /// `blocks` (block, slot; distinct slots); same contract as
    /// [`super::integrate::integrate_cpu`], but errors instead of panicking: [`Error::Shape`]
    /// for a slot beyond the capacity or a view whose slices do not match its size,
    /// [`Error::Gpu`] when the list or the map exceed the device's limits.
    pub fn integrate(
        &mut self,
        blocks: &[(BlockIndex, u32)],
        view: &DepthView,
        p: &IntegrateParams,
        sign: f32,
    ) -> Result<()> {
        view.check()?;
        self.check_listed(blocks.iter().map(|(_, s)| *s))?;
        if blocks.is_empty() {
            return Ok(());
        }
        let (block_count, (gx, gy)) = self.prepare_inputs(blocks.len(), view)?;
        let (Some(px), Some(list)) = (self.pixels.as_ref(), self.blocks.as_ref()) else {
            return Err(Error::Gpu("tsdf_integrate input buffers missing".into()));
        };

        let uniform = IntegrateUniform {
            rows: view.camera_from_world,
            intrinsics: [view.fx, view.fy, view.cx, view.cy],
            width: view.width,
            height: view.height,
            block_count,
            scale: view.scale,
            voxel_size: p.voxel_size,
            truncation: p.truncation,
            max_weight: p.max_weight,
            sign,
        };
        let entries: Vec<[i32; 4]> = blocks
            .iter()
            .map(|(b, s)| [b.x, b.y, b.z, *s as i32])
            .collect();
        let queue = self.ctx.queue();
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&uniform));
        queue.write_buffer(list, 0, bytemuck::cast_slice(&entries));
        queue.write_buffer(&px.depth, 0, bytemuck::cast_slice(view.depth));
        queue.write_buffer(&px.weight, 0, bytemuck::cast_slice(view.weight));
        queue.write_buffer(&px.color, 0, bytemuck::cast_slice(view.color));
        let device = self.ctx.device();
        self.ctx.checked("tsdf integration", || {
            fn bind(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
                wgpu::BindGroupEntry {
                    binding,
                    resource: buffer.as_entire_binding(),
                }
            }
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("tsdf_integrate"),
                layout: &self.pipeline.get_bind_group_layout(0),
                entries: &[
                    bind(0, &self.params),
                    bind(1, list),
                    bind(2, &px.depth),
                    bind(3, &px.weight),
                    bind(4, &px.color),
                    bind(5, &self.tsdf),
                    bind(6, &self.weight),
                    bind(7, &self.color),
                ],
            });
            let mut encoder = device.create_command_encoder(&Default::default());
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("tsdf_integrate"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, Some(&group), &[]);
                pass.dispatch_workgroups(gx, gy, 1);
            }
            queue.submit([encoder.finish()]);
        })
    }

    /// Checks an integration of `blocks` blocks and `view` against the device's limits and
    /// sizes the cached input buffers for it; the block count and the dispatch size.
    fn prepare_inputs(&mut self, blocks: usize, view: &DepthView) -> Result<(u32, (u32, u32))> {
        let limits = self.ctx.limits();
        let binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let pixels = view.pixels();
        let list_bytes = 16 * blocks as u64;
        if 4 * pixels as u64 > binding || list_bytes > binding {
            return Err(Error::Gpu(format!(
                "{blocks} blocks or a {}x{} map exceed the device's {binding}-byte storage binding",
                view.width, view.height
            )));
        }
        let block_count = u32::try_from(blocks)
            .map_err(|_| Error::Gpu(format!("{blocks} blocks in one integration")))?;
        let groups = u64::from(block_count) * (BLOCK_VOXELS as u64 / u64::from(WORKGROUP));
        let dispatch = dispatch_size(groups, limits.max_compute_workgroups_per_dimension)
            .ok_or_else(|| {
                Error::Gpu(format!(
                    "{block_count} blocks need more workgroups than the device allows"
                ))
            })?;
        if self.pixels.as_ref().is_none_or(|b| b.pixels != pixels) {
            let storage = |label: &str| self.ctx.storage_buffer(label, 4 * pixels as u64);
            self.pixels = Some(PixelBuffers {
                pixels,
                depth: storage("tsdf_integrate depth"),
                weight: storage("tsdf_integrate weight"),
                color: storage("tsdf_integrate color"),
            });
        }
        if self.blocks.as_ref().is_none_or(|b| b.size() < list_bytes) {
            let size = list_bytes.next_power_of_two().min(binding.max(list_bytes));
            self.blocks = Some(self.ctx.storage_buffer("tsdf_integrate blocks", size));
        }
        Ok((block_count, dispatch))
    }

    /// GPU memory held: the pool and the cached input buffers.
    pub fn bytes(&self) -> u64 {
        let inputs = self
            .pixels
            .as_ref()
            .map_or(0, |b| b.depth.size() + b.weight.size() + b.color.size());
        3 * u64::from(self.capacity) * SLOT_BYTES
            + self.params.size()
            + inputs
            + self.blocks.as_ref().map_or(0, wgpu::Buffer::size)
    }

    /// [`Error::Shape`] if a slot is beyond the pool's capacity.
    fn check_listed(&self, mut slots: impl Iterator<Item = u32>) -> Result<()> {
        match slots.find(|&s| s >= self.capacity) {
            Some(s) => Err(Error::Shape(format!(
                "voxel slot {s} beyond the pool's {} slots",
                self.capacity
            ))),
            None => Ok(()),
        }
    }
}

/// Most slots one pool buffer may hold on this device (`Error::Gpu` if `slots` exceeds it).
fn check_slots(ctx: &GpuContext, slots: u32) -> Result<u32> {
    let limits = ctx.limits();
    let binding = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    let max = u32::try_from(binding / SLOT_BYTES).unwrap_or(u32::MAX);
    if slots > max {
        return Err(Error::Gpu(format!(
            "{slots} voxel blocks exceed the device's storage binding ({binding} B = {max} blocks); \
             lower fusion.max_blocks"
        )));
    }
    Ok(max)
}

/// Three zero-filled pool buffers (tsdf, weight, colour) of `slots` slots.
fn allocate_pool(ctx: &GpuContext, slots: u32) -> [wgpu::Buffer; 3] {
    let bytes = u64::from(slots) * SLOT_BYTES;
    ["voxel tsdf", "voxel weight", "voxel color"].map(|label| ctx.storage_buffer(label, bytes))
}

/// Runs of consecutive increasing values in a list (sorted and deduplicated: every run), as
/// (first, count).
fn runs(values: &[u32]) -> Vec<(u32, u32)> {
    let mut out: Vec<(u32, u32)> = Vec::new();
    for &s in values {
        match out.last_mut() {
            Some((first, count)) if *first + *count == s => *count += 1,
            _ => out.push((s, 1)),
        }
    }
    out
}

/// Workgroups `(x, y)` covering `groups` flat workgroups with at most `max` per dimension
/// (`x · y ≥ groups`; the kernel skips the excess); `None` if even `max²` is too few.
fn dispatch_size(groups: u64, max: u32) -> Option<(u32, u32)> {
    let x = groups.min(u64::from(max));
    if x == 0 {
        return Some((0, 1));
    }
    let y = groups.div_ceil(x);
    Some((
        u32::try_from(x).ok()?,
        u32::try_from(y).ok().filter(|&y| y <= max)?,
    ))
}

#[cfg(test)]
#[path = "gpu_volume_tests.rs"]
mod tests;
