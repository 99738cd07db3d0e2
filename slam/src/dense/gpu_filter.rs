//! GPU runner of the adaptive filter kernel (`adaptive_filter.wgsl`, eqs. 4–8): uploads the
//! sanitised inputs and the list of valid pixels, runs one invocation per valid pixel (the
//! outputs are cleared first), reads D' and V' back.
//!
//! The definitions and the CPU reference are in [`super::filter`]; the kernel performs the
//! same f32 operations in the same order and agrees with it to float rounding (tested below on
//! random inputs of several sizes, with and without a prior).
//!
//! Buffers are kept between calls of the same image size (a keyframe after another at the
//! working resolution re-uses them); a call of another size re-allocates. Calls are serialised
//! by a mutex around those buffers, so one runner can be shared between threads.

use std::sync::{Arc, Mutex};

use bytemuck::{Pod, Zeroable};

use super::FilterParams;
use super::filter::{FilterInputs, FilterRaw, FilterStep, Prepared, check_params};
use crate::gpu::GpuContext;
use crate::image::ImageF32;
use crate::{Error, Result};

/// Invocations per workgroup (`@workgroup_size(64, 1, 1)` in the WGSL).
const WORKGROUP: u32 = 64;

/// Rust mirror of `AdaptiveFilterParams` in `adaptive_filter.wgsl` (uniform, 48 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct AdaptiveFilterParams {
    pub width: u32,
    pub height: u32,
    pub radius: u32,
    /// 1 when the prior buffer holds the aligned prior, 0 when a 1-float placeholder is bound.
    pub has_prior: u32,
    pub sigma_s: f32,
    pub sigma_d: f32,
    pub sigma_c: f32,
    pub sigma_u: f32,
    /// [`FilterParams::consistency_in_variance`] as 0 / 1.
    pub consistency_in_variance: u32,
    /// Number of valid pixels listed in the `pixels` buffer (one invocation each).
    pub count: u32,
    pub _pad1: u32,
    pub _pad2: u32,
}
const _: () = assert!(std::mem::size_of::<AdaptiveFilterParams>() == 48);

/// Device buffers for one image size (`len` pixels).
#[derive(Debug)]
struct Buffers {
    len: usize,
    intensity: wgpu::Buffer,
    idepth: wgpu::Buffer,
    variance: wgpu::Buffer,
    prior: wgpu::Buffer,
    out_idepth: wgpu::Buffer,
    out_variance: wgpu::Buffer,
    /// Row-major indices of the valid pixels.
    pixels: wgpu::Buffer,
    /// D' then V', back to back.
    staging: wgpu::Buffer,
}

impl Buffers {
    fn new(ctx: &GpuContext, len: usize) -> Self {
        let bytes = 4 * len as u64;
        let storage = |label: &str| ctx.storage_buffer(label, bytes);
        Self {
            len,
            intensity: storage("adaptive_filter intensity"),
            idepth: storage("adaptive_filter idepth"),
            variance: storage("adaptive_filter variance"),
            prior: storage("adaptive_filter prior"),
            out_idepth: storage("adaptive_filter out idepth"),
            out_variance: storage("adaptive_filter out variance"),
            pixels: storage("adaptive_filter pixels"),
            staging: ctx.staging_buffer("adaptive_filter readback", 2 * bytes),
        }
    }
}

/// The compiled kernel, its parameter uniform and the cached buffers; create once per
/// [`GpuContext`] and reuse.
#[derive(Debug)]
pub struct GpuAdaptiveFilter {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    params: wgpu::Buffer,
    /// Bound in place of the prior when there is none (the kernel never reads it then).
    no_prior: wgpu::Buffer,
    buffers: Mutex<Option<Buffers>>,
}

impl GpuAdaptiveFilter {
    /// Compiles (or fetches from the context's cache) the kernel.
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self> {
        use relfusion_shaders::{ADAPTIVE_FILTER, ENTRY_POINT};
        let pipeline = ctx.compute_pipeline("adaptive_filter", ADAPTIVE_FILTER, ENTRY_POINT)?;
        let params = ctx.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("adaptive_filter params"),
            size: std::mem::size_of::<AdaptiveFilterParams>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let no_prior = ctx.upload_f32("adaptive_filter no prior", &[0.0]);
        Ok(Self {
            ctx,
            pipeline,
            params,
            no_prior,
            buffers: Mutex::new(None),
        })
    }

