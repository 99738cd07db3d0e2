//! The plain data of sessions: the typed request the service edge parses a create request
//! into, and the checks and conversions between the JSON of the HTTP API (defined once, in
//! `relfusion_proto::http`) and the pipeline's types.

use relfusion_proto::http::MapStart;
use relfusion_slam::geometry::{PinholeCamera, Sim3};
use serde::Serialize;

pub use relfusion_proto::http::{
    CameraJson, CreateSession, FramePolicy, PoseJson, Progress, SessionInfo, SessionKind,
    SessionState,
};

use crate::ApiError;
pub use crate::auth::Owner;
pub use crate::convert::{
    IMAGE_SIDE_RANGE, camera_as_json, camera_from_json, camera_json, checked_camera,
};

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
        let camera = req.camera.as_ref().ok_or_else(|| {
            ApiError::bad_request("camera is required (or ros2.camera_info_topic to read it from)")
        })?;
        Ok(Self {
            map: req.map,
            ..Self::live(
                camera_from_json(camera)?,
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

/// A decoded frame waiting for the pipeline.
#[derive(Debug)]
pub struct QueuedFrame {
    /// The client's frame id (pose events carry it).
    pub frame_id: u64,
    pub timestamp: f64,
    pub rgb: image::RgbImage,
    /// When the server accepted it (frame-to-pose latency).
    pub received: std::time::Instant,
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
