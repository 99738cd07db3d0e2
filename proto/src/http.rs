//! Contract 2: the JSON of the HTTP API (`/v1/...`), defined once for the server (which also
//! describes these types in its OpenAPI document, with the `openapi` feature) and the client.
//!
//! Requests are strict (unknown fields are refused); answers ignore fields they do not know,
//! so a newer server does not break an older client.

use serde::{Deserialize, Serialize};
#[cfg(feature = "openapi")]
use utoipa::ToSchema;

/// What a live session does when frames arrive faster than its pipeline processes them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum FramePolicy {
    /// Drop the oldest queued frame (counted in `frames_dropped`): a live camera wants the
    /// newest frames.
    #[default]
    DropOldest,
    /// The request waits until there is room: replays and uploads lose nothing.
    Wait,
}

/// Pinhole intrinsics of a session's camera, in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(deny_unknown_fields)]
pub struct CameraJson {
    #[cfg_attr(feature = "openapi", schema(exclusive_minimum = 0.0))]
    pub fx: f64,
    #[cfg_attr(feature = "openapi", schema(exclusive_minimum = 0.0))]
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Image width in pixels; width × height is also bounded by the server's
    /// `limits.max_image_pixels` (1920×1080 by default).
    #[cfg_attr(feature = "openapi", schema(minimum = 16, maximum = 8192))]
    #[serde(deserialize_with = "integral_u32")]
    pub width: u32,
    #[cfg_attr(feature = "openapi", schema(minimum = 16, maximum = 8192))]
    #[serde(deserialize_with = "integral_u32")]
    pub height: u32,
    /// OpenCV radial-tangential coefficients `[k1, k2, p1, p2, k3]`; absent for undistorted
    /// images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(min_items = 5, max_items = 5))]
    pub distortion: Option<[f64; 5]>,
}

/// The protobuf form of the same camera (the Zenoh `SessionConfig` of an HTTP-style request).
impl From<CameraJson> for crate::v1::Camera {
    fn from(c: CameraJson) -> Self {
        crate::v1::Camera {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            width: c.width,
            height: c.height,
            distortion: c
                .distortion
                .map(|[k1, k2, p1, p2, k3]| crate::v1::Distortion { k1, k2, p1, p2, k3 }),
        }
    }
}

/// A `u32` from any JSON number with an integral value: `640.0` is the integer 640 in JSON
/// Schema (the OpenAPI document's `integer`), so it is accepted as such.
fn integral_u32<'de, D: serde::Deserializer<'de>>(d: D) -> Result<u32, D::Error> {
    let v = f64::deserialize(d)?;
    if v.fract() == 0.0 && (0.0..=f64::from(u32::MAX)).contains(&v) {
        Ok(v as u32)
    } else {
        Err(serde::de::Error::custom(format!(
            "expected a non-negative integer, got {v}"
        )))
    }
}

/// `POST /v1/sessions`: a live session.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(deny_unknown_fields)]
pub struct CreateSession {
    /// The camera; required unless `ros2.camera_info_topic` gives it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraJson>,
    /// Partial pipeline configuration, nested JSON (`{"dense": {"enabled": false}}`): only
    /// the user settings anyone may set (README, "Configuration"), each within its values;
    /// keys not given keep their defaults, any other key is refused by name.
    #[serde(default, skip_serializing_if = "serde_json::Value::is_null")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<Object>))]
    pub config: serde_json::Value,
    /// Depth model: `"none"`, `"default"` (the server's model, if any) or the server model's
    /// name. Absent = `"default"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    #[serde(default)]
    pub policy: FramePolicy,
    /// Start in a saved map (`POST /v1/maps`) of the same camera instead of an empty one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map: Option<MapStart>,
    /// The session on ROS 2 (servers with `[ros2] enabled`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ros2: Option<Ros2Session>,
}

/// A session's ROS 2 side: rmw_zenoh's wire format on the server's Zenoh session. Topic names
/// are ROS 2 names inside the tenant's namespace `/relfusion/<tenant>` (a relative name is
/// resolved in it).
#[derive(Clone, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(deny_unknown_fields)]
pub struct Ros2Session {
    /// Publish the session's `pose`, `tf`, `path`, `points` and `mesh` under
    /// `/relfusion/<tenant>/<session>/`.
    #[serde(default)]
    pub publish: bool,
    /// Take the frames from this topic: `sensor_msgs/Image`, or `sensor_msgs/CompressedImage`
    /// when the name ends in `/compressed` (image_transport's convention).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_topic: Option<String>,
    /// The camera's `sensor_msgs/CameraInfo`: required with `image_topic` when `camera` is not
    /// given, and then read once when the session is created.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_info_topic: Option<String>,
}

