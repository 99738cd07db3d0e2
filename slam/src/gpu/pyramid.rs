//! GPU runner of the pyramid kernels (`pyramid_downsample.wgsl`, `image_gradient.wgsl`): builds
//! every level of an image pyramid and its gradients in one submission.
//!
//! The CPU twin and the exact definitions (floor sizes, 2×2 box average, central differences
//! with clamp-to-edge borders) are in [`crate::image::pyramid`]; the GPU output matches it to
//! float rounding (tested below to < 1e-3 in 8-bit units).
//!
//! Memory layout: all levels live in one storage buffer per output (`intensity`, `gx`, `gy`,
//! `grad_mag`), level `L` starting at float offset [`LevelLayout::offset`]; pixel `(x, y)` of
//! level `L` is at `offset + y · width + x` in each of the four buffers. Later kernels
//! (tracking residuals, depth filtering) can bind a [`GpuPyramid`] directly.

use std::num::NonZeroU64;
use std::time::Duration;

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use super::{GpuContext, PassTimer};
use crate::image::ImageF32;
use crate::image::pyramid::{Pyramid, PyramidLevel, level_sizes};
use crate::{Error, Result};

/// Workgroup edge of both kernels (`@workgroup_size(16, 16, 1)` in the WGSL).
const WORKGROUP: u32 = 16;

/// Rust mirror of `DownsampleParams` in `pyramid_downsample.wgsl` (uniform, 32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct DownsampleParams {
    pub src_offset: u32,
    pub src_width: u32,
    pub src_height: u32,
    pub dst_offset: u32,
    pub dst_width: u32,
    pub dst_height: u32,
    pub _pad0: u32,
    pub _pad1: u32,
}
const _: () = assert!(std::mem::size_of::<DownsampleParams>() == 32);

/// Rust mirror of `GradientParams` in `image_gradient.wgsl` (uniform, 16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct GradientParams {
    pub offset: u32,
    pub width: u32,
    pub height: u32,
    pub _pad0: u32,
}
const _: () = assert!(std::mem::size_of::<GradientParams>() == 16);

/// Where one level lives in the pyramid buffers (all in floats, not bytes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LevelLayout {
    pub width: u32,
    pub height: u32,
    /// First float of the level in `intensity`, `gx`, `gy` and `grad_mag`.
    pub offset: u32,
}

impl LevelLayout {
    /// Number of pixels of the level.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// True for a 0-pixel level (never produced by [`level_sizes`]).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A pyramid resident on the GPU (see the module docs for the layout).
#[derive(Debug)]
pub struct GpuPyramid {
    pub levels: Vec<LevelLayout>,
    /// Total floats per buffer (sum of the level sizes).
    pub total_len: u32,
    pub intensity: wgpu::Buffer,
    pub gx: wgpu::Buffer,
    pub gy: wgpu::Buffer,
    pub grad_mag: wgpu::Buffer,
}

impl GpuPyramid {
    /// Copies all four outputs of every level back to the host (one submission, one map).
    pub fn download(&self, ctx: &GpuContext) -> Result<Pyramid> {
        let staging = ctx.staging_buffer("pyramid readback", 4 * self.byte_len());
        let mut encoder = ctx.device().create_command_encoder(&Default::default());
        self.record_readback(&mut encoder, &staging);
        ctx.checked("pyramid readback", || {
            ctx.queue().submit([encoder.finish()])
        })?;
        self.read_staging(ctx, &staging)
    }

    fn byte_len(&self) -> u64 {
        u64::from(self.total_len) * 4
    }

    /// Copies intensity, gx, gy, grad_mag back to back into `staging`.
    fn record_readback(&self, encoder: &mut wgpu::CommandEncoder, staging: &wgpu::Buffer) {
        let n = self.byte_len();
        for (i, buffer) in [&self.intensity, &self.gx, &self.gy, &self.grad_mag]
            .into_iter()
            .enumerate()
        {
            encoder.copy_buffer_to_buffer(buffer, 0, staging, i as u64 * n, n);
        }
    }

