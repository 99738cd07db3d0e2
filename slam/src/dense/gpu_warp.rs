//! GPU runner of the two-view forward warp (`two_view_warp.wgsl`, eq. 14 of DeepRelativeFusion).
//!
//! The CPU twin, and the definition of what the warp computes, is
//! [`super::two_view::warp_inverse_depth_cpu`]. Both do the same f32 arithmetic in the same
//! order; the only freedom a GPU has (fused multiply-adds, a division that is not correctly
//! rounded) moves a warped value by an ulp or so, and very rarely moves a projection that falls
//! within an ulp of a pixel boundary to the neighbouring pixel. The tests below bound both.
//!
//! The nearest-surface test is an `atomicMax` on the warped inverse depth's bit pattern
//! (positive floats order like their bits), so the result does not depend on the order in which
//! invocations run, and the cleared output buffer reads back directly as f32 (0 = empty).

use std::sync::{Arc, Mutex};

use bytemuck::{Pod, Zeroable};

use super::two_view::{InverseDepthWarp, WarpMatrix};
use crate::geometry::{PinholeCamera, Sim3};
use crate::gpu::GpuContext;
use crate::image::ImageF32;
use crate::{Error, Result};

/// Workgroup edge of the kernel (`@workgroup_size(16, 16, 1)` in the WGSL).
const WORKGROUP: u32 = 16;

/// Rust mirror of `WarpParams` in `two_view_warp.wgsl` (uniform, 96 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct WarpParams {
    /// Rows of `[sR | t]` of `dst_from_src`.
    pub rows: [[f32; 4]; 3],
    /// fx, fy, cx, cy.
    pub intrinsics: [f32; 4],
    /// 1/fx, 1/fy, minimum depth, unused.
    pub inverse: [f32; 4],
    pub width: u32,
    pub height: u32,
    /// 1 when source pixels with `exclude > 0` are skipped.
    pub has_exclude: u32,
    pub _pad: u32,
}
const _: () = assert!(std::mem::size_of::<WarpParams>() == 96);

impl WarpParams {
    /// The uniform for warping a `width × height` map (the f32 constants come from
    /// [`WarpMatrix`], shared with the CPU twin so both use bit-identical inputs).
    fn new(m: &WarpMatrix, width: u32, height: u32, has_exclude: bool) -> Self {
        Self {
            rows: m.rows,
            intrinsics: [m.fx, m.fy, m.cx, m.cy],
            inverse: [m.fx_inv, m.fy_inv, m.min_depth, 0.0],
            width,
            height,
            has_exclude: u32::from(has_exclude),
            _pad: 0,
        }
    }
}

/// Device buffers for one image size, reused while the size stays the same (every keyframe of
/// a session has the working resolution).
#[derive(Debug)]
struct Buffers {
    pixels: usize,
    params: wgpu::Buffer,
    src: wgpu::Buffer,
    exclude: wgpu::Buffer,
    dst: wgpu::Buffer,
    staging: wgpu::Buffer,
}

/// The compiled warp kernel with cached buffers; create once per [`GpuContext`] and share.
#[derive(Debug)]
pub struct GpuWarp {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    /// Behind a mutex so that [`GpuWarp::warp`] takes `&self` (the dense layer holds the
    /// runner in shared state); one warp at a time uses the buffers.
    buffers: Mutex<Option<Buffers>>,
}

impl GpuWarp {
    /// Compiles (or fetches from the context's cache) the kernel.
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self> {
        use relfusion_shaders::{ENTRY_POINT, TWO_VIEW_WARP};
        let pipeline = ctx.compute_pipeline("two_view_warp", TWO_VIEW_WARP, ENTRY_POINT)?;
        Ok(Self {
            ctx,
            pipeline,
            buffers: Mutex::new(None),
        })
    }

    /// The context the kernel runs on.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    fn allocate(&self, pixels: usize) -> Buffers {
        let device = self.ctx.device();
        let bytes = 4 * pixels as u64;
        let storage = |label: &str, extra: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | extra,
                mapped_at_creation: false,
            })
        };
        Buffers {
            pixels,
            params: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("two_view_warp params"),
                size: std::mem::size_of::<WarpParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            src: storage("two_view_warp src", wgpu::BufferUsages::empty()),
            // Bound even without an exclusion map (the kernel then never reads it).
            exclude: storage("two_view_warp exclude", wgpu::BufferUsages::empty()),
            dst: storage("two_view_warp dst", wgpu::BufferUsages::COPY_SRC),
            staging: self.ctx.staging_buffer("two_view_warp readback", bytes),
        }
    }
}

