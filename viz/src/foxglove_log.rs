//! A session for Foxglove: an MCAP file (`--mcap FILE`), a live Foxglove WebSocket server
//! (`--foxglove ADDR`), or both from one Foxglove SDK context, with the well-known Foxglove
//! schemas (protobuf) so the Foxglove app and the `mcap` tools read them without our protocol.
//!
//! Channels (frames: `map` is z-up; `world` is the first camera's, x right, y down, z forward,
//! turned into `map` by a fixed rotation sent with every `/tf`; `camera`; `keyframe_<id>`):
//!
//! | topic | schema | when |
//! |---|---|---|
//! | `/camera/image` | `foxglove.CompressedImage` | every frame sent |
//! | `/camera/calibration` | `foxglove.CameraCalibration` | with every image |
//! | `/camera/pose` | `foxglove.PoseInFrame` (`world`) | every tracked frame |
//! | `/tf` | `foxglove.FrameTransforms` | every tracked frame (`world → camera`), every keyframe made or moved (`world → keyframe_<id>`) |
//! | `/trajectory` | `foxglove.PosesInFrame` (`world`) | the keyframes' poses, after the keyframes changed |
//! | `/keyframes/points` | `foxglove.PointCloud` (`keyframe_<id>`) | a keyframe's dense depth; again when the pose graph rescales it |
//! | `/mesh` | `foxglove.SceneUpdate` (`world`) | every mesh update: one entity per block (`block_x_y_z`, a triangle list), deletions for blocks that lost their surface |
//!
//! Log times are the frames' capture times. A Foxglove client that connects late sees what is
//! logged from then on (the protocol keeps no history); the MCAP file holds everything.

use std::fs::File;
use std::io::BufWriter;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use foxglove::messages::{
    CameraCalibration, Color, CompressedImage, FrameTransform, FrameTransforms, PackedElementField,
    Point3, PointCloud, Pose as FoxPose, PoseInFrame, PosesInFrame, Quaternion, SceneEntity,
    SceneEntityDeletion, SceneUpdate, Timestamp, TriangleListPrimitive, Vector3,
    packed_element_field::NumericType, scene_entity_deletion::Type as DeletionType,
};
use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{Channel, Context, McapWriteOptions, McapWriterHandle, WebSocketServerHandle};
use relfusion_core::geometry::PinholeCamera;

use crate::clouds::KeyframeViews;
use crate::foxglove_front::FoxgloveFront;
use crate::session_log::{
    DepthRef, LogCounts, LogError, MeshBlockRef, POINTS_PER_KEYFRAME, Pose, SessionLog,
    image_format, nanos,
};

/// Topics, as the table above.
pub mod topics {
    pub const IMAGE: &str = "/camera/image";
    pub const CALIBRATION: &str = "/camera/calibration";
    pub const POSE: &str = "/camera/pose";
    pub const TF: &str = "/tf";
    pub const TRAJECTORY: &str = "/trajectory";
    pub const POINTS: &str = "/keyframes/points";
    pub const MESH: &str = "/mesh";
}

/// Where the log goes.
#[derive(Clone, Debug, Default)]
pub struct FoxgloveOptions {
    /// Write an MCAP file here (replaced if it exists).
    pub mcap: Option<PathBuf>,
    /// Serve the Foxglove WebSocket protocol on this address (port 0: any free port).
    pub serve: Option<SocketAddr>,
    /// Before the first message, wait up to this long for a Foxglove client to subscribe, so a
    /// viewer sees the session from its start.
    pub wait_for_client: Option<Duration>,
}

fn write_error(e: impl std::fmt::Display) -> LogError {
    LogError::Write {
        what: "foxglove",
        message: e.to_string(),
    }
}

/// Counts the channel subscriptions of WebSocket clients, to wait for a viewer.
#[derive(Debug, Default)]
struct Subscriptions {
    count: Mutex<(usize, Option<Instant>)>,
    changed: Condvar,
}

