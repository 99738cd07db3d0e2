//! Streams a TUM-layout sequence to a live session, as a camera would, and collects what comes
//! back.
//!
//! The image files are sent as they are on disk (JPEG or PNG, the server decodes them), either
//! paced at `fps` (a live camera: frame `i` leaves at `i / fps` seconds after the first) or as
//! fast as the server takes them. Sending runs in its own task so poses are consumed while
//! frames are still going out; with the `wait` policy the server's back-pressure slows the
//! sender, never the receiver.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use relfusion_core::dataset::TumSequence;
use relfusion_core::geometry::PinholeCamera;
use relfusion_proto::v1::{
    KeyframeDepth, MeshUpdate, ServerMessage, Sim3Pose, TrackingState, server_message,
};
use serde::Serialize;
use serde_json::Value;
use tokio::sync::mpsc;

use crate::api::{Client, CreateSession, FramePolicy, SessionInfo};
use crate::error::ClientError;
use crate::link::SessionLink;
use crate::message::{end_of_stream, frame_message};
use crate::transport::{Transport, open_session};

/// When each frame is sent.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Pace {
    /// As fast as the server accepts: with [`FramePolicy::Wait`] every frame is processed at
    /// the server's speed (a recorded sequence as a batch).
    #[default]
    Fast,
    /// At the sequence's own timestamps, as the camera delivered them (a live replay).
    Timestamps,
    /// At a fixed rate, frames per second.
    Fps(f64),
}

impl Pace {
    /// When frame `i` with timestamp `t` is due, after the start; `first` is the first
    /// frame's timestamp. `None`: at once.
    fn due(&self, i: usize, t: f64, first: f64) -> Option<Duration> {
        match *self {
            Pace::Fast => None,
            Pace::Timestamps => Some(Duration::from_secs_f64((t - first).max(0.0))),
            Pace::Fps(fps) => Some(Duration::from_secs_f64(i as f64 / fps)),
        }
    }
}

/// How to stream a dataset.
#[derive(Clone, Debug, Default)]
pub struct StreamOptions {
    /// When frames are sent.
    pub pace: Pace,
    /// `drop_oldest` for a live camera, `wait` to have every frame processed.
    pub policy: FramePolicy,
    /// Partial pipeline config (JSON object), `null` for the defaults.
    pub config: Value,
    /// Depth model name for the server (`None`: its default).
    pub model: Option<String>,
    /// HTTP/WebSocket or Zenoh.
    pub transport: Transport,
    /// Send only the first N frames.
    pub max_frames: Option<usize>,
    /// Intrinsics to use instead of the dataset's own (calibration.txt or a TUM preset).
    pub camera: Option<PinholeCamera>,
    /// Start in this saved map (`POST /v1/maps`) instead of an empty one.
    pub map: Option<relfusion_proto::http::MapStart>,
}

/// A pose as the CLI prints it: `world_from_camera` = `s·R(q)·p + t`, `q` = (x, y, z, w).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PoseLine {
    pub frame_id: u64,
    pub timestamp: f64,
    pub t: [f64; 3],
    pub q: [f64; 4],
    pub s: f64,
    /// `initializing`, `tracking`, `lost` (or `unspecified`).
    pub state: &'static str,
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub is_keyframe: bool,
}

/// What happens during a stream, in order, for the caller to print or record.
#[derive(Clone, Debug)]
pub enum StreamEvent {
    /// The session exists (always first).
    Session { id: String },
    /// Frame `frame_id` left the client.
    Sent { frame_id: u64 },
    /// A frame's pose.
    Pose(PoseLine),
    /// A keyframe was created or moved; `depth` when the dense layer finished it.
    Keyframe {
        keyframe_id: u64,
        frame_id: u64,
        pose: PoseLine,
        depth: Option<Arc<KeyframeDepth>>,
    },
    /// The fused mesh changed: the blocks that changed or lost their surface.
    Mesh { update: Arc<MeshUpdate> },
    /// The server rejected something (the stream goes on).
    ServerError { code: i32, message: String },
}

/// The outcome of a stream.
#[derive(Clone, Debug, Serialize)]
pub struct StreamSummary {
    pub session_id: String,
    pub frames_sent: u64,
    pub poses_received: u64,
    pub keyframe_updates: u64,
    /// Dropped by the server's drop-oldest queue (from the session's info; 0 when unknown).
    pub frames_dropped: u64,
    /// Messages the server answered with an `Error`.
    pub server_errors: Vec<String>,
    pub wall_s: f64,
    /// The session at the end, when the server could be asked.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub info: Option<SessionInfo>,
}