    /// Splits a mapped readback (see [`Self::record_readback`]) into a [`Pyramid`].
    fn read_staging(&self, ctx: &GpuContext, staging: &wgpu::Buffer) -> Result<Pyramid> {
        let total = self.total_len as usize;
        let planes: Vec<f32> = ctx.read_mapped(staging, |raw| {
            bytemuck::cast_slice::<u8, f32>(&raw[..4 * 4 * total]).to_vec()
        })?;
        let mut levels = Vec::with_capacity(self.levels.len());
        for level in &self.levels {
            let (w, h) = (level.width as usize, level.height as usize);
            let start = level.offset as usize;
            let plane = |p: usize| {
                let s = p * total + start;
                ImageF32::from_vec(w, h, planes[s..s + level.len()].to_vec())
            };
            levels.push(PyramidLevel {
                image: plane(0)?,
                gx: plane(1)?,
                gy: plane(2)?,
                grad_mag: plane(3)?,
            });
        }
        Ok(Pyramid { levels })
    }
}

/// The compiled pyramid kernels; create once per [`GpuContext`] and reuse.
#[derive(Debug)]
pub struct PyramidKernel {
    downsample: wgpu::ComputePipeline,
    gradient: wgpu::ComputePipeline,
}

impl PyramidKernel {
    /// Compiles (or fetches from the context's cache) both pipelines.
    pub fn new(ctx: &GpuContext) -> Result<Self> {
        use relfusion_shaders::{ENTRY_POINT, IMAGE_GRADIENT, PYRAMID_DOWNSAMPLE};
        Ok(Self {
            downsample: ctx.compute_pipeline(
                "pyramid_downsample",
                PYRAMID_DOWNSAMPLE,
                ENTRY_POINT,
            )?,
            gradient: ctx.compute_pipeline("image_gradient", IMAGE_GRADIENT, ENTRY_POINT)?,
        })
    }

    /// Builds `levels` levels of `image` on the GPU and downloads them: upload, all kernels
    /// and the readback go in one submission. Same contract as [`Pyramid::build_cpu`].
    pub fn build(&self, ctx: &GpuContext, image: &ImageF32, levels: usize) -> Result<Pyramid> {
        Ok(self.build_timed(ctx, image, levels)?.0)
    }

    /// Like [`Self::build`], also returning the GPU time of the kernels alone (measured with
    /// timestamp queries around the compute pass), or `None` when the device has no
    /// timestamp support.
    pub fn build_timed(
        &self,
        ctx: &GpuContext,
        image: &ImageF32,
        levels: usize,
    ) -> Result<(Pyramid, Option<Duration>)> {
        let pyramid = allocate(ctx, image, levels)?;
        let timer = ctx
            .supports_timestamps()
            .then(|| PassTimer::new(ctx, "pyramid"));
        let staging = ctx.staging_buffer("pyramid readback", 4 * pyramid.byte_len());
        ctx.queue()
            .write_buffer(&pyramid.intensity, 0, bytemuck::cast_slice(&image.data));
        ctx.checked("pyramid build", || -> Result<()> {
            let mut encoder = ctx.device().create_command_encoder(&Default::default());
            self.record(ctx, &mut encoder, &pyramid, timer.as_ref())?;
            pyramid.record_readback(&mut encoder, &staging);
            if let Some(timer) = &timer {
                timer.record_resolve(&mut encoder);
            }
            ctx.queue().submit([encoder.finish()]);
            Ok(())
        })??;
        let out = pyramid.read_staging(ctx, &staging)?;
        let kernel_time = match &timer {
            Some(timer) => Some(timer.read(ctx)?),
            None => None,
        };
        Ok((out, kernel_time))
    }

