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

    /// The whole pool copied back (tests, debugging); waits for the GPU.
    pub fn download(&self) -> Result<CpuVoxels> {
        let bytes = u64::from(self.capacity) * SLOT_BYTES;
        let staging = self.ctx.staging_buffer("voxel pool download", 3 * bytes);
        let device = self.ctx.device();
        self.ctx.checked("voxel pool download", || {
            let mut encoder = device.create_command_encoder(&Default::default());
            for (k, buffer) in [&self.tsdf, &self.weight, &self.color]
                .into_iter()
                .enumerate()
            {
                encoder.copy_buffer_to_buffer(buffer, 0, &staging, k as u64 * bytes, bytes);
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
        let limits = self.ctx.limits();
        let binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let pixels = view.pixels();
        let list_bytes = 16 * blocks.len() as u64;
        if 4 * pixels as u64 > binding || list_bytes > binding {
            return Err(Error::Gpu(format!(
                "{} blocks or a {}x{} map exceed the device's {binding}-byte storage binding",
                blocks.len(),
                view.width,
                view.height
            )));
        }
        let block_count = u32::try_from(blocks.len())
            .map_err(|_| Error::Gpu(format!("{} blocks in one integration", blocks.len())))?;
        let groups = u64::from(block_count) * (BLOCK_VOXELS as u64 / u64::from(WORKGROUP));
        let (gx, gy) = dispatch_size(groups, limits.max_compute_workgroups_per_dimension)
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

/// Runs of consecutive values in a sorted, deduplicated list, as (first, count).
fn runs(sorted: &[u32]) -> Vec<(u32, u32)> {
    let mut out: Vec<(u32, u32)> = Vec::new();
    for &s in sorted {
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
mod tests {
    use super::super::integrate::tests::{camera, random_maps, random_pose};
    use super::super::integrate::{integrate_cpu, touched_blocks};
    use super::*;
    use rand::seq::SliceRandom;
    use rand::{Rng, SeedableRng};
    use std::time::Instant;

    fn context() -> Arc<GpuContext> {
        crate::gpu::shared_context().unwrap_or_else(|e| panic!("no GPU context: {e}"))
    }

    /// Voxels whose update GPU and CPU may legitimately decide differently: the projection
    /// within 1e-4 px of a pixel boundary, or the signed distance within 1e-5 of −truncation
    /// (a rounding difference flips the test). Marks each pool entry of `blocks` that is so.
    fn mark_ambiguous(
        view: &DepthView,
        p: &IntegrateParams,
        blocks: &[(BlockIndex, u32)],
        out: &mut [bool],
    ) {
        let m = &view.camera_from_world;
        let near_half = |c: f32| ((c + 0.5) - (c + 0.5).round()).abs() < 1e-4;
        for &(b, slot) in blocks {
            for i in 0..BLOCK_VOXELS {
                let v = b.voxel([i as i32 & 7, (i as i32 >> 3) & 7, i as i32 >> 6]);
                let pw = v.map(|c| c as f32 * p.voxel_size);
                let row = |r: &[f32; 4]| ((r[0] * pw[0] + r[1] * pw[1]) + r[2] * pw[2]) + r[3];
                let (x, y, z) = (row(&m[0]), row(&m[1]), row(&m[2]));
                if z.is_nan() || z <= 0.0 {
                    continue;
                }
                let u = view.fx * (x / z) + view.cx;
                let vv = view.fy * (y / z) + view.cy;
                let (ur, vr) = ((u + 0.5).floor(), (vv + 0.5).floor());
                let mut ambiguous = near_half(u) || near_half(vv);
                if ur >= 0.0 && vr >= 0.0 && ur < view.width as f32 && vr < view.height as f32 {
                    let d = view.depth[vr as usize * view.width as usize + ur as usize];
                    let sdf = (d - z) * view.scale;
                    ambiguous |=
                        d > 0.0 && (sdf + p.truncation).abs() < 1e-5 * p.truncation.max(1.0);
                }
                out[slot as usize * BLOCK_VOXELS + i] |= ambiguous;
            }
        }
    }

    /// Compares every pool entry not marked ambiguous: tsdf and weight within 1e-5 (relative
    /// to max(1, |value|)), colour channels within 1. Returns the number compared.
    fn assert_pools_match(cpu: &CpuVoxels, gpu: &CpuVoxels, skip: &[bool], what: &str) -> usize {
        assert_eq!(cpu.tsdf.len(), gpu.tsdf.len(), "{what}: pool sizes");
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-5 * a.abs().max(1.0);
        let mut compared = 0;
        for k in (0..cpu.tsdf.len()).filter(|&k| !skip[k]) {
            compared += 1;
            assert!(
                close(cpu.weight[k], gpu.weight[k]) && close(cpu.tsdf[k], gpu.tsdf[k]),
                "{what}: entry {k}: cpu (t {}, w {}) gpu (t {}, w {})",
                cpu.tsdf[k],
                cpu.weight[k],
                gpu.tsdf[k],
                gpu.weight[k]
            );
            let (a, b) = (
                super::super::block::unpack_rgb(cpu.color[k]),
                super::super::block::unpack_rgb(gpu.color[k]),
            );
            assert!(
                (0..3).all(|c| a[c].abs_diff(b[c]) <= 1),
                "{what}: entry {k}: colour {a:?} vs {b:?}"
            );
        }
        compared
    }

    #[test]
    fn gpu_integration_matches_cpu_on_random_inputs() {
        let ctx = context();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(29);
        for (round, &(w, h)) in [(64u32, 48u32), (37, 23), (64, 48)].iter().enumerate() {
            let cam = camera(w, h);
            let n = (w * h) as usize;
            let pose_a = random_pose(&mut rng);
            let pose_b = random_pose(&mut rng);
            let (da, wa, ca) = random_maps(n, 0.5..3.0, 0.2, &mut rng);
            let (db, wb, cb) = random_maps(n, 0.5..3.0, 0.2, &mut rng);
            let view_a = DepthView::new(&cam, &pose_a, &da, &wa, &ca).expect("view a");
            let view_b = DepthView::new(&cam, &pose_b, &db, &wb, &cb).expect("view b");
            let voxel_size = 0.04 * pose_a.scale as f32;
            let p = IntegrateParams {
                voxel_size,
                truncation: 4.0 * voxel_size,
                max_weight: if round == 1 { 1.5 } else { 128.0 },
            };
            let mut blocks = touched_blocks(&view_a, &p);
            blocks.extend(touched_blocks(&view_b, &p));
            // Blocks no view reaches, and far ones behind or beside the cameras.
            for _ in 0..50 {
                blocks.push(BlockIndex::new(
                    rng.random_range(-300..300),
                    rng.random_range(-300..300),
                    rng.random_range(-300..300),
                ));
            }
            blocks.sort_unstable();
            blocks.dedup();
            // Random distinct slots in a pool with unused slots.
            let capacity = blocks.len() as u32 + 37;
            let mut slots: Vec<u32> = (0..capacity).collect();
            slots.shuffle(&mut rng);
            let listed: Vec<(BlockIndex, u32)> =
                blocks.iter().copied().zip(slots.iter().copied()).collect();

            let mut cpu = CpuVoxels::default();
            cpu.ensure_capacity(capacity);
            let mut gpu = GpuVoxels::new(Arc::clone(&ctx), capacity).expect("gpu pool");
            let mut skip = vec![false; capacity as usize * BLOCK_VOXELS];
            mark_ambiguous(&view_a, &p, &listed, &mut skip);
            mark_ambiguous(&view_b, &p, &listed, &mut skip);
            for (view, sign) in [(&view_a, 1.0), (&view_b, 1.0), (&view_a, -1.0)] {
                integrate_cpu(&mut cpu, &listed, view, &p, sign);
                gpu.integrate(&listed, view, &p, sign)
                    .expect("gpu integrate");
            }
            let downloaded = gpu.download().expect("download");
            let compared = assert_pools_match(&cpu, &downloaded, &skip, &format!("round {round}"));
            let observed = cpu.weight.iter().filter(|&&w| w > 0.0).count();
            assert!(
                observed > 1000,
                "round {round}: only {observed} voxels observed"
            );
            eprintln!(
                "round {round}: {} blocks, {observed} observed voxels, {compared} compared, {} \
                 skipped as boundary cases",
                listed.len(),
                skip.len() - compared
            );
            // Max weights agree too (the caller frees blocks whose weight fell to 0).
            let some: Vec<u32> = slots.iter().take(100).copied().collect();
            let (mg, mc) = (
                gpu.max_weights(&some).expect("max weights"),
                cpu.max_weights(&some),
            );
            for (g, c) in mg.iter().zip(&mc) {
                assert!((g - c).abs() <= 1e-5 * c.max(1.0), "max weight {g} vs {c}");
            }
        }
    }

    /// More blocks than 65535 workgroups of 64 reach (8191 blocks): the 2-D dispatch, with the
    /// only surface-holding blocks at the end of the list.
    #[test]
    fn gpu_integration_uses_a_2d_dispatch_for_long_block_lists() {
        let ctx = context();
        let max = ctx.limits().max_compute_workgroups_per_dimension;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let cam = camera(32, 24);
        let pose = random_pose(&mut rng);
        let (d, w, c) = random_maps(32 * 24, 1.0..1.5, 0.1, &mut rng);
        let view = DepthView::new(&cam, &pose, &d, &w, &c).expect("view");
        let voxel_size = 0.05 * pose.scale as f32;
        let p = IntegrateParams {
            voxel_size,
            truncation: 3.0 * voxel_size,
            max_weight: 128.0,
        };
        let touched = touched_blocks(&view, &p);
        let filler = (u64::from(max) * u64::from(WORKGROUP) / BLOCK_VOXELS as u64) as usize + 10;
        // Filler blocks far away (never seen), then the touched ones.
        let mut listed: Vec<(BlockIndex, u32)> = (0..filler)
            .map(|k| (BlockIndex::new(1000 + k as i32, -1000, 1000), k as u32))
            .collect();
        listed.extend(
            touched
                .iter()
                .enumerate()
                .map(|(k, b)| (*b, (filler + k) as u32)),
        );
        let capacity = listed.len() as u32;
        assert!(dispatch_size(capacity as u64 * 8, max).expect("fits").1 > 1);
        let mut cpu = CpuVoxels::default();
        cpu.ensure_capacity(capacity);
        let mut gpu = GpuVoxels::new(Arc::clone(&ctx), capacity).expect("gpu pool");
        integrate_cpu(&mut cpu, &listed, &view, &p, 1.0);
        gpu.integrate(&listed, &view, &p, 1.0)
            .expect("gpu integrate");
        let mut skip = vec![false; capacity as usize * BLOCK_VOXELS];
        mark_ambiguous(&view, &p, &listed[filler..], &mut skip);
        let got = gpu.download().expect("download");
        assert_pools_match(&cpu, &got, &skip, "2-D dispatch");
        let tail = filler * BLOCK_VOXELS..;
        assert!(
            got.weight[tail].iter().any(|&w| w > 0.0),
            "the tail blocks were integrated"
        );
    }

    #[test]
    fn gpu_pool_growth_preserves_contents_and_resets_clear_slots() {
        let ctx = context();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let cam = camera(24, 18);
        let pose = random_pose(&mut rng);
        let (d, w, c) = random_maps(24 * 18, 1.0..1.5, 0.0, &mut rng);
        let view = DepthView::new(&cam, &pose, &d, &w, &c).expect("view");
        let voxel_size = 0.1 * pose.scale as f32;
        let p = IntegrateParams {
            voxel_size,
            truncation: 2.0 * voxel_size,
            max_weight: 128.0,
        };
        let touched = touched_blocks(&view, &p);
        let listed: Vec<(BlockIndex, u32)> = touched
            .iter()
            .enumerate()
            .map(|(k, b)| (*b, k as u32))
            .collect();
        let n = listed.len() as u32;
        let mut gpu = GpuVoxels::new(Arc::clone(&ctx), n).expect("gpu pool");
        assert_eq!(gpu.buffers().capacity, n);
        gpu.integrate(&listed, &view, &p, 1.0).expect("integrate");
        let before = gpu.download().expect("download");
        assert!(before.weight.iter().any(|&w| w > 0.0));

        gpu.ensure_capacity(n + 1).expect("grow");
        assert_eq!(gpu.buffers().capacity, 2 * n, "grows by doubling");
        assert!(gpu.bytes() >= 3 * u64::from(2 * n) * SLOT_BYTES);
        let after = gpu.download().expect("download");
        let old = before.tsdf.len();
        assert_eq!(after.tsdf[..old], before.tsdf[..]);
        assert_eq!(after.weight[..old], before.weight[..]);
        assert_eq!(after.color[..old], before.color[..]);
        assert!(after.weight[old..].iter().all(|&w| w == 0.0));
        assert!(after.tsdf[old..].iter().all(|&t| t == 0.0));
        assert!(after.color[old..].iter().all(|&c| c == 0));
        gpu.ensure_capacity(3).expect("no-op");
        assert_eq!(gpu.buffers().capacity, 2 * n);

        // Resets: a run of consecutive slots, a lone one, a duplicate, out of order.
        let resets = [3, 1, 2, n - 1, 2];
        gpu.reset_slots(&resets).expect("reset");
        let mut cpu = after.clone();
        cpu.reset_slots(&resets);
        assert_eq!(gpu.download().expect("download"), cpu);
        let all: Vec<u32> = (0..2 * n).collect();
        assert_eq!(gpu.max_weights(&all).expect("max"), cpu.max_weights(&all));

        // Beyond the capacity or the device: errors, not panics.
        assert!(matches!(gpu.reset_slots(&[2 * n]), Err(Error::Shape(_))));
        assert!(matches!(gpu.max_weights(&[2 * n]), Err(Error::Shape(_))));
        let bad = [(BlockIndex::new(0, 0, 0), 2 * n)];
        assert!(matches!(
            gpu.integrate(&bad, &view, &p, 1.0),
            Err(Error::Shape(_))
        ));
        assert!(matches!(gpu.ensure_capacity(u32::MAX), Err(Error::Gpu(_))));
        assert_eq!(gpu.buffers().capacity, 2 * n);
    }

    #[test]
    fn dispatch_and_runs_helpers() {
        assert_eq!(dispatch_size(10, 65535), Some((10, 1)));
        assert_eq!(dispatch_size(65536, 65535), Some((65535, 2)));
        assert_eq!(dispatch_size(0, 65535), Some((0, 1)));
        assert_eq!(dispatch_size(65535u64 * 65535 + 1, 65535), None);
        assert_eq!(runs(&[1, 2, 3, 7, 9, 10]), vec![(1, 3), (7, 1), (9, 2)]);
        assert!(runs(&[]).is_empty());
    }

    /// One 320×240 view of a tilted plane, GPU against CPU (prints the times; dev profile).
    #[test]
    fn gpu_integration_of_a_working_resolution_view() {
        let ctx = context();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (w, h) = (320u32, 240u32);
        let cam = camera(w, h);
        let pose = random_pose(&mut rng);
        let n = (w * h) as usize;
        let (mut d, wt, c) = random_maps(n, 1.0..2.0, 0.05, &mut rng);
        for (i, x) in d.iter_mut().enumerate() {
            if *x > 0.0 {
                *x = 1.5 + 0.002 * ((i % w as usize) as f32 - 160.0);
            }
        }
        let view = DepthView::new(&cam, &pose, &d, &wt, &c).expect("view");
        // 128 voxels across the median depth, truncation 4 voxels (the defaults).
        let voxel_size = 1.5 * pose.scale as f32 / 128.0;
        let p = IntegrateParams {
            voxel_size,
            truncation: 4.0 * voxel_size,
            max_weight: 128.0,
        };
        let start = Instant::now();
        let touched = touched_blocks(&view, &p);
        let t_touched = start.elapsed();
        let listed: Vec<(BlockIndex, u32)> = touched
            .iter()
            .enumerate()
            .map(|(k, b)| (*b, k as u32))
            .collect();
        let cap = listed.len() as u32;
        let mut cpu = CpuVoxels::default();
        cpu.ensure_capacity(cap);
        let start = Instant::now();
        integrate_cpu(&mut cpu, &listed, &view, &p, 1.0);
        let t_cpu = start.elapsed();
        let mut gpu = GpuVoxels::new(Arc::clone(&ctx), cap).expect("gpu pool");
        // Warm-up (first dispatch allocates the input buffers and compiles on some drivers).
        gpu.integrate(&listed, &view, &p, 1.0)
            .expect("gpu integrate");
        ctx.wait().expect("wait");
        gpu.reset_slots(&(0..cap).collect::<Vec<_>>())
            .expect("reset");
        ctx.wait().expect("wait");
        let start = Instant::now();
        gpu.integrate(&listed, &view, &p, 1.0)
            .expect("gpu integrate");
        ctx.wait().expect("wait");
        let t_gpu = start.elapsed();
        let mut skip = vec![false; cap as usize * BLOCK_VOXELS];
        mark_ambiguous(&view, &p, &listed, &mut skip);
        assert_pools_match(&cpu, &gpu.download().expect("download"), &skip, "320x240");
        eprintln!(
            "320x240 view, {} blocks ({} voxels) on {}: touched_blocks {:.1} ms, CPU integrate \
             {:.1} ms, GPU integrate (upload + kernel) {:.1} ms",
            listed.len(),
            listed.len() * BLOCK_VOXELS,
            ctx.adapter_info().name,
            t_touched.as_secs_f64() * 1e3,
            t_cpu.as_secs_f64() * 1e3,
            t_gpu.as_secs_f64() * 1e3
        );
    }
}
