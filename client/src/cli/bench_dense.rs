//! `relfusion bench dense --run OUT`: per keyframe at the working resolution (320×240), the
//! dense layer's stages on the keyframes a `relfusion run` saved (`OUT/keyframes/`): prior
//! inference (as timed in the run), the adaptive filter and the 30-iteration densification,
//! each on the GPU kernel and on its CPU reference. Prints one JSON object.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::dense::densify::{DensifyProblem, densify, densify_cpu};
use relfusion_slam::dense::filter::{FilterInputs, adaptive_filter_cpu, filter_semidense};
use relfusion_slam::dense::gpu_densify::GpuDensifier;
use relfusion_slam::dense::gpu_filter::GpuAdaptiveFilter;
use relfusion_slam::dense::store::DenseStore;
use relfusion_slam::pipeline::Config;
use serde_json::json;

use super::gpu_info::adapter_json;
use super::timing::{median, ms};

#[derive(Debug, clap::Args)]
pub struct DenseArgs {
    /// Output folder of `relfusion run` (reads `keyframes/`).
    #[arg(long)]
    pub run: PathBuf,
    /// Pipeline config whose `[dense]` section is used (the paper's values without one).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Benchmark at most this many keyframes.
    #[arg(long, default_value_t = 10)]
    pub keyframes: usize,
}

pub fn dense(args: &DenseArgs) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    }
    .dense;
    let store = DenseStore::open(&args.run.join("keyframes"))
        .with_context(|| format!("opening {}/keyframes", args.run.display()))?;
    let ctx = relfusion_slam::gpu::shared_context()?;
    let gpu_filter = GpuAdaptiveFilter::new(ctx.clone())?;
    let gpu_densify = GpuDensifier::new(ctx.clone())?;
    let (mut prior, mut filt_gpu, mut filt_cpu, mut dens_gpu, mut dens_cpu) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut first = true;
    for kf in store
        .keyframes
        .iter()
        .filter(|k| k.has_stages() && !k.is_no_model())
        .take(args.keyframes)
    {
        let map = |name: &str| -> anyhow::Result<_> {
            store
                .read_map(kf, name)?
                .with_context(|| format!("keyframe {} has no {name} map", kf.stem))
        };
        let (intensity, semidense, variance, aligned) = (
            map("intensity")?,
            map("semidense")?,
            map("semidense_var")?,
            map("prior_aligned")?,
        );
        let inputs = FilterInputs {
            intensity: &intensity,
            semidense: &semidense,
            variance: &variance,
            prior: Some(&aligned),
        };
        if first {
            // Warm-up: pipeline compilation and buffer allocation are not per-keyframe costs.
            filter_semidense(&inputs, &config.filter, &gpu_filter)?;
            first = false;
        }
        let t = Instant::now();
        let (filtered, filtered_var) = filter_semidense(&inputs, &config.filter, &gpu_filter)?;
        filt_gpu.push(ms(t));
        let t = Instant::now();
        adaptive_filter_cpu(&inputs, &config.filter)?;
        filt_cpu.push(ms(t));
        let problem =
            DensifyProblem::with_prior(&aligned, &filtered, &filtered_var, &config.densify)?;
        densify(&problem, &config.densify, &gpu_densify)?;
        let t = Instant::now();
        densify(&problem, &config.densify, &gpu_densify)?;
        dens_gpu.push(ms(t));
        let t = Instant::now();
        densify_cpu(&problem, &config.densify)?;
        dens_cpu.push(ms(t));
        prior.push(kf.timings.prior_ms);
    }
    anyhow::ensure!(
        !dens_gpu.is_empty(),
        "no keyframe with stage maps and a prior in {}",
        args.run.display()
    );
    println!(
        "{}",
        serde_json::to_string_pretty(&json!({
            "bench": "dense",
            "build": if cfg!(debug_assertions) { "debug" } else { "release" },
            "adapter": adapter_json(&ctx),
            "width": store.width,
            "height": store.height,
            "keyframes": dens_gpu.len(),
            "iterations": config.densify.iterations,
            "median_ms": {
                "prior_inference_in_run": median(prior),
                "filter_gpu": median(filt_gpu),
                "filter_cpu_reference": median(filt_cpu),
                "densify_gpu": median(dens_gpu),
                "densify_cpu_reference": median(dens_cpu),
            },
        }))?
    );
    Ok(())
}
