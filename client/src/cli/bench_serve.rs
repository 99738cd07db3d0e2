//! `relfusion bench serve --server URL`: what a running relfusiond sustains, as one JSON object.
//!
//! 1. **Ingest over HTTP**: one drop-oldest session, `POST /v1/sessions/{id}/frames` as fast as
//!    `--concurrency` requests in flight allow; figure: accepted (202) frames per second. The
//!    server decodes and validates every frame before answering, so this is the ingest path's
//!    throughput, not the pipeline's (the pipeline drops what it cannot keep up with).
//! 2. **Ingest over Zenoh** (with `--zenoh`): the same frames published on the session's key;
//!    figure: frames the server counted as received per second of publishing.
//! 3. **Frame-to-pose latency at `--fps`**: one live session over the WebSocket, frames paced
//!    like a camera; each pose is matched to its frame by id, latency = pose received − frame
//!    sent, p50/p99 over the frames that got a pose; frames without one count as dropped.
//! 4. **Sessions sustained at `--fps`**: k = 1, 2, … concurrent live sessions as in 3 until the
//!    p99 latency over all of them exceeds 1 s, more than 5 % of the frames are dropped, or the
//!    server refuses a session (503); the figure is the largest k that passed.
//!
//! The frames come from `--dataset`, or a synthetic sequence rendered at `--width`×`--height`.
//! Nothing is spawned: the server is whatever `--server` points at.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use bytes::Bytes;
use relfusion_proto::v1::server_message;
use relfusion_sdk::message::{end_of_stream, frame_message};
use relfusion_sdk::{Client, CreateSession, FramePolicy};
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::synth::{SynthConfig, render_sequence};
use serde_json::{Value, json};

use relfusion_client::latency::{LiveRun, MAX_DROP_FRACTION, MAX_P99_MS, step_json};

use super::connect::{ConnectArgs, runtime};

/// How long to wait after the last frame for the session to finish and close its stream.
const DRAIN_TIMEOUT: Duration = Duration::from_secs(30);

#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Also measure ingest over Zenoh through this endpoint (e.g. tcp/127.0.0.1:7447).
    #[arg(long)]
    pub zenoh: Option<String>,
    #[command(flatten)]
    pub sequence: BenchSequence,
    /// Frames per live run (latency, each step of the sessions ramp).
    #[arg(long, default_value_t = 150)]
    pub frames: usize,
    /// Frames per ingest run (the sequence repeats; short runs measure mostly start-up).
    #[arg(long, default_value_t = 600)]
    pub ingest_frames: usize,
    /// Most concurrent sessions to try.
    #[arg(long, default_value_t = 4)]
    pub sessions_max: usize,
    /// Camera rate of the latency and sessions runs.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// HTTP requests in flight during the ingest run.
    #[arg(long, default_value_t = 4)]
    pub concurrency: usize,
    /// Depth model for the sessions ("none", "default", a configured name).
    #[arg(long)]
    pub model: Option<String>,
}

/// The frames of a run, encoded, in memory.
pub(super) struct Frames {
    pub camera: relfusion_sdk::CameraJson,
    pub items: Vec<(f64, Bytes)>,
    pub width: u32,
    pub height: u32,
    pub bytes_mean: f64,
}

