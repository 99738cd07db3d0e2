//! A session fed by a ROS 2 camera: its `sensor_msgs/Image` (`rgb8`, `bgr8`, `rgba8`,
//! `bgra8`, `mono8`) or `sensor_msgs/CompressedImage` (JPEG, PNG) topic, subscribed with an
//! `MS` liveliness token like any rmw_zenoh subscription, and the camera from its
//! `sensor_msgs/CameraInfo` (`plumb_bob` or `rational_polynomial`: the first five
//! coefficients are OpenCV's k1 k2 p1 p2 k3).
//!
//! Each message becomes a frame of the session (ids 1, 2, …; the header's stamp as its
//! time) through [`Session::push_frame`], so it is checked, bounded and queued like any
//! other frame; raw images are PNG-encoded first (fast compression), compressed ones go as
//! they are. A message that is not its type's CDR, or a frame the session refuses, is
//! counted and skipped. The subscription's channel holds `limits.frame_queue` messages.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use relfusion_proto::http::CameraJson;
use relfusion_viz::ros2::msgs::{self, ImageMsg};
use relfusion_viz::ros2::types::{CAMERA_INFO, COMPRESSED_IMAGE};
use tokio::task::JoinHandle;
use zenoh::handlers::FifoChannel;

use super::{Ros2Bridge, Ros2Input};
use crate::ApiError;
use crate::ros2_names::{self as names, Entity};
use crate::session::{FrameData, Session};

