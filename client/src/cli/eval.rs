//! `relfusion eval`: trajectory accuracy (ATE/RPE, figures equal to evo's) and depth accuracy
//! (the paper's percentage of correct depth, §V.A). Each subcommand prints one JSON object on
//! stdout so that scripts and the end-to-end tests can read it.
//!
//! `eval depth` has two modes: one depth map against one ground-truth map (`--gt-depth A --est
//! B`), or a whole run (`--dataset DIR --run OUT`): every dense-layer stage of the keyframes
//! `relfusion run` stored in `OUT/keyframes/` (`relfusion_slam::eval::dense_depth`).
//! `eval ablation` re-densifies those keyframes with each energy of the paper's Table II.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context as _;
use relfusion_slam::dataset::trajectory::{StampedPose, read_tum_trajectory};
use relfusion_slam::dense::DenseCompute;
use relfusion_slam::dense::gpu_densify::GpuDensifier;
use relfusion_slam::eval::ablation::{run_ablation, table_ii_rows};
use relfusion_slam::eval::dense_depth::evaluate_dense_depth;
use relfusion_slam::eval::{
    self, AlignMode, DEFAULT_DEPTH_THRESHOLD, DEFAULT_MAX_DT, associate_poses, ate_matched,
    percent_correct_depth, read_depth_map, rotation_gain, rpe_matched, scale_drift,
};
use relfusion_slam::pipeline::Config;
use serde_json::json;

#[derive(Debug, clap::Subcommand)]
pub enum EvalCommand {
    /// ATE/RPE of an estimated trajectory against ground truth (both TUM files
    /// `t tx ty tz qx qy qz qw`); same figures as `evo_ape`/`evo_rpe` with `--t_max_diff`.
    Traj(TrajArgs),
    /// Percentage of correct depth (relative error < threshold), counted over the valid
    /// ground-truth pixels (missing estimates count as wrong). Either one map
    /// (`--gt-depth A --est B`) or every dense-layer stage of a run's stored keyframes
    /// (`--dataset DIR --run OUT`: prior fitted to ground truth, prior aligned by the pipeline,
    /// raw and filtered semi-dense on their pixels, densified), scaled by the Sim(3) alignment
    /// of `OUT/keyframes.txt` to `DIR/groundtruth.txt`; and as a probe the densified depth at
    /// each keyframe's own scale, with each keyframe's ratio to the trajectory's.
    Depth(DepthArgs),
    /// The paper's Table II: re-densify a run's stored keyframes (`OUT/keyframes/`, written
    /// with their stage maps) with each combination of energy terms and score each result like
    /// `eval depth --dataset --run`'s `dense` stage.
    Ablation(AblationArgs),
    /// Accuracy and completeness of a run's fused mesh (`OUT/mesh.ply`) against the
    /// ground-truth surface the keyframes saw, after the Sim(3) alignment of
    /// `OUT/keyframes.txt`; also scores the mesh fused from ground-truth depth and poses (the
    /// upper bound) and our mesh against that mesh.
    Mesh(MeshArgs),
    /// How a sequence localised in a saved map (`relfusion run SEQ2 --map OUT/map --mode
    /// localize`) did: the share of its frames that see the mapped area (true pose within
    /// 0.3 m and 25° of a true pose of the mapping sequence) that got a pose, and their RMS
    /// position error after the Sim(3) that aligns the map's own keyframes to the mapping
    /// sequence's ground truth; localised frames more than `--wrong-m` off count as wrong.
    Localize(LocalizeArgs),
}

