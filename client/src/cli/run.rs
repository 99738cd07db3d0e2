//! `relfusion run`: the whole pipeline locally (no server) on a TUM-layout sequence.
//!
//! Writes `OUT/trajectory.txt` (every tracked frame, camera-to-world, TUM format),
//! `OUT/keyframes.txt` (keyframes after the final pose-graph optimisation) and
//! `OUT/semidense.ply` (coloured semi-dense points of all keyframes at their optimised poses),
//! and, from the dense layer, `OUT/dense.ply` (every densified keyframe back-projected at its
//! optimised pose) and `OUT/keyframes/` (`<timestamp>.depth.npy` per keyframe plus the stage
//! maps `relfusion eval depth` and `relfusion eval ablation` read), and, from the fusion,
//! `OUT/mesh.ply` and `OUT/mesh.glb` (the fused mesh at the optimised poses, with normals and
//! colours) and `OUT/mesh.json` (voxel size and the fusion's counters, read by
//! `relfusion eval mesh`), and `OUT/map/` (the map to localise in later, `docs/map-format.md`);
//! then prints a one-line JSON summary.
//!
//! The run is the pipeline's one driver, `relfusion_slam::pipeline::Engine`, as a service
//! session's is. With `--map MAP --mode localize` the sequence is localised in a saved map
//! instead (what it writes: `super::localize`); with `--mode extend` the pipeline starts from the map's keyframes
//! (`relfusion_slam::pipeline::Pipeline::extending`) and everything above covers both
//! sequences: `keyframes.txt` and `OUT/map/` hold the old keyframes and the new, the mesh is
//! fused from all of them, `trajectory.txt` holds the new frames.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::trajectory::{stamped_se3, write_tum_trajectory};
use relfusion_slam::dense::{DepthPrior, LoadOptions, ModelConfig, OnnxDepthPrior};
use relfusion_slam::eval::fused_mesh::write_mesh_stats;
use relfusion_slam::export::write_points_ply;
use relfusion_slam::geometry::Sim3;
use relfusion_slam::pipeline::{Config, Engine, Event, FrameInput, Pipeline, Start};

use super::recorders::{LogArgs, Logs};
use serde_json::json;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Sequence folder in TUM layout.
    pub dataset: PathBuf,
    /// Output folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// TOML/JSON pipeline config; keys not given keep the paper's defaults.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// ONNX depth model for the depth prior (first keyframe initialisation, dense layer).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Model description for models relfusion does not recognise.
    #[arg(long, requires = "model")]
    pub model_config: Option<PathBuf>,
    /// ONNX Runtime intra-op threads for the depth prior (default: the model's, 2). One on a
    /// machine whose cores are busy: parallel sections spin-wait for descheduled workers.
    #[arg(long, requires = "model", value_parser = clap::value_parser!(u16).range(1..=256))]
    pub prior_threads: Option<u16>,
    /// Process only the first N frames.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Run the back end in step with the frames (reproducible results).
    #[arg(long)]
    pub deterministic: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    #[command(flatten)]
    pub logs: LogArgs,
    /// A saved map (`OUT/map` of an earlier run) to work in instead of starting empty.
    #[arg(long, value_name = "MAP")]
    pub map: Option<PathBuf>,
    /// What to do with `--map`: `localize` gives every frame a pose in the map's frame (or
    /// reports it not localised) and never changes the map; `extend` maps on from where the
    /// camera is found in the map and writes the merged map, mesh and keyframes of both.
    #[arg(long, value_enum, default_value = "localize", requires = "map")]
    pub mode: MapMode,
    /// Spill keyframes older than the newest `backend.resident_keyframes +
    /// backend.held_keyframes` into this folder (created) and read them back when needed, as
    /// a service session does into its store: memory stays bounded, results do not change.
    #[arg(long, value_name = "DIR")]
    pub spill: Option<PathBuf>,
}

/// What a run does with a loaded map.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MapMode {
    Localize,
    Extend,
}

