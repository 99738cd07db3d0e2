//! `relfusion`: the command line of relfusion (local pipeline tools and, later, the service client).

use clap::{Parser, Subcommand};

mod cli;

#[derive(Debug, Parser)]
#[command(
    name = "relfusion",
    version,
    about = "DeepRelativeFusion: dense monocular SLAM"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the SLAM pipeline locally on a TUM-layout sequence (no server).
    Run(cli::run::Args),
    /// Render a synthetic textured-room RGB-D sequence with exact ground truth (TUM layout).
    Synth(cli::synth::Args),
    /// Evaluate trajectories (ATE/RPE) or depth maps (percentage of correct depth).
    #[command(subcommand)]
    Eval(cli::eval::EvalCommand),
    /// Print the wgpu adapter the pipeline would use, and its limits.
    GpuInfo(cli::gpu_info::Args),
    /// Run the depth prior (ONNX) on a sequence and report its accuracy against ground truth.
    Prior(cli::prior::Args),
    /// Benchmarks that print figures (GPU kernels vs their CPU references, ...).
    #[command(subcommand)]
    Bench(cli::bench::BenchCommand),
    /// Stream a TUM-layout sequence live to relfusiond; prints poses as JSON lines.
    Stream(cli::stream::Args),
    /// Upload a TUM-layout sequence to relfusiond and follow its processing.
    Upload(cli::upload::Args),
    /// Download a session's trajectory, keyframes, point cloud and mesh from relfusiond.
    Fetch(cli::fetch::Args),
    /// Saved maps on relfusiond: keep a finished session's map, list, show, delete.
    Maps(cli::maps::Args),
    /// Exit 0 when relfusiond answers its liveness check (`/healthz`), 1 otherwise.
    Health(cli::health::Args),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Run(args) => cli::run::run(args),
        Command::Synth(args) => cli::synth::run(args),
        Command::Eval(cmd) => cli::eval::run(cmd),
        Command::GpuInfo(args) => cli::gpu_info::run(args),
        Command::Prior(args) => cli::prior::run(args),
        Command::Bench(cmd) => cli::bench::run(cmd),
        Command::Stream(args) => cli::stream::run(args),
        Command::Upload(args) => cli::upload::run(args),
        Command::Fetch(args) => cli::fetch::run(args),
        Command::Maps(args) => cli::maps::run(args),
        Command::Health(args) => cli::health::run(args),
    }
}
