//! One session on Zenoh: its frames come in on
//! `relfusion/tenants/<tenant>/sessions/<id>/frames` (then `end`), its updates go out on
//! `poses` and `mesh` and, at the end, `finished`.
//!
//! Frames and the end marker are received by ONE subscriber of the session's keys (`…/<id>/*`)
//! (remote publications only, so the server's own updates are not looped back): Zenoh keeps
//! the order of one publisher's messages, so an `end` can never overtake the last frames.
//! The subscriber's channel holds `limits.frame_queue` messages; when it is full, Zenoh's
//! receive path waits, which pushes back on the publisher (with congestion control `block`).
//! That is how the `wait` policy reaches a Zenoh client; with `drop_oldest` the session's own
//! queue drops (and counts) the oldest frames, so the channel rarely fills.
//!
//! Updates are published by a second task from the session's event broadcast, so a frame that
//! waits for queue room never holds back the poses of earlier frames. Poses are published
//! with congestion control `block` (reliable: a subscriber sees every pose); a publisher that
//! falls behind the broadcast (`limits.event_buffer`) skips the events it missed.
//!
//! A malformed message, or a frame the session refuses (corrupt image, size mismatch, frame
//! id not increasing, after the end), is answered with an `Error` on `poses` and counted;
//! the session goes on.

use std::sync::Arc;

use relfusion_proto::Message as _;
use relfusion_proto::v1::server_message::Message;
use relfusion_proto::v1::{ClientMessage, EndOfStream, Frame, SessionFinished, client_message};
use relfusion_proto::zenoh_keys::{
    END, FINISHED, FRAMES, MESH, POSES, session_key, session_wildcard,
};
use tokio::sync::broadcast::error::RecvError;
use tokio::task::JoinHandle;
use zenoh::handlers::FifoChannel;
use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;
use zenoh::sample::{Locality, Sample};

use super::{Shared, bump, error_message_bytes};
use crate::ApiError;
use crate::session::{Session, SessionEvent, SessionInfo};

/// Declares the session's subscriber and publishers and starts its two tasks.
pub(crate) async fn attach(
    shared: Arc<Shared>,
    session: Arc<Session>,
) -> Result<Vec<JoinHandle<()>>, ApiError> {
    let id = session.id().to_string();
    let tenant = session.owner().tenant().to_string();
    let zerr = |what: &str, e: zenoh::Error| ApiError::internal(format!("Zenoh {what}: {e}"));
    // Subscribe to events before the first frame can arrive: every pose gets published.
    let events = session.subscribe();
    let poses = shared
        .zenoh
        .declare_publisher(session_key(&tenant, &id, POSES))
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| zerr("poses publisher", e))?;
    let mesh = shared
        .zenoh
        .declare_publisher(session_key(&tenant, &id, MESH))
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| zerr("mesh publisher", e))?;
    let capacity = shared.sessions.config().limits.frame_queue.max(1);
    let subscriber = shared
        .zenoh
        .declare_subscriber(session_wildcard(&tenant, &id))
        .allowed_origin(Locality::Remote)
        .with(FifoChannel::new(capacity))
        .await
        .map_err(|e| zerr("frames subscriber", e))?;

    let ingest = {
        let shared = shared.clone();
        let session = session.clone();
        let errors_key = session_key(&tenant, &id, POSES);
        tokio::spawn(async move {
            let mut shutdown = shared.shutdown.clone();
            let finished = session.wait_finished();
            tokio::pin!(finished);
            let deleted = session.deleted();
            tokio::pin!(deleted);
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
                if let Err(error) = handle(&shared, &session, &sample).await {
                    let put = shared
                        .zenoh
                        .put(errors_key.as_str(), error_message_bytes(&error))
                        .congestion_control(CongestionControl::Block);
                    if let Err(e) = put.await {
                        tracing::warn!(session = %session.id(), "publishing an error: {e}");
                    }
                }
            }
            if let Err(e) = subscriber.undeclare().await {
                tracing::debug!(session = %session.id(), "undeclaring the frames subscriber: {e}");
            }
        })
    };
    let publish = tokio::spawn(publish_updates(shared, session, events, poses, mesh));
    Ok(vec![ingest, publish])
}

