//! GPU runner of the densification (`densify_adam.wgsl`): all Adam iterations of eqs. 10–13 in
//! one submission — upload, one dispatch per iteration in a single compute pass, one readback.
//!
//! The CPU twin, the energy and the exact update are in [`super::densify`]; the kernel follows
//! the same order of operations per pixel, so the two agree to float rounding (tested below).
//!
//! # Layout
//! Pixels are grouped in *quads*, 4 horizontally adjacent pixels held in the lanes of a `vec4`,
//! and one invocation updates a block of 2 × 2 quads (8 × 2 pixels). Rows are padded to
//! [`row_quads`] quads (even), and every per-pixel map becomes a *plane* of
//! `n_quads = row_quads · height` vec4s; a buffer holds several planes back to back. Padding
//! pixels have zero weights, no semi-dense depth and `D = 1`: their gradient is 0, so Adam
//! never moves them, and (with `wx` zeroed at the last column, `wy` at the last row, where the
//! energy has no difference) no real pixel's gradient sees them.
//!
//! Why not one invocation per pixel: lavapipe (Mesa 22), the Vulkan driver of machines without
//! a GPU, executes every storage-buffer load or store instruction lane by lane with a bounds
//! check, so its cost follows the number of such instructions, whatever their width. One
//! invocation per pixel needed 12 per pixel and ran at half the CPU reference's speed; quads
//! need 5.5 (vec4 accesses, shared neighbours), 2 × 2-quad blocks 4.25, since the block's
//! rows and quads are each other's neighbours. Measured kernel times are in the report of
//! `relfusion bench densify`. On a real GPU these are coalesced 16-byte accesses, and 4 800
//! invocations per 320×240 dispatch are still plenty for a memory-bound 30-step loop.
//!
//! # Buffers
//! Per problem size, created once and reused while the size stays the same:
//! - `iterates[0..2]`: planes `D`, `ln D`, ping-pong — iteration `t` (from 0) reads
//!   `iterates[t % 2]` and writes the other, so the result lies in `iterates[iterations % 2]`;
//!   storing `ln D` costs each pixel one `log` per iteration instead of five;
//! - `moments`: planes `m`, `v`, cleared on the GPU at the start of each run;
//! - `grad_terms` (planes `wx`, `wy`, `tx`, `ty`) and `data_terms` (`semi`, `semi_var`, `cnn`,
//!   `cnn_weight`): five storage buffers in all (the WebGPU baseline guarantees eight);
//! - `uniforms`: one [`DensifyAdamParams`] slot per iteration at the device's uniform offset
//!   alignment (they differ only in Adam's step constants); each iteration's bind group
//!   points at its slot and its ping-pong pair, so the pass only switches bind groups.

use std::num::NonZeroU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytemuck::{Pod, Zeroable};

use super::config::DensifyParams;
use super::densify::{DensifyProblem, adam_step_constants};
use crate::gpu::{GpuContext, PassTimer};
use crate::image::ImageF32;
use crate::{Error, Result};

/// Invocations per workgroup (`@workgroup_size(64, 1, 1)` in the WGSL; 1-D over the quads).
const WORKGROUP: u32 = 64;

/// Pixels per quad (the lanes of a `vec4`).
const QUAD: usize = 4;

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
/// `flags` bit: some `cnn_weight` is non-zero (the kernel reads term 3's maps only then).
const FLAG_CNN_DEPTH: u32 = 2;

/// Rust mirror of `Params` in `densify_adam.wgsl` (uniform, 64 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct DensifyAdamParams {
    pub width: u32,
    pub height: u32,
    /// Quads per padded row, and `row_quads · height`.
    pub row_quads: u32,
    pub n_quads: u32,
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
    /// Bit 0: Charbonnier; bit 1: term 3 present.
    pub flags: u32,
    pub _pad0: u32,
}
const _: () = assert!(std::mem::size_of::<DensifyAdamParams>() == 64);
const PARAMS_SIZE: u64 = std::mem::size_of::<DensifyAdamParams>() as u64;

