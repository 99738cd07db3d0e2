//! `relfusion bench ...`: benchmarks that print JSON figures (GPU kernels vs their CPU twins).

use std::time::{Duration, Instant};

use relfusion_slam::gpu::{AdapterChoice, PyramidKernel};
use relfusion_slam::image::ImageF32;
use relfusion_slam::image::pyramid::Pyramid;
use serde_json::json;

use super::gpu_info::{adapter_json, open_context};
use super::timing::median_ms;

#[derive(Debug, clap::Subcommand)]
pub enum BenchCommand {
    /// GPU pyramid/gradient kernel vs its CPU reference.
    Pyramid(PyramidArgs),
    /// SLAM pipeline wall time per frame (unpaced) and the ATE spread over runs.
    Slam(super::bench_slam::SlamArgs),
    /// ATE, keyframe ATE and scale drift over several sequences, N threaded runs each plus one
    /// deterministic, with an aggregate line (judge a change on all of them).
    Accuracy(super::bench_accuracy::AccuracyArgs),
    /// The DSO-class odometry core alone (issue 35): ATE, keyframe ATE, scale drift, time.
    Odometry(super::bench_odometry::OdometryArgs),
    /// A running relfusiond: HTTP/Zenoh ingest rate, frame-to-pose latency, sessions at 30 fps.
    Serve(super::bench_serve::ServeArgs),
    /// relfusiond nodes on this machine as one service (spawned here: a router and 1..N
    /// nodes): sessions sustained at 30 fps per N, forwarding latency owner vs non-owner.
    Cluster(super::bench_cluster::ClusterArgs),
    /// Densification (eqs. 10–13, Adam) on saved inputs: GPU kernel vs CPU reference.
    Densify(super::bench_densify::DensifyArgs),
    /// Per keyframe of a saved run: prior, adaptive filter and densification, GPU vs CPU.
    Dense(super::bench_dense::DenseArgs),
    /// TSDF fusion of a saved run's keyframes: integration, meshing, re-integration, memory;
    /// GPU kernels vs CPU references.
    Fusion(super::bench_fusion::FusionArgs),
    /// The live viewer in headless Chromium: bundle size and frame rate with an N-triangle
    /// mesh (needs a running relfusiond and Debian's chromium + chromium-driver).
    Viewer(super::bench_viewer::ViewerArgs),
    /// A saved map: load and save times, size on disk per keyframe, memory once loaded.
    Map(super::bench_map::MapArgs),
    /// A session of minutes to hours against a running relfusiond (a synthetic hand-held loop
    /// streamed live): server RSS, keyframes resident/spilled, latency per interval; ATE and
    /// mesh at the end (issue 37).
    Long(super::bench_long::LongArgs),
    /// The pose graph of a long looping session at growing sizes: factor size in the solver's
    /// minimum-degree order vs insertion order, time of a full optimisation, error vs truth.
    Graph(super::bench_graph::GraphArgs),
}

#[derive(Debug, clap::Args)]
pub struct PyramidArgs {
    /// Image width in pixels (TUM RGB-D: 640).
    #[arg(long, default_value_t = 640)]
    pub width: usize,
    /// Image height in pixels (TUM RGB-D: 480).
    #[arg(long, default_value_t = 480)]
    pub height: usize,
    /// Pyramid levels (LSD-SLAM tracks on 5).
    #[arg(long, default_value_t = 5)]
    pub levels: usize,
    /// Timed iterations per variant (after 3 untimed warm-up runs).
    #[arg(long, default_value_t = 50)]
    pub iters: usize,
    /// Adapter kind: auto, gpu or cpu (auto lets RELFUSION_GPU decide).
    #[arg(long)]
    pub adapter: Option<AdapterChoice>,
}

