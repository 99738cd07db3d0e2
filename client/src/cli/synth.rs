//! `relfusion synth`: render a synthetic textured-room RGB-D sequence (TUM layout, exact
//! ground truth) and print a one-line JSON summary.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::dataset::{Motion, SynthConfig, render_sequence};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output folder (created; existing files with the same names are overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of frames (30 Hz).
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    /// Seed of the room (textures, furniture) and of the trajectory phases.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Motion preset: orbit, forward, rotation or shake.
    #[arg(long, default_value_t = Motion::Orbit)]
    pub motion: Motion,
    /// Image width in pixels (focal length scales with it: 525 at 640).
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Rendering threads.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = SynthConfig {
        frames: args.frames,
        seed: args.seed,
        motion: args.motion,
        width: args.width,
        height: args.height,
        threads: args.threads,
        ..SynthConfig::default()
    };
    let start = Instant::now();
    let summary = render_sequence(&config, &args.out).with_context(|| {
        format!(
            "rendering the synthetic sequence into {}",
            args.out.display()
        )
    })?;
    let line = serde_json::json!({
        "out": args.out,
        "frames": summary.frames,
        "seed": config.seed,
        "motion": config.motion,
        "width": config.width,
        "height": config.height,
        "path_length_m": summary.path_length_m,
        "max_rotation_deg": summary.max_rotation_deg,
        "seconds": start.elapsed().as_secs_f64(),
    });
    println!("{line}");
    Ok(())
}
