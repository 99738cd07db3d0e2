//! The viewers' logs of `relfusion stream` and `relfusion run` (`--rerun FILE.rrd`,
//! `--mcap FILE.mcap`, `--mcap-ros2 FILE.mcap`, `--foxglove [ADDR:]PORT`): what each command sees (the service's updates,
//! the local pipeline's events) translated once into [`SessionLog`] calls and given to every
//! log asked for. A log that fails is reported at the end; the stream or run itself goes on.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context as _;
use relfusion_sdk::dataset_stream::StreamEvent;
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::pipeline::Event;
use relfusion_viz::foxglove_log::{FoxgloveLog, FoxgloveOptions, parse_serve_address};
use relfusion_viz::pipeline_log::log_event;
use relfusion_viz::ros2::mcap::Ros2Bag;
use relfusion_viz::session_log::{DepthRef, LogError, MeshBlockRef, Pose, SessionLog};
use serde_json::{Map, Value};

/// The flags that ask for logs.
#[derive(Debug, clap::Args)]
pub struct LogArgs {
    /// Also write a rerun recording (images, poses, keyframe points, mesh blocks) to open in
    /// the rerun viewer; needs the cargo feature `rerun`.
    #[arg(long, value_name = "FILE.rrd")]
    pub rerun: Option<PathBuf>,
    /// Also write an MCAP recording with the Foxglove schemas (images, calibration, poses,
    /// transforms, trajectory, keyframe points, mesh blocks), for Foxglove or the `mcap` tools.
    #[arg(long, value_name = "FILE.mcap")]
    pub mcap: Option<PathBuf>,
    /// Also write a ROS 2 bag (MCAP, `ros2msg` schemas, CDR: what `ros2 bag record -s mcap`
    /// writes) that `ros2 bag play` replays: images, camera info, /tf, pose, path, keyframe
    /// points and the mesh as markers.
    #[arg(long, value_name = "FILE.mcap")]
    pub mcap_ros2: Option<PathBuf>,
    /// Serve the session live to the Foxglove app (Foxglove WebSocket protocol) on this port
    /// of 127.0.0.1, or on ADDR:PORT; the URL is printed on stderr as {"foxglove": URL}.
    #[arg(long, value_name = "[ADDR:]PORT", value_parser = parse_serve_address)]
    pub foxglove: Option<SocketAddr>,
    /// With --foxglove: wait up to this many seconds for a viewer to subscribe before the
    /// first frame, so it sees the session from the start.
    #[arg(long, value_name = "SECONDS", requires = "foxglove")]
    pub foxglove_wait: Option<f64>,
}

