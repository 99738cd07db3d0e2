//! The plain data of sessions: the typed request the service edge parses a create request
//! into, and the checks and conversions between the JSON of the HTTP API (defined once, in
//! `relfusion_proto::http`) and the pipeline's types.

use relfusion_proto::http::MapStart;
use relfusion_slam::geometry::{Distortion, PinholeCamera, Sim3};
use serde::{Deserialize, Serialize};

pub use relfusion_proto::http::{
    CameraJson, CreateSession, FramePolicy, PoseJson, Progress, SessionInfo, SessionKind,
    SessionState,
};

use crate::ApiError;

/// A session id: `s-` and 24 random hex digits.
pub type SessionId = String;

/// Whether `id` has the form of a session id (checked before one from another node names a
/// store key).
pub fn valid_session_id(id: &str) -> bool {
    id.len() == 26
        && id.starts_with("s-")
        && id[2..]
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

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

/// Smallest and largest accepted image side: below 16 pixels the 5-level pyramid has no
/// pixels left; the area is bounded separately (`limits.max_image_pixels`).
pub const IMAGE_SIDE_RANGE: std::ops::RangeInclusive<u32> = 16..=8192;

/// The one camera check of the service edge (HTTP JSON, protobuf, stored metadata): finite
/// values, `fx, fy > 0`, sides within [`IMAGE_SIDE_RANGE`], a finite distortion.
pub fn checked_camera(
    [fx, fy, cx, cy]: [f64; 4],
    width: u32,
    height: u32,
    distortion: Option<[f64; 5]>,
) -> Result<PinholeCamera, ApiError> {
    for (name, side) in [("width", width), ("height", height)] {
        if !IMAGE_SIDE_RANGE.contains(&side) {
            return Err(ApiError::bad_request(format!(
                "camera.{name} must be within {}..={} pixels, got {side}",
                IMAGE_SIDE_RANGE.start(),
                IMAGE_SIDE_RANGE.end()
            )));
        }
    }
    let camera = PinholeCamera::new(fx, fy, cx, cy, width, height)
        .map_err(|e| ApiError::bad_request(format!("camera: {e}")))?;
    match distortion {
        Some([k1, k2, p1, p2, k3]) => camera
            .with_distortion(Distortion::new(k1, k2, p1, p2, k3))
            .map_err(|e| ApiError::bad_request(format!("camera: {e}"))),
        None => Ok(camera),
    }
}

/// The validated camera of the API's JSON ([`checked_camera`]).
pub fn camera_from_json(c: &CameraJson) -> Result<PinholeCamera, ApiError> {
    checked_camera([c.fx, c.fy, c.cx, c.cy], c.width, c.height, c.distortion)
}

/// The JSON form of `camera`.
pub fn camera_json(camera: &PinholeCamera) -> CameraJson {
    CameraJson {
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
        width: camera.width,
        height: camera.height,
        distortion: camera.distortion.map(|d| [d.k1, d.k2, d.p1, d.p2, d.k3]),
    }
}

/// Serde of a [`PinholeCamera`] in the [`CameraJson`] layout, validated on the way in (the
/// stored session metadata).
pub mod camera_as_json {
    use super::{CameraJson, PinholeCamera, camera_from_json, camera_json};
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(camera: &PinholeCamera, s: S) -> Result<S::Ok, S::Error> {
        camera_json(camera).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<PinholeCamera, D::Error> {
        camera_from_json(&CameraJson::deserialize(d)?)
            .map_err(|e| serde::de::Error::custom(e.message))
    }
}

/// A live session's creation request, parsed once at the edge (HTTP [`CreateSession`] or
/// Zenoh `SessionConfig`): what the manager works with.
#[derive(Clone, Debug)]
pub struct SessionRequest {
    pub camera: PinholeCamera,
    /// The resolved pipeline configuration.
    pub config: relfusion_slam::pipeline::Config,
    /// Depth model name (`None` = the server's default).
    pub model: Option<String>,
    pub policy: FramePolicy,
    /// The saved map to start in (checked against the owner's maps by the manager).
    pub map: Option<MapStart>,
}

impl SessionRequest {
    /// The typed form of an HTTP create request: the camera validated, the overrides merged
    /// over the defaults of a live session with its policy.
    pub fn from_http(req: CreateSession) -> Result<Self, ApiError> {
        Ok(Self {
            map: req.map,
            ..Self::live(
                camera_from_json(&req.camera)?,
                &req.config,
                req.model,
                req.policy,
            )?
        })
    }

    /// A live session's request: `overrides` (a partial config, `null` for none) merged over
    /// the live defaults for `policy`.
    pub fn live(
        camera: PinholeCamera,
        overrides: &serde_json::Value,
        model: Option<String>,
        policy: FramePolicy,
    ) -> Result<Self, ApiError> {
        Ok(Self {
            camera,
            config: super::overrides::live_config(overrides, policy)?,
            model,
            policy,
            map: None,
        })
    }
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

/// The dense layer's mode for a session's config and model (`SessionInfo::dense_mode`).
pub fn dense_mode(config: &relfusion_slam::pipeline::Config, model: &str) -> String {
    match (config.dense.enabled, model) {
        (false, _) => "off",
        (true, "none") => "no_model",
        (true, _) => "prior",
    }
    .to_string()
}

/// `serialize_with` for the [`Sim3`] poses of events: their [`PoseJson`] form.
pub fn pose_as_json<S: serde::Serializer>(pose: &Sim3, s: S) -> Result<S::Ok, S::Error> {
    let q = pose.rotation.quaternion();
    PoseJson {
        t: [pose.translation.x, pose.translation.y, pose.translation.z],
        q: [q.i, q.j, q.k, q.w],
        s: pose.scale,
    }
    .serialize(s)
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
        assert!(camera_from_json(&cam()).is_ok());
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
            let e = camera_from_json(&bad).expect_err("invalid camera accepted");
            assert_eq!(e.status, 400, "{e}");
        }
        let with = CameraJson {
            distortion: Some([0.1, 0.0, 0.0, 0.0, 0.0]),
            ..cam()
        };
        assert_eq!(camera_json(&camera_from_json(&with).expect("valid")), with);
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
