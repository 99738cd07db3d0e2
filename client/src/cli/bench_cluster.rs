//! `relfusion bench cluster`: relfusiond nodes on this machine as one service, with 1, 2, …
//! `--nodes-max` nodes, as one JSON object. It spawns them itself: a Zenoh router
//! (`relfusiond --zenoh-router`) and N nodes joined to it, each with its own data folder.
//!
//! Per N, after one unmeasured warm-up session per node (a fresh node's first session starts
//! its GPU context):
//! 1. **Sessions sustained at `--fps`**: k = 1, 2, … concurrent live sessions, the i-th created
//!    and streamed through node i mod N (placement puts it on the least loaded node; a session
//!    on another node is relayed), until p99 frame-to-pose latency exceeds 1 s or more than 5 %
//!    of the frames get no pose (as `bench serve`).
//! 2. **Forwarding overhead** (N ≥ 2): one live session, created through the first node; its
//!    owner is read from the session info. Frames are posted at `--fps` (`POST …/frames`, the
//!    202 acknowledgement's round trip), first to the owner, then through a node that does not
//!    run it; then two more sessions stream over a WebSocket, one to its owner and one through
//!    another node (frame-to-pose latency). p50/p99 of each, owner vs non-owner: what a hop
//!    over Zenoh costs.
//!
//! The nodes share the machine's cores, so N nodes do not add capacity here: the figures show
//! the overhead of the cluster, not its scaling.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context as _;
use relfusion_sdk::{Client, CreateSession, FramePolicy};
use serde_json::{Value, json};

use relfusion_client::latency::{percentile, step_json};

use super::bench_serve::{
    self, BenchSequence, Frames, live_session, live_session_via, load_frames,
};
use super::connect::runtime;

#[derive(Debug, clap::Args)]
pub struct ClusterArgs {
    /// The relfusiond binary (default: the one beside this relfusion).
    #[arg(long)]
    pub relfusiond: Option<PathBuf>,
    /// Up to this many nodes (1, 2, … N).
    #[arg(long, default_value_t = 3)]
    pub nodes_max: usize,
    /// Sessions each node runs at once (`limits.max_sessions`).
    #[arg(long, default_value_t = 4)]
    pub node_sessions: usize,
    /// Most concurrent sessions to try per N.
    #[arg(long, default_value_t = 4)]
    pub sessions_max: usize,
    /// Frames per live run.
    #[arg(long, default_value_t = 150)]
    pub frames: usize,
    /// Camera rate.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    #[command(flatten)]
    pub sequence: BenchSequence,
}

/// A spawned process, killed when dropped.
struct Spawned(Child);