/// Maps the sequence, extends `--map` (`--mode extend`) or localises in it (`--mode localize`).
pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if args.deterministic {
        config.pipeline.deterministic = true;
    }
    // The stage maps are what `relfusion eval depth` / `eval ablation` score.
    config.dense.keep_stages = true;
    let localize = args.map.is_some() && args.mode == MapMode::Localize;
    // A localiser has no dense layer: no model to load.
    let prior = match localize {
        true => None,
        false => load_prior(
            args.model.as_deref(),
            args.model_config.as_deref(),
            args.prior_threads.map(usize::from),
        )?,
    };
    let seq = TumSequence::open(&args.dataset, None)
        .with_context(|| format!("opening {}", args.dataset.display()))?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let logs = Logs::open(&args.logs, &seq.camera)?;
    let started = start_engine(&args, &config, &seq, prior)?;
    match localize {
        true => localize_sequence(&args, &seq, started, logs),
        false => map_sequence(&args, &seq, started, logs),
    }
}

/// A run's engine, started from `--map` if given.
struct Started {
    engine: Engine,
    /// Keyframes of the map it started from.
    map_keyframes: Option<usize>,
    /// Seconds loading that map took.
    map_load_s: Option<f64>,
}

fn start_engine(
    args: &Args,
    config: &Config,
    seq: &TumSequence,
    prior: Option<Box<dyn DepthPrior>>,
) -> anyhow::Result<Started> {
    let t_map_load = Instant::now();
    let map = match &args.map {
        Some(dir) => Some(
            relfusion_slam::map::read_map(dir, Some(&seq.camera))
                .with_context(|| format!("loading the map {}", dir.display()))?,
        ),
        None => None,
    };
    let start = match (&map, args.mode) {
        (None, _) => Start::New,
        (Some(map), MapMode::Extend) => Start::Extend(map),
        (Some(map), MapMode::Localize) => Start::Localize(map),
    };
    let engine = Engine::start(config, &seq.camera, prior, None, start)?;
    if let Some(dir) = &args.spill {
        let store = relfusion_slam::spill::FolderStore::new(dir)?;
        engine.attach_spill(std::sync::Arc::new(store))?;
    }
    Ok(Started {
        engine,
        map_keyframes: map.as_ref().map(|m| m.keyframes.len()),
        map_load_s: map.is_some().then(|| t_map_load.elapsed().as_secs_f64()),
    })
}

/// The frames (at most `--frames`) of a sequence.
fn frame_count(args: &Args, seq: &TumSequence) -> usize {
    args.frames.unwrap_or(seq.len()).min(seq.len())
}

/// `--mode localize`: every frame localised in the map (what it writes: [`super::localize`]).
fn localize_sequence(
    args: &Args,
    seq: &TumSequence,
    started: Started,
    mut logs: Logs,
) -> anyhow::Result<()> {
    let mut log = super::localize::Log::create(&args.out)?;
    let n = frame_count(args, seq);
    // The localised poses are in the map's unit: metres when the map is metric.
    let scale = started.engine.stats().scale;
    let outcome = run_sequence(
        seq,
        n,
        started.engine,
        !args.quiet,
        &mut |i, events, engine| {
            if let Some(i) = i {
                log.frame(engine)?;
                logs.on_run_frame(seq, i, events)?;
            }
            Ok(())
        },
    )?;
    let recorded = logs.finish()?;
    let (trajectory, mut summary) = log.finish(outcome.frames, outcome.wall_s)?;
    write_trajectory(&args.out.join("trajectory.txt"), &trajectory)?;
    if let serde_json::Value::Object(fields) = &mut summary {
        fields.insert("map".into(), json!(args.map));
        fields.insert("map_keyframes".into(), json!(started.map_keyframes));
        fields.insert("map_load_s".into(), json!(started.map_load_s));
        fields.insert("scale".into(), json!(scale));
        fields.insert("out".into(), json!(args.out));
        fields.extend(recorded);
    }
    println!("{summary}");
    Ok(())
}