pub fn serve(args: &ServeArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.frames > 0, "--frames must be positive");
    anyhow::ensure!(args.ingest_frames > 0, "--ingest-frames must be positive");
    anyhow::ensure!(
        args.fps.is_finite() && args.fps > 0.0,
        "--fps must be positive"
    );
    anyhow::ensure!(args.concurrency > 0, "--concurrency must be positive");
    let frames = Arc::new(load_frames(&args.sequence, args.frames, args.fps)?);
    let client = args.connect.client()?;
    let report = runtime()?.block_on(async {
        client
            .health()
            .await
            .with_context(|| format!("{} is not answering /healthz", args.connect.server()))?;
        let version = client.version().await.unwrap_or(Value::Null);
        let http_ingest = http_ingest(&client, &frames, args).await?;
        let zenoh_ingest = match &args.zenoh {
            Some(endpoint) => zenoh_ingest(&client, &frames, endpoint, args)
                .await
                .unwrap_or_else(|e| json!({ "error": format!("{e:#}") })),
            None => Value::Null,
        };
        let (latency, sessions) = sessions_ramp(&client, &frames, args).await;
        anyhow::Ok(json!({
            "bench": "serve",
            "server": args.connect.server(),
            "server_version": version,
            "width": frames.width,
            "height": frames.height,
            "frames": frames.items.len(),
            "frame_bytes_mean": frames.bytes_mean,
            "http_ingest": http_ingest,
            "zenoh_ingest": zenoh_ingest,
            "latency": latency,
            "sessions": sessions,
            "notes": "ingest: accepted frames/s (decoded and validated by the server, drop-oldest \
                      queue behind); latency: pose received - frame sent, at `fps`, WebSocket; \
                      sessions: largest k concurrent sessions at `fps` with p99 <= 1 s and \
                      <= 5 % frames without a pose",
        }))
    })?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

/// The frames a service benchmark sends.
#[derive(Debug, clap::Args)]
pub struct BenchSequence {
    /// TUM-layout sequence to send (default: a synthetic one rendered at --width×--height).
    #[arg(long)]
    pub dataset: Option<PathBuf>,
    /// Width of the synthetic sequence.
    #[arg(long, default_value_t = 320)]
    pub width: u32,
    /// Height of the synthetic sequence.
    #[arg(long, default_value_t = 240)]
    pub height: u32,
}

