//! `relfusion bench long --server URL --minutes M`: a session of minutes to hours against a
//! running relfusiond, measured as it goes (issue 37).
//!
//! A synthetic hand-held loop (`Motion::Loop`: back over its start every 30 s, so every lap
//! closes loops with keyframes made a lap before) is rendered here, in memory, and streamed
//! live at `--fps` to `--sessions` sessions at once (the live drop-oldest policy, as a camera
//! would). The loop and its hand tremor repeat exactly every 30 s, so one lap is rendered once
//! and sent again; no file is read or written.
//!
//! stdout is JSON lines: one per `--report-s` interval (server RSS and heap in use from
//! `/metrics`, per session keyframes resident/spilled, bytes held and spilled, TSDF blocks,
//! fusion inputs spilled, far pose-graph edges, frames dropped, frame→pose p50/p99 in the
//! interval), then a summary with each session's ATE (Sim(3)-aligned) against the rendered
//! truth, as a percentage of the path, and its mesh size.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use relfusion_proto::v1::server_message;
use relfusion_sdk::message::{end_of_stream, frame_message};
use relfusion_sdk::{Client, CreateSession, FramePolicy};
use relfusion_slam::dataset::synth::nuisance::encode;
use relfusion_slam::dataset::synth::{Scene, Trajectory, path_length, render_frame_with};
use relfusion_slam::dataset::trajectory::{StampedPose, parse_tum_trajectory};
use relfusion_slam::dataset::{Motion, SynthConfig};
use relfusion_slam::eval::{AlignMode, ate};
use relfusion_slam::geometry::SE3;
use serde_json::{Value, json};

use super::connect::{ConnectArgs, print_line, runtime};
use relfusion_client::latency::percentile;

/// Seconds after which `Motion::Loop` repeats exactly (path and tremor).
const LOOP_PERIOD_S: f64 = 30.0;
/// How long a session may take to finish after its last frame (final optimisation, meshing):
/// 10 minutes, and 20 s more per minute streamed past 30, since at the defaults the final
/// pass grows with the keyframes (an hour's took 15 minutes; docs/tuning.md "An hour at the
/// defaults").
fn finish_timeout(minutes: f64) -> Duration {
    Duration::from_secs_f64(600.0 + 20.0 * (minutes - 30.0).max(0.0))
}

#[derive(Debug, clap::Args)]
pub struct LongArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Minutes of video per session.
    #[arg(long, default_value_t = 60.0)]
    pub minutes: f64,
    /// Camera rate.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Sessions streaming at once (each the same path).
    #[arg(long, default_value_t = 1)]
    pub sessions: usize,
    /// Seed of the room and the path.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Depth model on the server ("none" by default: the dense layer runs without a prior).
    #[arg(long, default_value = "none")]
    pub model: String,
    /// Pipeline config overrides (JSON or TOML file).
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
    /// Seconds between report lines.
    #[arg(long, default_value_t = 60.0)]
    pub report_s: f64,
    /// JPEG quality of the frames sent.
    #[arg(long, default_value_t = 90)]
    pub jpeg: u8,
}

/// One lap of the loop, encoded, with the truth of every frame of the run.
struct Lap {
    frames: Vec<Vec<u8>>,
    truth: Vec<SE3>,
}

impl Lap {
    /// Frame `i`'s image (the lap repeats).
    fn image(&self, i: usize) -> &[u8] {
        &self.frames[i % self.frames.len()]
    }
}

/// Renders one lap (or the whole run, if shorter, or if `fps` does not divide the period).
fn render_lap(args: &LongArgs, total: usize) -> anyhow::Result<Lap> {
    let config = SynthConfig {
        width: args.width,
        height: args.height,
        seed: args.seed,
        motion: Motion::Loop,
        fps: args.fps,
        ..SynthConfig::default()
    };
    config.validate()?;
    let camera = config.camera()?;
    let scene = Scene::generate(args.seed);
    let trajectory = Trajectory::new(Motion::Loop, args.seed);
    let per_lap = LOOP_PERIOD_S * args.fps;
    let lap = if (per_lap - per_lap.round()).abs() < 1e-9 {
        (per_lap.round() as usize).min(total)
    } else {
        total
    };
    let truth: Vec<SE3> = (0..total)
        .map(|i| trajectory.world_from_camera(i as f64 / args.fps))
        .collect();
    let slots: Vec<Mutex<Vec<u8>>> = (0..lap).map(|_| Mutex::new(Vec::new())).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let failed: Mutex<Option<anyhow::Error>> = Mutex::new(None);
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| {
                loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    if i >= lap {
                        break;
                    }
                    let (rgb, _) = render_frame_with(&scene, &camera, &truth[i], 1);
                    match encode(&rgb, args.jpeg) {
                        Ok(bytes) => *slots[i].lock().expect("slot") = bytes,
                        Err(e) => {
                            failed.lock().expect("error").get_or_insert(e.into());
                            next.store(lap, std::sync::atomic::Ordering::Relaxed);
                        }
                    }
                }
            });
        }
    });
    if let Some(e) = failed.into_inner().expect("error") {
        return Err(e);
    }
    Ok(Lap {
        frames: slots
            .into_iter()
            .map(|m| m.into_inner().expect("slot"))
            .collect(),
        truth,
    })
}

