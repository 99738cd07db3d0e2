//! Conversions between the pipeline's types (`relfusion_slam`), the wire schema
//! (`relfusion_proto::v1`) and the JSON of the HTTP API, plus the byte formats of results.
//! No math happens here: only re-packing.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use relfusion_proto::http::CameraJson;
use relfusion_proto::v1;
use relfusion_slam::export::ColoredPoint;
use relfusion_slam::geometry::{Distortion, PinholeCamera, SO3, Sim3};
use relfusion_slam::pipeline::TrackingState;

use crate::ApiError;

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

/// `Sim3` → protobuf `Sim3Pose`.
pub fn sim3_to_proto(pose: &Sim3) -> v1::Sim3Pose {
    let q = pose.rotation.quaternion();
    v1::Sim3Pose {
        translation: Some(v1::Vector3 {
            x: pose.translation.x,
            y: pose.translation.y,
            z: pose.translation.z,
        }),
        rotation: Some(v1::Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        }),
        scale: pose.scale,
    }
}

/// Protobuf `Sim3Pose` → `Sim3`; rejects a missing or zero quaternion, non-finite values and
/// a scale ≤ 0 (the unset field).
pub fn sim3_from_proto(pose: &v1::Sim3Pose) -> Result<Sim3, ApiError> {
    let t = pose.translation.unwrap_or_default();
    let q = pose
        .rotation
        .ok_or_else(|| ApiError::bad_request("pose: rotation is missing"))?;
    let values = [t.x, t.y, t.z, q.x, q.y, q.z, q.w, pose.scale];
    if values.iter().any(|v| !v.is_finite()) {
        return Err(ApiError::bad_request("pose: values must be finite"));
    }
    if pose.scale <= 0.0 {
        return Err(ApiError::bad_request("pose: scale must be > 0"));
    }
    let raw = Quaternion::new(q.w, q.x, q.y, q.z);
    if raw.norm() < 1e-12 {
        return Err(ApiError::bad_request(
            "pose: the zero quaternion is invalid",
        ));
    }
    Ok(Sim3::new(
        SO3::from_quaternion(UnitQuaternion::from_quaternion(raw)),
        Vector3::new(t.x, t.y, t.z),
        pose.scale,
    ))
}

/// `PinholeCamera` → protobuf `Camera`.
pub fn camera_to_proto(camera: &PinholeCamera) -> v1::Camera {
    v1::Camera {
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
        width: camera.width,
        height: camera.height,
        distortion: camera.distortion.map(|d| v1::Distortion {
            k1: d.k1,
            k2: d.k2,
            p1: d.p1,
            p2: d.p2,
            k3: d.k3,
        }),
    }
}

/// Protobuf `Camera` → validated `PinholeCamera` (400 on invalid intrinsics).
pub fn camera_from_proto(camera: &v1::Camera) -> Result<PinholeCamera, ApiError> {
    checked_camera(
        [camera.fx, camera.fy, camera.cx, camera.cy],
        camera.width,
        camera.height,
        camera
            .distortion
            .as_ref()
            .map(|d| [d.k1, d.k2, d.p1, d.p2, d.k3]),
    )
}

/// Tracking state → protobuf (the wire has no "relocalized": such a frame is tracked).
pub fn tracking_state_to_proto(state: TrackingState) -> v1::TrackingState {
    match state {
        TrackingState::Initializing => v1::TrackingState::Initializing,
        TrackingState::Tracking | TrackingState::Relocalized => v1::TrackingState::Tracking,
        TrackingState::Lost => v1::TrackingState::Lost,
    }
}

/// The bytes of a binary little-endian PLY point cloud, the layout of
/// `relfusion_slam::export::write_points_ply` (`x y z` float, `red green blue` uchar).
pub fn points_ply(points: &[ColoredPoint]) -> Vec<u8> {
    relfusion_slam::export::points_ply_bytes(points)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sim3_round_trips_through_proto() {
        let pose = Sim3::new(
            SO3::exp(&Vector3::new(0.1, -0.2, 0.3)),
            Vector3::new(1.0, 2.0, -3.0),
            0.7,
        );
        let back = sim3_from_proto(&sim3_to_proto(&pose)).expect("valid");
        assert!((back.matrix() - pose.matrix()).norm() < 1e-12);
        let mut bad = sim3_to_proto(&pose);
        bad.scale = 0.0;
        assert!(sim3_from_proto(&bad).is_err());
        bad.scale = 1.0;
        bad.rotation = Some(v1::Quaternion::default());
        assert!(sim3_from_proto(&bad).is_err());
    }

    #[test]
    fn camera_round_trips_through_proto() {
        let cam = PinholeCamera::tum_freiburg1();
        let back = camera_from_proto(&camera_to_proto(&cam)).expect("valid");
        assert_eq!(back, cam);
        let mut bad = camera_to_proto(&cam);
        bad.fx = f64::NAN;
        assert_eq!(camera_from_proto(&bad).expect_err("nan").status, 400);
    }

    #[test]
    fn ply_bytes_match_the_library_writer() {
        let points = [
            ColoredPoint {
                position: [1.0, 2.0, 3.0],
                color: [1, 2, 3],
            },
            ColoredPoint {
                position: [-1.0, 0.5, 9.0],
                color: [255, 0, 7],
            },
        ];
        let path = std::env::temp_dir().join(format!("relfusion-ply-{}.ply", std::process::id()));
        relfusion_slam::export::write_points_ply(&path, &points).expect("write");
        assert_eq!(std::fs::read(&path).expect("read"), points_ply(&points));
        let _ = std::fs::remove_file(path);
    }
}
