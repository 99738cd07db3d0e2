//! A session as ROS 2 topics: what a [`SessionLog`] is given, turned into CDR messages of
//! the standard types and handed to a [`Ros2Sink`] (the service's rmw_zenoh-compatible
//! publishers, or an MCAP file with the `ros2msg` schemas).
//!
//! Topics (relative names; the sink puts them in a namespace) and frames — the same as the
//! Foxglove channels: `map` is z-up, `world` the first camera's (x right, y down, z
//! forward), `camera` the camera's optical frame, `keyframe_<id>` each keyframe's:
//!
//! | topic | type | when |
//! |---|---|---|
//! | `pose` | `geometry_msgs/PoseStamped` (`world`) | every tracked frame |
//! | `tf` | `tf2_msgs/TFMessage` | every tracked frame: `map → world` (fixed), `world → camera`; every keyframe made or moved: `world → keyframe_<id>` |
//! | `path` | `nav_msgs/Path` (`world`) | the keyframes, once after each burst of keyframe changes (a pose-graph pass) |
//! | `points` | `sensor_msgs/PointCloud2` (`keyframe_<id>`) | a keyframe's dense depth; again when the pose graph rescales it |
//! | `mesh` | `visualization_msgs/MarkerArray` (`world`) | every mesh update: a `TRIANGLE_LIST` marker per changed block (namespace `block_x_y_z`, id 0, so it replaces the block's older one), `DELETE` for blocks that lost their surface |
//!
//! Stamps are the frames' capture times.

use std::collections::BTreeMap;

use super::msgs::{self, Marker, Rigid, Transform};
use super::types::{
    CAMERA_INFO, COMPRESSED_IMAGE, MARKER_ARRAY, PATH, POINT_CLOUD2, POSE_STAMPED, RosType,
    TF_MESSAGE,
};
use crate::clouds::KeyframeViews;
use crate::session_log::{
    DepthRef, LogCounts, LogError, MeshBlockRef, POINTS_PER_KEYFRAME, Pose, SessionLog, nanos,
};
use relfusion_core::geometry::PinholeCamera;

/// The topics of a session: what it computed ([`Topic::ALL`]) and, in a log that has them
/// (a recording of `relfusion stream` or `run`), the camera's images and calibration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Topic {
    Pose,
    Tf,
    Path,
    Points,
    Mesh,
    Image,
    CameraInfo,
}

impl Topic {
    /// What a session computed (the service's topics).
    pub const ALL: [Topic; 5] = [
        Topic::Pose,
        Topic::Tf,
        Topic::Path,
        Topic::Points,
        Topic::Mesh,
    ];

    /// The topic's name relative to the session's namespace.
    pub fn name(self) -> &'static str {
        match self {
            Topic::Pose => "pose",
            Topic::Tf => "tf",
            Topic::Path => "path",
            Topic::Points => "points",
            Topic::Mesh => "mesh",
            Topic::Image => "image/compressed",
            Topic::CameraInfo => "camera_info",
        }
    }

    pub fn ros_type(self) -> RosType {
        match self {
            Topic::Pose => POSE_STAMPED,
            Topic::Tf => TF_MESSAGE,
            Topic::Path => PATH,
            Topic::Points => POINT_CLOUD2,
            Topic::Mesh => MARKER_ARRAY,
            Topic::Image => COMPRESSED_IMAGE,
            Topic::CameraInfo => CAMERA_INFO,
        }
    }
}

/// Where a [`Ros2Log`]'s messages go.
pub trait Ros2Sink: std::fmt::Debug + Send {
    /// One CDR message (with its encapsulation header) of `topic`, stamped `stamp_ns`.
    fn publish(&mut self, topic: Topic, stamp_ns: u64, cdr: Vec<u8>) -> Result<(), LogError>;
}

/// A session's log as ROS 2 messages.
#[derive(Debug)]
pub struct Ros2Log<S: Ros2Sink> {
    sink: S,
    /// The newest frame's id and stamp.
    now: (u64, u64),
    keyframes: KeyframeViews,
    path_stale: bool,
    counts: LogCounts,
    mesh_updates: u64,
    messages: BTreeMap<Topic, u64>,
    /// With a camera, images go out (with its calibration); without, they stay with their
    /// sender.
    camera: Option<PinholeCamera>,
}

fn rigid(p: &Pose) -> Rigid {
    Rigid { t: p.t, q: p.q }
}

