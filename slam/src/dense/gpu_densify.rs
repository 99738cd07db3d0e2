//! GPU runner of the densification (`densify_adam.wgsl`): all Adam iterations of eqs. 10–13 in
//! one submission — upload, one dispatch per iteration in a single compute pass, one readback.
//!
//! The CPU twin, the energy and the exact update are in [`super::densify`]; the kernel follows
//! the same order of operations per pixel, so the two agree to float rounding (tested below).
//!
//! # Layout
//! Pixels are grouped in *quads*, 4 horizontally adjacent pixels held in the channels of one
//! `rgba32float` texel, and one invocation updates a block of 2 × 2 quads (8 × 2 pixels).
//! Every per-pixel map is one layer of a 2-D array texture of [`row_quads`] × `height` texels
//! (`row_quads` even). Padding pixels have zero weights, no semi-dense depth and `D = 1`: their
//! gradient is 0, so Adam never moves them, and (with `wx` zeroed at the last column, `wy` at
//! the last row, where the energy has no difference) no real pixel's gradient sees them.
//!
//! Why not storage buffers and one invocation per pixel: lavapipe (Mesa 22), the Vulkan driver
//! of machines without a GPU, executes every storage-buffer access lane by lane with a bounds
//! check (~12 x86 instructions per float, per invocation; measured with callgrind), while a
//! storage-image load is a vector gather. Instructions executed per pixel and iteration at
//! 320×240 (callgrind): CPU reference 161; this kernel on storage buffers 273; one invocation
//! per pixel on storage textures 198; this kernel (2 × 2-quad blocks on storage textures, a
//! pixel touching 4.25 texels per iteration since the block's quads and rows are each other's
//! neighbours) 119, of which about half are the four texel stores per quad. Lavapipe also runs
//! on every core where the reference runs on one. On a real GPU these are plain 16-byte image
//! accesses with 2-D locality.
//!
//! # Resources
//! Per problem size, created once and reused while the size stays the same:
//! - `states[0..2]`: layers `D`, `ln D`, `m`, `v` (Adam's moments), ping-pong — iteration `t`
//!   (from 0) reads `states[t % 2]` and writes the other, so the result lies in
//!   `states[iterations % 2]`; storing `ln D` costs each pixel one `log` per iteration instead
//!   of five;
//! - `terms`: layers `wx`, `wy`, `tx`, `ty`, `semi`, `semi_var`, `cnn`, `cnn_weight`;
//! - `uniforms`: one [`DensifyAdamParams`] slot per iteration at the device's uniform offset
//!   alignment (they differ only in Adam's step constants); each iteration's bind group
//!   points at its slot and its ping-pong pair, so the pass only switches bind groups.
//!
//! The pipeline has an explicit layout (WGSL's automatic layout cannot express read-only
//! storage textures' formats), so it is compiled here rather than in the context's cache.

use std::num::NonZeroU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytemuck::{Pod, Zeroable};

use super::config::DensifyParams;
use super::densify::{DensifyProblem, DensifySolver, adam_step_constants};
use crate::gpu::{GpuContext, PassTimer};
use crate::image::ImageF32;
use crate::{Error, Result};

/// Invocations per workgroup (`@workgroup_size(64, 1, 1)` in the WGSL; 1-D over the blocks).
const WORKGROUP: u32 = 64;

/// Pixels per quad (the channels of a texel).
const QUAD: usize = 4;

/// Layers of the state textures (`D`, `ln D`, `m`, `v`) and of the problem texture.
const STATE_LAYERS: u32 = 4;
const TERM_LAYERS: u32 = 8;

/// The texel format of every texture: one quad of one map.
const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;

/// Quads per padded row of a `width`-pixel map (even: an invocation takes 2 × 2 quads).
pub fn row_quads(width: usize) -> usize {
    width.div_ceil(2 * QUAD) * 2
}

/// Invocations per dispatch: one per block of 2 × 2 quads.
fn invocations(width: usize, height: usize) -> usize {
    row_quads(width) / 2 * height.div_ceil(2)
}

/// `flags` bit: generalised Charbonnier on the semi-dense term.
const FLAG_CHARBONNIER: u32 = 1;
/// `flags` bit: some `cnn_weight` is non-zero (the kernel reads term 3's layers only then).
const FLAG_CNN_DEPTH: u32 = 2;