#[derive(Debug, clap::Args)]
pub struct LocalizeArgs {
    /// Ground truth of the sequence the map was made from.
    #[arg(long)]
    pub map_gt: PathBuf,
    /// The map (`OUT/map` of the mapping run).
    #[arg(long)]
    pub map: PathBuf,
    /// Ground truth of the localised sequence.
    #[arg(long)]
    pub gt: PathBuf,
    /// The localised trajectory (`OUT2/trajectory.txt` of the localize run).
    #[arg(long)]
    pub est: PathBuf,
    /// Overlap: largest distance to a mapped frame (metres).
    #[arg(long, default_value_t = 0.3)]
    pub overlap_m: f64,
    /// Overlap: largest angle to that frame (degrees).
    #[arg(long, default_value_t = 25.0)]
    pub overlap_deg: f64,
    /// Error above which a localised frame counts as wrong (metres).
    #[arg(long, default_value_t = 0.2)]
    pub wrong_m: f64,
    /// The localised sequence's frames (`OUT2/localization.txt`, timestamps first): the ground
    /// truth is scored at these times only (TUM's ground truth runs at 100 Hz, its video at 30).
    #[arg(long)]
    pub frames: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct MeshArgs {
    /// The dataset folder (TUM layout with depth and groundtruth.txt).
    #[arg(long)]
    pub dataset: PathBuf,
    /// The output folder of `relfusion run` (mesh.ply, mesh.json, keyframes.txt).
    #[arg(long)]
    pub run: PathBuf,
    /// Pipeline config whose `[fusion]` section the ground-truth fusion uses (the run's, to
    /// compare like with like); defaults otherwise.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Fuse the run's stored keyframes (`OUT/keyframes/`) again with `--config`'s `[fusion]`
    /// and score that mesh instead of `OUT/mesh.ply` (tunes the fusion without the SLAM).
    #[arg(long)]
    pub refuse: bool,
    /// Distance bound of an accurate vertex / a covered point, in voxels (issue 5: 2).
    #[arg(long, default_value_t = 2.0)]
    pub threshold_voxels: f64,
}

#[derive(Debug, clap::Args)]
pub struct TrajArgs {
    /// Ground-truth trajectory (TUM format). Repeat it for an estimate that spans several
    /// sequences with distinct timestamps (a map extended by a second run): they are scored
    /// as one trajectory under one alignment.
    #[arg(long, required = true)]
    pub gt: Vec<PathBuf>,
    /// Estimated trajectory (TUM format).
    #[arg(long)]
    pub est: PathBuf,
    /// Alignment of the estimate before measuring: sim3 (monocular; `evo -a -s`), se3
    /// (`evo -a`) or none. Applies to ATE and RPE alike.
    #[arg(long, default_value = "sim3", value_parser = parse_align)]
    pub align: AlignMode,
    /// Largest timestamp difference (seconds) for a ground-truth/estimate pair.
    #[arg(long, default_value_t = DEFAULT_MAX_DT)]
    pub max_dt: f64,
    /// RPE frame offset Δ, in matched poses (`evo_rpe --delta Δ --delta_unit f`).
    #[arg(long, default_value_t = 1)]
    pub rpe_delta: usize,
    /// Frame offset of the per-axis rotation gain (`relfusion_slam::eval::rotation_gain`):
    /// gains below 1 about x and y with z near 1 mean the focal length is set too long, or
    /// rotation taken for translation (on 7-Scenes: a compressed depth map).
    /// Default 10: long enough that the rotation outweighs per-frame noise.
    #[arg(long, default_value_t = 10)]
    pub rotation_gain_delta: usize,
    /// Poses per window of the scale-drift report (`relfusion_slam::eval::scale_drift`): each
    /// window is Sim(3)-aligned on its own, which separates scale drift from shape error.
    /// Default 60 (2 s at 30 Hz). Reported with `--align sim3` only.
    #[arg(long, default_value_t = 60)]
    pub scale_window: usize,
}

#[derive(Debug, clap::Args)]
pub struct DepthArgs {
    /// Single map: ground-truth depth map, 16-bit PNG (divided by --png-scale) or float32 .npy
    /// in metres.
    #[arg(
        long,
        requires = "est",
        conflicts_with_all = ["dataset", "run"],
        required_unless_present = "dataset"
    )]
    pub gt_depth: Option<PathBuf>,
    /// Single map: estimated depth map, same size: .npy (float32 metres) or 16-bit PNG.
    #[arg(long, requires = "gt_depth")]
    pub est: Option<PathBuf>,
    /// Whole run: the dataset folder (TUM layout with depth and groundtruth.txt).
    #[arg(long, requires = "run")]
    pub dataset: Option<PathBuf>,
    /// Whole run: the output folder of `relfusion run` (keyframes.txt, keyframes/).
    #[arg(long, requires = "dataset")]
    pub run: Option<PathBuf>,
    /// Single map: scale applied to the estimate (monocular: trajectory scale × keyframe
    /// scale).
    #[arg(long, default_value_t = 1.0, conflicts_with = "dataset")]
    pub scale: f64,
    /// Relative error bound of a correct pixel (the paper: 10 %).
    #[arg(long, default_value_t = DEFAULT_DEPTH_THRESHOLD)]
    pub threshold: f64,
    /// Single map: units per metre of 16-bit PNG depth (TUM: 5000).
    #[arg(long, default_value_t = eval::depth::TUM_PNG_DEPTH_SCALE, conflicts_with = "dataset")]
    pub png_scale: f64,
}