impl Drop for Spawned {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `relfusiond ARGS` and returns it once it printed `ready` (and what followed).
fn spawn(binary: &PathBuf, args: &[String], ready: &str) -> anyhow::Result<(Spawned, String)> {
    let mut child = Command::new(binary)
        .args(args)
        .env("RUST_LOG", "error")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .with_context(|| format!("starting {}", binary.display()))?;
    let stdout = child.stdout.take().context("stdout")?;
    let child = Spawned(child);
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line)?;
    let rest = line
        .trim()
        .strip_prefix(ready)
        .with_context(|| format!("relfusiond did not start: {line:?}"))?;
    Ok((child, rest.to_string()))
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// A router and `n` nodes, and a client per node.
struct Cluster {
    _processes: Vec<Spawned>,
    clients: Vec<Client>,
    dir: PathBuf,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        self._processes.clear();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn start_cluster(args: &ClusterArgs, binary: &PathBuf, n: usize) -> anyhow::Result<Cluster> {
    let dir = std::env::temp_dir().join(format!(
        "relfusion-bench-cluster-{}-{n}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;
    let endpoint = format!("tcp/127.0.0.1:{}", free_port()?);
    let mut processes = Vec::new();
    let router_args = vec!["--zenoh-router".to_string(), endpoint.clone()];
    processes.push(spawn(binary, &router_args, "zenoh router on ")?.0);
    let mut clients = Vec::new();
    for i in 0..n {
        let config = dir.join(format!("node-{i}.toml"));
        std::fs::write(
            &config,
            format!(
                "[zenoh]\nenabled = true\nmode = \"client\"\nnode = \"node-{i}\"\n\
                 connect = [\"{endpoint}\"]\n[limits]\nmax_sessions = {}\n",
                args.node_sessions
            ),
        )?;
        let node_args = vec![
            "--config".to_string(),
            config.display().to_string(),
            "--listen".into(),
            "127.0.0.1:0".into(),
            "--data-dir".into(),
            dir.join(format!("node-{i}")).display().to_string(),
        ];
        let (process, addr) = spawn(binary, &node_args, "listening on ")?;
        processes.push(process);
        clients.push(Client::new(&format!("http://{addr}"), None)?);
    }
    Ok(Cluster {
        _processes: processes,
        clients,
        dir,
    })
}

/// Waits until the first node sees all `n` members with their capacity.
async fn wait_members(client: &Client, n: usize) -> anyhow::Result<()> {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let view = client.cluster().await.unwrap_or(Value::Null);
        let nodes = view["nodes"].as_array().map_or(0, |nodes| {
            nodes
                .iter()
                .filter(|n| n["max_sessions"].as_u64() > Some(0))
                .count()
        });
        if view["joined"] == true && nodes == n {
            return Ok(());
        }
        anyhow::ensure!(Instant::now() < deadline, "{n} nodes did not join: {view}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

fn request(frames: &Frames, policy: FramePolicy) -> CreateSession {
    CreateSession {
        camera: Some(frames.camera),
        config: Value::Null,
        model: Some("none".into()),
        policy,
        map: None,
        ros2: None,
    }
}

pub fn cluster(args: &ClusterArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.nodes_max > 0, "--nodes-max must be positive");
    anyhow::ensure!(
        args.fps.is_finite() && args.fps > 0.0,
        "--fps must be positive"
    );
    let binary = match &args.relfusiond {
        Some(path) => path.clone(),
        None => std::env::current_exe()?
            .parent()
            .context("the folder of relfusion")?
            .join("relfusiond"),
    };
    let frames = Arc::new(load_frames(&args.sequence, args.frames, args.fps)?);
    let mut per_n = Vec::new();
    for n in 1..=args.nodes_max {
        let cluster = start_cluster(args, &binary, n)?;
        let figures = runtime()?.block_on(async {
            wait_members(&cluster.clients[0], n).await?;
            warm_up(&cluster.clients, &frames, args).await;
            let sessions = ramp(&cluster.clients, &frames, args).await;
            let forwarding = if n >= 2 {
                forwarding(&cluster.clients, &frames, args)
                    .await
                    .unwrap_or_else(|e| json!({ "error": format!("{e:#}") }))
            } else {
                Value::Null
            };
            anyhow::Ok(json!({ "nodes": n, "sessions": sessions, "forwarding": forwarding }))
        })?;
        eprintln!("{}", serde_json::to_string(&figures)?);
        per_n.push(figures);
    }
    let report = json!({
        "bench": "cluster",
        "fps": args.fps,
        "frames": args.frames,
        "node_sessions": args.node_sessions,
        "cpus": std::thread::available_parallelism().map_or(0, |n| n.get()),
        "runs": per_n,
        "notes": "sessions: largest k concurrent live sessions at `fps` (the i-th created and \
                  streamed through node i mod N) with p99 frame-to-pose <= 1 s and <= 5 % \
                  frames without a pose; forwarding: the same session's frames posted (202 \
                  round trip) and streamed (frame-to-pose) to its owner vs through another node",
    });
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

/// One short session per node, not measured: a fresh node's first session pays for its GPU
/// context and pool start (placement spreads concurrent creates, one per node).
async fn warm_up(clients: &[Client], frames: &Arc<Frames>, args: &ClusterArgs) {
    let short = Arc::new(Frames {
        camera: frames.camera,
        items: frames.items.iter().take(30).cloned().collect(),
        width: frames.width,
        height: frames.height,
        bytes_mean: frames.bytes_mean,
    });
    let runs: Vec<_> = clients
        .iter()
        .map(|c| {
            tokio::spawn(live_session(
                c.clone(),
                short.clone(),
                args.fps,
                request(frames, FramePolicy::DropOldest),
            ))
        })
        .collect();
    for r in runs {
        let _ = r.await;
    }
}

/// k = 1, 2, … concurrent sessions spread over the nodes' APIs.
async fn ramp(clients: &[Client], frames: &Arc<Frames>, args: &ClusterArgs) -> Value {
    let req = request(frames, FramePolicy::DropOldest);
    let (sustained, steps) =
        bench_serve::ramp(clients, frames, args.fps, args.sessions_max, &req).await;
    json!({ "sustained": sustained, "steps": steps })
}

/// Frame acknowledgements and frame-to-pose latency to a session's owner vs another node.
async fn forwarding(
    clients: &[Client],
    frames: &Arc<Frames>,
    args: &ClusterArgs,
) -> anyhow::Result<Value> {
    let info = clients[0]
        .create_session(&request(frames, FramePolicy::DropOldest))
        .await?;
    let owner = node_index(&info)?;
    let other = (owner + 1) % clients.len();
    let owner_acks = post_acks(&clients[owner], &info.id, frames, args.fps, 0).await?;
    let other_acks = post_acks(
        &clients[other],
        &info.id,
        frames,
        args.fps,
        frames.items.len(),
    )
    .await?;
    let _ = clients[0].delete(&info.id).await;
    let mut streams = Vec::new();
    for relayed in [false, true] {
        let nodes = clients.to_vec();
        let pick = move |info: &relfusion_sdk::SessionInfo| {
            let owner = node_index(info).ok()?;
            let i = if relayed {
                (owner + 1) % nodes.len()
            } else {
                owner
            };
            nodes.get(i).cloned()
        };
        let mut run = live_session_via(
            clients[0].clone(),
            pick,
            frames.clone(),
            args.fps,
            request(frames, FramePolicy::DropOldest),
        )
        .await;
        streams.push(step_json(1, &mut run, args.fps));
    }
    Ok(json!({
        "frame_ack_owner": acks_json(owner_acks),
        "frame_ack_non_owner": acks_json(other_acks),
        "frame_to_pose_owner": streams[0],
        "frame_to_pose_non_owner": streams[1],
    }))
}

/// The index of the node a session runs on (nodes are named `node-<i>`).
fn node_index(info: &relfusion_sdk::SessionInfo) -> anyhow::Result<usize> {
    info.node
        .as_deref()
        .and_then(|n| n.strip_prefix("node-"))
        .and_then(|i| i.parse().ok())
        .with_context(|| format!("session {} names no known node", info.id))
}

/// Round trips of `POST …/frames` at `fps`, in ms.
async fn post_acks(
    client: &Client,
    id: &str,
    frames: &Frames,
    fps: f64,
    first_index: usize,
) -> anyhow::Result<Vec<f64>> {
    let start = tokio::time::Instant::now();
    let mut acks = Vec::with_capacity(frames.items.len());
    for (i, (_, bytes)) in frames.items.iter().enumerate() {
        tokio::time::sleep_until(start + Duration::from_secs_f64(i as f64 / fps)).await;
        let ts = (first_index + i) as f64 / fps;
        let t = Instant::now();
        client.push_frame(id, None, ts, bytes.clone()).await?;
        acks.push(1e3 * t.elapsed().as_secs_f64());
    }
    Ok(acks)
}

fn acks_json(mut acks: Vec<f64>) -> Value {
    acks.sort_by(f64::total_cmp);
    json!({
        "frames": acks.len(),
        "p50_ms": percentile(&acks, 0.5),
        "p99_ms": percentile(&acks, 0.99),
        "max_ms": acks.last(),
    })
}
