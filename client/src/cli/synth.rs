//! `relfusion synth`: render a synthetic textured-room RGB-D sequence (TUM layout, exact
//! ground truth) and print a one-line JSON summary.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::dataset::synth::Nuisances;
use relfusion_slam::dataset::{Motion, SynthConfig, render_sequence};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output folder (created; existing files with the same names are overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Number of frames.
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    /// Frame rate (Hz): frame i is the view at time i / fps on the same path, so another rate
    /// samples the same room from other poses.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Seed of the room (textures, furniture) and of the trajectory phases.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Motion preset: orbit, forward, rotation, shake, or the long hand-held paths handheld
    /// (no return to the start) and loop (back over the start every 900 frames).
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
    /// Photometric nuisances of a real camera, all at once (auto-exposure ±25 %, vignetting
    /// 0.3, noise σ 2, half-frame motion blur, JPEG 85); the flags below override each.
    #[arg(long)]
    pub camera_nuisances: bool,
    /// Auto-exposure: amplitude of the log gain (0.22 = gain within ±25 %).
    #[arg(long)]
    pub exposure: Option<f64>,
    /// Vignetting: brightness in the corners falls to 1 − k.
    #[arg(long)]
    pub vignetting: Option<f64>,
    /// Sensor noise σ in grey levels.
    #[arg(long)]
    pub noise: Option<f64>,
    /// Motion blur: shutter time as a fraction of the frame interval.
    #[arg(long)]
    pub motion_blur: Option<f64>,
    /// JPEG quality of the colour images (0 = PNG).
    #[arg(long)]
    pub jpeg: Option<u8>,
    /// Rolling shutter: row read-out time as a fraction of the frame interval (0 = global
    /// shutter; Kinect-class and phone sensors read out in most of a frame).
    #[arg(long)]
    pub rolling_shutter: Option<f64>,
}

impl Args {
    fn nuisances(&self) -> Nuisances {
        let base = if self.camera_nuisances {
            Nuisances::CAMERA
        } else {
            Nuisances::default()
        };
        Nuisances {
            exposure: self.exposure.unwrap_or(base.exposure),
            vignetting: self.vignetting.unwrap_or(base.vignetting),
            noise: self.noise.unwrap_or(base.noise),
            motion_blur: self.motion_blur.unwrap_or(base.motion_blur),
            jpeg_quality: self.jpeg.unwrap_or(base.jpeg_quality),
            rolling_shutter: self.rolling_shutter.unwrap_or(base.rolling_shutter),
        }
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = SynthConfig {
        frames: args.frames,
        seed: args.seed,
        motion: args.motion,
        width: args.width,
        height: args.height,
        threads: args.threads,
        nuisances: args.nuisances(),
        fps: args.fps,
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
        "nuisances": config.nuisances,
        "seconds": start.elapsed().as_secs_f64(),
    });
    println!("{line}");
    Ok(())
}