    /// Uploads `image` and builds the pyramid on the GPU without reading it back (the work is
    /// submitted; later submissions on the same queue see its results).
    pub fn build_resident(
        &self,
        ctx: &GpuContext,
        image: &ImageF32,
        levels: usize,
    ) -> Result<GpuPyramid> {
        let pyramid = allocate(ctx, image, levels)?;
        ctx.queue()
            .write_buffer(&pyramid.intensity, 0, bytemuck::cast_slice(&image.data));
        ctx.checked("pyramid build", || -> Result<()> {
            let mut encoder = ctx.device().create_command_encoder(&Default::default());
            self.record(ctx, &mut encoder, &pyramid, None)?;
            ctx.queue().submit([encoder.finish()]);
            Ok(())
        })??;
        Ok(pyramid)
    }

    /// The bind groups of the pass in dispatch order: per level, its downsampling (from level
    /// 1 on) then its gradients, each with its uniform slot.
    fn bind_groups(
        &self,
        device: &wgpu::Device,
        pyramid: &GpuPyramid,
        uniform_buffer: &wgpu::Buffer,
        stride: u64,
    ) -> Vec<wgpu::BindGroup> {
        let n = pyramid.levels.len();
        let slot = |index: usize, size: u64| {
            wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: uniform_buffer,
                offset: index as u64 * stride,
                size: NonZeroU64::new(size),
            })
        };
        let gradient_layout = self.gradient.get_bind_group_layout(0);
        let downsample_layout = self.downsample.get_bind_group_layout(0);
        let mut groups = Vec::with_capacity(2 * n);
        for l in 0..n {
            if l > 0 {
                groups.push(device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("pyramid_downsample"),
                    layout: &downsample_layout,
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: slot(2 * l + 1, 32),
                        },
                        wgpu::BindGroupEntry {
                            binding: 1,
                            resource: pyramid.intensity.as_entire_binding(),
                        },
                    ],
                }));
            }
            groups.push(device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("image_gradient"),
                layout: &gradient_layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: slot(2 * l, 16),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: pyramid.intensity.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 2,
                        resource: pyramid.gx.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 3,
                        resource: pyramid.gy.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: pyramid.grad_mag.as_entire_binding(),
                    },
                ],
            }));
        }
        groups
    }

    /// Records one compute pass: for each level `L`, downsample `L−1 → L` (if `L > 0`), then the
    /// gradients of `L`. wgpu orders dispatches within a pass (each is its own usage scope), so
    /// level `L` is complete before anything reads it.
    fn record(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        pyramid: &GpuPyramid,
        timer: Option<&PassTimer>,
    ) -> Result<()> {
        let device = ctx.device();
        // One uniform slot per dispatch, each at an offset the device accepts for bindings.
        let stride = u64::from(ctx.limits().min_uniform_buffer_offset_alignment).max(32);
        let uniforms = level_params(pyramid, stride as usize);
        let uniform_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("pyramid params"),
            contents: &uniforms,
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let groups = self.bind_groups(device, pyramid, &uniform_buffer, stride);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("pyramid"),
            timestamp_writes: timer.map(PassTimer::writes),
        });
        let mut groups = groups.iter();
        for (l, level) in pyramid.levels.iter().enumerate() {
            let dispatch = |pass: &mut wgpu::ComputePass<'_>,
                            pipeline: &wgpu::ComputePipeline,
                            group: Option<&wgpu::BindGroup>|
             -> Result<()> {
                let group =
                    group.ok_or_else(|| Error::Gpu("pyramid: bind group missing".into()))?;
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, Some(group), &[]);
                pass.dispatch_workgroups(
                    level.width.div_ceil(WORKGROUP),
                    level.height.div_ceil(WORKGROUP),
                    1,
                );
                Ok(())
            };
            if l > 0 {
                dispatch(&mut pass, &self.downsample, groups.next())?;
            }
            dispatch(&mut pass, &self.gradient, groups.next())?;
        }
        Ok(())
    }
}