pub fn run(cmd: BenchCommand) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Pyramid(args) => pyramid(&args),
        BenchCommand::Slam(args) => super::bench_slam::slam(&args),
        BenchCommand::Accuracy(args) => super::bench_accuracy::accuracy(&args),
        BenchCommand::Odometry(args) => super::bench_odometry::odometry(&args),
        BenchCommand::Serve(args) => super::bench_serve::serve(&args),
        BenchCommand::Cluster(args) => super::bench_cluster::cluster(&args),
        BenchCommand::Densify(args) => super::bench_densify::densify(&args),
        BenchCommand::Dense(args) => super::bench_dense::dense(&args),
        BenchCommand::Fusion(args) => super::bench_fusion::fusion(&args),
        BenchCommand::Viewer(args) => super::bench_viewer::viewer(&args),
        BenchCommand::Map(args) => super::bench_map::map(&args),
        BenchCommand::Long(args) => super::bench_long::long(&args),
        BenchCommand::Graph(args) => super::bench_graph::graph(&args),
    }
}

/// Untimed runs before measuring (pipeline compilation, first allocations, driver warm-up).
const WARMUP: usize = 3;

fn pyramid(args: &PyramidArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.iters > 0, "--iters must be positive");
    let image = noise_image(args.width, args.height, 0x5eed);
    let ctx = open_context(args.adapter)?;
    let kernel = PyramidKernel::new(&ctx)?;

    let cpu_ref = Pyramid::build_cpu(&image, args.levels)?;
    let gpu_out = kernel.build(&ctx, &image, args.levels)?;
    let max_abs_diff = cpu_ref.max_abs_diff(&gpu_out)?;

    let cpu = time(args.iters, || {
        Pyramid::build_cpu(&image, args.levels).map(drop)
    })?;
    // Upload + all kernels + readback of every level, one submission each.
    let mut kernel_only = Vec::new();
    let total = time(args.iters, || {
        let (_, t) = kernel.build_timed(&ctx, &image, args.levels)?;
        kernel_only.extend(t);
        Ok(())
    })?;
    // Upload + kernels, waiting for completion but reading nothing back.
    let resident = time(args.iters, || {
        kernel.build_resident(&ctx, &image, args.levels)?;
        ctx.wait()
    })?;
    // `total` ran WARMUP + iters times; keep the timed runs' kernel times only.
    let kernel_ms =
        (kernel_only.len() > WARMUP).then(|| median_ms(&mut kernel_only[WARMUP..].to_vec()));

    let report = json!({
        "bench": "pyramid",
        "adapter": adapter_json(&ctx),
        "width": args.width,
        "height": args.height,
        "levels": args.levels,
        "iters": args.iters,
        "gpu_total_ms_median": median_ms(&mut total.clone()),
        "gpu_no_readback_ms_median": median_ms(&mut resident.clone()),
        "gpu_kernel_ms_median": kernel_ms,
        "cpu_ms_median": median_ms(&mut cpu.clone()),
        "max_abs_diff": max_abs_diff,
        "notes": "gpu_total: upload + kernels + readback; gpu_no_readback: upload + kernels; \
                  gpu_kernel: timestamp queries around the compute pass (null without support)",
    });
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

/// Runs `f` WARMUP times untimed, then `iters` times timed.
fn time(
    iters: usize,
    mut f: impl FnMut() -> relfusion_slam::Result<()>,
) -> relfusion_slam::Result<Vec<Duration>> {
    for _ in 0..WARMUP {
        f()?;
    }
    (0..iters)
        .map(|_| {
            let start = Instant::now();
            f()?;
            Ok(start.elapsed())
        })
        .collect()
}

/// Deterministic uniform noise in [0, 255) (SplitMix64), so runs are comparable without a
/// dataset; the kernels' cost does not depend on content, so noise is as good as a real frame.
fn noise_image(width: usize, height: usize, seed: u64) -> ImageF32 {
    let mut state = seed;
    let data = (0..width * height)
        .map(|_| {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            (z >> 40) as f32 / (1u64 << 24) as f32 * 255.0
        })
        .collect();
    ImageF32 {
        width,
        height,
        data,
    }
}