impl ServerListener for Subscriptions {
    fn on_subscribe(&self, _client: Client, _channel: ChannelView) {
        if let Ok(mut c) = self.count.lock() {
            *c = (c.0 + 1, Some(Instant::now()));
            self.changed.notify_all();
        }
    }
}

impl Subscriptions {
    /// Waits until a client has subscribed and no further subscription came for a moment
    /// (the Foxglove app subscribes to each panel's topics in a burst), or until `timeout`.
    /// True when a client subscribed.
    fn wait(&self, timeout: Duration) -> bool {
        const SETTLE: Duration = Duration::from_millis(500);
        let deadline = Instant::now() + timeout;
        let Ok(mut c) = self.count.lock() else {
            return false;
        };
        loop {
            let now = Instant::now();
            if let (n, Some(last)) = *c
                && n > 0
                && now >= last + SETTLE
            {
                return true;
            }
            if now >= deadline {
                return c.0 > 0;
            }
            let until = match c.1 {
                Some(last) => (last + SETTLE).min(deadline),
                None => deadline,
            };
            c = match self
                .changed
                .wait_timeout(c, until.saturating_duration_since(now))
            {
                Ok((guard, _)) => guard,
                Err(_) => return false,
            };
        }
    }
}

/// One channel per topic.
struct Channels {
    image: Channel<CompressedImage>,
    calibration: Channel<CameraCalibration>,
    pose: Channel<PoseInFrame>,
    tf: Channel<FrameTransforms>,
    trajectory: Channel<PosesInFrame>,
    points: Channel<PointCloud>,
    mesh: Channel<SceneUpdate>,
}

impl Channels {
    fn new(ctx: &Arc<Context>) -> Channels {
        Channels {
            image: ctx.channel_builder(topics::IMAGE).build(),
            calibration: ctx.channel_builder(topics::CALIBRATION).build(),
            pose: ctx.channel_builder(topics::POSE).build(),
            tf: ctx.channel_builder(topics::TF).build(),
            trajectory: ctx.channel_builder(topics::TRAJECTORY).build(),
            points: ctx.channel_builder(topics::POINTS).build(),
            mesh: ctx.channel_builder(topics::MESH).build(),
        }
    }
}

/// An open Foxglove log (MCAP file and/or live server).
pub struct FoxgloveLog {
    /// The channels and sinks belong to it: kept for as long as they are used.
    _context: Arc<Context>,
    channels: Channels,
    mcap: Option<(PathBuf, McapWriterHandle<BufWriter<File>>)>,
    /// The SDK's server on a loopback port, and the front viewers connect to.
    server: Option<(WebSocketServerHandle, FoxgloveFront)>,
    camera: PinholeCamera,
    /// The newest frame's (id, capture time in ns): what is not about a frame is logged then.
    now: (u64, u64),
    keyframes: KeyframeViews,
    trajectory_stale: bool,
    counts: LogCounts,
    mesh_updates: u64,
}

impl std::fmt::Debug for FoxgloveLog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FoxgloveLog")
            .field("mcap", &self.mcap.as_ref().map(|(p, _)| p))
            .field("server", &self.server.as_ref().map(|(_, f)| f.addr()))
            .field("counts", &self.counts)
            .finish()
    }
}

fn timestamp(ns: u64) -> Option<Timestamp> {
    let sec = u32::try_from(ns / 1_000_000_000).unwrap_or(u32::MAX);
    Some(Timestamp::new(sec, (ns % 1_000_000_000) as u32))
}

fn vector(t: [f64; 3]) -> Option<Vector3> {
    Some(Vector3 {
        x: t[0],
        y: t[1],
        z: t[2],
    })
}

fn quaternion(q: [f64; 4]) -> Option<Quaternion> {
    Some(Quaternion {
        x: q[0],
        y: q[1],
        z: q[2],
        w: q[3],
    })
}