#[derive(Debug, clap::Args)]
pub struct AblationArgs {
    /// The dataset folder (TUM layout with depth and groundtruth.txt).
    #[arg(long)]
    pub dataset: PathBuf,
    /// The output folder of `relfusion run` (keyframes.txt, keyframes/ with stage maps).
    #[arg(long)]
    pub run: PathBuf,
    /// Pipeline config (TOML/JSON) whose `[dense.densify]` section gives every parameter but
    /// the energy terms; the paper's values otherwise. Use the run's config to reproduce it.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Densify with the CPU reference instead of the GPU kernel.
    #[arg(long)]
    pub cpu: bool,
    /// Relative error bound of a correct pixel (the paper: 10 %).
    #[arg(long, default_value_t = DEFAULT_DEPTH_THRESHOLD)]
    pub threshold: f64,
}

fn parse_align(s: &str) -> Result<AlignMode, String> {
    s.parse().map_err(|e: relfusion_slam::Error| e.to_string())
}

pub fn run(cmd: EvalCommand) -> anyhow::Result<()> {
    let report = match cmd {
        EvalCommand::Traj(args) => traj(&args)?,
        EvalCommand::Depth(args) => depth(&args)?,
        EvalCommand::Ablation(args) => ablation(&args)?,
        EvalCommand::Mesh(args) => mesh(&args)?,
        EvalCommand::Localize(args) => localize(&args)?,
    };
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn read_traj(path: &Path, what: &str) -> anyhow::Result<Vec<StampedPose>> {
    read_tum_trajectory(path).with_context(|| format!("reading the {what} trajectory"))
}

fn localize(args: &LocalizeArgs) -> anyhow::Result<serde_json::Value> {
    let map_gt = read_traj(&args.map_gt, "map's ground-truth")?;
    let mut gt = read_traj(&args.gt, "ground-truth")?;
    if let Some(frames) = &args.frames {
        gt = at_frames(&gt, frames)?;
    }
    let est = read_traj(&args.est, "localised")?;
    let keyframes = relfusion_slam::map::read_keyframe_poses(&args.map)
        .with_context(|| format!("reading {}", args.map.display()))?;
    let scores = eval::localization::score_localization(
        &map_gt,
        &relfusion_slam::dataset::trajectory::stamped_se3(&keyframes),
        &gt,
        &est,
        eval::localization::OverlapParams {
            distance_m: args.overlap_m,
            angle_deg: args.overlap_deg,
        },
        args.wrong_m,
    )?;
    Ok(serde_json::to_value(scores)?)
}

/// The ground-truth pose nearest to each frame timestamp listed in `frames` (first column),
/// within [`DEFAULT_MAX_DT`].
fn at_frames(gt: &[StampedPose], frames: &Path) -> anyhow::Result<Vec<StampedPose>> {
    let text =
        std::fs::read_to_string(frames).with_context(|| format!("reading {}", frames.display()))?;
    let stamps = text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|line| {
            line.split_whitespace()
                .next()
                .and_then(|v| v.parse::<f64>().ok())
                .with_context(|| format!("{}: bad line {line:?}", frames.display()))
        })
        .collect::<anyhow::Result<Vec<f64>>>()?;
    let gt_stamps: Vec<f64> = gt.iter().map(|p| p.timestamp).collect();
    Ok(eval::associate(&gt_stamps, &stamps, DEFAULT_MAX_DT)
        .into_iter()
        .map(|(g, f)| StampedPose {
            timestamp: stamps[f],
            world_from_camera: gt[g].world_from_camera,
        })
        .collect())
}