/// What a session does with a saved map.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum MapMode {
    /// Every frame gets a pose in the map's frame (`tracking` / `relocalized`), or `lost` when
    /// it is not in the map; the map is not changed and nothing new is mapped.
    #[default]
    Localize,
    /// Frames are `lost` until one is found in the map; from there the session maps on, new
    /// keyframes linked to the old ones (loop closures across sessions), the old poses held.
    /// The session's map (save it with `POST /v1/maps`) and mesh hold the old keyframes and
    /// the new.
    Extend,
}

/// A session's saved map and mode.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(deny_unknown_fields)]
pub struct MapStart {
    /// The map's id (`m-` and 12 hex digits), one of the caller's.
    pub id: String,
    #[serde(default)]
    pub mode: MapMode,
}

/// `POST /v1/maps`: keep a finished session's map.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(deny_unknown_fields)]
pub struct SaveMap {
    /// The finished session (one of the caller's).
    pub session: String,
    /// A name to recognise it by (at most 128 characters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
}

/// A saved map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapInfo {
    /// `m-` and 12 random hex digits.
    pub id: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// The session it was made by.
    pub session: String,
    /// Seconds since the Unix epoch.
    pub created_unix: u64,
    pub keyframes: u64,
    /// The camera it serves (a session starting from it must use the same).
    pub camera: CameraJson,
    /// Its size on disk.
    pub bytes: u64,
    /// Its on-disk format version (docs/map-format.md).
    pub format_version: u32,
    /// `"metric"` when a metric depth prior anchored it (its unit is the metre; sessions that
    /// extend or localise in it report the same), else `"arbitrary"`.
    #[serde(default = "arbitrary_scale")]
    pub scale: String,
}

fn arbitrary_scale() -> String {
    "arbitrary".into()
}

/// `GET /v1/maps`: the caller's maps, oldest first.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct MapList {
    pub maps: Vec<MapInfo>,
}

/// Where a session's frames come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum SessionKind {
    /// Frames pushed by a client (HTTP, WebSocket, Zenoh).
    Live,
    /// An uploaded dataset.
    Upload,
}

/// Life cycle of a session.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
#[serde(rename_all = "snake_case")]
pub enum SessionState {
    /// An acknowledged upload waiting for a free session slot.
    Queued,
    /// Processing frames.
    Running,
    /// End of stream received: the remaining frames and the final optimisation run.
    Finishing,
    /// Done; results are final and downloadable.
    Finished,
    /// Stopped by an error (see `error`); results so far stay downloadable.
    Failed,
}

impl SessionState {
    /// Finished or failed: nothing will change any more.
    pub fn is_terminal(self) -> bool {
        matches!(self, SessionState::Finished | SessionState::Failed)
    }
}

/// How far a session is.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct Progress {
    /// Frames processed.
    pub processed: u64,
    /// Frames in the upload (`None` for live sessions).
    pub total: Option<u64>,
}

/// Everything the server reports about a session.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct SessionInfo {
    /// The session's id: `s-` and 12 random hex digits.
    pub id: String,
    pub kind: SessionKind,
    pub state: SessionState,
    /// Frames accepted (live) or read from the upload.
    pub frames_received: u64,
    /// Frames that went through the pipeline.
    pub frames_processed: u64,
    /// Frames dropped because the stream outran the pipeline (live, `drop_oldest`).
    pub frames_dropped: u64,
    /// Processed frames whose tracking was lost.
    pub frames_lost: u64,
    pub keyframes: u64,
    /// Keyframes the dense layer finished (`KeyframeDensified` events).
    pub keyframes_densified: u64,
    /// Revision of the last `MeshUpdate` (0 before the first fused keyframe).
    pub mesh_revision: u64,
    /// Triangles of the fused mesh so far.
    pub mesh_triangles: u64,
    /// `prior` (the paper's dense layer), `no_model` (no depth model: densified from the
    /// semi-dense depth alone, with edge-aware smoothness) or `off`.
    pub dense_mode: String,
    pub progress: Progress,
    /// Creation time, seconds since the Unix epoch.
    pub created_unix: u64,
    pub camera: CameraJson,
    /// The depth model in use (`"none"` without one).
    pub model: String,
    /// Why the session failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Why a session ended without a failure (idle, map limit), or what a finishing session
    /// waits for (disk space).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notice: Option<String>,
    /// Most keyframes the session's map may hold (`limits.max_keyframes`, or what its memory
    /// share allows); it finishes when it reaches them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_keyframes: Option<u64>,
    /// The saved map it started from, and the mode.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map: Option<MapStart>,
    /// The node it runs on (`[zenoh] node`): where the cluster placed it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node: Option<String>,
    /// Where a running mapping session's keyframes live (issue 37), updated at each keyframe.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory: Option<SessionMemory>,
    /// `"metric"` when a metric depth prior (or a metric map) makes the session's unit the
    /// metre, `"arbitrary"` otherwise (a monocular map's unit); absent until its pipeline
    /// starts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<String>,
}

