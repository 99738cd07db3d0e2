//! `relfusion stream DATASET --server URL`: a TUM-layout sequence streamed live to relfusiond,
//! at its own timestamps by default (`--fps F` at a fixed rate, `--fast --wait` as fast as the
//! server takes every frame).
//!
//! stdout is JSON lines, for scripts: `{"session": ID}` first, then one line per pose as it
//! arrives (`frame_id`, `timestamp`, `t`, `q` (x y z w), `s`, `state`), then
//! `{"summary": {...}}`, with the final trajectory's ATE when the dataset has ground truth.
//! On a terminal a progress bar runs on stderr.

use std::io::IsTerminal as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use relfusion_sdk::dataset_stream::{StreamEvent, StreamOptions, stream_dataset};
use relfusion_sdk::{Client, FramePolicy, Pace, Transport};
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::trajectory::parse_tum_trajectory;
use relfusion_slam::eval::{AlignMode, ate};
use serde_json::{Value, json};

use super::connect::{ConnectArgs, print_line, progress_bar, runtime};
use super::recorders::{LogArgs, Logs};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Sequence folder in TUM layout (rgb.txt, rgb/, optional groundtruth.txt, calibration.txt).
    pub dataset: PathBuf,
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Stream over Zenoh through this endpoint (e.g. tcp/127.0.0.1:7447) instead of the
    /// WebSocket; --server is still used for the final figures.
    #[arg(long)]
    pub zenoh: Option<String>,
    /// Send frames at F frames/s (default: at the sequence's own timestamps, as the camera
    /// delivered them).
    #[arg(long, conflicts_with = "fast")]
    pub fps: Option<f64>,
    /// Send frames as fast as the server takes them; needs --wait (a live camera's policy
    /// would drop most of them).
    #[arg(long, requires = "wait")]
    pub fast: bool,
    /// Pipeline config overrides (JSON or TOML file, e.g. {"pipeline":{"deterministic":true}}).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Every frame is processed: the server stops reading while the session's queue is full
    /// (default: a live camera's policy, the oldest queued frame is dropped).
    #[arg(long)]
    pub wait: bool,
    /// Depth model on the server: "none", "default" or a configured name.
    #[arg(long)]
    pub model: Option<String>,
    /// Stream only the first N frames.
    #[arg(long)]
    pub frames: Option<usize>,
    #[command(flatten)]
    pub logs: LogArgs,
    /// Start in this saved map (an id from `relfusion maps list`) instead of an empty one:
    /// every pose is in the map's frame, frames outside it are `lost` (`--map-mode`).
    #[arg(long, value_name = "MAP_ID")]
    pub map: Option<String>,
    /// What to do with `--map`: `localize` (the map is left as it is) or `extend` (map on
    /// from where the camera is found; the session's map holds both).
    #[arg(long, value_enum, default_value = "localize", requires = "map")]
    pub map_mode: super::run::MapMode,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let client = args.connect.client()?;
    let config = match &args.config {
        Some(path) => load_config_json(path)?,
        None => Value::Null,
    };
    let opts = stream_options(&args, config);
    let seq = TumSequence::open(&args.dataset, None)
        .with_context(|| format!("opening {}", args.dataset.display()))?;
    let n = args.frames.unwrap_or(seq.len()).min(seq.len());
    let bar = std::io::stderr()
        .is_terminal()
        .then(|| progress_bar(n as u64, "frames"));
    let print = |value: Value| match &bar {
        Some(bar) => bar.suspend(|| print_line(&value)),
        None => print_line(&value),
    };
    let mut logs = Logs::open(&args.logs, &seq.camera)?;
    let frames: Vec<(f64, PathBuf)> = seq
        .frames
        .iter()
        .map(|f| (f.timestamp, f.rgb.clone()))
        .collect();
    runtime()?.block_on(async {
        let summary = stream_dataset(&client, &args.dataset, &opts, |event| {
            logs.on_stream_event(&event, &frames);
            match event {
                StreamEvent::Session { id } => print(json!({ "session": id })),
                StreamEvent::Sent { .. } => {
                    if let Some(bar) = &bar {
                        bar.inc(1);
                    }
                }
                StreamEvent::Pose(pose) => print(json!(pose)),
                StreamEvent::ServerError { code, message } => {
                    print(json!({ "server_error": { "code": code, "message": message } }));
                }
                StreamEvent::Keyframe { .. } | StreamEvent::Mesh { .. } => {}
            }
        })
        .await?;
        if let Some(bar) = &bar {
            bar.finish_and_clear();
        }
        let mut out = json!({
            "frames_sent": summary.frames_sent,
            "poses_received": summary.poses_received,
            "keyframe_updates": summary.keyframe_updates,
            "frames_dropped": summary.frames_dropped,
            "server_errors": summary.server_errors.len(),
            "wall_s": summary.wall_s,
        });
        if let Some(info) = &summary.info {
            out["state"] = json!(info.state);
            out["frames_processed"] = json!(info.frames_processed);
            out["keyframes"] = json!(info.keyframes);
            out["scale"] = json!(info.scale);
            if let Some(map) = &info.map {
                out["map"] = json!(map);
            }
        }
        if let Some(ate) = final_ate(&client, &summary.session_id, &seq).await {
            out["ate"] = ate;
        }
        let recorded = std::mem::take(&mut logs).finish()?;
        if let Value::Object(fields) = &mut out {
            fields.extend(recorded);
        }
        print(json!({ "summary": out }));
        if let Some(first) = summary.server_errors.first() {
            anyhow::bail!(
                "the server rejected {} message(s); the first: {first}",
                summary.server_errors.len()
            );
        }
        anyhow::Ok(())
    })
}

