//! `relfusion bench odometry`: the DSO-class odometry core (`relfusion_slam::odometry`) alone
//! on TUM-layout sequences with ground truth, before it drives the pipeline (issue 35): frames
//! posed, ATE of every frame and of the keyframes (Sim(3)-aligned), scale drift and the wall
//! time per frame, so that the new core is judged on the same figures as `bench accuracy`.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use relfusion_slam::dataset::trajectory::StampedPose;
use relfusion_slam::eval::{AlignMode, DEFAULT_MAX_DT, associate_poses, ate, scale_drift};
use relfusion_slam::frame::Frame;
use relfusion_slam::geometry::UndistortMap;
use relfusion_slam::odometry::{Odometry, OdometryConfig};

use super::bench_accuracy::load;

/// Poses per window of the scale-drift figure (as `bench accuracy`).
const SCALE_WINDOW: usize = 60;

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
        let path: f64 = loaded
            .gt
            .windows(2)
            .map(|w| {
                (w[1].world_from_camera.translation - w[0].world_from_camera.translation).norm()
            })
            .sum();
        for _ in 0..args.runs {
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
            if let Some(dir) = &args.save {
                std::fs::create_dir_all(dir)?;
                let name = dataset
                    .file_name()
                    .map_or_else(|| "sequence".into(), |n| n.to_string_lossy().into_owned());
                let out = dir.join(format!("{name}.txt"));
                let text: String = est
                    .iter()
                    .map(|p| {
                        let q = p.world_from_camera.rotation.quaternion();
                        let t = p.world_from_camera.translation;
                        format!(
                            "{} {} {} {} {} {} {} {}\n",
                            p.timestamp, t.x, t.y, t.z, q.i, q.j, q.k, q.w
                        )
                    })
                    .collect();
                std::fs::write(&out, text)?;
            }
            let kf_est: Vec<StampedPose> = est
                .iter()
                .filter(|p| keyframe_stamps.contains(&p.timestamp))
                .cloned()
                .collect();
            let ate_of =
                |e: &[StampedPose]| ate(&loaded.gt, e, AlignMode::Sim3).ok().map(|r| r.rmse);
            let drift = associate_poses(&loaded.gt, &est, DEFAULT_MAX_DT)
                .ok()
                .and_then(|m| scale_drift(&m, SCALE_WINDOW).ok())
                .and_then(|d| d.drift);
            let fmt =
                |v: Option<f64>, d: usize| v.map_or_else(|| "-".into(), |x| format!("{x:.d$}"));
            let traj = ate_of(&est);
            println!(
                "{:<48} {:>6} {:>7} {:>4} {:>9} {:>9} {:>7} {:>7} {:>8.1}",
                dataset.display().to_string(),
                frames.len(),
                tracked,
                odometry.keyframe_count(),
                fmt(traj, 4),
                fmt(ate_of(&kf_est), 4),
                fmt(traj.map(|a| 100.0 * a / path.max(1e-9)), 2),
                fmt(drift, 2),
                ms
            );
        }
    }
    Ok(())
}