/// Where a mapping session's keyframes and fusion data live: in full, compact in memory, or
/// spilled to the session's store.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct SessionMemory {
    /// Keyframes held in full (the working set: pyramids, tracking references).
    pub keyframes_resident: u64,
    /// Keyframes whose compact image and depth are spilled to the store.
    pub keyframes_spilled: u64,
    /// Bytes of keyframe data held in memory (compact, full and dense maps).
    pub keyframe_bytes: u64,
    /// Bytes written to the store so far (compressed).
    pub spilled_bytes: u64,
    /// TSDF blocks in memory.
    pub fusion_blocks: u64,
    /// TSDF blocks spilled to the store with their meshes (`fusion.resident_blocks`: a soft
    /// limit, the blocks the newest keyframe integrated into stay).
    #[serde(default)]
    pub fusion_blocks_spilled: u64,
    /// Spilled chunks of TSDF blocks read back so far.
    #[serde(default)]
    pub fusion_chunk_loads: u64,
    /// Fusion inputs spilled to the store (read back when their keyframe moves).
    pub fusion_inputs_spilled: u64,
    /// Block indices the fused keyframes keep (to take a keyframe out of the volume again
    /// when the pose graph moves it), and the bytes those lists hold (delta-coded).
    #[serde(default)]
    pub fusion_keyframe_blocks: u64,
    #[serde(default)]
    pub fusion_keyframe_block_bytes: u64,
    /// Blocks of the session's copy of the mesh (what downloads, results and map snapshots
    /// read) in memory.
    #[serde(default)]
    pub mesh_blocks: u64,
    /// Blocks of that copy spilled to the store with their meshes (past
    /// `fusion.resident_blocks`, the chunks changed least recently).
    #[serde(default)]
    pub mesh_blocks_spilled: u64,
    /// Pose-graph edges reaching past the working set (loop closures to old keyframes).
    pub far_edges: u64,
    /// Keyframes whose full constraint search waits because the back end fell behind.
    #[serde(default)]
    pub searches_deferred: u64,
    /// Deferred searches given up so far (the back end stayed behind; those keyframes keep
    /// their tracking edge and remain candidates of later searches).
    #[serde(default)]
    pub searches_given_up: u64,
    /// Pose-graph optimisations of the whole graph so far (the final one, and live passes whose
    /// new edges close a loop beyond the bounded neighbourhood).
    #[serde(default)]
    pub optimizations_full: u64,
    /// Live pose-graph optimisations bounded to the neighbourhood of what changed.
    #[serde(default)]
    pub optimizations_bounded: u64,
    /// Commands queued for the back end and not yet handled: how far behind it is (each holds
    /// a keyframe's compact form or depth update).
    #[serde(default)]
    pub backend_commands_waiting: u64,
    /// Times an old keyframe became the current one again instead of a new keyframe being
    /// made: a camera revisiting a place adds no keyframes for it.
    #[serde(default)]
    pub keyframes_reactivated: u64,
}

/// A pose in events: `world_from_camera` as translation, unit quaternion `[x, y, z, w]` and
/// Sim(3) scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct PoseJson {
    pub t: [f64; 3],
    pub q: [f64; 4],
    pub s: f64,
}

/// Answer to a successful create (live session or upload).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct CreatedSession {
    /// The new session's id (unguessable; use it in every `/v1/sessions/{id}` path).
    pub id: String,
    pub session: SessionInfo,
}

/// Every session the caller owns.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct SessionList {
    pub sessions: Vec<SessionInfo>,
}

/// A frame was accepted (queued for the pipeline).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct FrameAccepted {
    /// Index of the frame in the session (0 for the first accepted frame).
    pub frame_index: u64,
}

/// The body of every error response.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

/// What went wrong, for programs (`code`) and for people (`message`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(ToSchema))]
pub struct ErrorDetail {
    /// Stable code: `invalid_argument`, `unauthorized`, `forbidden`, `not_found`, `conflict`,
    /// `payload_too_large`, `unsupported_media_type`, `resource_exhausted`, `internal`.
    #[cfg_attr(feature = "openapi", schema(example = "invalid_argument"))]
    pub code: String,
    /// Says what was wrong and what to do about it.
    pub message: String,
}