/// The SDK's options for the command's flags.
fn stream_options(args: &Args, config: Value) -> StreamOptions {
    StreamOptions {
        pace: match (args.fps, args.fast) {
            (Some(fps), _) => Pace::Fps(fps),
            (None, true) => Pace::Fast,
            (None, false) => Pace::Timestamps,
        },
        policy: if args.wait {
            FramePolicy::Wait
        } else {
            FramePolicy::DropOldest
        },
        config,
        model: args.model.clone(),
        transport: match &args.zenoh {
            Some(endpoint) => Transport::Zenoh {
                endpoint: endpoint.clone(),
            },
            None => Transport::Http,
        },
        max_frames: args.frames,
        camera: None,
        map: args.map.clone().map(|id| relfusion_sdk::MapStart {
            id,
            mode: match args.map_mode {
                super::run::MapMode::Localize => relfusion_sdk::MapMode::Localize,
                super::run::MapMode::Extend => relfusion_sdk::MapMode::Extend,
            },
        }),
    }
}

/// ATE (Sim(3)-aligned) of the session's final trajectory against the dataset's ground truth;
/// `None` without ground truth or when the trajectory cannot be fetched.
async fn final_ate(client: &Client, id: &str, seq: &TumSequence) -> Option<Value> {
    let gt = seq.groundtruth_poses();
    if gt.is_empty() {
        return None;
    }
    let text = client.trajectory(id).await.ok()?;
    let est = parse_tum_trajectory(&text, "server trajectory").ok()?;
    let result = ate(&gt, &est, AlignMode::Sim3).ok()?;
    Some(json!({ "rmse": result.rmse, "matched": result.matched, "align": "sim3" }))
}

/// A partial pipeline config as a JSON object, from a `.json` or `.toml` file.
pub fn load_config_json(path: &Path) -> anyhow::Result<Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let value: Value = if path.extension().is_some_and(|e| e == "toml") {
        let table: toml::Table =
            toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        serde_json::to_value(table)?
    } else {
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
    };
    anyhow::ensure!(
        value.is_object(),
        "{}: the config must be an object",
        path.display()
    );
    Ok(value)
}