/// One message from the client.
async fn handle(shared: &Shared, session: &Session, sample: &Sample) -> Result<(), ApiError> {
    let key = sample.key_expr().as_str();
    let leaf = key.rsplit('/').next().unwrap_or_default();
    match leaf {
        FRAMES => {
            let payload = sample.payload().to_bytes();
            let frame = Frame::decode(payload.as_ref()).map_err(|e| {
                bump(&shared.stats.malformed_messages);
                ApiError::bad_request(format!(
                    "malformed message on {key}: not a protobuf relfusion.v1.Frame ({e})"
                ))
            })?;
            push(shared, session, frame).await
        }
        END => {
            session
                .apply(client(client_message::Message::EndOfStream(EndOfStream {})))
                .await
        }
        // Other keys of the session (another node's updates, say) are not ours to consume.
        _ => Ok(()),
    }
}

async fn push(shared: &Shared, session: &Session, frame: Frame) -> Result<(), ApiError> {
    match session
        .apply(client(client_message::Message::Frame(frame)))
        .await
    {
        Ok(()) => {
            bump(&shared.stats.frames_accepted);
            Ok(())
        }
        Err(e) => {
            bump(&shared.stats.frames_refused);
            Err(e)
        }
    }
}

/// Publishes the session's events until it has finished or failed, then `finished`: mesh
/// deltas as bare `MeshUpdate`s on `…/mesh`, everything else as `ServerMessage`s on `…/poses`.
async fn publish_updates(
    shared: Arc<Shared>,
    session: Arc<Session>,
    mut events: tokio::sync::broadcast::Receiver<SessionEvent>,
    poses: Publisher<'static>,
    mesh: Publisher<'static>,
) {
    let id = session.id().to_string();
    let deleted = session.deleted();
    tokio::pin!(deleted);
    loop {
        let received = tokio::select! {
            received = events.recv() => received,
            _ = &mut deleted => {
                // A deleted session emits nothing more and has no map to announce.
                let _ = poses.undeclare().await;
                let _ = mesh.undeclare().await;
                return;
            }
        };
        let event = match received {
            Ok(event) => event,
            Err(RecvError::Lagged(missed)) => {
                tracing::warn!(session = %id, missed, "Zenoh publisher fell behind; events skipped");
                continue;
            }
            Err(RecvError::Closed) => break,
        };
        for message in event.to_proto(&id) {
            let put = match &message.message {
                Some(Message::Mesh(update)) => mesh.put(update.encode_to_vec()).await,
                _ => poses.put(message.encode_to_vec()).await,
            };
            if let Err(e) = put {
                tracing::warn!(session = %id, "publishing an update: {e}");
            }
        }
        if event.is_last() {
            break;
        }
    }
    let info = session.info();
    let finished = finished_message(&info);
    if let Err(e) = shared
        .zenoh
        .put(
            session_key(session.owner().tenant(), &id, FINISHED),
            finished.encode_to_vec(),
        )
        .congestion_control(CongestionControl::Block)
        .await
    {
        tracing::warn!(session = %id, "publishing the end of the session: {e}");
    }
    if let Err(e) = poses.undeclare().await {
        tracing::debug!(session = %id, "undeclaring the poses publisher: {e}");
    }
    if let Err(e) = mesh.undeclare().await {
        tracing::debug!(session = %id, "undeclaring the mesh publisher: {e}");
    }
}

/// The `SessionFinished` message for a session's final info.
pub fn finished_message(info: &SessionInfo) -> SessionFinished {
    SessionFinished {
        session_id: info.id.clone(),
        state: crate::session::snapshot::state_name(info.state),
        error: info.error.clone().unwrap_or_default(),
        frames_received: info.frames_received,
        frames_processed: info.frames_processed,
        frames_dropped: info.frames_dropped,
        keyframes: info.keyframes,
    }
}

/// A client message of `message` (Zenoh carries the frame and the end on keys of their own).
fn client(message: client_message::Message) -> ClientMessage {
    ClientMessage {
        message: Some(message),
    }
}