/// What the receiver of one session collected.
#[derive(Default)]
struct Received {
    /// Frame→pose latencies (ms) since the last report.
    interval_ms: Vec<f64>,
    all_ms: Vec<f64>,
    poses: u64,
    error: Option<String>,
}

/// One streaming session.
struct Running {
    id: String,
    received: Arc<Mutex<Received>>,
    sender: tokio::task::JoinHandle<u64>,
    receiver: tokio::task::JoinHandle<()>,
    /// The WebSocket's reader and writer (aborted when dropped).
    _tasks: relfusion_sdk::link::TaskGuard,
}

pub fn long(args: &LongArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.fps.is_finite() && args.fps > 0.0 && args.minutes > 0.0 && args.sessions > 0,
        "--fps, --minutes and --sessions must be positive"
    );
    let total = (args.minutes * 60.0 * args.fps).round() as usize;
    let t = Instant::now();
    let lap = Arc::new(render_lap(args, total)?);
    print_line(&json!({
        "rendered": lap.frames.len(),
        "frames": total,
        "render_s": t.elapsed().as_secs_f64(),
        "mean_jpeg_kb": lap.frames.iter().map(Vec::len).sum::<usize>() as f64
            / lap.frames.len().max(1) as f64 / 1024.0,
    }));
    let client = args.connect.client()?;
    let config = match &args.config {
        Some(path) => super::stream::load_config_json(path)?,
        None => Value::Null,
    };
    let camera = SynthConfig {
        width: args.width,
        height: args.height,
        ..SynthConfig::default()
    }
    .camera()?;
    let req = CreateSession {
        camera: Some(relfusion_sdk::api::camera_json(&camera)),
        config,
        model: Some(args.model.clone()),
        policy: FramePolicy::DropOldest,
        map: None,
        ros2: None,
    };
    runtime()?.block_on(async {
        let mut sessions = Vec::new();
        for _ in 0..args.sessions {
            sessions.push(start(&client, &req, lap.clone(), total, args.fps).await?);
        }
        let start_at = Instant::now();
        let mut report = 1;
        while !sessions.iter().all(|s| s.sender.is_finished()) {
            let due = start_at + Duration::from_secs_f64(report as f64 * args.report_s);
            tokio::time::sleep_until(due.into()).await;
            print_line(&report_line(&client, &sessions, report as f64 * args.report_s).await);
            report += 1;
        }
        let mut summaries = Vec::new();
        for s in sessions {
            summaries.push(finish(&client, s, &lap, args.fps, finish_timeout(args.minutes)).await);
        }
        print_line(&json!({ "summary": {
            "minutes": args.minutes,
            "fps": args.fps,
            "width": args.width,
            "height": args.height,
            "rss_mb": server_rss_mb(&client).await,
            "sessions": summaries,
        }}));
        anyhow::Ok(())
    })
}

/// Creates a session and starts its sender (paced at `fps`) and receiver.
async fn start(
    client: &Client,
    req: &CreateSession,
    lap: Arc<Lap>,
    total: usize,
    fps: f64,
) -> anyhow::Result<Running> {
    let info = client
        .create_session(req)
        .await
        .context("creating a session")?;
    let mut link = relfusion_sdk::ws::connect(client, &info.id).await?;
    let sent_at: Arc<Mutex<Vec<Option<Instant>>>> = Arc::new(Mutex::new(vec![None; total]));
    let tx = link.frames.clone();
    drop(std::mem::replace(
        &mut link.frames,
        tokio::sync::mpsc::channel(1).0,
    ));
    let sent_w = sent_at.clone();
    let sender = tokio::spawn(async move {
        let start = tokio::time::Instant::now();
        let mut sent = 0;
        for i in 0..total {
            tokio::time::sleep_until(start + Duration::from_secs_f64(i as f64 / fps)).await;
            if let Ok(mut s) = sent_w.lock() {
                s[i] = Some(Instant::now());
            }
            let msg = frame_message(i as u64, i as f64 / fps, lap.image(i).to_vec());
            if tx.send(msg).await.is_err() {
                break;
            }
            sent += 1;
        }
        let _ = tx.send(end_of_stream()).await;
        sent
    });
    let received = Arc::new(Mutex::new(Received::default()));
    let received_w = received.clone();
    let tasks = std::mem::take(&mut link.tasks);
    let mut updates = link.updates;
    let receiver = tokio::spawn(async move {
        while let Some(update) = updates.recv().await {
            let mut r = received_w.lock().expect("received");
            match update {
                Ok(msg) => {
                    if let Some(server_message::Message::Pose(p)) = msg.message {
                        r.poses += 1;
                        let sent = sent_at
                            .lock()
                            .ok()
                            .and_then(|s| s.get(p.frame_id as usize).copied().flatten());
                        if let Some(t) = sent {
                            let ms = 1e3 * t.elapsed().as_secs_f64();
                            r.interval_ms.push(ms);
                            r.all_ms.push(ms);
                        }
                    }
                }
                Err(e) => {
                    r.error = Some(e.report());
                    break;
                }
            }
        }
    });
    Ok(Running {
        id: info.id,
        received,
        sender,
        receiver,
        _tasks: tasks,
    })
}

