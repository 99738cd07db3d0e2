//! Frames into a live session: each is checked (size, timestamp, id order, camera), decoded
//! and queued for the pipeline under the session's [`FramePolicy`], before it is acknowledged.

use std::sync::atomic::Ordering;
use std::time::Instant;

use relfusion_proto::Message as _;
use relfusion_proto::v1::{ClientMessage, client_message};

use super::decode::decode_frame;
use super::events::SessionEvent;
use super::handle::Session;
use super::types::{FrameData, FramePolicy, QueuedFrame, SessionKind, SessionState};
use crate::ApiError;
use crate::metrics::Stage;

/// Largest timestamp magnitude accepted, in seconds (year ~5000 as Unix time): trajectories
/// print timestamps with six decimals, which `f64` keeps exactly up to about here.
const MAX_TIMESTAMP: f64 = 1e11;

impl Session {
    /// A protobuf `ClientMessage` as it arrived (WebSocket, or a stream relayed through
    /// another node): decoded, then [`Session::apply`]ed.
    pub async fn apply_encoded(&self, data: &[u8]) -> Result<(), ApiError> {
        let message = ClientMessage::decode(data).map_err(|e| {
            ApiError::bad_request(format!(
                "malformed message: not a protobuf relfusion.v1.ClientMessage ({e})"
            ))
        })?;
        self.apply(message).await
    }

    /// One client message acting on the session: the one place a client's message takes
    /// effect, whatever its transport (WebSocket, Zenoh, a relay through another node).
    pub async fn apply(&self, message: ClientMessage) -> Result<(), ApiError> {
        match message.message {
            Some(client_message::Message::Frame(frame)) => {
                self.push_proto_frame(frame).await?;
                Ok(())
            }
            Some(client_message::Message::EndOfStream(_)) => {
                self.end_of_stream();
                Ok(())
            }
            // The session was configured when it was created; a repeated config changes nothing.
            Some(client_message::Message::Config(_)) => Ok(()),
            None => Err(ApiError::bad_request(
                "empty ClientMessage: set one of frame, end_of_stream",
            )),
        }
    }

    /// [`Session::push_frame`] for a protobuf `Frame` (WebSocket, Zenoh): the frame may
    /// repeat the session camera but not change it (the pipeline has one camera), and every
    /// error names the frame.
    pub async fn push_proto_frame(
        &self,
        frame: relfusion_proto::v1::Frame,
    ) -> Result<u64, ApiError> {
        let frame_id = frame.frame_id;
        let result = match &frame.camera {
            Some(camera) => self.check_same_camera(camera),
            None => Ok(()),
        };
        let result = match result {
            Ok(()) => {
                self.push_frame(FrameData {
                    frame_id: Some(frame_id),
                    timestamp: frame.timestamp,
                    bytes: frame.image.into(),
                })
                .await
            }
            Err(e) => Err(e),
        };
        result.map_err(|e| ApiError {
            message: format!("frame {frame_id}: {}", e.message),
            ..e
        })
    }

    fn check_same_camera(&self, camera: &relfusion_proto::v1::Camera) -> Result<(), ApiError> {
        let own = &self.camera;
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * a.abs().max(1.0);
        let same = camera.width == own.width
            && camera.height == own.height
            && close(camera.fx, own.fx)
            && close(camera.fy, own.fy)
            && close(camera.cx, own.cx)
            && close(camera.cy, own.cy);
        if same {
            return Ok(());
        }
        Err(ApiError::bad_request(format!(
            "the frame's camera ({}x{}, fx {} fy {} cx {} cy {}) differs from the session's \
             ({}x{}, fx {} fy {} cx {} cy {}); open a new session for another camera",
            camera.width,
            camera.height,
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            own.width,
            own.height,
            own.fx,
            own.fy,
            own.cx,
            own.cy
        )))
    }