fn traj(args: &TrajArgs) -> anyhow::Result<serde_json::Value> {
    let mut gt = Vec::new();
    for path in &args.gt {
        gt.extend(read_traj(path, "ground-truth")?);
    }
    gt.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    let est = read_traj(&args.est, "estimated")?;
    let matched = associate_poses(&gt, &est, args.max_dt)?;
    let ate = ate_matched(&matched, args.align)?;
    let rpe = rpe_matched(&matched, args.rpe_delta, args.align)?;
    // A trajectory shorter than the offset (a few keyframes) simply has no gain.
    let gain = (matched.len() > args.rotation_gain_delta)
        .then(|| rotation_gain(&matched, args.rotation_gain_delta))
        .transpose()?;
    // Too short a trajectory for two windows (a few keyframes) has no drift figure.
    let drift = (args.align == AlignMode::Sim3
        && args.scale_window >= 3
        && matched.len() >= 2 * args.scale_window)
        .then(|| scale_drift(&matched, args.scale_window))
        .transpose()?;
    Ok(json!({
        "align": args.align,
        "max_dt_s": args.max_dt,
        "gt_poses": gt.len(),
        "est_poses": est.len(),
        "matched": ate.matched,
        "scale": ate.scale,
        "ate_rmse_m": ate.rmse,
        "ate_mean_m": ate.mean,
        "ate_median_m": ate.median,
        "ate_std_m": ate.std,
        "ate_min_m": ate.min,
        "ate_max_m": ate.max,
        "rpe_delta": rpe.delta,
        "rpe_pairs": rpe.pairs,
        "rpe_trans_rmse_m": rpe.trans_rmse,
        "rpe_trans_mean_m": rpe.trans.mean,
        "rpe_trans_max_m": rpe.trans.max,
        "rpe_rot_rmse_deg": rpe.rot_rmse_deg,
        "rpe_rot_mean_deg": rpe.rot_deg.mean,
        "rpe_rot_max_deg": rpe.rot_deg.max,
        "rotation_gain_delta": args.rotation_gain_delta,
        "rotation_gain_xyz": gain.as_ref().map(|g| g.gain),
        "rotation_gt_rms_deg_xyz": gain.as_ref().map(|g| g.gt_rms_deg),
        "scale_window": args.scale_window,
        "scale_drift": drift.as_ref().and_then(|d| d.drift),
        "window_ate_rmse_max_m": drift.as_ref().map(|d| d.window_ate_rmse_max),
        "scale_windows": drift.as_ref().map(|d| &d.windows),
    }))
}

fn depth(args: &DepthArgs) -> anyhow::Result<serde_json::Value> {
    let (gt_path, est_path) = match (&args.dataset, &args.run, &args.gt_depth, &args.est) {
        (Some(dataset), Some(run), _, _) => {
            let report = evaluate_dense_depth(dataset, run, args.threshold).with_context(|| {
                format!(
                    "evaluating the keyframes of {} against {}",
                    run.display(),
                    dataset.display()
                )
            })?;
            return Ok(serde_json::to_value(report)?);
        }
        (_, _, Some(gt), Some(est)) => (gt, est),
        // clap's `requires` rules make other combinations unreachable.
        _ => anyhow::bail!("give --gt-depth and --est, or --dataset and --run"),
    };
    let gt = read_depth_map(gt_path, args.png_scale)?;
    let est = read_depth_map(est_path, args.png_scale)?;
    let acc = percent_correct_depth(&est, &gt, args.scale, args.threshold)?;
    Ok(json!({
        "percent_correct": acc.percent,
        "valid_gt": acc.valid_gt,
        "evaluated": acc.evaluated,
        "correct": acc.correct,
        "scale": args.scale,
        "threshold": args.threshold,
    }))
}

fn ablation(args: &AblationArgs) -> anyhow::Result<serde_json::Value> {
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let gpu = if args.cpu || config.dense.compute == DenseCompute::Cpu {
        None
    } else {
        // Like the pipeline: the kernel when an adapter opens, else the CPU reference.
        match super::gpu_info::open_context(None)
            .and_then(|ctx| Ok(GpuDensifier::new(Arc::new(ctx))?))
        {
            Ok(g) => Some(g),
            Err(e) => {
                tracing::warn!("no GPU for densification ({e:#}); using the CPU reference");
                None
            }
        }
    };
    let report = run_ablation(
        &args.dataset,
        &args.run,
        &table_ii_rows(),
        &config.dense.densify,
        gpu.as_ref(),
        args.threshold,
    )
    .with_context(|| {
        format!(
            "ablation on the keyframes of {} against {}",
            args.run.display(),
            args.dataset.display()
        )
    })?;
    Ok(serde_json::to_value(report)?)
}

fn mesh(args: &MeshArgs) -> anyhow::Result<serde_json::Value> {
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    use relfusion_slam::eval::fused_mesh::{MeshSource, evaluate_fused_mesh};
    let report = evaluate_fused_mesh(
        &args.dataset,
        &args.run,
        &config.fusion,
        if args.refuse {
            MeshSource::Refuse
        } else {
            MeshSource::RunMesh
        },
        args.threshold_voxels,
    )?;
    Ok(serde_json::to_value(report)?)
}
