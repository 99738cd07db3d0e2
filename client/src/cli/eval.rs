//! `relfusion eval`: trajectory accuracy (ATE/RPE, figures equal to evo's) and depth accuracy
//! (the paper's percentage of correct depth, §V.A). Each subcommand prints one JSON object on
//! stdout so that scripts and the end-to-end tests can read it.
//!
//! Later additions (whole-run evaluation, `--dataset DIR --run OUT`) become further variants of
//! [`EvalCommand`]; the single-file subcommands stay as they are.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use relfusion_slam::dataset::trajectory::{StampedPose, read_tum_trajectory};
use relfusion_slam::eval::{
    self, AlignMode, DEFAULT_DEPTH_THRESHOLD, DEFAULT_MAX_DT, associate_poses, ate_matched,
    percent_correct_depth, read_depth_map, rpe_matched,
};
use serde_json::json;

#[derive(Debug, clap::Subcommand)]
pub enum EvalCommand {
    /// ATE/RPE of an estimated trajectory against ground truth (both TUM files
    /// `t tx ty tz qx qy qz qw`); same figures as `evo_ape`/`evo_rpe` with `--t_max_diff`.
    Traj(TrajArgs),
    /// Percentage of correct depth (relative error < threshold) of one depth map against ground
    /// truth, counted over the valid ground-truth pixels (missing estimates count as wrong).
    Depth(DepthArgs),
}

#[derive(Debug, clap::Args)]
pub struct TrajArgs {
    /// Ground-truth trajectory (TUM format).
    #[arg(long)]
    pub gt: PathBuf,
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
}

#[derive(Debug, clap::Args)]
pub struct DepthArgs {
    /// Ground-truth depth map: 16-bit PNG (divided by --png-scale) or float32 .npy in metres.
    #[arg(long)]
    pub gt_depth: PathBuf,
    /// Estimated depth map, same size: .npy (float32 metres) or 16-bit PNG.
    #[arg(long)]
    pub est: PathBuf,
    /// Scale applied to the estimate (monocular: trajectory scale × keyframe scale).
    #[arg(long, default_value_t = 1.0)]
    pub scale: f64,
    /// Relative error bound of a correct pixel (the paper: 10 %).
    #[arg(long, default_value_t = DEFAULT_DEPTH_THRESHOLD)]
    pub threshold: f64,
    /// Units per metre of 16-bit PNG depth (TUM: 5000).
    #[arg(long, default_value_t = eval::depth::TUM_PNG_DEPTH_SCALE)]
    pub png_scale: f64,
}

fn parse_align(s: &str) -> Result<AlignMode, String> {
    s.parse().map_err(|e: relfusion_slam::Error| e.to_string())
}

pub fn run(cmd: EvalCommand) -> anyhow::Result<()> {
    let report = match cmd {
        EvalCommand::Traj(args) => traj(&args)?,
        EvalCommand::Depth(args) => depth(&args)?,
    };
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

fn read_traj(path: &Path, what: &str) -> anyhow::Result<Vec<StampedPose>> {
    read_tum_trajectory(path).with_context(|| format!("reading the {what} trajectory"))
}

fn traj(args: &TrajArgs) -> anyhow::Result<serde_json::Value> {
    let gt = read_traj(&args.gt, "ground-truth")?;
    let est = read_traj(&args.est, "estimated")?;
    let matched = associate_poses(&gt, &est, args.max_dt)?;
    let ate = ate_matched(&matched, args.align)?;
    let rpe = rpe_matched(&matched, args.rpe_delta, args.align)?;
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
    }))
}

fn depth(args: &DepthArgs) -> anyhow::Result<serde_json::Value> {
    let gt = read_depth_map(&args.gt_depth, args.png_scale)?;
    let est = read_depth_map(&args.est, args.png_scale)?;
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