impl InverseDepthWarp for GpuWarp {
    /// Forward-warps `src` into the other view on the GPU; same contract and checks as
    /// [`super::two_view::warp_inverse_depth_cpu`]. Upload, clear, kernel and readback are one
    /// submission.
    fn warp(
        &self,
        src: &ImageF32,
        exclude: Option<&ImageF32>,
        camera: &PinholeCamera,
        dst_from_src: &Sim3,
    ) -> Result<ImageF32> {
        super::two_view::check_warp_inputs(src, exclude, camera)?;
        let (w, h) = (src.width, src.height);
        let n = w * h;
        let (wu, hu) = (
            u32::try_from(w).map_err(|_| Error::Shape(format!("width {w} too large")))?,
            u32::try_from(h).map_err(|_| Error::Shape(format!("height {h} too large")))?,
        );
        let max_groups = self.ctx.limits().max_compute_workgroups_per_dimension;
        if wu.div_ceil(WORKGROUP) > max_groups || hu.div_ceil(WORKGROUP) > max_groups {
            return Err(Error::Gpu(format!(
                "{w}x{h} needs more workgroups than the device allows ({max_groups})"
            )));
        }
        let bytes = 4 * n as u64;
        let limits = self.ctx.limits();
        if bytes
            > limits
                .max_storage_buffer_binding_size
                .min(limits.max_buffer_size)
        {
            return Err(Error::Gpu(format!(
                "a {w}x{h} map needs {bytes} B; more than the device binds"
            )));
        }
        let matrix = WarpMatrix::new(camera, dst_from_src);
        let params = WarpParams::new(&matrix, wu, hu, exclude.is_some());

        let mut guard = self
            .buffers
            .lock()
            .map_err(|_| Error::Gpu("two-view warp buffers poisoned by a panic".into()))?;
        if guard.as_ref().is_none_or(|b| b.pixels != n) {
            *guard = Some(self.allocate(n));
        }
        let buffers = guard
            .as_ref()
            .ok_or_else(|| Error::Gpu("two-view warp buffers missing".into()))?;

        let queue = self.ctx.queue();
        queue.write_buffer(&buffers.params, 0, bytemuck::bytes_of(&params));
        queue.write_buffer(&buffers.src, 0, bytemuck::cast_slice(&src.data));
        if let Some(ex) = exclude {
            queue.write_buffer(&buffers.exclude, 0, bytemuck::cast_slice(&ex.data));
        }
        let device = self.ctx.device();
        self.ctx.checked("two-view warp", || {
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("two_view_warp"),
                layout: &self.pipeline.get_bind_group_layout(0),
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: buffers.params.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: buffers.src.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: buffers.exclude.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: buffers.dst.as_entire_binding(),
                    },
                ],
            });
            let mut encoder = device.create_command_encoder(&Default::default());
            encoder.clear_buffer(&buffers.dst, 0, None);
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("two_view_warp"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, Some(&group), &[]);
                pass.dispatch_workgroups(wu.div_ceil(WORKGROUP), hu.div_ceil(WORKGROUP), 1);
            }
            encoder.copy_buffer_to_buffer(&buffers.dst, 0, &buffers.staging, 0, bytes);
            queue.submit([encoder.finish()]);
        })?;
        // The atomics hold the bits of positive f32 values (or 0u = 0.0): read them as f32.
        let data = self.ctx.read_mapped(&buffers.staging, |raw| {
            bytemuck::cast_slice::<u8, f32>(&raw[..4 * n]).to_vec()
        })?;
        ImageF32::from_vec(w, h, data).map_err(Into::into)
    }
}