    /// The context the kernel runs on.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Eqs. 7–8 on the GPU: same contract and same result (to float rounding) as
    /// [`super::filter::adaptive_filter_cpu`]. Blocks until the result is read back. Takes
    /// `&self`: concurrent calls wait for each other.
    pub fn run(&self, inputs: &FilterInputs, params: &FilterParams) -> Result<FilterRaw> {
        check_params(params)?;
        let p = Prepared::new(inputs)?;
        let (w, h) = (p.width, p.height);
        let n = w * h;
        // Only the valid pixels get an invocation: a semi-dense map covers a fraction of the
        // image, and an invocation on an invalid pixel would still hold its SIMD lanes for
        // the whole window loop.
        let pixels: Vec<u32> = (0..n)
            .filter(|&i| p.idepth[i] > 0.0)
            .map(|i| u32::try_from(i).map_err(|_| self.too_large(w, h)))
            .collect::<Result<_>>()?;
        if pixels.is_empty() {
            let zeros = ImageF32::filled(w, h, 0.0);
            return Ok(FilterRaw {
                idepth: zeros.clone(),
                variance: zeros,
            });
        }
        let gpu_params = self.uniform(w, h, &pixels, p.prior.is_some(), params)?;
        let ctx = &*self.ctx;
        let mut cache = self
            .buffers
            .lock()
            .map_err(|_| Error::Gpu("adaptive filter buffers poisoned by a panic".into()))?;
        if cache.as_ref().is_none_or(|b| b.len != n) {
            *cache = Some(ctx.checked("adaptive_filter buffers", || Buffers::new(ctx, n))?);
        }
        let b = cache
            .as_ref()
            .ok_or_else(|| Error::Gpu("adaptive filter buffers missing".into()))?;
        let queue = ctx.queue();
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&gpu_params));
        queue.write_buffer(&b.intensity, 0, bytemuck::cast_slice(p.intensity));
        queue.write_buffer(&b.idepth, 0, bytemuck::cast_slice(&p.idepth));
        queue.write_buffer(&b.variance, 0, bytemuck::cast_slice(&p.variance));
        queue.write_buffer(&b.pixels, 0, bytemuck::cast_slice(&pixels));
        let prior = match &p.prior {
            Some(prior) => {
                queue.write_buffer(&b.prior, 0, bytemuck::cast_slice(prior));
                &b.prior
            }
            None => &self.no_prior,
        };
        let bytes = 4 * n as u64;
        ctx.checked("adaptive_filter", || {
            let layout = self.pipeline.get_bind_group_layout(0);
            let entries: Vec<wgpu::BindGroupEntry> = [
                &self.params,
                &b.intensity,
                &b.idepth,
                &b.variance,
                prior,
                &b.out_idepth,
                &b.out_variance,
                &b.pixels,
            ]
            .into_iter()
            .enumerate()
            .map(|(i, buffer)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: buffer.as_entire_binding(),
            })
            .collect();
            let group = ctx.device().create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("adaptive_filter"),
                layout: &layout,
                entries: &entries,
            });
            let mut encoder = ctx.device().create_command_encoder(&Default::default());
            // The kernel writes only the pixels it keeps.
            encoder.clear_buffer(&b.out_idepth, 0, None);
            encoder.clear_buffer(&b.out_variance, 0, None);
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("adaptive_filter"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&self.pipeline);
                pass.set_bind_group(0, Some(&group), &[]);
                pass.dispatch_workgroups(gpu_params.count.div_ceil(WORKGROUP), 1, 1);
            }
            encoder.copy_buffer_to_buffer(&b.out_idepth, 0, &b.staging, 0, bytes);
            encoder.copy_buffer_to_buffer(&b.out_variance, 0, &b.staging, bytes, bytes);
            queue.submit([encoder.finish()]);
        })?;
        let (d, v) = ctx.read_mapped(&b.staging, |raw| {
            let planes = bytemuck::cast_slice::<u8, f32>(&raw[..2 * n * 4]);
            (planes[..n].to_vec(), planes[n..].to_vec())
        })?;
        Ok(FilterRaw {
            idepth: ImageF32::from_vec(w, h, d)?,
            variance: ImageF32::from_vec(w, h, v)?,
        })
    }

    fn too_large(&self, w: usize, h: usize) -> Error {
        Error::Gpu(format!(
            "adaptive filter: {w}x{h} exceeds the device limits"
        ))
    }

    /// The uniform for a `w × h` image and its list of valid `pixels`, after checking them
    /// against the device limits.
    fn uniform(
        &self,
        w: usize,
        h: usize,
        pixels: &[u32],
        has_prior: bool,
        params: &FilterParams,
    ) -> Result<AdaptiveFilterParams> {
        let limits = self.ctx.limits();
        let width = u32::try_from(w).map_err(|_| self.too_large(w, h))?;
        let height = u32::try_from(h).map_err(|_| self.too_large(w, h))?;
        let count = u32::try_from(pixels.len()).map_err(|_| self.too_large(w, h))?;
        let bytes = 4 * w as u64 * h as u64;
        let max_bytes = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size / 2);
        if count.div_ceil(WORKGROUP) > limits.max_compute_workgroups_per_dimension
            || bytes > max_bytes
        {
            return Err(self.too_large(w, h));
        }
        Ok(AdaptiveFilterParams {
            width,
            height,
            // check_params bounds it by MAX_RADIUS.
            radius: params.radius as u32,
            has_prior: u32::from(has_prior),
            sigma_s: params.sigma_s,
            sigma_d: params.sigma_d,
            sigma_c: params.sigma_c,
            sigma_u: params.sigma_u,
            consistency_in_variance: u32::from(params.consistency_in_variance),
            count,
            _pad1: 0,
            _pad2: 0,
        })
    }
}

