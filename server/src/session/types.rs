//! The plain data of sessions: what a client sends to create one and what the server reports
//! about it. These types are the JSON of the HTTP API (and are described in its OpenAPI).

use relfusion_slam::geometry::{Distortion, PinholeCamera};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::ApiError;

/// A session id: `s-` and 12 random hex digits.
pub type SessionId = String;

/// Who owns a session: the name of the bearer token that created it (`None` when auth is off).
/// A token sees only its own sessions.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Owner(pub Option<String>);

impl Owner {
    /// The owner's Zenoh tenant (`relfusion/tenants/<tenant>/…`): its token name, or the
    /// public tenant when auth is off.
    pub fn tenant(&self) -> &str {
        self.0
            .as_deref()
            .unwrap_or(relfusion_proto::zenoh_keys::PUBLIC_TENANT)
    }
}

/// What a live session does when frames arrive faster than its pipeline processes them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
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
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CameraJson {
    #[schema(exclusive_minimum = 0.0)]
    pub fx: f64,
    #[schema(exclusive_minimum = 0.0)]
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Image width in pixels; width × height is also bounded by the server's
    /// `limits.max_image_pixels` (1920×1080 by default).
    #[schema(minimum = 16, maximum = 8192)]
    #[serde(deserialize_with = "integral_u32")]
    pub width: u32,
    #[schema(minimum = 16, maximum = 8192)]
    #[serde(deserialize_with = "integral_u32")]
    pub height: u32,
    /// OpenCV radial-tangential coefficients `[k1, k2, p1, p2, k3]`; absent for undistorted
    /// images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(min_items = 5, max_items = 5)]
    pub distortion: Option<[f64; 5]>,
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

/// Smallest and largest accepted image side: below 16 pixels the 5-level pyramid has no
/// pixels left; the area is bounded separately (`limits.max_image_pixels`).
pub const IMAGE_SIDE_RANGE: std::ops::RangeInclusive<u32> = 16..=8192;

impl CameraJson {
    /// The validated camera: finite values, `fx, fy > 0`, sides within [`IMAGE_SIDE_RANGE`].
    pub fn to_camera(&self) -> Result<PinholeCamera, ApiError> {
        for (name, side) in [("width", self.width), ("height", self.height)] {
            if !IMAGE_SIDE_RANGE.contains(&side) {
                return Err(ApiError::bad_request(format!(
                    "camera.{name} must be within {}..={} pixels, got {side}",
                    IMAGE_SIDE_RANGE.start(),
                    IMAGE_SIDE_RANGE.end()
                )));
            }
        }
        let camera =
            PinholeCamera::new(self.fx, self.fy, self.cx, self.cy, self.width, self.height)
                .map_err(|e| ApiError::bad_request(format!("camera: {e}")))?;
        match self.distortion {
            Some([k1, k2, p1, p2, k3]) => camera
                .with_distortion(Distortion::new(k1, k2, p1, p2, k3))
                .map_err(|e| ApiError::bad_request(format!("camera: {e}"))),
            None => Ok(camera),
        }
    }

    /// The JSON form of `camera`.
    pub fn from_camera(camera: &PinholeCamera) -> Self {
        Self {
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            width: camera.width,
            height: camera.height,
            distortion: camera.distortion.map(|d| [d.k1, d.k2, d.p1, d.p2, d.k3]),
        }
    }
}

/// `POST /v1/sessions`: a live session.
#[derive(Clone, Debug, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateSession {
    pub camera: CameraJson,
    /// Partial pipeline configuration (sections `pipeline`, `tracking`, `mapping`,
    /// `backend`); keys not given keep their defaults, unknown keys are rejected.
    #[serde(default)]
    #[schema(value_type = Option<Object>)]
    pub config: serde_json::Value,
    /// Depth model: `"none"`, `"default"` (the server's model, if any) or the server model's
    /// name. Absent = `"default"`.
    #[serde(default)]
    pub model: Option<String>,
    #[serde(default)]
    pub policy: FramePolicy,
}

/// One frame pushed into a live session.
#[derive(Clone, Debug)]
pub struct FrameData {
    /// The client's id for the frame (strictly increasing); `None` = the server numbers
    /// frames 0, 1, 2, …
    pub frame_id: Option<u64>,
    /// Capture time in seconds.
    pub timestamp: f64,
    /// A JPEG or PNG (recognised from its first bytes).
    pub bytes: bytes::Bytes,
}

/// Where a session's frames come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum SessionKind {
    /// Frames pushed by a client (HTTP, WebSocket, Zenoh).
    Live,
    /// An uploaded dataset.
    Upload,
}

/// Life cycle of a session.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
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
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct Progress {
    /// Frames processed.
    pub processed: u64,
    /// Frames in the upload (`None` for live sessions).
    pub total: Option<u64>,
}

/// Everything the server reports about a session.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct SessionInfo {
    pub id: SessionId,
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
}

/// The dense layer's mode for a session's config and model (`SessionInfo::dense_mode`).
pub fn dense_mode(config: &relfusion_slam::pipeline::Config, model: &str) -> String {
    match (config.dense.enabled, model) {
        (false, _) => "off",
        (true, "none") => "no_model",
        (true, _) => "prior",
    }
    .to_string()
}

/// A pose in events: `world_from_camera` as translation, unit quaternion `[x, y, z, w]` and
/// Sim(3) scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct PoseJson {
    pub t: [f64; 3],
    pub q: [f64; 4],
    pub s: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> CameraJson {
        CameraJson {
            fx: 300.0,
            fy: 300.0,
            cx: 160.0,
            cy: 120.0,
            width: 320,
            height: 240,
            distortion: None,
        }
    }

    #[test]
    fn camera_validation() {
        assert!(cam().to_camera().is_ok());
        for bad in [
            CameraJson { fx: 0.0, ..cam() },
            CameraJson { fy: -1.0, ..cam() },
            CameraJson {
                cx: f64::NAN,
                ..cam()
            },
            CameraJson { width: 8, ..cam() },
            CameraJson {
                height: 9000,
                ..cam()
            },
            CameraJson {
                distortion: Some([f64::INFINITY, 0.0, 0.0, 0.0, 0.0]),
                ..cam()
            },
        ] {
            let e = bad.to_camera().expect_err("invalid camera accepted");
            assert_eq!(e.status, 400, "{e}");
        }
        let with = CameraJson {
            distortion: Some([0.1, 0.0, 0.0, 0.0, 0.0]),
            ..cam()
        };
        assert_eq!(
            CameraJson::from_camera(&with.to_camera().expect("valid")),
            with
        );
    }

    #[test]
    fn create_session_rejects_unknown_fields_and_defaults_the_rest() {
        let ok: CreateSession = serde_json::from_value(serde_json::json!({
            "camera": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 16, "height": 16}
        }))
        .expect("parse");
        assert_eq!(ok.policy, FramePolicy::DropOldest);
        assert!(ok.config.is_null());
        let bad = serde_json::from_value::<CreateSession>(serde_json::json!({
            "camera": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 16, "height": 16},
            "polcy": "wait"
        }));
        assert!(bad.is_err());
    }
}