fn block_ns(index: [i32; 3]) -> String {
    format!("block_{}_{}_{}", index[0], index[1], index[2])
}

/// `map` (z up) from `world` (y down, z forward): a quarter turn about x.
fn map_from_world(stamp_ns: u64) -> Transform {
    let h = std::f64::consts::FRAC_1_SQRT_2;
    Transform {
        stamp_ns,
        parent: "map".into(),
        child: "world".into(),
        rigid: Rigid {
            t: [0.0; 3],
            q: [-h, 0.0, 0.0, h],
        },
    }
}

impl<S: Ros2Sink> Ros2Log<S> {
    pub fn new(sink: S) -> Self {
        Ros2Log {
            sink,
            now: (0, 0),
            keyframes: KeyframeViews::new(),
            path_stale: false,
            counts: LogCounts::default(),
            mesh_updates: 0,
            messages: BTreeMap::new(),
            camera: None,
        }
    }

    /// A log that also sends the images, as `sensor_msgs/CompressedImage` with the camera's
    /// `sensor_msgs/CameraInfo` (its lens distortion as `plumb_bob`).
    pub fn with_images(sink: S, camera: &PinholeCamera) -> Self {
        Ros2Log {
            camera: Some(*camera),
            ..Self::new(sink)
        }
    }

    /// The sink, for a caller that collects the messages and sends them itself.
    pub fn sink_mut(&mut self) -> &mut S {
        &mut self.sink
    }

    /// Sends what waits for the next frame (the path after keyframe changes): before the end.
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.send_path()
    }

    fn send(&mut self, topic: Topic, cdr: Vec<u8>) -> Result<(), LogError> {
        self.sink.publish(topic, self.now.1, cdr)?;
        *self.messages.entry(topic).or_default() += 1;
        Ok(())
    }

    fn send_tf(&mut self, child: String, pose: &Pose) -> Result<(), LogError> {
        let ns = self.now.1;
        let transforms = [
            map_from_world(ns),
            Transform {
                stamp_ns: ns,
                parent: "world".into(),
                child,
                rigid: rigid(pose),
            },
        ];
        self.send(Topic::Tf, msgs::tf_message(&transforms))
    }

    fn send_path(&mut self) -> Result<(), LogError> {
        if !self.path_stale {
            return Ok(());
        }
        self.path_stale = false;
        let ns = self.now.1;
        let poses: Vec<(u64, Rigid)> = self.keyframes.poses().map(|p| (ns, rigid(p))).collect();
        self.send(Topic::Path, msgs::path(ns, "world", &poses))
    }

    fn send_points(&mut self, keyframe_id: u64) -> Result<(), LogError> {
        let Some(points) = self.keyframes.points_to_send(keyframe_id)? else {
            return Ok(());
        };
        let cdr = msgs::point_cloud2(self.now.1, &format!("keyframe_{keyframe_id}"), &points);
        self.send(Topic::Points, cdr)
    }

    fn advance(&mut self, frame_id: u64, seconds: f64) {
        if frame_id >= self.now.0 {
            self.now = (frame_id, nanos(seconds));
        }
    }
}

impl<S: Ros2Sink> SessionLog for Ros2Log<S> {
    fn image(&mut self, frame_id: u64, timestamp: f64, encoded: &[u8]) -> Result<(), LogError> {
        self.advance(frame_id, timestamp);
        let Some(c) = self.camera else {
            return Ok(());
        };
        let ns = self.now.1;
        let format = crate::session_log::image_format(encoded);
        self.send(
            Topic::Image,
            msgs::compressed_image(ns, "camera", format, encoded),
        )?;
        let d = c
            .distortion
            .map_or([0.0; 5], |d| [d.k1, d.k2, d.p1, d.p2, d.k3]);
        let info =
            msgs::camera::camera_info(ns, "camera", c.width, c.height, [c.fx, c.fy, c.cx, c.cy], d);
        self.send(Topic::CameraInfo, info)?;
        self.counts.images += 1;
        Ok(())
    }

    fn pose(&mut self, frame_id: u64, timestamp: f64, pose: &Pose) -> Result<(), LogError> {
        self.advance(frame_id, timestamp);
        self.send(
            Topic::Pose,
            msgs::pose_stamped(self.now.1, "world", &rigid(pose)),
        )?;
        self.send_tf("camera".into(), pose)?;
        // Keyframe changes come in bursts (a pose-graph pass moves many): the path goes out
        // once per burst, with the next frame.
        self.send_path()?;
        self.counts.poses += 1;
        Ok(())
    }