/// The densification kernel on one [`GpuContext`], with its buffers cached for the last
/// problem size (keyframes all have the working resolution, so they are made once).
#[derive(Debug)]
pub struct GpuDensifier {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    resources: Mutex<Option<Resources>>,
}

/// The buffers and bind groups of one `(width, height, iterations)`.
#[derive(Debug)]
struct Resources {
    width: usize,
    height: usize,
    iterations: usize,
    /// Vec4s per plane.
    n_quads: usize,
    iterates: [wgpu::Buffer; 2],
    moments: wgpu::Buffer,
    grad_terms: wgpu::Buffer,
    data_terms: wgpu::Buffer,
    uniforms: wgpu::Buffer,
    /// Bytes between two uniform slots.
    stride: u64,
    staging: wgpu::Buffer,
    /// Bind group of iteration `t` (from 0).
    groups: Vec<wgpu::BindGroup>,
    timer: Option<PassTimer>,
}

impl GpuDensifier {
    /// Compiles (or fetches from the context's cache) the kernel.
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self> {
        let pipeline = ctx.compute_pipeline(
            "densify_adam",
            relfusion_shaders::DENSIFY_ADAM,
            relfusion_shaders::ENTRY_POINT,
        )?;
        Ok(Self {
            ctx,
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
            .map_err(|_| Error::Gpu("densify buffers poisoned by a panic".into()))?;
        let fits = cache.as_ref().is_some_and(|r| {
            (r.width, r.height, r.iterations) == (problem.width, problem.height, params.iterations)
        });
        if !fits {
            // Drop the old buffers first: at most one set is alive.
            *cache = None;
            *cache = Some(self.allocate(problem.width, problem.height, params.iterations)?);
        }
        let res = cache
            .as_ref()
            .ok_or_else(|| Error::Gpu("densify buffers missing".into()))?;
        self.upload(res, problem, params, &start);
        let ctx = &self.ctx;
        let plane_bytes = 16 * res.n_quads as u64;
        ctx.checked("densify", || {
            let mut encoder = ctx.device().create_command_encoder(&Default::default());
            encoder.clear_buffer(&res.moments, 0, None);
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
            // The D plane of the last iterate.
            let result = &res.iterates[params.iterations % 2];
            encoder.copy_buffer_to_buffer(result, 0, &res.staging, 0, plane_bytes);
            if let Some(timer) = &res.timer {
                timer.record_resolve(&mut encoder);
            }
            ctx.queue().submit([encoder.finish()]);
        })?;
        let padded_width = QUAD * row_quads(problem.width);
        let data: Vec<f32> = ctx.read_mapped(&res.staging, |raw| {
            let plane = bytemuck::cast_slice::<u8, f32>(&raw[..plane_bytes as usize]);
            plane
                .chunks_exact(padded_width)
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

    /// Writes the problem's maps as padded planes, the start `(D, ln D)` and every iteration's
    /// uniform slot.
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
        let plane = 4 * res.n_quads;
        // Maps laid out as padded planes, back to back (see the module docs).
        let pack = |maps: &[(&[f32], f32)]| {
            let mut out = vec![0.0f32; maps.len() * plane];
            for (dst, &(src, fill)) in out.chunks_exact_mut(plane).zip(maps) {
                for (row, src_row) in dst.chunks_exact_mut(padded_width).zip(src.chunks_exact(w)) {
                    row[..w].copy_from_slice(src_row);
                    row[w..].fill(fill);
                }
            }
            out
        };
        let mut grad = pack(&[(&p.wx, 0.0), (&p.wy, 0.0), (&p.tx, 0.0), (&p.ty, 0.0)]);
        // No difference leaves the last column (wx, tx) or row (wy, ty): the energy's
        // definition, whatever the problem holds there.
        for k in [0, 2] {
            for row in grad[k * plane..(k + 1) * plane].chunks_exact_mut(padded_width) {
                row[w - 1] = 0.0;
            }
        }
        for k in [1, 3] {
            let last = k * plane + (h - 1) * padded_width;
            grad[last..last + padded_width].fill(0.0);
        }
        let data = pack(&[
            (&p.semi, 0.0),
            (&p.semi_var, 0.0),
            (&p.cnn, 0.0),
            (&p.cnn_weight, 0.0),
        ]);
        // Padding: D = 1, ln D = 0 (finite, never moved).
        let logs: Vec<f32> = start.iter().map(|d| d.ln()).collect();
        let iterate = pack(&[(start, 1.0), (&logs, 0.0)]);
        queue.write_buffer(&res.grad_terms, 0, bytemuck::cast_slice(&grad));
        queue.write_buffer(&res.data_terms, 0, bytemuck::cast_slice(&data));
        queue.write_buffer(&res.iterates[0], 0, bytemuck::cast_slice(&iterate));
        let mut flags = 0;
        if params.terms.charbonnier {
            flags |= FLAG_CHARBONNIER;
        }
        if p.cnn_weight.iter().any(|&c| c != 0.0) {
            flags |= FLAG_CNN_DEPTH;
        }
        let stride = res.stride as usize;
        let mut uniforms = vec![0u8; params.iterations * stride];
        for t in 0..params.iterations {
            let (step_size, bias2_sqrt) = adam_step_constants(params, t + 1);
            let slot = DensifyAdamParams {
                width: w as u32,
                height: h as u32,
                row_quads: row_quads(w) as u32,
                n_quads: res.n_quads as u32,
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
                flags,
                _pad0: 0,
            };
            uniforms[t * stride..t * stride + PARAMS_SIZE as usize]
                .copy_from_slice(bytemuck::bytes_of(&slot));
        }
        queue.write_buffer(&res.uniforms, 0, &uniforms);
    }

    /// Creates the buffers and per-iteration bind groups, after checking the device limits.
    fn allocate(&self, width: usize, height: usize, iterations: usize) -> Result<Resources> {
        let ctx = &self.ctx;
        let device = ctx.device();
        let limits = ctx.limits();
        let n_quads = row_quads(width) * height;
        let too_large = || Error::Gpu(format!("densify: {width}x{height} is too large"));
        u32::try_from(n_quads).map_err(|_| too_large())?;
        let max_groups = limits.max_compute_workgroups_per_dimension;
        if (invocations(width, height) as u32).div_ceil(WORKGROUP) > max_groups {
            return Err(Error::Gpu(format!(
                "densify: {width}x{height} needs more workgroups than the device allows \
                 ({max_groups})"
            )));
        }
        let plane = 16 * n_quads as u64;
        let widest = 4 * plane;
        let max_binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        if widest > max_binding {
            return Err(Error::Gpu(format!(
                "densify: a {width}x{height} map needs {widest} B buffers; the device binds at \
                 most {max_binding} B"
            )));
        }
        let stride = u64::from(limits.min_uniform_buffer_offset_alignment).max(PARAMS_SIZE);
        let uniform_bytes = stride * iterations as u64;
        if uniform_bytes > limits.max_buffer_size {
            return Err(Error::Gpu(format!(
                "densify: {iterations} iterations need {uniform_bytes} B of uniforms"
            )));
        }
        let storage = |label: &str, bytes: u64| ctx.storage_buffer(label, bytes);
        let iterates = [
            storage("densify iterate 0", 2 * plane),
            storage("densify iterate 1", 2 * plane),
        ];
        let moments = storage("densify moments", 2 * plane);
        let grad_terms = storage("densify grad terms", 4 * plane);
        let data_terms = storage("densify data terms", 4 * plane);
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("densify params"),
            size: uniform_bytes,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let layout = self.pipeline.get_bind_group_layout(0);
        let groups = (0..iterations)
            .map(|t| {
                device.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("densify_adam"),
                    layout: &layout,
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &uniforms,
                                offset: t as u64 * stride,
                                size: NonZeroU64::new(PARAMS_SIZE),
                            }),
                        },
                        entry(1, &iterates[t % 2]),
                        entry(2, &iterates[(t + 1) % 2]),
                        entry(3, &moments),
                        entry(4, &grad_terms),
                        entry(5, &data_terms),
                    ],
                })
            })
            .collect();
        Ok(Resources {
            width,
            height,
            iterations,
            n_quads,
            staging: ctx.staging_buffer("densify readback", plane),
            timer: ctx
                .supports_timestamps()
                .then(|| PassTimer::new(ctx, "densify")),
            iterates,
            moments,
            grad_terms,
            data_terms,
            uniforms,
            stride,
            groups,
        })
    }
}

fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dense::EnergyTerms;
    use crate::dense::densify::testing::{random_problem, synthetic_scene};
    use crate::dense::densify::{densify, densify_cpu, energy};
    use crate::gpu::GpuConfig;

    /// A real adapter is required (lavapipe on machines without a GPU); fails, never skips.
    fn densifier() -> GpuDensifier {
        let ctx = GpuContext::new(&GpuConfig::default())
            .unwrap_or_else(|e| panic!("no GPU context: {e}"));
        GpuDensifier::new(Arc::new(ctx)).expect("kernel compiles")
    }

    /// Largest |gpu − cpu| relative to the mean of the CPU map.
    fn relative_max_diff(gpu: &ImageF32, cpu: &ImageF32) -> f32 {
        assert_eq!((gpu.width, gpu.height), (cpu.width, cpu.height));
        let mean = cpu.data.iter().sum::<f32>() / cpu.data.len() as f32;
        let diff = gpu
            .data
            .iter()
            .zip(&cpu.data)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        diff / mean
    }

    /// GPU and CPU run the same f32 operations in the same order; they differ only by the
    /// GPU's `log`, `pow` and fused multiply-adds (an ulp or two per gradient). Adam divides
    /// each step by sqrt(v), so a gradient error δg moves a step by about lr·δg/sqrt(v): for
    /// almost every pixel that is rounding-level, and 30 such steps stay below 1e-5 of a map
    /// whose mean is ~1. The exception is a pixel whose terms cancel so that its gradient is
    /// itself at rounding level for its whole history: there the normalised step follows the
    /// rounding and the two sides may part by a fraction of a step (any two implementations
    /// of Adam do, PyTorch's CPU and CUDA ones included). Measured on lavapipe over 50 random
    /// 320×240 problems: at most 6 pixels per map (of 76 800) beyond 1e-5 of the mean, the
    /// worst 2e-3 (0.04·lr), energies equal to 1e-8. Hence the checks: at most 1 pixel in 10⁴
    /// (plus one) beyond 1e-5 of the mean, none beyond lr/10, the energy equal to 1e-6.
    fn assert_agree(
        name: &str,
        gpu: &ImageF32,
        cpu: &ImageF32,
        problem: &DensifyProblem,
        params: &DensifyParams,
    ) {
        assert_eq!(
            (gpu.width, gpu.height),
            (cpu.width, cpu.height),
            "{name}: size"
        );
        assert!(
            gpu.data.iter().all(|v| v.is_finite()),
            "{name}: non-finite output"
        );
        let n = cpu.data.len();
        let mean = cpu.data.iter().sum::<f32>() / n as f32;
        let diffs: Vec<f32> = gpu
            .data
            .iter()
            .zip(&cpu.data)
            .map(|(a, b)| (a - b).abs())
            .collect();
        let outliers = diffs.iter().filter(|&&d| d > 1e-5 * mean).count();
        let max = diffs.iter().fold(0.0f32, |m, &d| m.max(d));
        assert!(
            outliers <= 1 + n / 10_000,
            "{name}: {outliers} of {n} pixels differ by more than 1e-5 of the mean {mean}"
        );
        assert!(
            max < 0.1 * params.learning_rate,
            "{name}: max |gpu − cpu| = {max}"
        );
        let (e_gpu, e_cpu) = (
            energy(problem, &gpu.data, params),
            energy(problem, &cpu.data, params),
        );
        assert!(
            (e_gpu - e_cpu).abs() <= 1e-6 * e_cpu.abs(),
            "{name}: energies {e_gpu:.9e} (gpu) and {e_cpu:.9e} (cpu)"
        );
    }

    #[test]
    fn gpu_densify_matches_cpu_on_random_problems() {
        let gpu = densifier();
        let params = DensifyParams::default();
        let charbonnier_off = DensifyParams {
            terms: EnergyTerms {
                charbonnier: false,
                ..EnergyTerms::default()
            },
            ..params.clone()
        };
        for (k, &(w, h)) in [(320, 240), (97, 33), (5, 1), (1, 7), (320, 240)]
            .iter()
            .enumerate()
        {
            let problem = random_problem(w, h, 11 + k as u64);
            let p = if k == 4 { &charbonnier_off } else { &params };
            let cpu = densify_cpu(&problem, p).expect("cpu");
            let out = gpu.run(&problem, p).expect("gpu");
            assert_agree(&format!("random {w}x{h}"), &out, &cpu, &problem, p);
            // The iterations did move the map (a kernel that did nothing would fail here).
            let start = problem.start(p);
            let moved = out
                .data
                .iter()
                .zip(&start)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(moved > 0.1, "{w}x{h}: the map moved by only {moved}");
        }
        // A realistic keyframe (prior, sparse semi-dense) with the paper's energy, and the same
        // keyframe without a model.
        let (_, prior, semi, var) = synthetic_scene(320, 240, 5);
        let paper = DensifyProblem::with_prior(&prior, &semi, &var, &params).expect("paper");
        let out = gpu.run(&paper, &params).expect("gpu");
        assert_agree(
            "synthetic 320x240",
            &out,
            &densify_cpu(&paper, &params).expect("cpu"),
            &paper,
            &params,
        );
        let image = crate::dense::densify::testing::noise(320, 240, 0.0, 255.0, 6);
        let no_model =
            DensifyProblem::without_prior(&image, &semi, &var, &params).expect("no model");
        let out = gpu.run(&no_model, &params).expect("gpu");
        let cpu = densify_cpu(&no_model, &params).expect("cpu");
        assert_agree("no model 320x240", &out, &cpu, &no_model, &params);
    }

    #[test]
    fn gpu_densify_reuses_buffers_and_handles_iteration_counts() {
        let gpu = densifier();
        let (truth, prior, semi, var) = synthetic_scene(64, 48, 3);
        let params = DensifyParams::default();
        let problem = DensifyProblem::with_prior(&prior, &semi, &var, &params).expect("problem");
        let first = gpu.run(&problem, &params).expect("first");
        // Same size again: cached buffers, moments cleared, identical result.
        let (second, kernel_time) = gpu.run_timed(&problem, &params).expect("second");
        assert_eq!(first.data, second.data);
        assert_eq!(kernel_time.is_some(), gpu.context().supports_timestamps());
        assert!(
            energy(&problem, &first.data, &params)
                < energy(&problem, &problem.start(&params), &params)
        );
        assert_eq!(truth.data.len(), first.data.len());
        // Odd and even iteration counts read the result from each ping-pong buffer.
        for iterations in [0, 1, 2, 7] {
            let p = DensifyParams {
                iterations,
                ..params.clone()
            };
            let cpu = densify_cpu(&problem, &p).expect("cpu");
            let out = densify(&problem, &p, Some(&gpu)).expect("gpu");
            assert!(
                relative_max_diff(&out, &cpu) < 1e-5,
                "{iterations} iterations differ"
            );
        }
        // A broken problem is refused before anything is dispatched.
        let mut broken = problem.clone();
        broken.wx.pop();
        assert!(matches!(gpu.run(&broken, &params), Err(Error::Shape(_))));
    }
}
