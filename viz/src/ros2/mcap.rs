//! A session as a ROS 2 bag: an MCAP file with `ros2msg` schemas and CDR messages, what
//! `ros2 bag record -s mcap` writes, so `ros2 bag play` replays it to ROS 2 nodes and
//! Foxglove opens it (`relfusion stream|run --mcap-ros2 FILE`).
//!
//! Topics: `/camera/image/compressed`, `/camera/camera_info`, `/tf`, and the session's
//! `/relfusion/pose`, `/relfusion/path`, `/relfusion/points`, `/relfusion/mesh`
//! ([`super::log`] says what each carries and when). Log times are the frames' capture times.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use relfusion_core::geometry::PinholeCamera;

use super::log::{Ros2Log, Ros2Sink, Topic};
use crate::session_log::{DepthRef, LogError, MeshBlockRef, Pose, SessionLog};

/// The topic of `topic` in a bag.
pub fn bag_topic(topic: Topic) -> String {
    match topic {
        Topic::Tf => "/tf".into(),
        Topic::Image | Topic::CameraInfo => format!("/camera/{}", topic.name()),
        other => format!("/relfusion/{}", other.name()),
    }
}

/// Writes the messages of a [`super::Ros2Log`] into an MCAP file.
pub struct McapSink {
    writer: Option<mcap::Writer<BufWriter<File>>>,
    channels: BTreeMap<Topic, u16>,
    sequence: u32,
    path: String,
}

impl std::fmt::Debug for McapSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("McapSink")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

fn write_error(e: impl std::fmt::Display) -> LogError {
    LogError::Write {
        what: "the ROS 2 MCAP recording",
        message: e.to_string(),
    }
}

impl McapSink {
    pub fn create(path: &Path) -> Result<Self, LogError> {
        let create = |e: &dyn std::fmt::Display| LogError::Create {
            what: "ROS 2 MCAP recording",
            path: path.display().to_string(),
            message: e.to_string(),
        };
        let file = File::create(path).map_err(|e| create(&e))?;
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .create(BufWriter::new(file))
            .map_err(|e| create(&e))?;
        Ok(McapSink {
            writer: Some(writer),
            channels: BTreeMap::new(),
            sequence: 0,
            path: path.display().to_string(),
        })
    }

    /// Writes the summary and closes the file.
    pub fn close(&mut self) -> Result<(), LogError> {
        if let Some(mut writer) = self.writer.take() {
            writer.finish().map_err(write_error)?;
        }
        Ok(())
    }
}

impl Ros2Sink for McapSink {
    fn publish(&mut self, topic: Topic, stamp_ns: u64, cdr: Vec<u8>) -> Result<(), LogError> {
        let Some(writer) = self.writer.as_mut() else {
            return Err(write_error("already closed"));
        };
        let channel = match self.channels.get(&topic) {
            Some(id) => *id,
            None => {
                let ty = topic.ros_type();
                let schema = writer
                    .add_schema(ty.name(), "ros2msg", ty.msg_definition().as_bytes())
                    .map_err(write_error)?;
                let id = writer
                    .add_channel(schema, &bag_topic(topic), "cdr", &BTreeMap::new())
                    .map_err(write_error)?;
                self.channels.insert(topic, id);
                id
            }
        };
        self.sequence = self.sequence.wrapping_add(1);
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: self.sequence,
                    log_time: stamp_ns,
                    publish_time: stamp_ns,
                },
                &cdr,
            )
            .map_err(write_error)
    }
}

impl Drop for McapSink {
    fn drop(&mut self) {
        let _ = self.close();
    }
}

/// A session's ROS 2 bag: a [`Ros2Log`] with images into an [`McapSink`], closed (and its
/// errors reported) when it finishes.
#[derive(Debug)]
pub struct Ros2Bag {
    log: Ros2Log<McapSink>,
}

impl Ros2Bag {
    pub fn create(path: &Path, camera: &PinholeCamera) -> Result<Self, LogError> {
        Ok(Ros2Bag {
            log: Ros2Log::with_images(McapSink::create(path)?, camera),
        })
    }
}

impl SessionLog for Ros2Bag {
    fn image(&mut self, frame_id: u64, timestamp: f64, encoded: &[u8]) -> Result<(), LogError> {
        self.log.image(frame_id, timestamp, encoded)
    }

    fn pose(&mut self, frame_id: u64, timestamp: f64, pose: &Pose) -> Result<(), LogError> {
        self.log.pose(frame_id, timestamp, pose)
    }

    fn keyframe(&mut self, keyframe_id: u64, pose: &Pose) -> Result<(), LogError> {
        self.log.keyframe(keyframe_id, pose)
    }

    fn keyframe_depth(&mut self, keyframe_id: u64, depth: &DepthRef<'_>) -> Result<(), LogError> {
        self.log.keyframe_depth(keyframe_id, depth)
    }

    fn mesh_update(
        &mut self,
        changed: &[MeshBlockRef<'_>],
        removed: &[[i32; 3]],
    ) -> Result<(), LogError> {
        self.log.mesh_update(changed, removed)
    }

    fn finish(mut self: Box<Self>) -> Result<serde_json::Value, LogError> {
        self.log.flush()?;
        let sink = self.log.sink_mut();
        sink.close()?;
        let path = sink.path.clone();
        let mut counts = Box::new(self.log).finish()?;
        counts["mcap_ros2"] = path.into();
        Ok(counts)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bag_has_a_schema_and_channel_per_topic() {
        let path = std::env::temp_dir().join(format!("relfusion-bag-{}.mcap", std::process::id()));
        let camera = PinholeCamera::new(100.0, 100.0, 32.0, 24.0, 64, 48).expect("camera");
        let mut bag = Box::new(Ros2Bag::create(&path, &camera).expect("create"));
        bag.image(0, 1.0, b"\x89PNG\r\n\x1a\n").expect("image");
        bag.pose(0, 1.0, &Pose::IDENTITY).expect("pose");
        bag.keyframe(0, &Pose::IDENTITY).expect("keyframe");
        let counts = bag.finish().expect("finish");
        assert_eq!(counts["messages"]["pose"], 1);
        let bytes = std::fs::read(&path).expect("read");
        let mut topics = BTreeMap::new();
        for message in mcap::MessageStream::new(&bytes).expect("MCAP") {
            let message = message.expect("message");
            let schema = message.channel.schema.as_ref().expect("schema");
            assert_eq!(schema.encoding, "ros2msg");
            assert_eq!(message.channel.message_encoding, "cdr");
            *topics.entry(message.channel.topic.clone()).or_insert(0) += 1;
        }
        let _ = std::fs::remove_file(&path);
        let names: Vec<&str> = topics.keys().map(String::as_str).collect();
        assert_eq!(
            names,
            [
                "/camera/camera_info",
                "/camera/image/compressed",
                "/relfusion/path",
                "/relfusion/pose",
                "/tf"
            ]
        );
        assert_eq!(topics["/tf"], 2, "the camera's and the keyframe's");
    }
}
