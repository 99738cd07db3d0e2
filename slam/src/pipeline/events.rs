//! What the pipeline tells the world: one event stream per session.

use std::sync::Arc;

use crate::dense::{DenseKeyframe, DenseMode};
use crate::fusion::MeshDelta;
use crate::geometry::Sim3;
use crate::graph::KeyframeId;

/// Tracking state of one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackingState {
    /// The first frame: it became the first keyframe.
    Initializing,
    /// Tracked against the current keyframe.
    Tracking,
    /// Tracking failed; the pose is the last good one until relocalisation succeeds.
    Lost,
    /// Tracking had been lost and this frame was relocalised against an earlier keyframe.
    Relocalized,
}

/// The pose of one frame, as soon as it is tracked.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PoseEvent {
    /// The caller's id of the frame (`FrameInput::frame_id`; the pipeline's count when it
    /// gave none).
    pub frame_id: u64,
    pub timestamp: f64,
    /// Camera-to-world in the map's (monocular, arbitrary) scale, at the time of tracking; the
    /// back end may later move its keyframe (see [`Event::KeyframePoses`]).
    pub world_from_camera: Sim3,
    pub state: TrackingState,
    /// The keyframe this frame was tracked against (or became).
    pub keyframe_id: KeyframeId,
    pub is_keyframe: bool,
}

/// A keyframe's pose after a pose-graph optimisation.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct KeyframePose {
    pub keyframe_id: KeyframeId,
    /// The caller's id of the frame it was made from; `None` for a keyframe of the saved map
    /// an extending pipeline started from.
    pub frame_id: Option<u64>,
    pub timestamp: f64,
    pub world_from_keyframe: Sim3,
}

/// A keyframe was created.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct KeyframeEvent {
    pub keyframe_id: KeyframeId,
    /// The caller's id of the frame it was made from, as in [`PoseEvent::frame_id`].
    pub frame_id: u64,
    pub timestamp: f64,
    pub world_from_keyframe: Sim3,
}

/// Everything [`super::Pipeline::push`] can report.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Event {
    Pose(PoseEvent),
    Keyframe(KeyframeEvent),
    /// The back end optimised the pose graph: the current pose of every keyframe.
    KeyframePoses {
        poses: Vec<KeyframePose>,
    },
    /// The dense layer finished a keyframe: dense inverse depth and variance at the working
    /// resolution (320×240 by default) with the keyframe's pose (paper §III-D).
    KeyframeDensified {
        keyframe_id: KeyframeId,
        /// As in [`KeyframePose::frame_id`].
        frame_id: Option<u64>,
        timestamp: f64,
        mode: DenseMode,
        #[serde(skip)]
        keyframe: Arc<DenseKeyframe>,
    },
    /// The fused mesh changed: the blocks re-meshed since the last update (§III-F).
    MeshUpdated {
        revision: u64,
        #[serde(skip)]
        delta: Arc<MeshDelta>,
    },
}
