//! `relfusion bench accuracy`: the whole development set at once — every TUM-layout sequence
//! given, run N times in the threaded default mode plus once deterministically, judged against
//! its ground truth (issue 22: a change is judged on all sequences, never on one).
//!
//! Per sequence it prints the frames with a pose, the ATE (Sim(3)-aligned RMSE) of all frames
//! and of the keyframes (median and worst of the threaded runs, and the deterministic run),
//! the ATE as a share of the ground-truth path, the scale drift (largest over smallest scale of
//! 60-frame windows, [`relfusion_slam::eval::scale_drift`]), the wall time per frame and the
//! probes of the keyframes' semi-dense depth against the sensor's ([`relfusion_client::depth_probe`]:
//! depth-shape slope 1 s after the start, its range, the depth scale's drift), so that the
//! cause of a bad trajectory stays visible (issue 35); with a metric prior (issue 39) also the
//! ATE after a rigid SE(3) alignment (no scale) and the Sim(3) alignment's scale (1 = metres);
//! for the deterministic run with the dense layer on, the dense columns (issue 39): % of
//! correct depth of the prior as the pipeline aligned it, of the prior fitted to the sensor, of
//! the densified depth, and the fused mesh's accuracy and completeness (what `relfusion eval
//! depth --dataset --run` and `eval mesh` report for a stored run); then one aggregate line over
//! the sequences.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::trajectory::{StampedPose, stamped_se3};
use relfusion_slam::eval::dense_depth::evaluate_dense_depth;
use relfusion_slam::eval::fused_mesh::{MeshSource, evaluate_fused_mesh};
use relfusion_slam::eval::{
    AlignMode, AteResult, DEFAULT_DEPTH_THRESHOLD, DEFAULT_MAX_DT, associate_poses, ate,
    scale_drift,
};
use relfusion_slam::geometry::Sim3;
use relfusion_slam::pipeline::{Config, FrameInput, Pipeline};
use serde::Serialize;

use super::run::{load_prior, write_results};
use relfusion_client::depth_probe::{DepthProbe, ShapeSummary, map_pairs};

/// Poses per window of the scale-drift figure (2 s at 30 Hz: short enough that tracking is
/// accurate within it, long enough for a well-conditioned Sim(3) fit).
const SCALE_WINDOW: usize = 60;

/// Distance bound of an accurate mesh vertex / a covered surface point, in voxels (as `eval
/// mesh`'s default, issue 5).
const MESH_THRESHOLD_VOXELS: f64 = 2.0;

#[derive(Debug, clap::Args)]
pub struct AccuracyArgs {
    /// Sequence folders in TUM layout (real or `relfusion synth`), each with ground truth.
    #[arg(required = true)]
    pub datasets: Vec<PathBuf>,
    /// Threaded runs per sequence (one deterministic run is added).
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// ONNX depth model (first-keyframe initialisation and the dense layer).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Pipeline config (TOML/JSON); default: the built-in defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Map on the mapping thread (`pipeline.mapping_thread`, as live sessions do).
    #[arg(long)]
    pub mapping_thread: bool,
    /// Turn the dense layer off.
    #[arg(long)]
    pub no_dense: bool,
    /// Skip the deterministic run.
    #[arg(long)]
    pub no_deterministic: bool,
    /// Print one JSON document instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// One run of one sequence.
#[derive(Clone, Debug, Serialize)]
pub struct RunFigures {
    pub deterministic: bool,
    pub frames_with_pose: usize,
    pub keyframes: usize,
    /// Old keyframes made current again instead of new ones (`pipeline.reactivation_candidates`).
    pub keyframes_reactivated: usize,
    pub frames_batched: usize,
    pub ate_trajectory_m: Option<f64>,
    pub ate_keyframes_m: Option<f64>,
    pub scale_drift: Option<f64>,
    pub ms_per_frame: f64,
    /// The keyframes' semi-dense depth against the sensor's (issue 35's probes).
    pub depth: ShapeSummary,
    /// `"metric"` when a metric prior anchored the scale, else `"arbitrary"`.
    pub scale: &'static str,
    /// With a metric scale: the trajectory's ATE after a rigid (SE(3)) alignment, no scale.
    pub ate_se3_m: Option<f64>,
    /// The scale of the trajectory's Sim(3) alignment (1 = metric).
    pub sim3_scale: Option<f64>,
    /// The deterministic run's dense layer and mesh against the sensor (dense layer on).
    pub dense: Option<DenseFigures>,
}

/// The dense columns: % of correct depth (the paper's §V.A, mean over keyframes) of the dense
/// layer's stages, and the fused mesh against the surface the sensor saw.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct DenseFigures {
    /// The prior as the pipeline aligned it (eq. 3).
    pub prior_aligned: Option<f64>,
    /// The prior fitted to the sensor's depth (the paper's baseline).
    pub prior_gt_fit: Option<f64>,
    pub densified: Option<f64>,
    /// The densified depth at each keyframe's own best scale instead of the trajectory's (a
    /// probe: the gap is what the keyframes' disagreement with the trajectory's scale costs).
    pub densified_keyframe_scale: Option<f64>,
    /// Fraction of mesh vertices within [`MESH_THRESHOLD_VOXELS`] of the sensor's surface.
    pub mesh_accuracy: Option<f64>,
    /// Fraction of the sensor's surface within that distance of a mesh vertex.
    pub mesh_completeness: Option<f64>,
}