/// Rust mirror of `Params` in `densify_adam.wgsl` (uniform, 64 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct DensifyAdamParams {
    pub width: u32,
    pub height: u32,
    /// Texels per row: quads per padded row.
    pub row_quads: u32,
    /// Bit 0: Charbonnier; bit 1: term 3 present.
    pub flags: u32,
    /// Adam's `lr / (1 − β1^t)` and `sqrt(1 − β2^t)` of this slot's iteration `t` (from 1),
    /// from [`adam_step_constants`].
    pub step_size: f32,
    pub bias2_sqrt: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub adam_epsilon: f32,
    pub semi_scale: f32,
    pub grad_scale: f32,
    pub alpha: f32,
    pub epsilon: f32,
    pub min_idepth: f32,
    pub _pad0: u32,
    pub _pad1: u32,
}
const _: () = assert!(std::mem::size_of::<DensifyAdamParams>() == 64);
const PARAMS_SIZE: u64 = std::mem::size_of::<DensifyAdamParams>() as u64;

/// The densification kernel on one [`GpuContext`], with its textures cached for the last
/// problem size (keyframes all have the working resolution, so they are made once).
#[derive(Debug)]
pub struct GpuDensifier {
    ctx: Arc<GpuContext>,
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    resources: Mutex<Option<Resources>>,
}

/// The textures, buffers and bind groups of one `(width, height, iterations)`.
#[derive(Debug)]
struct Resources {
    width: usize,
    height: usize,
    iterations: usize,
    states: [wgpu::Texture; 2],
    terms: wgpu::Texture,
    uniforms: wgpu::Buffer,
    /// Bytes between two uniform slots.
    stride: u64,
    staging: wgpu::Buffer,
    /// Bytes per row of `staging` (copies align rows to 256 bytes).
    staging_row: u32,
    /// Bind group of iteration `t` (from 0).
    groups: Vec<wgpu::BindGroup>,
    timer: Option<PassTimer>,
}

