//! `relfusion bench odometry`: the DSO-class odometry core (`relfusion_slam::odometry`) alone
//! on TUM-layout sequences with ground truth, before it drives the pipeline (issue 35): frames
//! posed, ATE of every frame and of the keyframes (Sim(3)-aligned), scale drift and the wall
//! time per frame, so that the new core is judged on the same figures as `bench accuracy`.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use relfusion_slam::dataset::trajectory::{StampedPose, write_tum_trajectory};
use relfusion_slam::frame::Frame;
use relfusion_slam::geometry::UndistortMap;
use relfusion_slam::odometry::{Odometry, OdometryConfig};

use super::bench_accuracy::load;

#[derive(Debug, clap::Args)]
pub struct OdometryArgs {
    /// Sequence folders in TUM layout (real or `relfusion synth`), each with ground truth.
    #[arg(required = true)]
    pub datasets: Vec<PathBuf>,
    /// Runs per sequence (the core is deterministic; more runs show the timing spread).
    #[arg(long, default_value_t = 1)]
    pub runs: usize,
    /// Write each sequence's trajectory (TUM format, `<sequence>.txt`) into this folder, for
    /// `relfusion eval traj`.
    #[arg(long)]
    pub save: Option<PathBuf>,
}

pub fn odometry(args: &OdometryArgs) -> anyhow::Result<()> {
    println!(
        "{:<48} {:>6} {:>7} {:>4} {:>9} {:>9} {:>7} {:>7} {:>8}",
        "sequence", "frames", "tracked", "kfs", "ATE m", "kf ATE m", "% path", "drift", "ms/frame"
    );
    for dataset in &args.datasets {
        let loaded = load(dataset, None)?;
        let camera = loaded.seq.camera;
        let undistort = camera
            .distortion
            .is_some()
            .then(|| UndistortMap::new(&camera));
        let frames = loaded
            .frames
            .iter()
            .enumerate()
            .map(|(i, f)| {
                Frame::from_camera_rgb(
                    i as u64,
                    f.timestamp,
                    &camera,
                    undistort.as_ref(),
                    f.rgb.clone(),
                )
                .map(Arc::new)
            })
            .collect::<Result<Vec<_>, _>>()?;
        let path = loaded.path_length();
        for run in 0..args.runs {
            let mut odometry = Odometry::new(OdometryConfig::default())?;
            let mut tracked = 0;
            let mut keyframe_stamps = Vec::new();
            let t0 = Instant::now();
            for f in &frames {
                let outcome = odometry.push(f.clone())?;
                tracked += usize::from(outcome.tracked);
                if outcome.keyframe {
                    keyframe_stamps.push(f.timestamp);
                }
            }
            let ms = 1e3 * t0.elapsed().as_secs_f64() / frames.len().max(1) as f64;
            let est: Vec<StampedPose> = odometry
                .trajectory()
                .into_iter()
                .map(|(id, pose)| StampedPose {
                    timestamp: frames[id as usize].timestamp,
                    world_from_camera: pose,
                })
                .collect();
            // The core is deterministic: every run's trajectory is the first's.
            if let (Some(dir), 0) = (&args.save, run) {
                std::fs::create_dir_all(dir)?;
                let name = dataset
                    .file_name()
                    .map_or_else(|| "sequence".into(), |n| n.to_string_lossy().into_owned());
                write_tum_trajectory(&dir.join(format!("{name}.txt")), &est)?;
            }
            let kf_est: Vec<StampedPose> = est
                .iter()
                .filter(|p| keyframe_stamps.contains(&p.timestamp))
                .cloned()
                .collect();
            let drift = loaded.scale_drift(&est);
            let fmt =
                |v: Option<f64>, d: usize| v.map_or_else(|| "-".into(), |x| format!("{x:.d$}"));
            let traj = loaded.ate(&est);
            println!(
                "{:<48} {:>6} {:>7} {:>4} {:>9} {:>9} {:>7} {:>7} {:>8.1}",
                dataset.display().to_string(),
                frames.len(),
                tracked,
                odometry.keyframe_count(),
                fmt(traj, 4),
                fmt(loaded.ate(&kf_est), 4),
                fmt(traj.map(|a| 100.0 * a / path.max(1e-9)), 2),
                fmt(drift, 2),
                ms
            );
        }
    }
    Ok(())
}