/// The logs asked for, each under the name its summary is reported with.
#[derive(Debug, Default)]
pub struct Logs {
    logs: Vec<(&'static str, Box<dyn SessionLog>)>,
    failure: Option<(&'static str, LogError)>,
}

#[cfg(feature = "rerun")]
fn rerun_log(path: &Path, camera: &PinholeCamera) -> anyhow::Result<Box<dyn SessionLog>> {
    Ok(Box::new(relfusion_viz::rerun_log::RerunLog::create(
        path, camera,
    )?))
}

#[cfg(not(feature = "rerun"))]
fn rerun_log(_: &Path, _: &PinholeCamera) -> anyhow::Result<Box<dyn SessionLog>> {
    anyhow::bail!(
        "this relfusion was built without rerun recordings: cargo build --release -p relfusion-client --features rerun"
    )
}

fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn triples<T: Copy>(values: &[T]) -> Vec<[T; 3]> {
    values.chunks_exact(3).map(|v| [v[0], v[1], v[2]]).collect()
}

impl Logs {
    /// Opens every log the flags ask for (none: an empty set that does nothing).
    pub fn open(args: &LogArgs, camera: &PinholeCamera) -> anyhow::Result<Logs> {
        let mut logs = Logs::default();
        if let Some(path) = &args.rerun {
            logs.logs.push(("rerun", rerun_log(path, camera)?));
        }
        if args.mcap.is_some() || args.foxglove.is_some() {
            let wait = args
                .foxglove_wait
                .map(|s| {
                    anyhow::ensure!(
                        s.is_finite() && (0.0..=3600.0).contains(&s),
                        "--foxglove-wait must be 0-3600 seconds, got {s}"
                    );
                    Ok(Duration::from_secs_f64(s))
                })
                .transpose()?;
            let options = FoxgloveOptions {
                mcap: args.mcap.clone(),
                serve: args.foxglove,
                wait_for_client: wait,
            };
            logs.logs
                .push(("foxglove", Box::new(FoxgloveLog::open(&options, camera)?)));
        }
        if let Some(path) = &args.mcap_ros2 {
            logs.logs
                .push(("ros2_bag", Box::new(Ros2Bag::create(path, camera)?)));
        }
        Ok(logs)
    }

    pub fn is_empty(&self) -> bool {
        self.logs.is_empty()
    }

    /// Calls `f` on every log; the first failure is kept and that log is left out from then on.
    fn each(&mut self, mut f: impl FnMut(&mut dyn SessionLog) -> Result<(), LogError>) {
        let mut failed = None;
        for (i, (name, log)) in self.logs.iter_mut().enumerate() {
            if let Err(e) = f(log.as_mut()) {
                failed = Some(i);
                self.failure.get_or_insert((*name, e));
                break;
            }
        }
        if let Some(i) = failed {
            self.logs.remove(i);
        }
    }

    /// One event of `relfusion stream`; `frames` are the sequence's (timestamp, image).
    pub fn on_stream_event(&mut self, event: &StreamEvent, frames: &[(f64, PathBuf)]) {
        if self.is_empty() {
            return;
        }
        match event {
            StreamEvent::Sent { frame_id } => {
                let Some((timestamp, path)) =
                    usize::try_from(*frame_id).ok().and_then(|i| frames.get(i))
                else {
                    return;
                };
                match std::fs::read(path) {
                    Ok(bytes) => self.each(|l| l.image(*frame_id, *timestamp, &bytes)),
                    Err(e) => {
                        // Every log would miss it: they all stop here.
                        let e = LogError::Write {
                            what: "reading a frame",
                            message: format!("{}: {e}", path.display()),
                        };
                        self.failure.get_or_insert(("viewer", e));
                        self.logs.clear();
                    }
                }
            }
            StreamEvent::Pose(p) if p.state != "lost" => {
                let pose = Pose {
                    t: p.t,
                    q: p.q,
                    s: p.s,
                };
                self.each(|l| l.pose(p.frame_id, p.timestamp, &pose));
            }
            StreamEvent::Keyframe {
                keyframe_id,
                pose,
                depth,
                ..
            } => {
                let pose = Pose {
                    t: pose.t,
                    q: pose.q,
                    s: pose.s,
                };
                self.each(|l| l.keyframe(*keyframe_id, &pose));
                if let Some(d) = depth
                    && let Some(c) = &d.camera
                {
                    let inverse_depth = floats(&d.inverse_depth);
                    let depth = DepthRef {
                        width: d.width as usize,
                        height: d.height as usize,
                        inverse_depth: &inverse_depth,
                        fx: c.fx,
                        fy: c.fy,
                        cx: c.cx,
                        cy: c.cy,
                    };
                    self.each(|l| l.keyframe_depth(*keyframe_id, &depth));
                }
            }
            StreamEvent::Mesh { update } => {
                let removed: Vec<[i32; 3]> = update
                    .removed_blocks
                    .iter()
                    .map(|b| [b.x, b.y, b.z])
                    .collect();
                let blocks: Vec<_> = update
                    .changed_blocks
                    .iter()
                    .map(|b| {
                        (
                            b.index.as_ref().map_or([0; 3], |i| [i.x, i.y, i.z]),
                            triples(&floats(&b.vertices)),
                            triples(&floats(&b.normals)),
                            triples(&b.colors),
                            &b.indices,
                        )
                    })
                    .collect();
                let changed: Vec<MeshBlockRef<'_>> = blocks
                    .iter()
                    .map(
                        |(index, positions, normals, colors, indices)| MeshBlockRef {
                            index: *index,
                            positions,
                            colors,
                            normals,
                            indices,
                        },
                    )
                    .collect();
                self.each(|l| l.mesh_update(&changed, &removed));
            }
            StreamEvent::Session { .. }
            | StreamEvent::Pose(_)
            | StreamEvent::ServerError { .. } => {}
        }
    }

    /// Frame `index` of `seq` went through the local pipeline and these events came out.
    pub fn on_run_frame(
        &mut self,
        seq: &TumSequence,
        index: usize,
        events: &[Event],
    ) -> anyhow::Result<()> {
        if self.is_empty() {
            return Ok(());
        }
        let frame = &seq.frames[index];
        let bytes = std::fs::read(&frame.rgb)
            .with_context(|| format!("reading {}", frame.rgb.display()))?;
        self.each(|l| l.image(index as u64, frame.timestamp, &bytes));
        self.on_run_events(events);
        Ok(())
    }

    /// Events of the local pipeline that came out without a frame (the final flush).
    pub fn on_run_events(&mut self, events: &[Event]) {
        for event in events {
            self.each(|l| log_event(l, event));
        }
    }

    /// Writes every log out: its summary under its name ("rerun", "foxglove").
    pub fn finish(self) -> anyhow::Result<Map<String, Value>> {
        if let Some((name, e)) = self.failure {
            return Err(anyhow::Error::new(e).context(format!("writing the {name} log")));
        }
        let mut out = Map::new();
        for (name, log) in self.logs {
            let summary = log
                .finish()
                .with_context(|| format!("finishing the {name} log"))?;
            out.insert(name.into(), summary);
        }
        Ok(out)
    }
}
