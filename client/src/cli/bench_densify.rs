//! `relfusion bench densify --inputs DIR`: the densification (eqs. 10–13, Adam) on saved
//! inputs, on the GPU kernel and on its CPU reference, with the outputs written beside the
//! inputs so that other implementations of the same energy (e.g. the paper's PyTorch code)
//! can be run on the same arrays and compared.
//!
//! Inputs (float32 `.npy`, H×W, all the same size): `prior.npy` (the eq. (3)-aligned prior
//! inverse depth), `semidense.npy` (filtered semi-dense inverse depth, 0 = none),
//! `variance.npy` (its variance). Outputs: `dense_gpu.npy`, `dense_cpu.npy`. Prints one JSON
//! line.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use relfusion_slam::dense::densify::{DensifyProblem, densify_cpu, energy};
use relfusion_slam::dense::gpu_densify::GpuDensifier;
use relfusion_slam::gpu::{GpuConfig, GpuContext};
use relfusion_slam::image::ImageF32;
use relfusion_slam::npy;
use relfusion_slam::pipeline::Config;
use serde_json::json;

use super::timing::median_ms;

#[derive(Debug, clap::Args)]
pub struct DensifyArgs {
    /// Folder with prior.npy, semidense.npy and variance.npy; the outputs go there too.
    #[arg(long)]
    pub inputs: PathBuf,
    /// Pipeline config (TOML or JSON) whose `[dense]` section sets the energy and Adam;
    /// the paper's values without one.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Timed runs per path, after one untimed warm-up run (pipeline compilation, buffers).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
}

/// Reads `DIR/name` as a float32 map (its errors name the file).
fn read_map(dir: &Path, name: &str) -> anyhow::Result<ImageF32> {
    Ok(npy::read_f32(&dir.join(name))?)
}

pub fn densify(args: &DensifyArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.runs > 0, "--runs must be positive");
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let params = &config.dense.densify;
    let prior = read_map(&args.inputs, "prior.npy")?;
    let semidense = read_map(&args.inputs, "semidense.npy")?;
    let variance = read_map(&args.inputs, "variance.npy")?;
    for (name, map) in [("semidense.npy", &semidense), ("variance.npy", &variance)] {
        anyhow::ensure!(
            (map.width, map.height) == (prior.width, prior.height),
            "{} is {}x{} (W×H) but prior.npy is {}x{}",
            args.inputs.join(name).display(),
            map.width,
            map.height,
            prior.width,
            prior.height
        );
    }
    let problem = DensifyProblem::with_prior(&prior, &semidense, &variance, params)?;

    let ctx = Arc::new(GpuContext::new(&GpuConfig::default())?);
    let gpu = GpuDensifier::new(Arc::clone(&ctx))?;
    // One warm-up each, then `runs` timed rounds that alternate the two paths, so that both
    // medians see the same machine load. GPU: wall time of upload + kernels + readback, and
    // the GPU's own time of the compute pass (timestamp queries) where the device has them.
    let mut gpu_out = gpu.run(&problem, params)?;
    let mut cpu_out = densify_cpu(&problem, params)?;
    let mut gpu_total = Vec::with_capacity(args.runs);
    let mut gpu_kernel = Vec::with_capacity(args.runs);
    let mut cpu_times = Vec::with_capacity(args.runs);
    for _ in 0..args.runs {
        let start = Instant::now();
        let (out, kernel) = gpu.run_timed(&problem, params)?;
        gpu_total.push(start.elapsed());
        gpu_kernel.extend(kernel);
        gpu_out = out;
        let start = Instant::now();
        cpu_out = densify_cpu(&problem, params)?;
        cpu_times.push(start.elapsed());
    }

    for (name, map) in [("dense_gpu.npy", &gpu_out), ("dense_cpu.npy", &cpu_out)] {
        let path = args.inputs.join(name);
        npy::write_f32(&path, map).with_context(|| format!("cannot write {}", path.display()))?;
    }
    let max_abs_diff = gpu_out
        .data
        .iter()
        .zip(&cpu_out.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let report = json!({
        "bench": "densify",
        "width": problem.width,
        "height": problem.height,
        "iterations": params.iterations,
        "runs": args.runs,
        "adapter": ctx.adapter_info().name,
        "device_type": format!("{:?}", ctx.adapter_info().device_type),
        "gpu_ms": median_ms(&mut gpu_total),
        "gpu_kernel_ms": (!gpu_kernel.is_empty()).then(|| median_ms(&mut gpu_kernel)),
        "cpu_ms": median_ms(&mut cpu_times),
        "max_abs_diff": max_abs_diff,
        "energy_init": energy(&problem, &problem.start(params), params),
        "energy_gpu": energy(&problem, &gpu_out.data, params),
        "energy_cpu": energy(&problem, &cpu_out.data, params),
        "notes": "medians over runs after one warm-up; gpu_ms: upload + all iterations + \
                  readback (wall time); gpu_kernel_ms: the compute pass alone (timestamp \
                  queries, null without support); cpu_ms: the CPU reference (one thread)",
    });
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}