fn fox_pose(p: &Pose) -> FoxPose {
    FoxPose {
        position: vector(p.t),
        orientation: quaternion(p.q),
    }
}

/// `map` (z up) from `world` (y down, z forward): a quarter turn about x.
fn map_from_world(ns: u64) -> FrameTransform {
    let h = std::f64::consts::FRAC_1_SQRT_2;
    FrameTransform {
        timestamp: timestamp(ns),
        parent_frame_id: "map".into(),
        child_frame_id: "world".into(),
        translation: vector([0.0; 3]),
        rotation: quaternion([-h, 0.0, 0.0, h]),
    }
}

fn block_id(index: [i32; 3]) -> String {
    format!("block_{}_{}_{}", index[0], index[1], index[2])
}

impl FoxgloveLog {
    /// Opens the sinks in `options` for a camera with these intrinsics; with a server and
    /// `wait_for_client`, returns once a client subscribed or the wait is over.
    pub fn open(options: &FoxgloveOptions, camera: &PinholeCamera) -> Result<Self, LogError> {
        let context = Context::new();
        let channels = Channels::new(&context);
        let mcap = match &options.mcap {
            Some(path) => {
                let create = |e: &dyn std::fmt::Display| LogError::Create {
                    what: "the MCAP file",
                    path: path.display().to_string(),
                    message: e.to_string(),
                };
                let file = File::create(path).map_err(|e| create(&e))?;
                // One compression thread: zstd's multi-threaded mode held 42 MB of buffers per
                // recording on 2 cores (heaptrack, `bench long`), and more with more cores,
                // for a log of a few MB a minute.
                let options = McapWriteOptions::default().compression_threads(0);
                let handle = context
                    .mcap_writer_with_options(options)
                    .create(BufWriter::new(file))
                    .map_err(|e| create(&e))?;
                Some((path.clone(), handle))
            }
            None => None,
        };
        let server = match options.serve {
            Some(addr) => {
                let failed = |e: &dyn std::fmt::Display| LogError::Create {
                    what: "the Foxglove WebSocket server on",
                    path: addr.to_string(),
                    message: e.to_string(),
                };
                let subscriptions = Arc::new(Subscriptions::default());
                let handle = context
                    .websocket_server()
                    .name("relfusion")
                    .bind("127.0.0.1", 0)
                    .listener(subscriptions.clone())
                    .start_blocking()
                    .map_err(|e| failed(&e))?;
                let front = FoxgloveFront::start(addr, handle.port()).map_err(|e| failed(&e))?;
                // The port is what a viewer needs first (port 0 picks one).
                eprintln!(
                    "{}",
                    serde_json::json!({ "foxglove": format!("ws://{}", front.addr()) })
                );
                if let Some(timeout) = options.wait_for_client {
                    subscriptions.wait(timeout);
                }
                Some((handle, front))
            }
            None => None,
        };
        Ok(FoxgloveLog {
            _context: context,
            channels,
            mcap,
            server,
            camera: *camera,
            now: (0, 0),
            keyframes: KeyframeViews::new(),
            trajectory_stale: false,
            counts: LogCounts::default(),
            mesh_updates: 0,
        })
    }

    /// Moves the log's clock forward to a frame (never back).
    fn advance(&mut self, frame_id: u64, seconds: f64) {
        if frame_id >= self.now.0 {
            self.now = (frame_id, nanos(seconds));
        }
    }

    fn calibration(&self) -> CameraCalibration {
        let c = &self.camera;
        CameraCalibration {
            timestamp: timestamp(self.now.1),
            frame_id: "camera".into(),
            width: c.width,
            height: c.height,
            // The images are logged as the camera took them: with its lens distortion.
            distortion_model: "plumb_bob".into(),
            d: c.distortion
                .map_or(vec![0.0; 5], |d| vec![d.k1, d.k2, d.p1, d.p2, d.k3]),
            k: vec![c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0],
            r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: vec![
                c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
            ],
        }
    }

