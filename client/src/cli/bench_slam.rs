//! `relfusion bench slam`: wall time of the SLAM pipeline per frame, unpaced, over a whole
//! sequence, with the tracking and mapping shares; and the spread of the threaded (default)
//! mode's ATE over several runs.
//!
//! Frames are decoded into memory first, so the figure is the pipeline's own (image decoding
//! is reported separately: a live stream pays it, but on the client's or ingest side).

use std::path::PathBuf;
use std::time::Instant;

use relfusion_slam::dataset::trajectory::stamped_se3;
use relfusion_slam::eval::{AlignMode, ate};
use relfusion_slam::geometry::Sim3;
use relfusion_slam::pipeline::Pipeline;
use serde_json::json;

use super::bench_accuracy::{Loaded, bench_config, load};
use super::run::load_prior;

#[derive(Debug, clap::Args)]
pub struct SlamArgs {
    /// Sequence folder in TUM layout.
    pub dataset: PathBuf,
    /// Pipeline config (TOML/JSON).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// ONNX depth model (first-keyframe initialisation).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Runs of the sequence (the spread of ATE and time is reported over them).
    #[arg(long, default_value_t = 1)]
    pub runs: usize,
    /// Run the back end in step with the frames instead of on its own thread.
    #[arg(long)]
    pub deterministic: bool,
    /// Use only the first N frames.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Feed the frames at this rate, as a live camera does (default: unpaced, each frame as
    /// soon as the previous one is done). Paced, the mapping thread has the time between
    /// frames: the figure to read for how much of the stream a live session maps.
    #[arg(long)]
    pub fps: Option<f64>,
    /// Map on the mapping thread (`pipeline.mapping_thread`, as live sessions do): tracking
    /// never waits for the mapping, which observes the frames it has time for.
    #[arg(long)]
    pub mapping_thread: bool,
    /// Turn the dense layer off (compare tracking time with it on: it must not slow
    /// tracking down, issue 4).
    #[arg(long)]
    pub no_dense: bool,
}

pub fn slam(args: &SlamArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.runs > 0, "--runs must be positive");
    anyhow::ensure!(
        args.fps.is_none_or(|f| f.is_finite() && f > 0.0),
        "--fps must be positive"
    );
    let mut config = bench_config(args.config.as_deref(), args.no_dense, args.mapping_thread)?;
    config.pipeline.deterministic |= args.deterministic;
    let t_decode = Instant::now();
    let Loaded { seq, frames, gt } = load(&args.dataset, args.frames)?;
    let n = frames.len();
    let decode_ms = 1e3 * t_decode.elapsed().as_secs_f64() / n.max(1) as f64;

    let mut runs = Vec::new();
    for _ in 0..args.runs {
        let prior = load_prior(args.model.as_deref(), None, None)?;
        let mut pipeline = Pipeline::new(config.clone(), seq.camera, prior)?;
        let t0 = Instant::now();
        let mut per_frame = Vec::with_capacity(n);
        for (i, frame) in frames.iter().enumerate() {
            if let Some(fps) = args.fps {
                let due = t0 + std::time::Duration::from_secs_f64(i as f64 / fps);
                std::thread::sleep(due.saturating_duration_since(Instant::now()));
            }
            let tf = Instant::now();
            pipeline.push(frame.clone())?;
            per_frame.push(1e3 * tf.elapsed().as_secs_f64());
        }
        // Paced, the wall time per frame is the frame interval: the pipeline's own time is the
        // sum of the per-frame times.
        let frames_s = match args.fps {
            Some(_) => per_frame.iter().sum::<f64>() / 1e3,
            None => t0.elapsed().as_secs_f64(),
        };
        let t_finish = Instant::now();
        pipeline.finish()?;
        let finish_s = t_finish.elapsed().as_secs_f64();
        let stats = pipeline.stats().clone();
        per_frame.sort_by(f64::total_cmp);
        let ate_of = |poses: &[(f64, Sim3)]| -> Option<f64> {
            ate(&gt, &stamped_se3(poses), AlignMode::Sim3)
                .ok()
                .map(|r| r.rmse)
        };
        runs.push(json!({
            "ms_per_frame": 1e3 * frames_s / n as f64,
            "ms_per_frame_p50": per_frame[n / 2],
            "ms_per_frame_p99": per_frame[(n * 99 / 100).min(n - 1)],
            "final_optimisation_s": finish_s,
            "tracking_ms_per_frame": 1e3 * stats.tracking_s / n as f64,
            "mapping_ms_per_frame": 1e3 * stats.mapping_s / n as f64,
            "frames_batched": stats.frames_batched,
            "keyframes": stats.keyframes,
            "keyframes_densified": stats.keyframes_densified,
            "keyframes_not_densified": stats.keyframes_not_densified,
            "frames_lost": stats.frames_lost,
            "ate_trajectory_m": ate_of(&pipeline.trajectory()?),
            "ate_keyframes_m": ate_of(&pipeline.keyframe_trajectory()),
        }));
    }
    let spread = |key: &str| {
        let v: Vec<f64> = runs.iter().filter_map(|r| r[key].as_f64()).collect();
        let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
        let min = v.iter().copied().fold(f64::INFINITY, f64::min);
        let max = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        json!({ "mean": mean, "min": min, "max": max })
    };
    println!(
        "{}",
        serde_json::to_string_pretty(&json!({
            "bench": "slam",
            "dataset": args.dataset,
            "frames": n,
            "width": seq.camera.width,
            "height": seq.camera.height,
            "mode": if config.pipeline.deterministic { "deterministic" } else { "threaded" },
            "mapping": if config.pipeline.maps_on_thread() {
                "thread"
            } else {
                "in step"
            },
            "dense": if config.dense.enabled { "on" } else { "off" },
            "build": if cfg!(debug_assertions) { "debug" } else { "release" },
            "fps": args.fps,
            "image_decode_ms_per_frame": decode_ms,
            "runs": runs,
            "spread": {
                "ms_per_frame": spread("ms_per_frame"),
                "tracking_ms_per_frame": spread("tracking_ms_per_frame"),
                "frames_batched": spread("frames_batched"),
                "ate_trajectory_m": spread("ate_trajectory_m"),
                "ate_keyframes_m": spread("ate_keyframes_m"),
            },
        }))?
    );
    Ok(())
}