/// `count` frames of the `--dataset` (cycled), or of a synthetic sequence of its size, timed
/// at `fps`.
pub(super) fn load_frames(
    sequence: &BenchSequence,
    count: usize,
    fps: f64,
) -> anyhow::Result<Frames> {
    let (width, height) = (sequence.width, sequence.height);
    let mut rendered = None;
    let dir = match sequence.dataset.as_deref() {
        Some(d) => d.to_path_buf(),
        None => {
            let dir = std::env::temp_dir().join(format!(
                "relfusion-bench-serve-{width}x{height}-{}",
                std::process::id()
            ));
            let config = SynthConfig {
                frames: count,
                width,
                height,
                seed: 1,
                ..SynthConfig::default()
            };
            render_sequence(&config, &dir).context("rendering the synthetic sequence")?;
            rendered = Some(dir.clone());
            dir
        }
    };
    let seq =
        TumSequence::open(&dir, None).with_context(|| format!("opening {}", dir.display()))?;
    // Longer runs than the sequence cycle through it (timestamps keep increasing).
    let items = (0..count)
        .map(|i| {
            let path = &seq.frames[i % seq.len()].rgb;
            let bytes =
                std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            Ok((i as f64 / fps, Bytes::from(bytes)))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    if let Some(dir) = rendered {
        let _ = std::fs::remove_dir_all(dir);
    }
    let bytes_mean = items.iter().map(|(_, b)| b.len() as f64).sum::<f64>() / items.len() as f64;
    Ok(Frames {
        camera: relfusion_sdk::camera_json(&seq.camera),
        width: seq.camera.width,
        height: seq.camera.height,
        items,
        bytes_mean,
    })
}

fn request(frames: &Frames, policy: FramePolicy, args: &ServeArgs) -> CreateSession {
    CreateSession {
        camera: Some(frames.camera),
        config: Value::Null,
        model: args.model.clone(),
        policy,
        map: None,
        ros2: None,
    }
}

async fn http_ingest(
    client: &Client,
    frames: &Arc<Frames>,
    args: &ServeArgs,
) -> anyhow::Result<Value> {
    let info = client
        .create_session(&request(frames, FramePolicy::DropOldest, args))
        .await
        .context("creating the ingest session")?;
    let id = Arc::new(info.id);
    let next = Arc::new(AtomicUsize::new(0));
    let (total, fps) = (args.ingest_frames, args.fps);
    let t0 = Instant::now();
    let workers: Vec<_> = (0..args.concurrency)
        .map(|_| {
            let (client, frames, id, next) =
                (client.clone(), frames.clone(), id.clone(), next.clone());
            tokio::spawn(async move {
                let (mut accepted, mut errors, mut first_error) = (0u64, 0u64, None);
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= total {
                        break;
                    }
                    let (_, bytes) = &frames.items[i % frames.items.len()];
                    let ts = i as f64 / fps;
                    match client.push_frame(&id, None, ts, bytes.clone()).await {
                        Ok(_) => accepted += 1,
                        Err(e) => {
                            errors += 1;
                            first_error.get_or_insert_with(|| e.report());
                        }
                    }
                }
                (accepted, errors, first_error)
            })
        })
        .collect();
    let (mut accepted, mut errors, mut first_error) = (0, 0, None);
    for w in workers {
        let (a, e, f) = w.await?;
        accepted += a;
        errors += e;
        first_error = first_error.or(f);
    }
    let wall_s = t0.elapsed().as_secs_f64();
    let info = client.session(&id).await.ok();
    let _ = client.delete(&id).await;
    Ok(json!({
        "frames_posted": total,
        "accepted_202": accepted,
        "errors": errors,
        "first_error": first_error,
        "wall_s": wall_s,
        "frames_per_s": accepted as f64 / wall_s,
        "mb_per_s": accepted as f64 * frames.bytes_mean / wall_s / 1e6,
        "concurrency": args.concurrency,
        "pipeline_processed": info.as_ref().map(|i| i.frames_processed),
        "pipeline_dropped": info.as_ref().map(|i| i.frames_dropped),
    }))
}

/// Ingest over Zenoh, measured by the Zenoh transport itself (publishing is fire-and-forget,
/// so it counts what the server accepted, through the session's map queryable).
async fn zenoh_ingest(
    client: &Client,
    frames: &Arc<Frames>,
    endpoint: &str,
    args: &ServeArgs,
) -> anyhow::Result<Value> {
    // The same cycled sequence as the HTTP ingest run (`Bytes` clones share the images).
    let items: Vec<(f64, Bytes)> = (0..args.ingest_frames)
        .map(|i| {
            let (_, bytes) = &frames.items[i % frames.items.len()];
            (i as f64 / args.fps, bytes.clone())
        })
        .collect();
    let req = CreateSession {
        camera: Some(frames.camera),
        config: Value::Null,
        model: None,
        policy: FramePolicy::DropOldest,
        map: None,
        ros2: None,
    };
    let identity = relfusion_sdk::zenoh_transport::Identity::of(client);
    let rate =
        relfusion_sdk::zenoh_transport::ingest_rate(endpoint, &identity, &req, &items).await?;
    Ok(serde_json::to_value(rate)?)
}

/// Streams every frame at `fps` to a new live session and matches poses to frames.
pub(super) async fn live_session(
    client: Client,
    frames: Arc<Frames>,
    fps: f64,
    req: CreateSession,
) -> LiveRun {
    live_session_via(client, |_| None, frames, fps, req).await
}

/// [`live_session`], created through `client` and streamed over the WebSocket of the client
/// `via` picks for the created session (`None`: `client`; another node of a cluster).
pub(super) async fn live_session_via(
    client: Client,
    via: impl FnOnce(&relfusion_sdk::SessionInfo) -> Option<Client>,
    frames: Arc<Frames>,
    fps: f64,
    req: CreateSession,
) -> LiveRun {
    let mut run = LiveRun::default();
    let opened = async {
        let info = client.create_session(&req).await?;
        let stream = via(&info).unwrap_or_else(|| client.clone());
        let mut link = relfusion_sdk::ws::connect(&stream, &info.id).await?;
        link.info = Some(info);
        Ok::<_, relfusion_sdk::ClientError>(link)
    };
    let mut link = match opened.await {
        Ok(link) => link,
        Err(e) => {
            run.error = Some(e.report());
            return run;
        }
    };
    let id = link.session_id.clone();
    let n = frames.items.len();
    let sent_at: Arc<std::sync::Mutex<Vec<Option<Instant>>>> =
        Arc::new(std::sync::Mutex::new(vec![None; n]));
    let tx = link.frames.clone();
    let (sent_w, frames_w) = (sent_at.clone(), frames.clone());
    let sender = tokio::spawn(async move {
        let start = tokio::time::Instant::now();
        let mut sent = 0u64;
        for (i, (ts, bytes)) in frames_w.items.iter().enumerate() {
            tokio::time::sleep_until(start + Duration::from_secs_f64(i as f64 / fps)).await;
            if let Ok(mut s) = sent_w.lock() {
                s[i] = Some(Instant::now());
            }
            if tx
                .send(frame_message(i as u64, *ts, bytes.to_vec()))
                .await
                .is_err()
            {
                break;
            }
            sent += 1;
        }
        let _ = tx.send(end_of_stream()).await;
        sent
    });
    // Dropping our own sender lets the stream close once the sender task is done.
    drop(std::mem::replace(
        &mut link.frames,
        tokio::sync::mpsc::channel(1).0,
    ));
    let deadline =
        tokio::time::Instant::now() + Duration::from_secs_f64(n as f64 / fps) + DRAIN_TIMEOUT;
    loop {
        match tokio::time::timeout_at(deadline, link.updates.recv()).await {
            Ok(Some(Ok(msg))) => {
                if let Some(server_message::Message::Pose(p)) = msg.message {
                    let now = Instant::now();
                    let sent = sent_at
                        .lock()
                        .ok()
                        .and_then(|s| s.get(p.frame_id as usize).copied().flatten());
                    if let Some(t) = sent {
                        run.latencies_ms
                            .push(1e3 * now.duration_since(t).as_secs_f64());
                    }
                }
            }
            Ok(Some(Err(e))) => {
                run.error = Some(e.report());
                break;
            }
            Ok(None) => break,
            Err(_) => {
                run.error = Some("the session did not finish in time".into());
                break;
            }
        }
    }
    sender.abort();
    run.sent = sent_at
        .lock()
        .map(|s| s.iter().flatten().count() as u64)
        .unwrap_or(0);
    if let Ok(info) = client.session(&id).await {
        run.server_dropped = info.frames_dropped;
    }
    let _ = client.delete(&id).await;
    run
}

/// Runs k = 1..=sessions_max concurrent live sessions; returns the single-session latency
/// figures and the ramp.
async fn sessions_ramp(client: &Client, frames: &Arc<Frames>, args: &ServeArgs) -> (Value, Value) {
    let req = request(frames, FramePolicy::DropOldest, args);
    let (sustained, steps) = ramp(
        std::slice::from_ref(client),
        frames,
        args.fps,
        args.sessions_max,
        &req,
    )
    .await;
    let latency = steps.first().cloned().unwrap_or(Value::Null);
    let sessions = json!({
        "sustained": sustained,
        "fps": args.fps,
        "criterion": format!("p99 <= {MAX_P99_MS} ms and drops <= {}%", 100.0 * MAX_DROP_FRACTION),
        "steps": steps,
    });
    (latency, sessions)
}

/// k = 1, 2, … `sessions_max` concurrent live sessions of `req` at `fps`, the i-th through
/// `clients[i mod len]`, until a step fails; returns the largest k that passed and every step.
pub(super) async fn ramp(
    clients: &[Client],
    frames: &Arc<Frames>,
    fps: f64,
    sessions_max: usize,
    req: &CreateSession,
) -> (usize, Vec<Value>) {
    let mut steps = Vec::new();
    let mut sustained = 0;
    for k in 1..=sessions_max.max(1) {
        let runs: Vec<_> = (0..k)
            .map(|i| {
                tokio::spawn(live_session(
                    clients[i % clients.len()].clone(),
                    frames.clone(),
                    fps,
                    req.clone(),
                ))
            })
            .collect();
        let mut all = LiveRun::default();
        for r in runs {
            let run = r.await.unwrap_or_else(|e| LiveRun {
                error: Some(e.to_string()),
                ..LiveRun::default()
            });
            all.sent += run.sent;
            all.latencies_ms.extend(run.latencies_ms);
            all.server_dropped += run.server_dropped;
            all.error = all.error.or(run.error);
        }
        let step = step_json(k, &mut all, fps);
        let ok = step["ok"].as_bool().unwrap_or(false);
        steps.push(step);
        if !ok {
            break;
        }
        sustained = k;
    }
    (sustained, steps)
}