    fn log_tf(&self, child: String, pose: &Pose) {
        let ns = self.now.1;
        let transforms = vec![
            map_from_world(ns),
            FrameTransform {
                timestamp: timestamp(ns),
                parent_frame_id: "world".into(),
                child_frame_id: child,
                translation: vector(pose.t),
                rotation: quaternion(pose.q),
            },
        ];
        self.channels
            .tf
            .log_with_time(&FrameTransforms { transforms }, ns);
    }

    fn log_points(&mut self, keyframe_id: u64) -> Result<(), LogError> {
        let ns = self.now.1;
        let Some(points) = self.keyframes.points_to_send(keyframe_id)? else {
            return Ok(());
        };
        let data: Vec<u8> = points
            .iter()
            .flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes()))
            .collect();
        let field = |name: &str, offset: u32| PackedElementField {
            name: name.into(),
            offset,
            r#type: NumericType::Float32 as i32,
        };
        self.channels.points.log_with_time(
            &PointCloud {
                timestamp: timestamp(ns),
                frame_id: format!("keyframe_{keyframe_id}"),
                pose: Some(fox_pose(&Pose::IDENTITY)),
                point_stride: 12,
                fields: vec![field("x", 0), field("y", 4), field("z", 8)],
                data: data.into(),
            },
            ns,
        );
        Ok(())
    }

    fn log_trajectory(&mut self) {
        if !self.trajectory_stale {
            return;
        }
        self.trajectory_stale = false;
        let ns = self.now.1;
        self.channels.trajectory.log_with_time(
            &PosesInFrame {
                timestamp: timestamp(ns),
                frame_id: "world".into(),
                poses: self.keyframes.poses().map(fox_pose).collect(),
            },
            ns,
        );
    }
}

fn unit_color(c: [u8; 3]) -> Color {
    Color {
        r: f64::from(c[0]) / 255.0,
        g: f64::from(c[1]) / 255.0,
        b: f64::from(c[2]) / 255.0,
        a: 1.0,
    }
}

fn scene_entity(block: &MeshBlockRef<'_>, ns: u64) -> SceneEntity {
    let colors = if block.colors.len() == block.positions.len() {
        block.colors.iter().map(|c| unit_color(*c)).collect()
    } else {
        Vec::new()
    };
    SceneEntity {
        timestamp: timestamp(ns),
        frame_id: "world".into(),
        id: block_id(block.index),
        triangles: vec![TriangleListPrimitive {
            pose: None,
            points: block
                .positions
                .iter()
                .map(|p| Point3 {
                    x: f64::from(p[0]),
                    y: f64::from(p[1]),
                    z: f64::from(p[2]),
                })
                .collect(),
            color: Some(unit_color([200, 200, 200])),
            colors,
            indices: block.indices.to_vec(),
        }],
        ..Default::default()
    }
}

impl SessionLog for FoxgloveLog {
    fn image(&mut self, frame_id: u64, timestamp_s: f64, encoded: &[u8]) -> Result<(), LogError> {
        self.advance(frame_id, timestamp_s);
        let ns = self.now.1;
        self.channels.image.log_with_time(
            &CompressedImage {
                timestamp: timestamp(ns),
                frame_id: "camera".into(),
                data: encoded.to_vec().into(),
                format: image_format(encoded).into(),
            },
            ns,
        );
        self.channels
            .calibration
            .log_with_time(&self.calibration(), ns);
        self.counts.images += 1;
        Ok(())
    }

    fn pose(&mut self, frame_id: u64, timestamp_s: f64, pose: &Pose) -> Result<(), LogError> {
        self.advance(frame_id, timestamp_s);
        let ns = self.now.1;
        self.channels.pose.log_with_time(
            &PoseInFrame {
                timestamp: timestamp(ns),
                frame_id: "world".into(),
                pose: Some(fox_pose(pose)),
            },
            ns,
        );
        self.log_tf("camera".into(), pose);
        // Keyframe changes come in bursts (a pose-graph pass moves many): the trajectory
        // goes out once per burst, with the next frame.
        self.log_trajectory();
        self.counts.poses += 1;
        Ok(())
    }