/// Streams the sequence in `dir` to a new session and returns once the server has finished
/// the session and closed the stream. `on_event` sees every event as it happens.
pub async fn stream_dataset(
    client: &Client,
    dir: &Path,
    opts: &StreamOptions,
    mut on_event: impl FnMut(StreamEvent),
) -> Result<StreamSummary, ClientError> {
    if let Pace::Fps(fps) = opts.pace
        && !(fps.is_finite() && fps > 0.0)
    {
        return Err(ClientError::InvalidOption(format!(
            "fps must be positive, got {fps}"
        )));
    }
    let seq = TumSequence::open(dir, opts.camera)?;
    let n = opts.max_frames.unwrap_or(seq.len()).min(seq.len());
    let frames: Vec<(f64, PathBuf)> = seq.frames[..n]
        .iter()
        .map(|f| (f.timestamp, f.rgb.clone()))
        .collect();
    let req = CreateSession {
        // The dataset's calibration.txt wins inside `open`; an explicit override wins here.
        camera: Some(crate::api::camera_json(&opts.camera.unwrap_or(seq.camera))),
        config: opts.config.clone(),
        model: opts.model.clone(),
        policy: opts.policy,
        map: opts.map.clone(),
        ros2: None,
    };
    let t0 = Instant::now();
    let SessionLink {
        session_id,
        info: _,
        frames: frames_tx,
        mut updates,
        tasks: _tasks,
    } = open_session(client, &opts.transport, &req).await?;
    on_event(StreamEvent::Session {
        id: session_id.clone(),
    });

    let (sent_tx, mut sent_rx) = mpsc::unbounded_channel();
    let sender = tokio::spawn(send_frames(frames, opts.pace, frames_tx, sent_tx));
    let mut summary = StreamSummary {
        session_id: session_id.clone(),
        frames_sent: 0,
        poses_received: 0,
        keyframe_updates: 0,
        frames_dropped: 0,
        server_errors: Vec::new(),
        wall_s: 0.0,
        info: None,
    };
    loop {
        tokio::select! {
            // Report sends as they happen; `biased` keeps them ahead of the poses they cause.
            biased;
            Some(frame_id) = sent_rx.recv() => on_event(StreamEvent::Sent { frame_id }),
            update = updates.recv() => match update {
                Some(Ok(msg)) => handle_update(msg, &mut summary, &mut on_event),
                Some(Err(e)) => {
                    sender.abort();
                    return Err(e);
                }
                None => break,
            },
        }
    }
    while let Ok(frame_id) = sent_rx.try_recv() {
        on_event(StreamEvent::Sent { frame_id });
    }
    // The stream is closed, so the sender has nothing left to wait for.
    let sent = match tokio::time::timeout(Duration::from_secs(5), sender).await {
        Ok(Ok(result)) => result?,
        Ok(Err(join)) => return Err(ClientError::Protocol(format!("frame sender: {join}"))),
        Err(_) => {
            return Err(ClientError::Protocol(
                "the server closed the stream before all frames were sent".into(),
            ));
        }
    };
    summary.frames_sent = sent.frames;
    if !sent.ended {
        return Err(ClientError::Protocol(format!(
            "the server closed the stream after {} of {n} frames",
            sent.frames
        )));
    }
    summary.wall_s = t0.elapsed().as_secs_f64();
    // Counters live on the server; a Zenoh-only deployment may have no HTTP to ask.
    if let Ok(Ok(info)) =
        tokio::time::timeout(Duration::from_secs(10), client.session(&session_id)).await
    {
        summary.frames_dropped = info.frames_dropped;
        summary.info = Some(info);
    }
    Ok(summary)
}

/// What the sender task managed to send.
#[derive(Debug)]
struct Sent {
    frames: u64,
    /// The end-of-stream marker went out.
    ended: bool,
}

/// Sends every frame at its `pace`, then the end-of-stream marker. Stops early when the
/// transport is gone (the reader reports why).
async fn send_frames(
    frames: Vec<(f64, PathBuf)>,
    pace: Pace,
    tx: mpsc::Sender<relfusion_proto::v1::ClientMessage>,
    sent: mpsc::UnboundedSender<u64>,
) -> Result<Sent, ClientError> {
    let start = tokio::time::Instant::now();
    let first = frames.first().map_or(0.0, |f| f.0);
    let mut count = 0;
    for (i, (timestamp, path)) in frames.into_iter().enumerate() {
        let image = tokio::fs::read(&path)
            .await
            .map_err(|e| ClientError::io(&path, e))?;
        if let Some(due) = pace.due(i, timestamp, first) {
            tokio::time::sleep_until(start + due).await;
        }
        if tx
            .send(frame_message(i as u64, timestamp, image))
            .await
            .is_err()
        {
            return Ok(Sent {
                frames: count,
                ended: false,
            });
        }
        count += 1;
        let _ = sent.send(i as u64);
    }
    let ended = tx.send(end_of_stream()).await.is_ok();
    Ok(Sent {
        frames: count,
        ended,
    })
}