/// Median and worst of a figure over the threaded runs.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Spread {
    pub median: f64,
    pub worst: f64,
}

impl Spread {
    /// Median and the value farthest from 1 (in ratio) of scale factors; `None` when empty.
    fn of_scale(values: impl Iterator<Item = f64>) -> Option<Self> {
        let mut v: Vec<f64> = values.collect();
        v.sort_by(f64::total_cmp);
        let worst = v
            .iter()
            .copied()
            .max_by(|a, b| a.ln().abs().total_cmp(&b.ln().abs()))?;
        Some(Self {
            median: v[v.len() / 2],
            worst,
        })
    }

    /// `None` when no run has the figure; a run without it (no alignment possible) counts as
    /// infinitely bad.
    fn of(values: impl Iterator<Item = Option<f64>>) -> Option<Self> {
        let mut v: Vec<f64> = values.map(|x| x.unwrap_or(f64::INFINITY)).collect();
        if v.is_empty() || v.iter().all(|x| x.is_infinite()) {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(Self {
            median: v[v.len() / 2],
            worst: v[v.len() - 1],
        })
    }
}

/// Everything printed for one sequence.
#[derive(Clone, Debug, Serialize)]
pub struct SequenceFigures {
    pub dataset: PathBuf,
    pub frames: usize,
    pub path_length_m: f64,
    pub frames_with_pose_min: usize,
    pub ate_trajectory_m: Option<Spread>,
    pub ate_keyframes_m: Option<Spread>,
    pub scale_drift: Option<Spread>,
    pub ms_per_frame: Option<Spread>,
    /// Median over the threaded runs of the depth-shape slope 1 s after the start.
    pub shape_after_1s: Option<f64>,
    /// Lowest and highest depth-shape slope of any threaded run from 1 s on.
    pub shape_range: Option<(f64, f64)>,
    /// Largest over smallest keyframe depth scale against the sensor's, median and worst.
    pub depth_scale_ratio: Option<Spread>,
    /// Over the threaded runs with a metric scale: SE(3)-aligned ATE, and the Sim(3)
    /// alignment's scale (median and farthest from 1).
    pub ate_se3_m: Option<Spread>,
    pub sim3_scale: Option<Spread>,
    pub deterministic: Option<RunFigures>,
    pub runs: Vec<RunFigures>,
}

/// The config of a benchmark: the file's (or the defaults), with the dense layer switched off
/// and the mapping thread switched on when asked.
pub(super) fn bench_config(
    path: Option<&Path>,
    no_dense: bool,
    mapping_thread: bool,
) -> anyhow::Result<Config> {
    let mut config = match path {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    config.dense.enabled &= !no_dense;
    config.pipeline.mapping_thread |= mapping_thread;
    Ok(config)
}

pub fn accuracy(args: &AccuracyArgs) -> anyhow::Result<()> {
    let mut config = bench_config(args.config.as_deref(), args.no_dense, args.mapping_thread)?;
    config.pipeline.deterministic = false;
    let mut all = Vec::new();
    for dataset in &args.datasets {
        let figures = sequence(dataset, &config, args)?;
        if !args.json {
            print_row(&figures);
        }
        all.push(figures);
    }
    let aggregate = Aggregate::of(&all);
    if args.json {
        let doc = serde_json::json!({
            "bench": "accuracy",
            "build": if cfg!(debug_assertions) { "debug" } else { "release" },
            "runs": args.runs,
            "model": args.model,
            "mapping": if config.pipeline.mapping_thread { "thread" } else { "in step" },
            "dense": if config.dense.enabled { "on" } else { "off" },
            "sequences": all,
            "aggregate": aggregate,
        });
        println!("{}", serde_json::to_string_pretty(&doc)?);
    } else {
        println!("{}", aggregate.line());
    }
    Ok(())
}

/// Frames decoded into memory and the ground truth of one sequence.
pub(super) struct Loaded {
    pub seq: TumSequence,
    pub frames: Vec<FrameInput>,
    pub gt: Vec<StampedPose>,
}

impl Loaded {
    /// Length of the ground-truth path, metres.
    pub fn path_length(&self) -> f64 {
        self.gt
            .windows(2)
            .map(|w| {
                (w[1].world_from_camera.translation - w[0].world_from_camera.translation).norm()
            })
            .sum()
    }

    /// ATE (Sim(3)-aligned RMSE) of `est` against the ground truth.
    pub fn ate(&self, est: &[StampedPose]) -> Option<f64> {
        self.ate_aligned(est, AlignMode::Sim3).map(|r| r.rmse)
    }

    /// The ATE of `est` after the alignment `mode`, with the alignment.
    pub fn ate_aligned(&self, est: &[StampedPose], mode: AlignMode) -> Option<AteResult> {
        ate(&self.gt, est, mode).ok()
    }

    /// Scale drift of `est` over [`SCALE_WINDOW`]-pose windows.
    pub fn scale_drift(&self, est: &[StampedPose]) -> Option<f64> {
        associate_poses(&self.gt, est, DEFAULT_MAX_DT)
            .ok()
            .and_then(|m| scale_drift(&m, SCALE_WINDOW).ok())
            .and_then(|d| d.drift)
    }
}

/// Opens `dataset` and decodes its first `limit` frames (all by default) into memory, so that
/// a benchmark times the pipeline, not the image decoding.
pub(super) fn load(dataset: &Path, limit: Option<usize>) -> anyhow::Result<Loaded> {
    let seq = TumSequence::open(dataset, None)
        .with_context(|| format!("opening {}", dataset.display()))?;
    let n = limit.unwrap_or(seq.len()).min(seq.len());
    let frames = (0..n)
        .map(|i| {
            Ok(FrameInput {
                frame_id: None,
                timestamp: seq.frames[i].timestamp,
                rgb: seq.load_rgb(i)?,
                depth: None,
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let gt: Vec<StampedPose> = seq
        .frames
        .iter()
        .filter_map(|f| {
            f.world_from_camera.map(|p| StampedPose {
                timestamp: f.timestamp,
                world_from_camera: p,
            })
        })
        .collect();
    Ok(Loaded { seq, frames, gt })
}

fn sequence(
    dataset: &Path,
    config: &Config,
    args: &AccuracyArgs,
) -> anyhow::Result<SequenceFigures> {
    let loaded = load(dataset, None)?;
    anyhow::ensure!(
        loaded.gt.len() >= 2 * SCALE_WINDOW,
        "{} has ground truth for {} frames; the accuracy bench needs at least {}",
        dataset.display(),
        loaded.gt.len(),
        2 * SCALE_WINDOW
    );
    let mut runs = Vec::new();
    for _ in 0..args.runs {
        runs.push(run_once(&loaded, config, args.model.as_deref())?);
    }
    let deterministic = if args.no_deterministic {
        None
    } else {
        let mut config = config.clone();
        config.pipeline.deterministic = true;
        // The stage maps are what the dense columns score.
        config.dense.keep_stages = true;
        Some(run_once(&loaded, &config, args.model.as_deref())?)
    };
    let path_length_m = loaded.path_length();
    Ok(SequenceFigures {
        dataset: dataset.to_path_buf(),
        frames: loaded.frames.len(),
        path_length_m,
        frames_with_pose_min: runs
            .iter()
            .chain(&deterministic)
            .map(|r| r.frames_with_pose)
            .min()
            .unwrap_or(0),
        ate_trajectory_m: Spread::of(runs.iter().map(|r| r.ate_trajectory_m)),
        ate_keyframes_m: Spread::of(runs.iter().map(|r| r.ate_keyframes_m)),
        scale_drift: Spread::of(runs.iter().map(|r| r.scale_drift)),
        ms_per_frame: Spread::of(runs.iter().map(|r| Some(r.ms_per_frame))),
        shape_after_1s: median(runs.iter().filter_map(|r| r.depth.slope_after_1s)),
        shape_range: runs
            .iter()
            .filter_map(|r| r.depth.slope_range)
            .reduce(|(a, b), (c, d)| (a.min(c), b.max(d))),
        depth_scale_ratio: Spread::of(runs.iter().map(|r| r.depth.scale_ratio)),
        ate_se3_m: Spread::of(runs.iter().map(|r| r.ate_se3_m)),
        sim3_scale: Spread::of_scale(runs.iter().filter_map(|r| r.sim3_scale)),
        deterministic,
        runs,
    })
}

fn run_once(loaded: &Loaded, config: &Config, model: Option<&Path>) -> anyhow::Result<RunFigures> {
    let prior = load_prior(model, None, None)?;
    let mut pipeline = Pipeline::new(config.clone(), loaded.seq.camera, prior)?;
    let t0 = Instant::now();
    for frame in &loaded.frames {
        pipeline.push(frame.clone())?;
    }
    let frames_s = t0.elapsed().as_secs_f64();
    pipeline.finish()?;
    let dense = (config.pipeline.deterministic && config.dense.enabled)
        .then(|| dense_figures(&loaded.seq.root, &mut pipeline))
        .transpose()?;
    let trajectory = pipeline.trajectory()?;
    let keyframes = pipeline.keyframe_trajectory();
    let ate_of = |poses: &[(f64, Sim3)]| loaded.ate(&stamped_se3(poses));
    let drift = loaded.scale_drift(&stamped_se3(&trajectory));
    let stats = pipeline.stats();
    let metric = stats.scale == "metric";
    let sim3 = loaded.ate_aligned(&stamped_se3(&trajectory), AlignMode::Sim3);
    let se3 = metric
        .then(|| loaded.ate_aligned(&stamped_se3(&trajectory), AlignMode::Se3))
        .flatten();
    let mut probe = DepthProbe::default();
    for (_, frame, depth) in pipeline.keyframe_depths()? {
        if let Some(sensor) = loaded.seq.load_depth(frame.id as usize)? {
            probe.add(frame.timestamp, &map_pairs(&depth, &sensor));
        }
    }
    let start = loaded.frames.first().map_or(0.0, |f| f.timestamp);
    Ok(RunFigures {
        deterministic: config.pipeline.deterministic,
        frames_with_pose: trajectory.len(),
        keyframes: keyframes.len(),
        keyframes_reactivated: stats.keyframes_reactivated,
        frames_batched: stats.frames_batched,
        ate_trajectory_m: ate_of(&trajectory),
        ate_keyframes_m: ate_of(&keyframes),
        scale_drift: drift,
        ms_per_frame: 1e3 * frames_s / loaded.frames.len().max(1) as f64,
        depth: probe.summary(start),
        scale: stats.scale,
        ate_se3_m: se3.map(|r| r.rmse),
        sim3_scale: metric.then(|| sim3.map(|r| r.scale)).flatten(),
        dense,
    })
}

/// Writes a finished run into a scratch folder as `relfusion run` does and scores it as `eval
/// depth --dataset --run` and `eval mesh` do; a stage or mesh that cannot be scored is `None`
/// (with a warning), never an error that loses the other figures.
fn dense_figures(dataset: &Path, pipeline: &mut Pipeline) -> anyhow::Result<DenseFigures> {
    let out = std::env::temp_dir().join(format!(
        "relfusion-bench-accuracy-{}-{}",
        std::process::id(),
        dataset
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into())
    ));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    write_results(&out, pipeline)?;
    let depth = evaluate_dense_depth(dataset, &out, DEFAULT_DEPTH_THRESHOLD)
        .inspect_err(|e| tracing::warn!("dense depth of {}: {e}", dataset.display()))
        .ok();
    let fusion = &pipeline.config().fusion;
    let mesh = evaluate_fused_mesh(
        dataset,
        &out,
        fusion,
        MeshSource::RunMesh,
        MESH_THRESHOLD_VOXELS,
    )
    .inspect_err(|e| tracing::warn!("mesh of {}: {e}", dataset.display()))
    .ok();
    if let Err(e) = std::fs::remove_dir_all(&out) {
        tracing::warn!("removing {}: {e}", out.display());
    }
    let stage = |f: fn(&relfusion_slam::eval::dense_depth::StageScores) -> Option<f64>| {
        depth.as_ref().and_then(|d| f(&d.stages))
    };
    Ok(DenseFigures {
        prior_aligned: stage(|s| s.prior_aligned.map(|x| x.percent_mean)),
        prior_gt_fit: stage(|s| s.prior_gt_fit.map(|x| x.percent_mean)),
        densified: stage(|s| s.dense.map(|x| x.percent_mean)),
        densified_keyframe_scale: stage(|s| s.dense_keyframe_scale.map(|x| x.percent_mean)),
        mesh_accuracy: mesh.as_ref().map(|m| m.ours.accuracy),
        mesh_completeness: mesh.as_ref().map(|m| m.ours.completeness),
    })
}

/// The median of `values` (the upper one of an even count); `None` when empty.
pub(super) fn median(values: impl Iterator<Item = f64>) -> Option<f64> {
    let mut v: Vec<f64> = values.collect();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}

fn fmt_m(v: Option<f64>) -> String {
    v.map_or_else(|| "-".into(), |x| format!("{x:.4}"))
}

fn fmt_spread(s: Option<Spread>, digits: usize) -> String {
    s.map_or_else(
        || "-".into(),
        |s| format!("{:.d$}/{:.d$}", s.median, s.worst, d = digits),
    )
}

fn print_row(f: &SequenceFigures) {
    let name = f.dataset.file_name().map_or_else(
        || f.dataset.display().to_string(),
        |n| n.to_string_lossy().into(),
    );
    let det = f.deterministic.as_ref();
    println!(
        "{name}: poses {}/{} | ATE traj median/worst {} m (det {}) | keyframes {} m (det {}) \
         | kf ATE {} % of {:.2} m path | scale drift {} (det {}) | {} ms/frame \
         | depth shape@1s {} range {} scale× {}",
        f.frames_with_pose_min,
        f.frames,
        fmt_spread(f.ate_trajectory_m, 4),
        fmt_m(det.and_then(|d| d.ate_trajectory_m)),
        fmt_spread(f.ate_keyframes_m, 4),
        fmt_m(det.and_then(|d| d.ate_keyframes_m)),
        f.ate_keyframes_m.map_or_else(
            || "-".into(),
            |s| format!("{:.2}", 100.0 * s.median / f.path_length_m)
        ),
        f.path_length_m,
        fmt_spread(f.scale_drift, 2),
        det.and_then(|d| d.scale_drift)
            .map_or_else(|| "-".into(), |x| format!("{x:.2}")),
        fmt_spread(f.ms_per_frame, 1),
        f.shape_after_1s
            .map_or_else(|| "-".into(), |x| format!("{x:.2}")),
        f.shape_range
            .map_or_else(|| "-".into(), |(a, b)| format!("{a:.2}–{b:.2}")),
        fmt_spread(f.depth_scale_ratio, 2),
    );
    let det_metric = det.is_some_and(|d| d.ate_se3_m.is_some() || d.sim3_scale.is_some());
    if f.ate_se3_m.is_some() || f.sim3_scale.is_some() || det_metric {
        println!(
            "  metric: ATE traj SE(3) median/worst {} m (det {}) | Sim(3) scale median/farthest {} (det {})",
            fmt_spread(f.ate_se3_m, 4),
            fmt_m(det.and_then(|d| d.ate_se3_m)),
            fmt_spread(f.sim3_scale, 3),
            fmt_m(det.and_then(|d| d.sim3_scale)),
        );
    }
    if let Some(d) = det.and_then(|d| d.dense) {
        let pct = |v: Option<f64>| v.map_or_else(|| "-".into(), |x| format!("{x:.1}"));
        let gain = d
            .densified
            .zip(d.prior_gt_fit)
            .map(|(a, b)| format!("{:+.1}", a - b));
        println!(
            "  dense (det): % correct prior aligned {} | prior GT-fitted {} | densified {} ({} vs \
             GT-fitted; {} at each keyframe's own scale) | mesh accuracy {} completeness {}",
            pct(d.prior_aligned),
            pct(d.prior_gt_fit),
            pct(d.densified),
            gain.unwrap_or_else(|| "-".into()),
            pct(d.densified_keyframe_scale),
            d.mesh_accuracy
                .map_or_else(|| "-".into(), |x| format!("{x:.3}")),
            d.mesh_completeness
                .map_or_else(|| "-".into(), |x| format!("{x:.3}")),
        );
    }
}

/// One line over all sequences: the mean of the per-sequence medians (each sequence weighs the
/// same), the worst single run, and whether every frame of every run got a pose.
#[derive(Clone, Debug, Serialize)]
pub struct Aggregate {
    pub sequences: usize,
    pub every_frame_posed: bool,
    pub ate_trajectory_mean_of_medians_m: Option<f64>,
    pub ate_keyframes_mean_of_medians_m: Option<f64>,
    pub ate_keyframes_mean_percent_of_path: Option<f64>,
    pub ate_trajectory_worst_m: Option<f64>,
    pub scale_drift_worst: Option<f64>,
    pub ms_per_frame_mean: Option<f64>,
}

impl Aggregate {
    fn of(all: &[SequenceFigures]) -> Self {
        let mean = |v: Vec<Option<f64>>| -> Option<f64> {
            let v: Option<Vec<f64>> = v.into_iter().collect();
            v.filter(|v| !v.is_empty())
                .map(|v| v.iter().sum::<f64>() / v.len() as f64)
        };
        let worst = |v: Vec<Option<f64>>| -> Option<f64> {
            let v: Option<Vec<f64>> = v.into_iter().collect();
            v.and_then(|v| v.into_iter().reduce(f64::max))
        };
        Self {
            sequences: all.len(),
            every_frame_posed: all.iter().all(|f| f.frames_with_pose_min == f.frames),
            ate_trajectory_mean_of_medians_m: mean(
                all.iter()
                    .map(|f| f.ate_trajectory_m.map(|s| s.median))
                    .collect(),
            ),
            ate_keyframes_mean_of_medians_m: mean(
                all.iter()
                    .map(|f| f.ate_keyframes_m.map(|s| s.median))
                    .collect(),
            ),
            ate_keyframes_mean_percent_of_path: mean(
                all.iter()
                    .map(|f| {
                        f.ate_keyframes_m
                            .map(|s| 100.0 * s.median / f.path_length_m.max(1e-9))
                    })
                    .collect(),
            ),
            ate_trajectory_worst_m: worst(
                all.iter()
                    .map(|f| f.ate_trajectory_m.map(|s| s.worst))
                    .collect(),
            ),
            scale_drift_worst: worst(all.iter().map(|f| f.scale_drift.map(|s| s.worst)).collect()),
            ms_per_frame_mean: mean(
                all.iter()
                    .map(|f| f.ms_per_frame.map(|s| s.median))
                    .collect(),
            ),
        }
    }

    fn line(&self) -> String {
        format!(
            "aggregate over {} sequences: every frame posed {} | ATE traj mean of medians {} m, \
             worst {} m | keyframes mean of medians {} m ({} % of path) | scale drift worst {} \
             | {} ms/frame",
            self.sequences,
            self.every_frame_posed,
            fmt_m(self.ate_trajectory_mean_of_medians_m),
            fmt_m(self.ate_trajectory_worst_m),
            fmt_m(self.ate_keyframes_mean_of_medians_m),
            self.ate_keyframes_mean_percent_of_path
                .map_or_else(|| "-".into(), |x| format!("{x:.2}")),
            self.scale_drift_worst
                .map_or_else(|| "-".into(), |x| format!("{x:.2}")),
            self.ms_per_frame_mean
                .map_or_else(|| "-".into(), |x| format!("{x:.1}")),
        )
    }
}
