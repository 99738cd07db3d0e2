//! A session's outputs as ROS 2 topics: one publisher per topic of
//! `relfusion_viz::ros2::Topic` under the session's namespace, each with its `MP` liveliness
//! token; the session's events become CDR messages through the same translation as its
//! recording (`session::recording::log_event`), each sent with rmw_zenoh's attachment.
//!
//! Messages are sent reliably (congestion control `block`, like the session's Zenoh
//! updates); a publisher that falls behind the session's event broadcast
//! (`limits.event_buffer`) skips what it missed and says so in the log.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use relfusion_viz::SessionLog as _;
use relfusion_viz::ros2::{Ros2Log, Ros2Sink, Topic};
use relfusion_viz::session_log::LogError;
use tokio::sync::broadcast::error::RecvError;
use tokio::task::JoinHandle;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;

use super::{Ros2Bridge, Ros2Stats};
use crate::ApiError;
use crate::ros2_names::{self as names, Entity};
use crate::session::Session;
use crate::session::recording::log_event;

/// The messages of one event, collected to be sent once it is translated.
#[derive(Debug, Default)]
struct Outbox(Vec<(Topic, Vec<u8>)>);

impl Ros2Sink for Outbox {
    fn publish(&mut self, topic: Topic, _stamp_ns: u64, cdr: Vec<u8>) -> Result<(), LogError> {
        self.0.push((topic, cdr));
        Ok(())
    }
}

/// One topic's publisher and what its attachment carries.
struct Endpoint {
    publisher: Publisher<'static>,
    _token: LivelinessToken,
    gid: [u8; 16],
    sequence: i64,
}

/// Declares the session's publishers and their tokens, and starts sending its events.
pub(super) async fn start(
    bridge: &Ros2Bridge,
    session: Arc<Session>,
    namespace: &str,
    node_id: u64,
) -> Result<JoinHandle<()>, ApiError> {
    // Subscribe before the first frame can arrive: every pose gets published.
    let events = session.subscribe();
    let zerr = |what: &str, e: zenoh::Error| ApiError::internal(format!("ROS 2 {what}: {e}"));
    let mut endpoints = BTreeMap::new();
    for topic in Topic::ALL {
        let full = format!("{namespace}/{}", topic.name());
        let ty = topic.ros_type();
        let token_key = names::liveliness_key(
            &bridge.place(node_id, bridge.next_id(), namespace),
            Entity::Publisher { topic: &full, ty },
        );
        let gid = names::gid(&token_key);
        let token = bridge
            .zenoh
            .liveliness()
            .declare_token(token_key)
            .await
            .map_err(|e| zerr("publisher token", e))?;
        let publisher = bridge
            .zenoh
            .declare_publisher(names::topic_key(bridge.domain, &full, ty))
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(|e| zerr("publisher", e))?;
        endpoints.insert(
            topic,
            Endpoint {
                publisher,
                _token: token,
                gid,
                sequence: 0,
            },
        );
    }
    let shutdown = bridge.shutdown.clone();
    Ok(tokio::spawn(run(
        session,
        events,
        endpoints,
        shutdown,
        bridge.stats.clone(),
    )))
}

async fn run(
    session: Arc<Session>,
    mut events: tokio::sync::broadcast::Receiver<crate::session::SessionEvent>,
    mut endpoints: BTreeMap<Topic, Endpoint>,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
    stats: Arc<Ros2Stats>,
) {
    let id = session.id().to_string();
    let deleted = session.deleted();
    tokio::pin!(deleted);
    let mut log = Ros2Log::new(Outbox::default());
    loop {
        let received = tokio::select! {
            received = events.recv() => received,
            _ = &mut deleted => break,
            _ = shutdown.wait_for(|stop| *stop) => break,
        };
        let event = match received {
            Ok(event) => event,
            Err(RecvError::Lagged(missed)) => {
                tracing::warn!(session = %id, missed, "ROS 2 publisher fell behind; events skipped");
                continue;
            }
            Err(RecvError::Closed) => break,
        };
        let mut written = log_event(&mut log, &event);
        if event.is_last() {
            written = written.and_then(|()| log.flush());
        }
        if let Err(e) = written {
            tracing::warn!(session = %id, "ROS 2 messages of an event: {e}");
        }
        for (topic, cdr) in std::mem::take(&mut log.sink_mut().0) {
            let Some(endpoint) = endpoints.get_mut(&topic) else {
                continue;
            };
            endpoint.sequence += 1;
            let attachment = names::attachment(endpoint.sequence, now_ns(), &endpoint.gid);
            match endpoint
                .publisher
                .put(cdr)
                .attachment(attachment.to_vec())
                .await
            {
                Ok(()) => {
                    stats.messages_published.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => tracing::warn!(session = %id, "publishing on ROS 2: {e}"),
            }
        }
        if event.is_last() {
            break;
        }
    }
    match Box::new(log).finish() {
        Ok(counts) => tracing::debug!(session = %id, %counts, "ROS 2 topics closed"),
        Err(e) => tracing::debug!(session = %id, "ROS 2 counts: {e}"),
    }
    for (_, endpoint) in endpoints {
        let _ = endpoint.publisher.undeclare().await;
    }
}

/// Nanoseconds since the Unix epoch (the attachment's source time).
fn now_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}