fn handle_update(
    msg: ServerMessage,
    summary: &mut StreamSummary,
    on_event: &mut impl FnMut(StreamEvent),
) {
    match msg.message {
        Some(server_message::Message::Pose(p)) => {
            summary.poses_received += 1;
            on_event(StreamEvent::Pose(PoseLine {
                frame_id: p.frame_id,
                timestamp: p.timestamp,
                is_keyframe: p.is_keyframe,
                ..pose_line(p.world_from_camera.as_ref(), p.tracking_state)
            }));
        }
        Some(server_message::Message::Keyframe(k)) => {
            summary.keyframe_updates += 1;
            on_event(StreamEvent::Keyframe {
                keyframe_id: k.keyframe_id,
                frame_id: k.frame_id,
                pose: PoseLine {
                    frame_id: k.frame_id,
                    timestamp: k.timestamp,
                    is_keyframe: true,
                    ..pose_line(k.world_from_camera.as_ref(), 0)
                },
                depth: k.depth.map(Arc::new),
            });
        }
        Some(server_message::Message::Mesh(m)) => {
            on_event(StreamEvent::Mesh {
                update: Arc::new(m),
            });
        }
        Some(server_message::Message::Error(e)) => {
            summary.server_errors.push(e.message.clone());
            on_event(StreamEvent::ServerError {
                code: e.code,
                message: e.message,
            });
        }
        None => {}
    }
}

/// The pose part of a [`PoseLine`] (ids and stamps are filled in by the caller).
pub fn pose_line(pose: Option<&Sim3Pose>, tracking_state: i32) -> PoseLine {
    let t = pose
        .and_then(|p| p.translation.as_ref())
        .map_or([0.0; 3], |v| [v.x, v.y, v.z]);
    let q = pose
        .and_then(|p| p.rotation.as_ref())
        .map_or([0.0, 0.0, 0.0, 1.0], |q| [q.x, q.y, q.z, q.w]);
    let state = match TrackingState::try_from(tracking_state) {
        Ok(TrackingState::Initializing) => "initializing",
        Ok(TrackingState::Tracking) => "tracking",
        Ok(TrackingState::Lost) => "lost",
        Ok(TrackingState::Unspecified) | Err(_) => "unspecified",
    };
    PoseLine {
        frame_id: 0,
        timestamp: 0.0,
        t,
        q,
        s: pose.map_or(1.0, |p| p.scale),
        state,
        is_keyframe: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relfusion_proto::v1::{PoseUpdate, Quaternion, Vector3};

    #[test]
    fn pace_sends_at_the_timestamps_a_rate_or_at_once() {
        let ms = |d: Option<Duration>| d.map(|d| d.as_millis());
        assert_eq!(ms(Pace::Timestamps.due(0, 10.0, 10.0)), Some(0));
        // A gap in the recording stays a gap; the frame index does not matter.
        assert_eq!(ms(Pace::Timestamps.due(1, 10.5, 10.0)), Some(500));
        assert_eq!(ms(Pace::Fps(20.0).due(3, 99.0, 10.0)), Some(150));
        assert_eq!(Pace::Fast.due(3, 99.0, 10.0), None);
        assert_eq!(Pace::default(), Pace::Fast);
    }

    #[test]
    fn pose_updates_become_pose_lines() {
        let mut summary = StreamSummary {
            session_id: "s".into(),
            frames_sent: 0,
            poses_received: 0,
            keyframe_updates: 0,
            frames_dropped: 0,
            server_errors: vec![],
            wall_s: 0.0,
            info: None,
        };
        let msg = ServerMessage {
            message: Some(server_message::Message::Pose(PoseUpdate {
                session_id: "s".into(),
                frame_id: 4,
                timestamp: 0.125,
                world_from_camera: Some(Sim3Pose {
                    translation: Some(Vector3 {
                        x: 1.0,
                        y: 2.0,
                        z: 3.0,
                    }),
                    rotation: Some(Quaternion {
                        x: 0.0,
                        y: 0.0,
                        z: 0.0,
                        w: 1.0,
                    }),
                    scale: 0.5,
                }),
                tracking_state: TrackingState::Tracking as i32,
                is_keyframe: false,
                keyframe_id: 0,
            })),
        };
        let mut seen = Vec::new();
        handle_update(msg, &mut summary, &mut |e| seen.push(e));
        assert_eq!(summary.poses_received, 1);
        let [StreamEvent::Pose(p)] = seen.as_slice() else {
            panic!("one pose event, got {seen:?}")
        };
        assert_eq!((p.frame_id, p.timestamp, p.s), (4, 0.125, 0.5));
        assert_eq!(p.t, [1.0, 2.0, 3.0]);
        assert_eq!(p.state, "tracking");
        let json = serde_json::to_value(p).expect("serialises");
        assert!(json.get("is_keyframe").is_none(), "only keyframes say so");
    }
}