    fn keyframe(&mut self, keyframe_id: u64, pose: &Pose) -> Result<(), LogError> {
        self.log_tf(format!("keyframe_{keyframe_id}"), pose);
        self.trajectory_stale = true;
        if self.keyframes.set_pose(keyframe_id, pose) {
            self.log_points(keyframe_id)?;
        }
        Ok(())
    }

    fn keyframe_depth(&mut self, keyframe_id: u64, depth: &DepthRef<'_>) -> Result<(), LogError> {
        self.keyframes
            .set_points(keyframe_id, depth.points(POINTS_PER_KEYFRAME))?;
        self.log_points(keyframe_id)
    }

    fn mesh_update(
        &mut self,
        changed: &[MeshBlockRef<'_>],
        removed: &[[i32; 3]],
    ) -> Result<(), LogError> {
        let ns = self.now.1;
        let update = SceneUpdate {
            deletions: removed
                .iter()
                .map(|index| SceneEntityDeletion {
                    timestamp: timestamp(ns),
                    r#type: DeletionType::MatchingId as i32,
                    id: block_id(*index),
                })
                .collect(),
            entities: changed.iter().map(|b| scene_entity(b, ns)).collect(),
        };
        self.channels.mesh.log_with_time(&update, ns);
        self.counts.mesh_blocks_logged += changed.len() as u64;
        self.counts.mesh_blocks_cleared += removed.len() as u64;
        self.mesh_updates += 1;
        Ok(())
    }

    fn finish(mut self: Box<Self>) -> Result<serde_json::Value, LogError> {
        self.log_trajectory();
        self.counts.keyframes = self.keyframes.len() as u64;
        let mut out = serde_json::to_value(self.counts).map_err(write_error)?;
        out["mesh_updates"] = self.mesh_updates.into();
        if let Some((path, handle)) = self.mcap.take() {
            let mut file = handle.close().map_err(write_error)?;
            std::io::Write::flush(&mut file).map_err(write_error)?;
            out["mcap"] = path.display().to_string().into();
        }
        if let Some((server, front)) = self.server.take() {
            out["foxglove_port"] = front.addr().port().into();
            drop(front);
            // Stops accepting and closes the clients; the process's exit finishes it.
            drop(server.stop());
        }
        Ok(out)
    }
}

/// Parses `--foxglove`'s value: a port (served on 127.0.0.1: the protocol has no
/// authentication, so it stays on this machine unless an address is given) or `ADDR:PORT`.
pub fn parse_serve_address(value: &str) -> Result<SocketAddr, String> {
    if let Ok(port) = value.parse::<u16>() {
        return Ok(SocketAddr::from(([127, 0, 0, 1], port)));
    }
    value
        .parse::<SocketAddr>()
        .map_err(|_| format!("expected a port or ADDR:PORT, got {value:?}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serve_addresses_default_to_loopback() {
        assert_eq!(
            parse_serve_address("8765"),
            Ok("127.0.0.1:8765".parse().expect("addr"))
        );
        assert_eq!(
            parse_serve_address("0.0.0.0:9000"),
            Ok("0.0.0.0:9000".parse().expect("addr"))
        );
        assert!(parse_serve_address("localhost").is_err());
    }

    #[test]
    fn the_map_frame_turns_y_down_into_z_up() {
        let t = map_from_world(0);
        let q = t.rotation.expect("rotation");
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            q.w, q.x, q.y, q.z,
        ));
        // "Down" in the camera's world is −z in the map; "forward" is +y.
        let down = q * nalgebra::Vector3::new(0.0, 1.0, 0.0);
        let forward = q * nalgebra::Vector3::new(0.0, 0.0, 1.0);
        assert!((down - nalgebra::Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        assert!((forward - nalgebra::Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
    }
}