impl GpuDensifier {
    /// Compiles the kernel with its explicit layout.
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self> {
        let device = ctx.device();
        let texture = |binding: u32, access| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::StorageTexture {
                access,
                format: FORMAT,
                view_dimension: wgpu::TextureViewDimension::D2Array,
            },
            count: None,
        };
        let (layout, pipeline) = ctx.checked("kernel densify_adam", || {
            let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("densify_adam"),
                entries: &[
                    wgpu::BindGroupLayoutEntry {
                        binding: 0,
                        visibility: wgpu::ShaderStages::COMPUTE,
                        ty: wgpu::BindingType::Buffer {
                            ty: wgpu::BufferBindingType::Uniform,
                            has_dynamic_offset: false,
                            min_binding_size: NonZeroU64::new(PARAMS_SIZE),
                        },
                        count: None,
                    },
                    texture(1, wgpu::StorageTextureAccess::ReadOnly),
                    texture(2, wgpu::StorageTextureAccess::WriteOnly),
                    texture(3, wgpu::StorageTextureAccess::ReadOnly),
                ],
            });
            let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("densify_adam"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("densify_adam"),
                source: wgpu::ShaderSource::Wgsl(relfusion_shaders::DENSIFY_ADAM.into()),
            });
            let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some("densify_adam"),
                layout: Some(&pipeline_layout),
                module: &module,
                entry_point: Some(relfusion_shaders::ENTRY_POINT),
                compilation_options: Default::default(),
                cache: None,
            });
            (layout, pipeline)
        })?;
        Ok(Self {
            ctx,
            layout,
            pipeline,
            resources: Mutex::new(None),
        })
    }

    /// The context the kernel runs on.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Runs `params.iterations` Adam iterations on the GPU; same contract and result (to float
    /// rounding) as [`super::densify::densify_cpu`].
    pub fn run(&self, problem: &DensifyProblem, params: &DensifyParams) -> Result<ImageF32> {
        Ok(self.run_timed(problem, params)?.0)
    }

    /// Like [`Self::run`], also returning the GPU time of the compute pass alone (timestamp
    /// queries), or `None` when the device has no timestamp support.
    pub fn run_timed(
        &self,
        problem: &DensifyProblem,
        params: &DensifyParams,
    ) -> Result<(ImageF32, Option<Duration>)> {
        problem.validate()?;
        let start = problem.start(params);
        if params.iterations == 0 {
            return Ok((
                ImageF32::from_vec(problem.width, problem.height, start)?,
                None,
            ));
        }
        let mut cache = self
            .resources
            .lock()
            .map_err(|_| Error::Gpu("densify resources poisoned by a panic".into()))?;
        let fits = cache.as_ref().is_some_and(|r| {
            (r.width, r.height, r.iterations) == (problem.width, problem.height, params.iterations)
        });
        if !fits {
            // Drop the old resources first: at most one set is alive.
            *cache = None;
            *cache = Some(self.allocate(problem.width, problem.height, params.iterations)?);
        }
        let res = cache
            .as_ref()
            .ok_or_else(|| Error::Gpu("densify resources missing".into()))?;
        let ctx = &self.ctx;
        let extent = wgpu::Extent3d {
            width: row_quads(problem.width) as u32,
            height: problem.height as u32,
            depth_or_array_layers: 1,
        };
        ctx.checked("densify", || {
            self.upload(res, problem, params, &start);
            let mut encoder = ctx.device().create_command_encoder(&Default::default());
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("densify_adam"),
                    timestamp_writes: res.timer.as_ref().map(PassTimer::writes),
                });
                pass.set_pipeline(&self.pipeline);
                let groups = (invocations(res.width, res.height) as u32).div_ceil(WORKGROUP);
                for group in &res.groups {
                    pass.set_bind_group(0, Some(group), &[]);
                    pass.dispatch_workgroups(groups, 1, 1);
                }
            }
            // Layer D of the last iterate.
            encoder.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: &res.states[params.iterations % 2],
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: &res.staging,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(res.staging_row),
                        rows_per_image: Some(extent.height),
                    },
                },
                extent,
            );
            if let Some(timer) = &res.timer {
                timer.record_resolve(&mut encoder);
            }
            ctx.queue().submit([encoder.finish()]);
        })?;
        let row_floats = res.staging_row as usize / 4;
        let data: Vec<f32> = ctx.read_mapped(&res.staging, |raw| {
            let rows = &raw[..res.staging_row as usize * problem.height];
            bytemuck::cast_slice::<u8, f32>(rows)
                .chunks_exact(row_floats)
                .flat_map(|row| &row[..problem.width])
                .copied()
                .collect()
        })?;
        let kernel_time = match &res.timer {
            Some(timer) => Some(timer.read(ctx)?),
            None => None,
        };
        Ok((
            ImageF32::from_vec(problem.width, problem.height, data)?,
            kernel_time,
        ))
    }

    /// Writes the problem's maps and the start `(D, ln D, m = 0, v = 0)` as texture layers, and
    /// every iteration's uniform slot.
    fn upload(
        &self,
        res: &Resources,
        problem: &DensifyProblem,
        params: &DensifyParams,
        start: &[f32],
    ) {
        let queue = self.ctx.queue();
        let p = problem;
        let (w, h) = (p.width, p.height);
        let padded_width = QUAD * row_quads(w);
        let layer = padded_width * h;
        // Maps as padded layers, back to back, each padded with its `fill`.
        let pack = |maps: &[(&[f32], f32)]| {
            let mut out = vec![0.0f32; maps.len() * layer];
            for (dst, &(src, fill)) in out.chunks_exact_mut(layer).zip(maps) {
                for (row, src_row) in dst.chunks_exact_mut(padded_width).zip(src.chunks_exact(w)) {
                    row[..w].copy_from_slice(src_row);
                    row[w..].fill(fill);
                }
            }
            out
        };
        let mut terms = pack(&[
            (&p.wx, 0.0),
            (&p.wy, 0.0),
            (&p.tx, 0.0),
            (&p.ty, 0.0),
            (&p.semi, 0.0),
            (&p.semi_var, 0.0),
            (&p.cnn, 0.0),
            (&p.cnn_weight, 0.0),
        ]);
        // No difference leaves the last column (wx, tx) or row (wy, ty): the energy's
        // definition, whatever the problem holds there.
        for k in [0, 2] {
            for row in terms[k * layer..(k + 1) * layer].chunks_exact_mut(padded_width) {
                row[w - 1] = 0.0;
            }
        }
        for k in [1, 3] {
            let last = k * layer + (h - 1) * padded_width;
            terms[last..last + padded_width].fill(0.0);
        }
        // Padding: D = 1, ln D = 0 (finite, never moved); the moments start at 0.
        let logs: Vec<f32> = start.iter().map(|d| d.ln()).collect();
        let zeros = vec![0.0f32; w * h];
        let state = pack(&[(start, 1.0), (&logs, 0.0), (&zeros, 0.0), (&zeros, 0.0)]);
        let write = |texture: &wgpu::Texture, data: &[f32], layers: u32| {
            queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                bytemuck::cast_slice(data),
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * padded_width as u32),
                    rows_per_image: Some(h as u32),
                },
                wgpu::Extent3d {
                    width: row_quads(w) as u32,
                    height: h as u32,
                    depth_or_array_layers: layers,
                },
            );
        };
        write(&res.terms, &terms, TERM_LAYERS);
        write(&res.states[0], &state, STATE_LAYERS);
        let uniforms = iteration_uniforms(p, params, res.stride as usize);
        queue.write_buffer(&res.uniforms, 0, &uniforms);
    }

    /// Creates the textures, buffers and per-iteration bind groups, after checking the device
    /// limits.
    fn allocate(&self, width: usize, height: usize, iterations: usize) -> Result<Resources> {
        let ctx = &self.ctx;
        let device = ctx.device();
        let rq = row_quads(width);
        let stride = uniform_stride(ctx.limits(), width, height, iterations)?;
        let uniform_bytes = stride * iterations as u64;
        let texture = |label: &str, layers: u32| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d {
                    width: rq as u32,
                    height: height as u32,
                    depth_or_array_layers: layers,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: FORMAT,
                usage: wgpu::TextureUsages::STORAGE_BINDING
                    | wgpu::TextureUsages::COPY_DST
                    | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            })
        };
        let states = [
            texture("densify state 0", STATE_LAYERS),
            texture("densify state 1", STATE_LAYERS),
        ];
        let terms = texture("densify terms", TERM_LAYERS);
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("densify params"),
            size: uniform_bytes,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let array_view = |texture: &wgpu::Texture| {
            texture.create_view(&wgpu::TextureViewDescriptor {
                dimension: Some(wgpu::TextureViewDimension::D2Array),
                ..Default::default()
            })
        };
        let state_views = [array_view(&states[0]), array_view(&states[1])];
        let terms_view = array_view(&terms);
        let groups = (0..iterations)
            .map(|t| {
                device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("densify_adam"),
                    layout: &self.layout,
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &uniforms,
                                offset: t as u64 * stride,
                                size: NonZeroU64::new(PARAMS_SIZE),
                            }),
                        },
                        texture_entry(1, &state_views[t % 2]),
                        texture_entry(2, &state_views[(t + 1) % 2]),
                        texture_entry(3, &terms_view),
                    ],
                })
            })
            .collect();
        let staging_row = (16 * rq as u32).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
        Ok(Resources {
            width,
            height,
            iterations,
            staging: ctx.staging_buffer("densify readback", u64::from(staging_row) * height as u64),
            staging_row,
            timer: ctx
                .supports_timestamps()
                .then(|| PassTimer::new(ctx, "densify")),
            states,
            terms,
            uniforms,
            stride,
            groups,
        })
    }
}