/// A new map, or `--map` extended: the pipeline's results written, the summary printed.
fn map_sequence(
    args: &Args,
    seq: &TumSequence,
    started: Started,
    mut logs: Logs,
) -> anyhow::Result<()> {
    let n = frame_count(args, seq);
    let map_load_s = started.map_load_s;
    let mut outcome = run_sequence(
        seq,
        n,
        started.engine,
        !args.quiet,
        &mut |i, events, _| match i {
            Some(i) => logs.on_run_frame(seq, i, events),
            None => {
                logs.on_run_events(events);
                Ok(())
            }
        },
    )?;
    let recorded = logs.finish()?;
    let (wall_s, load_s) = (outcome.wall_s, outcome.load_s);
    let Some(pipeline) = outcome.engine.pipeline_mut() else {
        anyhow::bail!("a mapping run without a pipeline");
    };
    let extend = args.map.clone();
    let peak_rss_run_mb = peak_rss_mb();

    let Written {
        mesh_triangles,
        fusion,
        map_save_s,
    } = write_results(&args.out, pipeline)?;
    let stats = pipeline.stats();
    let mut summary = json!({
            "frames": stats.frames,
            "keyframes": stats.keyframes,
            "keyframes_reactivated": stats.keyframes_reactivated,
            "map": extend,
            "map_keyframes": pipeline.map_keyframes(),
            "map_load_s": map_load_s,
            "frames_lost": stats.frames_lost,
            "fragments": stats.fragments,
            "fragments_apart": stats.fragments_apart,
            "wall_s": wall_s,
            "ms_per_frame": 1e3 * wall_s / n.max(1) as f64,
            "ms_per_frame_excluding_image_loading": 1e3 * (wall_s - load_s) / n.max(1) as f64,
            "tracking_ms_per_frame": 1e3 * stats.tracking_s / n.max(1) as f64,
            "mapping_ms_per_frame": 1e3 * stats.mapping_s / n.max(1) as f64,
            "frames_batched": stats.frames_batched,
            "dense_mode": stats.dense_mode,
            "scale": stats.scale,
            "keyframes_densified": stats.keyframes_densified,
            "keyframes_not_densified": stats.keyframes_not_densified,
            "depth_refinements": stats.depth_refinements,
            "keyframes_fused": stats.keyframes_fused,
            "keyframes_not_fused": stats.keyframes_not_fused,
            "mesh_triangles": mesh_triangles,
            "voxel_size": fusion.as_ref().map(|f| f.voxel_size),
            "fusion_blocks": fusion.as_ref().map(|f| serde_json::json!({
                "resident": f.blocks,
                "spilled": f.blocks_spilled,
                "chunk_loads": f.chunk_loads,
            })),
            "map_save_s": map_save_s,
            "keyframe_memory": pipeline.keyframe_memory(),
            "peak_rss_mb": {"run": peak_rss_run_mb, "with_outputs": peak_rss_mb()},
            "out": args.out,
    });
    if let serde_json::Value::Object(fields) = &mut summary {
        fields.extend(recorded);
    }
    println!("{summary}");
    Ok(())
}

/// The process's peak resident memory so far in MiB (Linux `VmHWM`; `None` elsewhere).
fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// What [`write_results`] wrote that the summary reports.
pub(super) struct Written {
    pub mesh_triangles: u64,
    pub fusion: Option<relfusion_slam::fusion::FusionStats>,
    pub map_save_s: f64,
}

/// Writes a finished run into `out`: trajectory, keyframes, point clouds, the dense keyframes,
/// the mesh and its statistics, and the map.
pub(super) fn write_results(
    out: &std::path::Path,
    pipeline: &mut Pipeline,
) -> anyhow::Result<Written> {
    write_trajectory(&out.join("trajectory.txt"), &pipeline.trajectory()?)?;
    write_trajectory(&out.join("keyframes.txt"), &pipeline.keyframe_trajectory())?;
    write_points_ply(&out.join("semidense.ply"), &pipeline.semidense_points()?)?;
    if pipeline.config().dense.enabled {
        write_points_ply(&out.join("dense.ply"), &pipeline.dense_points()?)?;
        // The maps inside are shared (`Arc`): cloning a keyframe copies no pixels.
        let dense: Vec<_> = pipeline
            .dense_keyframes()?
            .into_iter()
            .map(|(kf, pose)| ((*kf).clone(), pose))
            .collect();
        relfusion_slam::dense::store::write_dense_keyframes(&out.join("keyframes"), &dense)?;
    }
    // Written a block at a time: a long run's spilled chunks are read back a slab at a time.
    let mesh_triangles = pipeline.write_mesh(out)?.map_or(0, |c| c.triangles);
    let fusion = pipeline.fusion_stats();
    if let Some(fusion) = &fusion {
        write_mesh_stats(out, fusion)?;
    }
    let t_map = Instant::now();
    let map_dir = out.join("map");
    pipeline
        .write_map(&map_dir)
        .with_context(|| format!("writing {}", map_dir.display()))?;
    let map_save_s = t_map.elapsed().as_secs_f64();
    Ok(Written {
        mesh_triangles,
        fusion,
        map_save_s,
    })
}