impl FilterStep for GpuAdaptiveFilter {
    fn run(&self, inputs: &FilterInputs, params: &FilterParams) -> Result<FilterRaw> {
        GpuAdaptiveFilter::run(self, inputs, params)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dense::filter::adaptive_filter_cpu;
    use crate::gpu::GpuConfig;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A real adapter is required (lavapipe on machines without a GPU); fails, never skips.
    fn filter() -> GpuAdaptiveFilter {
        let ctx = GpuContext::new(&GpuConfig::default())
            .unwrap_or_else(|e| panic!("no GPU context: {e}"));
        GpuAdaptiveFilter::new(Arc::new(ctx)).expect("kernel compiles")
    }

    /// Random intensity, ~30 % valid inverse depths in [0.2, 3], variances in [1e-4, 1e-2]
    /// (also where D = 0: the filter must ignore them), a prior in [0.2, 3] with 10 % holes.
    fn random_inputs(w: usize, h: usize, seed: u64) -> [ImageF32; 4] {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut make = |f: &dyn Fn(&mut ChaCha8Rng) -> f32| {
            let data = (0..w * h).map(|_| f(&mut rng)).collect();
            ImageF32::from_vec(w, h, data).expect("sizes match")
        };
        let intensity = make(&|r| r.random_range(0.0..255.0));
        let d = make(&|r| {
            if r.random::<f32>() < 0.3 {
                r.random_range(0.2..3.0)
            } else {
                0.0
            }
        });
        let v = make(&|r| r.random_range(1e-4..1e-2));
        let p = make(&|r| {
            if r.random::<f32>() < 0.1 {
                0.0
            } else {
                r.random_range(0.2..3.0)
            }
        });
        [intensity, d, v, p]
    }

    /// GPU vs CPU on random inputs.
    ///
    /// Bound: |gpu − cpu| ≤ 1e-4·|cpu| + 1e-6. Both sides evaluate the same f32 expressions in
    /// the same order; they differ only by WGSL's `exp` (3 + 2|x| ULP) and division (2.5 ULP)
    /// accuracy and by FMA contraction, i.e. a few 1e-6 relative on the weights of any
    /// neighbour that matters (a weight is relevant only while its exponent is ≲ 20). D' is a
    /// convex combination, so it inherits that relative error; V' is to first order
    /// insensitive to an error in D' (Σ w·(D' − D) = 0), so it too is off by ~1e-6 relative,
    /// except where it is ~0 and only the cancellation D' − D(n) remains (≪ 1e-6 absolute).
    /// 1e-4 leaves a margin of ~20× for lavapipe and real GPUs alike; validity depends only on
    /// integer counts and the sanitised inputs, so the masks must be identical.
    #[test]
    fn gpu_filter_matches_cpu_on_random_inputs() {
        let gpu = filter();
        let sizes = [(320, 240), (97, 33), (16, 16), (5, 1), (1, 7)];
        for (k, &(w, h)) in sizes.iter().enumerate() {
            let [intensity, d, v, p] = random_inputs(w, h, 100 + k as u64);
            for (prior, literal) in [(None, false), (Some(&p), false), (Some(&p), true)] {
                let params = FilterParams {
                    consistency_in_variance: literal,
                    ..FilterParams::default()
                };
                let what = format!("{w}x{h} prior {} literal {literal}", prior.is_some());
                let inputs = FilterInputs {
                    intensity: &intensity,
                    semidense: &d,
                    variance: &v,
                    prior,
                };
                let cpu = adaptive_filter_cpu(&inputs, &params).expect("cpu");
                let g = gpu.run(&inputs, &params).expect("gpu");
                let mut valid = 0;
                for (name, a, b) in [
                    ("D'", &cpu.idepth, &g.idepth),
                    ("V'", &cpu.variance, &g.variance),
                ] {
                    assert_eq!((b.width, b.height), (w, h), "{what}");
                    let mut worst = 0.0f32;
                    for (i, (&c, &x)) in a.data.iter().zip(&b.data).enumerate() {
                        assert!(x.is_finite(), "{what} {name} at {i}: {x}");
                        assert_eq!(
                            cpu.idepth.data[i] > 0.0,
                            g.idepth.data[i] > 0.0,
                            "{what}: validity differs at {i}"
                        );
                        let tol = 1e-4 * c.abs() + 1e-6;
                        worst = worst.max((x - c).abs() / tol);
                    }
                    assert!(worst <= 1.0, "{what} {name}: error {worst} × the bound");
                    valid = a.data.iter().filter(|&&x| x > 0.0).count();
                }
                // The inputs have multi-pixel windows except in the tiny images: a GPU that
                // wrote nothing would pass the comparison against an empty CPU result.
                if w * h >= 256 {
                    assert!(valid > w * h / 10, "{what}: only {valid} filtered pixels");
                }
            }
        }
    }

    /// Re-using the cached buffers across sizes and prior / no prior gives the same results
    /// as a fresh runner (nothing stale is read).
    #[test]
    fn gpu_filter_reuses_buffers_across_calls() {
        let gpu = filter();
        let params = FilterParams::default();
        let [i1, d1, v1, p1] = random_inputs(40, 30, 1);
        let [i2, d2, v2, _] = random_inputs(23, 11, 2);
        let first = FilterInputs {
            intensity: &i1,
            semidense: &d1,
            variance: &v1,
            prior: Some(&p1),
        };
        let no_prior = FilterInputs {
            prior: None,
            ..first
        };
        let other = FilterInputs {
            intensity: &i2,
            semidense: &d2,
            variance: &v2,
            prior: None,
        };
        let a = gpu.run(&first, &params).expect("run");
        let b = gpu.run(&no_prior, &params).expect("run");
        let c = gpu.run(&other, &params).expect("run");
        let a2 = gpu.run(&first, &params).expect("run");
        assert_eq!(a, a2);
        assert_ne!(a, b, "the prior must change the result");
        assert_eq!(b, filter().run(&no_prior, &params).expect("fresh"));
        // Same size, fewer valid pixels: what the previous call wrote must not survive.
        let mut d_sparse = d1.clone();
        d_sparse.data.iter_mut().step_by(2).for_each(|x| *x = 0.0);
        let sparse = FilterInputs {
            semidense: &d_sparse,
            ..first
        };
        assert_eq!(
            gpu.run(&sparse, &params).expect("run"),
            filter().run(&sparse, &params).expect("fresh")
        );
        assert_eq!((c.idepth.width, c.idepth.height), (23, 11));
        // Empty images and bad shapes.
        let empty = ImageF32::filled(0, 3, 0.0);
        let raw = gpu
            .run(
                &FilterInputs {
                    intensity: &empty,
                    semidense: &empty,
                    variance: &empty,
                    prior: None,
                },
                &params,
            )
            .expect("empty");
        assert!(raw.idepth.data.is_empty());
        assert!(matches!(
            gpu.run(
                &FilterInputs {
                    semidense: &d2,
                    ..first
                },
                &params
            ),
            Err(Error::Shape(_))
        ));
    }

    /// CPU reference vs GPU at the working resolution, warm, median of 20 (release:
    /// `cargo test --release -p relfusion-slam --lib gpu_filter_timing -- --ignored --nocapture`).
    #[test]
    #[ignore = "timing"]
    fn gpu_filter_timing_320x240() {
        let gpu = filter();
        let params = FilterParams::default();
        let [intensity, d, v, p] = random_inputs(320, 240, 5);
        for prior in [Some(&p), None] {
            let inputs = FilterInputs {
                intensity: &intensity,
                semidense: &d,
                variance: &v,
                prior,
            };
            let median = |f: &dyn Fn() -> FilterRaw| {
                f();
                let mut t: Vec<f64> = (0..20)
                    .map(|_| {
                        let start = std::time::Instant::now();
                        let raw = f();
                        assert!(raw.idepth.data.iter().any(|&x| x > 0.0));
                        start.elapsed().as_secs_f64() * 1e3
                    })
                    .collect();
                t.sort_by(f64::total_cmp);
                t[t.len() / 2]
            };
            let cpu = median(&|| adaptive_filter_cpu(&inputs, &params).expect("cpu"));
            let g = median(&|| gpu.run(&inputs, &params).expect("gpu"));
            eprintln!(
                "adaptive filter 320x240 prior={}: cpu {cpu:.3} ms, gpu {g:.3} ms (incl. upload and readback) on {}",
                prior.is_some(),
                gpu.context().adapter_info().name
            );
        }
    }
}