/// Every iteration's uniform slot (Adam's step constants of iteration `t + 1`), `stride` bytes
/// apart.
fn iteration_uniforms(p: &DensifyProblem, params: &DensifyParams, stride: usize) -> Vec<u8> {
    let w = p.width;
    let mut flags = 0;
    if params.terms.charbonnier {
        flags |= FLAG_CHARBONNIER;
    }
    if p.cnn_weight.iter().any(|&c| c != 0.0) {
        flags |= FLAG_CNN_DEPTH;
    }
    let mut uniforms = vec![0u8; params.iterations * stride];
    for t in 0..params.iterations {
        let (step_size, bias2_sqrt) = adam_step_constants(params, t + 1);
        let slot = DensifyAdamParams {
            width: w as u32,
            height: p.height as u32,
            row_quads: row_quads(w) as u32,
            flags,
            step_size,
            bias2_sqrt,
            beta1: params.beta1,
            beta2: params.beta2,
            adam_epsilon: params.adam_epsilon,
            semi_scale: p.semi_scale,
            grad_scale: p.grad_scale,
            alpha: params.alpha,
            epsilon: params.epsilon,
            min_idepth: params.min_idepth,
            _pad0: 0,
            _pad1: 0,
        };
        uniforms[t * stride..t * stride + PARAMS_SIZE as usize]
            .copy_from_slice(bytemuck::bytes_of(&slot));
    }
    uniforms
}

/// The uniform slot stride of a `width × height` problem of `iterations` iterations, after
/// checking its textures, workgroups and uniforms against the device's limits.
fn uniform_stride(
    limits: &wgpu::Limits,
    width: usize,
    height: usize,
    iterations: usize,
) -> Result<u64> {
    let rq = row_quads(width);
    let max_side = limits.max_texture_dimension_2d as usize;
    if rq > max_side || height > max_side {
        return Err(Error::Gpu(format!(
            "densify: a {width}x{height} map needs {rq}x{height} textures; the device \
             allows {max_side}x{max_side}"
        )));
    }
    let max_groups = limits.max_compute_workgroups_per_dimension as usize;
    if invocations(width, height).div_ceil(WORKGROUP as usize) > max_groups {
        return Err(Error::Gpu(format!(
            "densify: {width}x{height} needs more workgroups than the device allows \
             ({max_groups})"
        )));
    }
    let stride = u64::from(limits.min_uniform_buffer_offset_alignment).max(PARAMS_SIZE);
    let uniform_bytes = stride * iterations as u64;
    if uniform_bytes > limits.max_buffer_size {
        return Err(Error::Gpu(format!(
            "densify: {iterations} iterations need {uniform_bytes} B of uniforms"
        )));
    }
    Ok(stride)
}

fn texture_entry(binding: u32, view: &wgpu::TextureView) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: wgpu::BindingResource::TextureView(view),
    }
}

impl DensifySolver for GpuDensifier {
    fn run(&self, problem: &DensifyProblem, params: &DensifyParams) -> Result<ImageF32> {
        GpuDensifier::run(self, problem, params)
    }
}

#[cfg(test)]
#[path = "gpu_densify_tests.rs"]
mod tests;