#[cfg(test)]
mod tests {
    use super::super::two_view::tests::random_idepth;
    use super::super::two_view::warp_inverse_depth_cpu;
    use super::*;
    use crate::geometry::SO3;
    use crate::gpu::GpuConfig;
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};

    /// A real adapter is required (lavapipe on machines without a GPU); fails, never skips.
    fn context() -> Arc<GpuContext> {
        Arc::new(
            GpuContext::new(&GpuConfig::default())
                .unwrap_or_else(|e| panic!("no GPU context: {e}")),
        )
    }

    /// Small rotation (≤ ~0.1 rad), translation (≤ 0.2 of the mean depth), scale 0.8–1.25.
    fn random_sim3(rng: &mut impl Rng) -> Sim3 {
        let mut v = |a: f64| {
            Vector3::new(
                rng.random_range(-a..a),
                rng.random_range(-a..a),
                rng.random_range(-a..a),
            )
        };
        let phi = v(0.06);
        let t = v(0.2);
        let scale = rng.random_range(0.8f64.ln()..1.25f64.ln()).exp();
        Sim3::new(SO3::exp(&phi), t, scale)
    }

    fn camera_for(w: usize, h: usize) -> PinholeCamera {
        let f = 0.9 * w.max(h) as f64;
        PinholeCamera::new(
            f,
            1.02 * f,
            0.5 * (w as f64 - 1.0) + 0.3,
            0.5 * (h as f64 - 1.0) - 0.2,
            w as u32,
            h as u32,
        )
        .expect("valid camera")
    }

    /// Pixels where GPU and CPU disagree beyond 8 ulps (value differences, or one empty
    /// and the other not), and the largest relative difference where both hold a value.
    fn compare(cpu: &ImageF32, gpu: &ImageF32) -> (usize, f32, usize) {
        let (mut differ, mut worst, mut filled) = (0, 0.0f32, 0);
        for (&c, &g) in cpu.data.iter().zip(&gpu.data) {
            if c > 0.0 {
                filled += 1;
            }
            if c == g {
                continue;
            }
            if c > 0.0 && g > 0.0 {
                let rel = (c - g).abs() / c;
                worst = worst.max(rel);
                // GPU division need not be correctly rounded (Vulkan allows 2.5 ulp), and
                // drivers may fuse multiply-adds: a few ulps (≤ 4 seen on lavapipe).
                if rel <= 8.0 * f32::EPSILON {
                    continue;
                }
            }
            differ += 1;
        }
        (differ, worst, filled)
    }

    #[test]
    fn gpu_warp_matches_cpu_on_random_maps_and_poses() {
        let ctx = context();
        let warp = GpuWarp::new(Arc::clone(&ctx)).expect("kernel compiles");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
        let mut exact = 0usize;
        let mut total = 0usize;
        for &(w, h) in &[(320, 240), (97, 33), (5, 1), (320, 240), (97, 33), (1, 7)] {
            for round in 0..3 {
                let camera = camera_for(w, h);
                let src = random_idepth(w, h, 0.3, &mut rng);
                let exclude = (round == 1).then(|| random_idepth(w, h, 0.7, &mut rng));
                let pose = if round == 2 && w * h > 100 {
                    Sim3::identity()
                } else {
                    random_sim3(&mut rng)
                };
                let cpu = warp_inverse_depth_cpu(&src, exclude.as_ref(), &camera, &pose)
                    .expect("cpu warp");
                let gpu = warp
                    .warp(&src, exclude.as_ref(), &camera, &pose)
                    .expect("gpu warp");
                assert_eq!((gpu.width, gpu.height), (w, h));
                let (differ, worst, filled) = compare(&cpu, &gpu);
                let allowed = (w * h) / 1000;
                assert!(
                    differ <= allowed,
                    "{w}x{h} round {round}: {differ} pixels differ (allowed {allowed}), \
                     worst relative difference {worst}"
                );
                // Something must have landed, or the comparison says nothing.
                assert!(filled > 0 || w * h < 8, "{w}x{h} round {round}: empty warp");
                exact += cpu
                    .data
                    .iter()
                    .zip(&gpu.data)
                    .filter(|(c, g)| c == g)
                    .count();
                total += w * h;
            }
        }
        eprintln!("gpu warp: {exact}/{total} pixels bit-identical to the CPU twin");
    }

    #[test]
    fn gpu_warp_reuses_buffers_across_sizes_and_checks_shapes() {
        let ctx = context();
        let warp = GpuWarp::new(ctx).expect("kernel compiles");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let pose = random_sim3(&mut rng);
        // Big, small, big again: the cached buffers are replaced each time the size changes.
        for &(w, h) in &[(64, 48), (13, 9), (64, 48)] {
            let camera = camera_for(w, h);
            let src = random_idepth(w, h, 0.1, &mut rng);
            let cpu = warp_inverse_depth_cpu(&src, None, &camera, &pose).expect("cpu");
            let gpu = warp.warp(&src, None, &camera, &pose).expect("gpu");
            assert!(compare(&cpu, &gpu).0 <= 1, "{w}x{h}");
        }
        let camera = camera_for(64, 48);
        let wrong = ImageF32::filled(63, 48, 1.0);
        assert!(matches!(
            warp.warp(&wrong, None, &camera, &pose),
            Err(Error::Shape(_))
        ));
        let src = ImageF32::filled(64, 48, 1.0);
        let bad_exclude = ImageF32::filled(64, 47, 0.0);
        assert!(matches!(
            warp.warp(&src, Some(&bad_exclude), &camera, &pose),
            Err(Error::Shape(_))
        ));
    }

    #[test]
    fn gpu_warp_identity_returns_input_and_skips_invalid_values() {
        let ctx = context();
        let warp = GpuWarp::new(ctx).expect("kernel compiles");
        let (w, h) = (33, 21);
        let camera = camera_for(w, h);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut src = random_idepth(w, h, 0.2, &mut rng);
        src.data[3] = f32::NAN;
        src.data[4] = f32::INFINITY;
        src.data[5] = -1.0;
        let out = warp
            .warp(&src, None, &camera, &Sim3::identity())
            .expect("gpu warp");
        for (i, (&s, &o)) in src.data.iter().zip(&out.data).enumerate() {
            let expected = if s > 0.0 && s.is_finite() { s } else { 0.0 };
            let rel = (o - expected).abs() / expected.max(1e-30);
            assert!(
                o == expected || rel <= 2.0 * f32::EPSILON,
                "pixel {i}: {o} vs {expected}"
            );
        }
    }
}