/// Sees the events of frame `Some(i)` after it went through the engine (which it may read),
/// and `None`'s: what finishing produced (the last dense keyframes, the mesh at the final
/// poses).
pub type FrameObserver<'a> = dyn FnMut(Option<usize>, &[Event], &Engine) -> anyhow::Result<()> + 'a;

/// A finished run over a sequence.
#[derive(Debug)]
pub struct RunOutcome {
    pub engine: Engine,
    /// Frames pushed.
    pub frames: usize,
    /// Wall time of the whole run, image loading included (seconds).
    pub wall_s: f64,
    /// Of which loading and decoding images (seconds).
    pub load_s: f64,
}

/// Pushes the first `n` frames of `seq` through `engine`, unpaced, then finishes it (final
/// pose-graph optimisation).
pub fn run_sequence(
    seq: &TumSequence,
    n: usize,
    mut engine: Engine,
    progress: bool,
    observe: &mut FrameObserver<'_>,
) -> anyhow::Result<RunOutcome> {
    let sensor_depth = engine
        .pipeline()
        .is_some_and(|p| p.config().dense.two_view.ground_truth_depth);
    if sensor_depth && seq.frames.iter().take(n).all(|f| f.depth.is_none()) {
        anyhow::bail!(
            "dense.two_view.ground_truth_depth needs the sequence's depth images, and {} lists none",
            seq.root.join("depth.txt").display()
        );
    }
    let bar = progress.then(|| progress_bar(n as u64));
    let t0 = Instant::now();
    let mut load_s = 0.0;
    for (i, frame) in seq.frames.iter().enumerate().take(n) {
        let tl = Instant::now();
        let rgb = seq.load_rgb(i)?;
        let depth = if sensor_depth {
            seq.load_depth(i)?
        } else {
            None
        };
        load_s += tl.elapsed().as_secs_f64();
        let events = engine.push(FrameInput {
            frame_id: None,
            timestamp: frame.timestamp,
            rgb,
            depth,
        })?;
        observe(Some(i), &events, &engine)?;
        if let Some(bar) = &bar {
            bar.inc(1);
        }
    }
    // What finishing produced: the last dense keyframes, the mesh at the final poses.
    let (_, events) = engine.finish()?;
    observe(None, &events, &engine)?;
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    Ok(RunOutcome {
        engine,
        frames: n,
        wall_s: t0.elapsed().as_secs_f64(),
        load_s,
    })
}

/// Loads the depth prior of `--model` / `--model-config` / `--prior-threads`, if given.
pub fn load_prior(
    model: Option<&Path>,
    model_config: Option<&Path>,
    intra_threads: Option<usize>,
) -> anyhow::Result<Option<Box<dyn DepthPrior>>> {
    let Some(model) = model else { return Ok(None) };
    let model_config = model_config.map(ModelConfig::from_file).transpose()?;
    let options = LoadOptions {
        intra_threads,
        ..LoadOptions::default()
    };
    let prior = OnnxDepthPrior::load_with(model, model_config, &options)
        .with_context(|| format!("loading {}", model.display()))?;
    Ok(Some(Box::new(prior)))
}

/// TUM trajectory file of Sim(3) poses: the scale is dropped from the rotation (it lives in the
/// map, not in the camera), positions keep the map's scale.
pub fn write_trajectory(path: &Path, poses: &[(f64, Sim3)]) -> anyhow::Result<()> {
    write_tum_trajectory(path, &stamped_se3(poses))
        .with_context(|| format!("writing {}", path.display()))
}

fn progress_bar(len: u64) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} frames {per_sec}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar
}