/// The uniform parameters of every dispatch, each in its own `stride`-aligned slot: slot
/// `2L` the gradients of level `L`, slot `2L + 1` its downsampling from `L − 1`.
fn level_params(pyramid: &GpuPyramid, stride: usize) -> Vec<u8> {
    let n = pyramid.levels.len();
    let mut uniforms = vec![0u8; 2 * n * stride];
    for (l, level) in pyramid.levels.iter().enumerate() {
        let g = GradientParams {
            offset: level.offset,
            width: level.width,
            height: level.height,
            _pad0: 0,
        };
        let at = 2 * l * stride;
        uniforms[at..at + 16].copy_from_slice(bytemuck::bytes_of(&g));
        if l > 0 {
            let src = pyramid.levels[l - 1];
            let d = DownsampleParams {
                src_offset: src.offset,
                src_width: src.width,
                src_height: src.height,
                dst_offset: level.offset,
                dst_width: level.width,
                dst_height: level.height,
                _pad0: 0,
                _pad1: 0,
            };
            let at = (2 * l + 1) * stride;
            uniforms[at..at + 32].copy_from_slice(bytemuck::bytes_of(&d));
        }
    }
    uniforms
}

/// Creates the four level buffers, after checking the sizes against the device limits.
fn allocate(ctx: &GpuContext, image: &ImageF32, levels: usize) -> Result<GpuPyramid> {
    image.check_size()?;
    let sizes = level_sizes(image.width, image.height, levels)?;
    let limits = ctx.limits();
    let max_groups = u64::from(limits.max_compute_workgroups_per_dimension);
    let mut layout = Vec::with_capacity(sizes.len());
    let mut total: u64 = 0;
    for &(w, h) in &sizes {
        let (w, h) = (w as u64, h as u64);
        if w.div_ceil(u64::from(WORKGROUP)) > max_groups
            || h.div_ceil(u64::from(WORKGROUP)) > max_groups
        {
            return Err(Error::Gpu(format!(
                "{w}x{h} needs more workgroups than the device allows ({max_groups})"
            )));
        }
        let offset = u32::try_from(total)
            .map_err(|_| Error::Gpu("pyramid too large for u32 offsets".into()))?;
        layout.push(LevelLayout {
            width: w as u32,
            height: h as u32,
            offset,
        });
        total += w * h;
    }
    let bytes = total * 4;
    let max_binding = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    if bytes > max_binding || bytes * 4 > limits.max_buffer_size {
        return Err(Error::Gpu(format!(
            "a {}x{} pyramid needs {bytes} B per buffer; the device binds at most {max_binding} B",
            image.width, image.height
        )));
    }
    let total_len =
        u32::try_from(total).map_err(|_| Error::Gpu("pyramid too large for u32 offsets".into()))?;
    let buffer = |label: &str| ctx.storage_buffer(label, bytes);
    Ok(GpuPyramid {
        levels: layout,
        total_len,
        intensity: buffer("pyramid intensity"),
        gx: buffer("pyramid gx"),
        gy: buffer("pyramid gy"),
        grad_mag: buffer("pyramid grad_mag"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::GpuConfig;
    use rand::{Rng, SeedableRng};

    fn random_image(width: usize, height: usize, seed: u64) -> ImageF32 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let data = (0..width * height)
            .map(|_| rng.random_range(0.0f32..255.0))
            .collect();
        ImageF32::from_vec(width, height, data).expect("sizes match")
    }

    /// A real adapter is required: on machines without a GPU install mesa-vulkan-drivers
    /// (lavapipe). The test fails loudly instead of skipping.
    fn context() -> GpuContext {
        GpuContext::new(&GpuConfig::default()).unwrap_or_else(|e| panic!("no GPU context: {e}"))
    }

    #[test]
    fn gpu_pyramid_matches_cpu_on_random_images() {
        let ctx = context();
        let kernel = PyramidKernel::new(&ctx).expect("kernels compile");
        for (i, &(w, h, levels)) in [
            (640, 480, 5),
            (641, 479, 5),
            (97, 33, 3),
            (16, 16, 5),
            (1, 7, 1),
            (5, 1, 1),
        ]
        .iter()
        .enumerate()
        {
            let image = random_image(w, h, 7 + i as u64);
            let cpu = Pyramid::build_cpu(&image, levels).expect("cpu pyramid");
            let gpu = kernel.build(&ctx, &image, levels).expect("gpu pyramid");
            assert_eq!(gpu.levels.len(), levels);
            // Per level and per output, so a failure says where.
            for (l, (c, g)) in cpu.levels.iter().zip(&gpu.levels).enumerate() {
                for (name, a, b) in [
                    ("image", &c.image, &g.image),
                    ("gx", &c.gx, &g.gx),
                    ("gy", &c.gy, &g.gy),
                    ("grad_mag", &c.grad_mag, &g.grad_mag),
                ] {
                    assert_eq!(
                        (a.width, a.height),
                        (b.width, b.height),
                        "{w}x{h} level {l} {name} size"
                    );
                    let diff = a
                        .data
                        .iter()
                        .zip(&b.data)
                        .map(|(p, q)| (p - q).abs())
                        .fold(0.0f32, f32::max);
                    assert!(
                        diff < 1e-3 && b.data.iter().all(|v| v.is_finite()),
                        "{w}x{h} level {l} {name}: max |gpu - cpu| = {diff}"
                    );
                }
            }
            // The random images have texture everywhere: an all-zero gradient means the
            // kernel did not run.
            assert!(gpu.levels[0].grad_mag.data.iter().any(|&v| v > 1.0) || w.min(h) == 1);
        }
    }

    #[test]
    fn gpu_pyramid_resident_download_and_timed_agree() {
        let ctx = context();
        let kernel = PyramidKernel::new(&ctx).expect("kernels compile");
        let image = random_image(123, 77, 99);
        let resident = kernel.build_resident(&ctx, &image, 4).expect("resident");
        assert_eq!(
            resident.levels[3],
            LevelLayout {
                width: 15,
                height: 9,
                offset: 123 * 77 + 61 * 38 + 30 * 19
            }
        );
        let downloaded = resident.download(&ctx).expect("download");
        let (timed, kernel_time) = kernel.build_timed(&ctx, &image, 4).expect("timed");
        assert_eq!(downloaded.max_abs_diff(&timed).expect("same shape"), 0.0);
        assert_eq!(kernel_time.is_some(), ctx.supports_timestamps());
    }

    #[test]
    fn gpu_pyramid_rejects_bad_shapes() {
        let ctx = context();
        let kernel = PyramidKernel::new(&ctx).expect("kernels compile");
        let image = random_image(8, 8, 1);
        assert!(matches!(
            kernel.build(&ctx, &image, 0),
            Err(Error::Shape(_))
        ));
        assert!(matches!(
            kernel.build(&ctx, &image, 5),
            Err(Error::Shape(_))
        ));
        let broken = ImageF32 {
            width: 8,
            height: 8,
            data: vec![0.0; 10],
        };
        assert!(matches!(
            kernel.build(&ctx, &broken, 1),
            Err(Error::Shape(_))
        ));
    }

    #[test]
    fn gpu_pipeline_cache_compiles_once_and_reports_bad_kernels() {
        let ctx = context();
        let a = ctx
            .compute_pipeline("image_gradient", relfusion_shaders::IMAGE_GRADIENT, "main")
            .expect("compiles");
        // Same name: served from the cache even with a different (here: broken) source.
        let b = ctx
            .compute_pipeline("image_gradient", "not wgsl", "main")
            .expect("cached");
        assert_eq!(a, b);
        let err = ctx.compute_pipeline(
            "broken",
            "@compute @workgroup_size(1) fn main() { let x: u32 = 1.5; }",
            "main",
        );
        match err {
            Err(Error::Gpu(msg)) => assert!(msg.contains("broken"), "{msg}"),
            other => panic!("expected Error::Gpu, got {other:?}"),
        }
    }
}