/// Declares the session's camera subscription and its token, and starts feeding its frames.
pub(super) async fn start(
    bridge: &Ros2Bridge,
    session: Arc<Session>,
    input: &Ros2Input,
    namespace: &str,
    node_id: u64,
) -> Result<JoinHandle<()>, ApiError> {
    let zerr = |what: &str, e: zenoh::Error| ApiError::internal(format!("ROS 2 {what}: {e}"));
    let ty = input.image_type;
    let token = bridge
        .zenoh
        .liveliness()
        .declare_token(names::liveliness_key(
            &bridge.place(node_id, bridge.next_id(), namespace),
            Entity::Subscription {
                topic: &input.image_topic,
                ty,
            },
        ))
        .await
        .map_err(|e| zerr("subscription token", e))?;
    let subscriber = bridge
        .zenoh
        .declare_subscriber(names::topic_key(bridge.domain, &input.image_topic, ty))
        .with(FifoChannel::new(bridge.frame_queue))
        .await
        .map_err(|e| zerr("subscription", e))?;
    let stats = bridge.stats.clone();
    let mut shutdown = bridge.shutdown.clone();
    let compressed = ty == COMPRESSED_IMAGE;
    Ok(tokio::spawn(async move {
        let finished = session.wait_finished();
        tokio::pin!(finished);
        let deleted = session.deleted();
        tokio::pin!(deleted);
        let mut next_id = 1u64;
        loop {
            let sample = tokio::select! {
                sample = subscriber.recv_async() => match sample {
                    Ok(sample) => sample,
                    Err(_) => break,
                },
                _ = &mut finished => break,
                _ = &mut deleted => break,
                _ = shutdown.wait_for(|stop| *stop) => break,
            };
            let payload = sample.payload().to_bytes();
            let frame = if compressed {
                compressed_frame(&payload, next_id)
            } else {
                raw_frame(&payload, next_id, session.camera())
            };
            let pushed = match frame {
                Ok(frame) => session.push_frame(frame).await.map(|_| ()),
                Err(e) => Err(e),
            };
            match pushed {
                Ok(()) => {
                    next_id += 1;
                    stats.frames_in.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => {
                    let refused = stats.messages_refused.fetch_add(1, Ordering::Relaxed);
                    // A camera repeats its mistakes at frame rate: the first few are enough.
                    if refused < 10 {
                        tracing::warn!(session = %session.id(), "a ROS 2 camera message: {}", e.message);
                    }
                }
            }
        }
        let _ = subscriber.undeclare().await;
        drop(token);
    }))
}

fn seconds(stamp_ns: u64) -> f64 {
    stamp_ns as f64 * 1e-9
}

fn compressed_frame(payload: &[u8], frame_id: u64) -> Result<FrameData, ApiError> {
    let msg = msgs::read_compressed_image(payload)
        .map_err(|e| ApiError::bad_request(format!("not a sensor_msgs/CompressedImage: {e}")))?;
    Ok(FrameData {
        frame_id: Some(frame_id),
        timestamp: seconds(msg.stamp_ns),
        bytes: bytes::Bytes::copy_from_slice(msg.data),
    })
}

fn raw_frame(
    payload: &[u8],
    frame_id: u64,
    camera: &relfusion_slam::geometry::PinholeCamera,
) -> Result<FrameData, ApiError> {
    let msg = msgs::read_image(payload)
        .map_err(|e| ApiError::bad_request(format!("not a sensor_msgs/Image: {e}")))?;
    if (msg.width, msg.height) != (camera.width, camera.height) {
        // Checked before any pixel is touched: the camera bounds the work.
        return Err(ApiError::bad_request(format!(
            "the image is {}x{}, the session's camera {}x{}",
            msg.width, msg.height, camera.width, camera.height
        )));
    }
    let rgb = rgb_of(&msg)?;
    let mut png = Vec::with_capacity(rgb.len() / 2);
    let encoder = image::codecs::png::PngEncoder::new_with_quality(
        &mut png,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::NoFilter,
    );
    image::ImageEncoder::write_image(
        encoder,
        &rgb,
        msg.width,
        msg.height,
        image::ExtendedColorType::Rgb8,
    )
    .map_err(|e| ApiError::internal(format!("encoding a ROS 2 image: {e}")))?;
    Ok(FrameData {
        frame_id: Some(frame_id),
        timestamp: seconds(msg.stamp_ns),
        bytes: png.into(),
    })
}

/// Tightly packed RGB of an 8-bit `sensor_msgs/Image`.
fn rgb_of(msg: &ImageMsg<'_>) -> Result<Vec<u8>, ApiError> {
    // (channels, index of red, green, blue in a pixel)
    let (channels, [r, g, b]) = match msg.encoding.as_str() {
        "rgb8" => (3, [0, 1, 2]),
        "bgr8" => (3, [2, 1, 0]),
        "rgba8" => (4, [0, 1, 2]),
        "bgra8" => (4, [2, 1, 0]),
        "mono8" | "8UC1" => (1, [0, 0, 0]),
        other => {
            return Err(ApiError::bad_request(format!(
                "image encoding {other:?}: relfusion reads rgb8, bgr8, rgba8, bgra8 and mono8"
            )));
        }
    };
    let (w, h, step) = (msg.width as usize, msg.height as usize, msg.step as usize);
    if step < w * channels || msg.data.len() < step * h {
        return Err(ApiError::bad_request(format!(
            "image of {w}x{h} {} with step {step} has {} bytes",
            msg.encoding,
            msg.data.len()
        )));
    }
    let mut rgb = Vec::with_capacity(w * h * 3);
    for row in msg.data.chunks_exact(step).take(h) {
        for px in row[..w * channels].chunks_exact(channels) {
            rgb.extend_from_slice(&[px[r], px[g], px[b]]);
        }
    }
    Ok(rgb)
}

/// See [`Ros2Bridge::camera_from_info`]. The subscription is in the graph (its `MS` token)
/// while it waits.
pub(super) async fn camera_from_info(
    bridge: &Ros2Bridge,
    topic: &str,
    tenant: &str,
) -> Result<CameraJson, ApiError> {
    let zerr = |what: &str, e: zenoh::Error| ApiError::internal(format!("ROS 2 {what}: {e}"));
    let namespace = names::tenant_namespace(tenant);
    let node_id = bridge.next_id();
    let mut tokens = Vec::new();
    for (entity_id, entity) in [
        (node_id, Entity::Node),
        (
            bridge.next_id(),
            Entity::Subscription {
                topic,
                ty: CAMERA_INFO,
            },
        ),
    ] {
        let key = names::liveliness_key(&bridge.place(node_id, entity_id, &namespace), entity);
        tokens.push(
            bridge
                .zenoh
                .liveliness()
                .declare_token(key)
                .await
                .map_err(|e| zerr("subscription token", e))?,
        );
    }
    let subscriber = bridge
        .zenoh
        .declare_subscriber(names::topic_key(bridge.domain, topic, CAMERA_INFO))
        .with(FifoChannel::new(4))
        .await
        .map_err(|e| zerr("subscription", e))?;
    let timeout: Duration = bridge.camera_info_timeout;
    let sample = tokio::time::timeout(timeout, subscriber.recv_async()).await;
    let _ = subscriber.undeclare().await;
    let sample = match sample {
        Ok(Ok(sample)) => sample,
        _ => {
            return Err(ApiError::bad_request(format!(
                "no sensor_msgs/CameraInfo on {topic} within {timeout:?} (ros2.camera_info_topic); \
                 or give the camera in the request"
            )));
        }
    };
    let info = msgs::read_camera_info(&sample.payload().to_bytes()).map_err(|e| {
        ApiError::bad_request(format!("{topic}: not a sensor_msgs/CameraInfo: {e}"))
    })?;
    camera_of_info(&info)
}

/// The camera of a `CameraInfo` (checked like any camera when the session is created).
fn camera_of_info(info: &msgs::CameraInfoMsg) -> Result<CameraJson, ApiError> {
    let distortion = match info.distortion_model.as_str() {
        _ if info.d.iter().all(|&v| v == 0.0) => None,
        "plumb_bob" | "rational_polynomial" if info.d.len() >= 5 => {
            Some([info.d[0], info.d[1], info.d[2], info.d[3], info.d[4]])
        }
        model => {
            return Err(ApiError::bad_request(format!(
                "CameraInfo distortion model {model:?} with {} coefficients: relfusion \
                 takes plumb_bob (k1 k2 p1 p2 k3)",
                info.d.len()
            )));
        }
    };
    Ok(CameraJson {
        fx: info.k[0],
        fy: info.k[4],
        cx: info.k[2],
        cy: info.k[5],
        width: info.width,
        height: info.height,
        distortion,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use relfusion_viz::ros2::msgs::camera;

    #[test]
    fn camera_info_gives_the_camera_and_its_distortion() {
        let cdr = camera::camera_info(
            0,
            "cam",
            640,
            480,
            [500.0, 502.0, 319.5, 239.5],
            [0.1, -0.2, 0.001, 0.002, 0.03],
        );
        let info = msgs::read_camera_info(&cdr).expect("CDR");
        let cam = camera_of_info(&info).expect("camera");
        assert_eq!(
            (cam.fx, cam.fy, cam.cx, cam.cy),
            (500.0, 502.0, 319.5, 239.5)
        );
        assert_eq!(cam.distortion, Some([0.1, -0.2, 0.001, 0.002, 0.03]));
        let fisheye = msgs::CameraInfoMsg {
            distortion_model: "equidistant".into(),
            ..info
        };
        assert!(camera_of_info(&fisheye).is_err());
    }

    #[test]
    fn raw_images_of_every_8_bit_layout_become_rgb() {
        let image = |encoding: &str, data: &'static [u8], step: u32| ImageMsg {
            stamp_ns: 0,
            height: 1,
            width: 2,
            encoding: encoding.into(),
            big_endian: false,
            step,
            data,
        };
        assert_eq!(
            rgb_of(&image("rgb8", &[1, 2, 3, 4, 5, 6], 6)).expect("rgb"),
            [1, 2, 3, 4, 5, 6]
        );
        assert_eq!(
            rgb_of(&image("bgra8", &[3, 2, 1, 0, 6, 5, 4, 0], 8)).expect("bgra"),
            [1, 2, 3, 4, 5, 6]
        );
        assert_eq!(
            rgb_of(&image("mono8", &[9, 8, 0], 3)).expect("mono"),
            [9, 9, 9, 8, 8, 8]
        );
        assert!(rgb_of(&image("rgb8", &[1, 2, 3], 6)).is_err(), "short");
        assert!(rgb_of(&image("16UC1", &[0; 4], 4)).is_err(), "depth");
    }
}