    fn keyframe(&mut self, keyframe_id: u64, pose: &Pose) -> Result<(), LogError> {
        self.send_tf(format!("keyframe_{keyframe_id}"), pose)?;
        self.path_stale = true;
        if self.keyframes.set_pose(keyframe_id, pose) {
            self.send_points(keyframe_id)?;
        }
        Ok(())
    }

    fn keyframe_depth(&mut self, keyframe_id: u64, depth: &DepthRef<'_>) -> Result<(), LogError> {
        self.keyframes
            .set_points(keyframe_id, depth.points(POINTS_PER_KEYFRAME))?;
        self.send_points(keyframe_id)
    }

    fn mesh_update(
        &mut self,
        changed: &[MeshBlockRef<'_>],
        removed: &[[i32; 3]],
    ) -> Result<(), LogError> {
        let names: Vec<String> = changed
            .iter()
            .map(|b| block_ns(b.index))
            .chain(removed.iter().map(|i| block_ns(*i)))
            .collect();
        let markers: Vec<Marker<'_>> = changed
            .iter()
            .zip(&names)
            .map(|(b, ns)| Marker::Triangles {
                ns,
                positions: b.positions,
                colors: b.colors,
                indices: b.indices,
            })
            .chain(
                names[changed.len()..]
                    .iter()
                    .map(|ns| Marker::Delete { ns }),
            )
            .collect();
        let cdr = msgs::marker_array(self.now.1, "world", &markers);
        self.send(Topic::Mesh, cdr)?;
        self.counts.mesh_blocks_logged += changed.len() as u64;
        self.counts.mesh_blocks_cleared += removed.len() as u64;
        self.mesh_updates += 1;
        Ok(())
    }

    fn finish(mut self: Box<Self>) -> Result<serde_json::Value, LogError> {
        self.flush()?;
        self.counts.keyframes = self.keyframes.len() as u64;
        let mut out = serde_json::to_value(self.counts).map_err(|e| LogError::Write {
            what: "ROS 2 counts",
            message: e.to_string(),
        })?;
        out["mesh_updates"] = self.mesh_updates.into();
        out["messages"] = self
            .messages
            .iter()
            .map(|(t, n)| (t.name().to_string(), serde_json::Value::from(*n)))
            .collect::<serde_json::Map<_, _>>()
            .into();
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Default)]
    struct Collect(Vec<(Topic, u64, Vec<u8>)>);

    impl Ros2Sink for &mut Collect {
        fn publish(&mut self, topic: Topic, stamp: u64, cdr: Vec<u8>) -> Result<(), LogError> {
            self.0.push((topic, stamp, cdr));
            Ok(())
        }
    }

    #[test]
    fn paths_go_out_once_per_burst_and_rescaled_points_again() {
        let mut out = Collect::default();
        let mut log = Box::new(Ros2Log::new(&mut out));
        log.pose(1, 0.5, &Pose::IDENTITY).expect("pose");
        log.keyframe(0, &Pose::IDENTITY).expect("kf");
        let idepth = vec![0.5f32; 16 * 16];
        let depth = DepthRef {
            width: 16,
            height: 16,
            inverse_depth: &idepth,
            fx: 10.0,
            fy: 10.0,
            cx: 8.0,
            cy: 8.0,
        };
        log.keyframe_depth(0, &depth).expect("depth");
        log.keyframe(1, &Pose::IDENTITY).expect("kf");
        log.keyframe(
            0,
            &Pose {
                s: 1.5,
                ..Pose::IDENTITY
            },
        )
        .expect("moved");
        log.pose(2, 1.0, &Pose::IDENTITY).expect("pose");
        log.mesh_update(&[], &[[1, 2, 3]]).expect("mesh");
        let counts = log.finish().expect("finish");
        let topics: Vec<&str> = out.0.iter().map(|(t, _, _)| t.name()).collect();
        assert_eq!(
            topics,
            [
                "pose", "tf", "tf", "points", "tf", "tf", "points", "pose", "tf", "path", "mesh"
            ],
            "one path for three keyframe changes; points again after the rescale"
        );
        assert_eq!(out.0[7].1, 1_000_000_000, "stamped with the frame's time");
        assert_eq!(counts["messages"]["tf"], 5);
        assert_eq!(counts["keyframes"], 2);
    }
}