/// A gauge of the server's `/metrics` in MiB: `resident_memory_bytes` (RSS),
/// `heap_in_use_bytes` (what the program holds of the heap) or `heap_free_bytes`.
async fn server_gauge_mb(client: &Client, name: &str) -> Option<f64> {
    let text = client.metrics().await.ok()?;
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' '))
        .and_then(|v| v.trim().parse::<f64>().ok())
        .map(|b| b / (1024.0 * 1024.0))
}

/// The server's resident memory, MiB.
async fn server_rss_mb(client: &Client) -> Option<f64> {
    server_gauge_mb(client, "resident_memory_bytes").await
}

/// One interval's line: server RSS and each session's figures.
async fn report_line(client: &Client, sessions: &[Running], at_s: f64) -> Value {
    let mut per = Vec::new();
    for s in sessions {
        let (p50, p99, poses) = {
            let mut r = s.received.lock().expect("received");
            let mut ms = std::mem::take(&mut r.interval_ms);
            ms.sort_by(f64::total_cmp);
            (percentile(&ms, 0.5), percentile(&ms, 0.99), r.poses)
        };
        let info = client.session(&s.id).await.ok();
        per.push(json!({
            "poses": poses,
            "p50_ms": p50,
            "p99_ms": p99,
            "state": info.as_ref().map(|i| i.state),
            "keyframes": info.as_ref().map(|i| i.keyframes),
            "frames_dropped": info.as_ref().map(|i| i.frames_dropped),
            "memory": info.as_ref().and_then(|i| i.memory),
            "notice": info.as_ref().and_then(|i| i.notice.clone()),
        }));
    }
    json!({
        "minute": at_s / 60.0,
        "rss_mb": server_rss_mb(client).await,
        "heap_mb": server_gauge_mb(client, "heap_in_use_bytes").await,
        "heap_free_mb": server_gauge_mb(client, "heap_free_bytes").await,
        "sessions": per,
    })
}

/// Waits for a session to finish; its ATE against the rendered truth and its mesh.
async fn finish(client: &Client, s: Running, lap: &Lap, fps: f64, wait: Duration) -> Value {
    let (sent, sender_error) = match s.sender.await {
        Ok(sent) => (sent, None),
        Err(e) => (0, Some(e.to_string())),
    };
    let info = match tokio::time::timeout(
        wait,
        client.wait_finished(&s.id, Duration::from_secs(2), |_| {}),
    )
    .await
    {
        Ok(info) => info.map_err(|e| e.report()),
        Err(_) => Err("the session did not finish in time".to_string()),
    };
    let _ = tokio::time::timeout(Duration::from_secs(30), s.receiver).await;
    let mut out = {
        let r = s.received.lock().expect("received");
        let mut all = r.all_ms.clone();
        all.sort_by(f64::total_cmp);
        json!({
            "id": s.id,
            "frames_sent": sent,
            "poses": r.poses,
            "p50_ms": percentile(&all, 0.5),
            "p99_ms": percentile(&all, 0.99),
            "stream_error": r.error.clone().or(sender_error),
        })
    };
    match info {
        Ok(info) => {
            out["state"] = json!(info.state);
            out["keyframes"] = json!(info.keyframes);
            out["frames_processed"] = json!(info.frames_processed);
            out["frames_dropped"] = json!(info.frames_dropped);
            out["mesh_triangles"] = json!(info.mesh_triangles);
            out["notice"] = json!(info.notice);
        }
        Err(e) => out["error"] = json!(e),
    }
    if let Ok(text) = client.trajectory(&s.id).await
        && let Ok(est) = parse_tum_trajectory(&text, "server trajectory")
    {
        let gt: Vec<StampedPose> = lap
            .truth
            .iter()
            .enumerate()
            .map(|(i, p)| StampedPose {
                timestamp: i as f64 / fps,
                world_from_camera: *p,
            })
            .collect();
        // The path the estimate covers (a session that ended early covers less than was sent).
        let last = est
            .iter()
            .map(|p| (p.timestamp * fps).round() as usize)
            .max()
            .unwrap_or(0);
        let path = path_length(&lap.truth[..(last + 1).min(lap.truth.len())]);
        if let Ok(result) = ate(&gt, &est, AlignMode::Sim3) {
            out["ate_m"] = json!(result.rmse);
            out["ate_matched"] = json!(result.matched);
            out["path_m"] = json!(path);
            out["ate_percent_of_path"] = json!(100.0 * result.rmse / path.max(1e-9));
        }
    }
    out
}