    /// Decodes and checks one frame now (400 for a corrupt image or a size that does not match
    /// the camera, 413 beyond `limits.max_frame_bytes`), then queues it for the pipeline:
    /// with `drop_oldest` a full queue loses its oldest frame (counted), with `wait` the call
    /// waits for room. Returns the frame's id. 409 after end of stream.
    pub async fn push_frame(&self, frame: FrameData) -> Result<u64, ApiError> {
        let Some(queue) = &self.queue else {
            return Err(self.not_accepting());
        };
        if self.has_ended() {
            return Err(self.not_accepting());
        }
        if frame.bytes.len() as u64 > self.max_frame_bytes {
            return Err(ApiError::payload_too_large(format!(
                "frame of {} bytes exceeds limits.max_frame_bytes = {}",
                frame.bytes.len(),
                self.max_frame_bytes
            )));
        }
        if !(frame.timestamp.is_finite() && frame.timestamp.abs() <= MAX_TIMESTAMP) {
            return Err(ApiError::bad_request(format!(
                "timestamp must be a finite number of seconds within ±{MAX_TIMESTAMP:e}, got {}",
                frame.timestamp
            )));
        }
        let mut last = self.push_order.lock().await;
        let frame_id = match (frame.frame_id, *last) {
            (Some(id), Some((prev, _))) if id <= prev => {
                return Err(ApiError::bad_request(format!(
                    "frame_id {id} is not greater than the previous frame_id {prev}; \
                     frame ids must strictly increase"
                )));
            }
            (Some(id), _) => id,
            (None, Some((prev, _))) => prev.checked_add(1).ok_or_else(|| {
                ApiError::bad_request(format!(
                    "frame ids are used up: the previous frame_id is {prev}; open a new session"
                ))
            })?,
            (None, None) => 0,
        };
        if let Some((_, prev_t)) = *last {
            let step = frame.timestamp - prev_t;
            if !(step > 0.0 && step <= self.max_timestamp_step) {
                return Err(ApiError::bad_request(format!(
                    "timestamp {} follows {prev_t}: timestamps must increase, by at most {} s \
                     per frame (limits.max_timestamp_step_s)",
                    frame.timestamp, self.max_timestamp_step
                )));
            }
        }
        let start = Instant::now();
        let (w, h) = (self.camera.width, self.camera.height);
        let bytes = frame.bytes;
        let rgb = tokio::task::spawn_blocking(move || decode_frame(&bytes, w, h))
            .await
            .map_err(|e| ApiError::internal(format!("decoding task failed: {e}")))??;
        self.metrics
            .observe_stage(Stage::Decode, start.elapsed().as_secs_f64());
        let queued = QueuedFrame {
            frame_id,
            timestamp: frame.timestamp,
            rgb,
            received: Instant::now(),
        };
        match self.policy {
            FramePolicy::DropOldest => {
                let dropped = queue
                    .push_drop_oldest(queued)
                    .map_err(|_| self.not_accepting())?;
                self.metrics.frame_queue_depth.inc();
                if dropped.is_some() {
                    self.metrics.frame_queue_depth.dec();
                    let total = self.counters.dropped.fetch_add(1, Ordering::Relaxed) + 1;
                    self.metrics.frames_dropped.inc();
                    self.emit(SessionEvent::Dropped {
                        frames_dropped: total,
                    });
                }
            }
            FramePolicy::Wait => {
                queue
                    .push_wait(queued)
                    .await
                    .map_err(|_| self.not_accepting())?;
                self.metrics.frame_queue_depth.inc();
            }
        }
        *last = Some((frame_id, frame.timestamp));
        self.counters.received.fetch_add(1, Ordering::Relaxed);
        self.metrics.frames_received.inc();
        Ok(frame_id)
    }

    fn not_accepting(&self) -> ApiError {
        let status = self.lifecycle.status();
        if status.state == SessionState::Failed {
            return ApiError::conflict(format!(
                "session {} failed ({}); it takes no more frames",
                self.id,
                status.error.as_deref().unwrap_or("no reason recorded")
            ));
        }
        match self.kind {
            SessionKind::Upload => ApiError::conflict(format!(
                "session {} is an upload; it takes no frames",
                self.id
            )),
            SessionKind::Live => ApiError::conflict(format!(
                "session {} has ended (end of stream); it takes no more frames",
                self.id
            )),
        }
    }
}
