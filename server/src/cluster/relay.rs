//! A session's WebSocket stream served by a node that does not run it.
//!
//! The WebSocket stays on the node the client reached; the session stays on its owner:
//! - frames: each client message goes to the owner as one query (`…/nodes/<owner>/push`),
//!   which hands it to the session as a local WebSocket would; the next message is read only
//!   after the owner answered, so the session's `wait` policy pushes back on the client exactly
//!   as it does on a direct connection, and a refused frame comes back as the same `Error`;
//! - updates: before the 101, the node asks the owner to relay the session's updates
//!   (`…/nodes/<owner>/watch`) to a key of its own, `relfusion/cluster/relay/<node>/<n>`, which
//!   it subscribes to first; the owner publishes every `ServerMessage` there (reliable,
//!   congestion control `block`) and an end marker after the session's last update, and stops
//!   when nobody listens any more.
//!
//! Both carry the client's bearer token: the owner authenticates it as if it had been called
//! directly (another tenant's session is NOT_FOUND there too).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use relfusion_proto::Message as _;
use relfusion_proto::v1::{self, ErrorCode, ServerMessage, server_message};
use serde::{Deserialize, Serialize};
use tokio::sync::broadcast::error::RecvError;
use zenoh::qos::CongestionControl;

use super::{CLUSTER_ROOT, Cluster, node_key};
use crate::ApiError;
use crate::session::Owner;

/// Leaf of the frame queryable.
pub const PUSH: &str = "push";
/// Leaf of the relay-starting queryable.
pub const WATCH: &str = "watch";
/// The attachment of the relay's last sample.
const END_MARKER: &[u8] = b"end";
/// How long one pushed frame may wait on the owner (queue room under the `wait` policy).
const PUSH_TIMEOUT: Duration = Duration::from_secs(60);
/// How often a relay checks that someone still listens.
const RELAY_CHECK: Duration = Duration::from_secs(1);
/// Checks in a row without a listener before a relay stops.
const RELAY_IDLE_CHECKS: u32 = 5;

static RELAY_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A request about one session, with the client's credentials.
#[derive(Debug, Serialize, Deserialize)]
struct SessionCall {
    id: String,
    /// The `Authorization` header's value, if any.
    authorization: Option<String>,
    /// For `watch`: where to publish.
    #[serde(default)]
    relay: String,
    /// For `watch`: what the updates are wanted as.
    #[serde(default)]
    format: RelayFormat,
}

/// What a relay carries: the WebSocket's protobuf `ServerMessage`s, or the server-sent events'
/// `{"event", "data"}` JSON (the owner's own SSE encoding, so both nodes' streams are alike).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RelayFormat {
    #[default]
    Protobuf,
    Sse,
}

/// One server-sent event on a relay.
#[derive(Debug, Serialize, Deserialize)]
pub struct RelayedSse {
    pub event: String,
    pub data: String,
}

impl RelayedSse {
    pub fn of(event: &crate::session::SessionEvent) -> Self {
        Self {
            event: event.kind().to_string(),
            data: serde_json::to_string(event).unwrap_or_else(|_| "null".into()),
        }
    }

    fn bytes(&self) -> Vec<u8> {
        serde_json::to_vec(self).unwrap_or_default()
    }
}

/// An error reply: the refusal as the owner's API would give it.
#[derive(Debug, Serialize, Deserialize)]
struct Refusal {
    status: u16,
    code: String,
    message: String,
}

fn refusal_of(bytes: &[u8]) -> ApiError {
    match serde_json::from_slice::<Refusal>(bytes) {
        Ok(r) => ApiError {
            status: r.status,
            code: ApiError::known_code(&r.code),
            message: r.message,
        },
        Err(_) => ApiError::unavailable(String::from_utf8_lossy(bytes).into_owned()),
    }
}

/// The relay of one session's updates to this node.
#[derive(Debug)]
pub struct Relay {
    pub subscriber:
        zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    /// The session had ended before the relay started.
    pub ended: bool,
}

/// What a relayed sample is.
#[derive(Debug)]
pub enum Relayed {
    Message(Vec<u8>),
    End,
}

/// Classifies a sample of a relay.
pub fn relayed(sample: &zenoh::sample::Sample) -> Relayed {
    if sample
        .attachment()
        .is_some_and(|a| a.to_bytes().as_ref() == END_MARKER)
    {
        Relayed::End
    } else {
        Relayed::Message(sample.payload().to_bytes().into_owned())
    }
}

impl Cluster {
    /// Asks `node` to relay session `id`'s updates here; the relay's samples arrive on the
    /// returned subscriber from the moment this returns.
    pub async fn watch(
        &self,
        node: &str,
        id: &str,
        authorization: Option<String>,
        capacity: usize,
        format: RelayFormat,
    ) -> Result<Relay, ApiError> {
        let zenoh = self
            .zenoh()
            .ok_or_else(|| ApiError::unavailable("the cluster is not joined"))?;
        let n = RELAY_COUNTER.fetch_add(1, Ordering::Relaxed);
        let relay = format!("{CLUSTER_ROOT}/relay/{}/{n}", self.node);
        let subscriber = zenoh
            .declare_subscriber(&relay)
            .with(zenoh::handlers::FifoChannel::new(capacity.max(16)))
            .await
            .map_err(|e| ApiError::internal(format!("Zenoh relay subscriber: {e}")))?;
        let call = SessionCall {
            id: id.to_string(),
            authorization,
            relay,
            format,
        };
        let reply = self
            .call(node, WATCH, &call, Vec::new(), PUSH_TIMEOUT)
            .await?;
        Ok(Relay {
            subscriber,
            ended: reply.as_slice() == END_MARKER,
        })
    }

    /// Hands one client message (`ClientMessage` bytes) to session `id` on `node`.
    pub async fn push(
        &self,
        node: &str,
        id: &str,
        authorization: Option<String>,
        message: Vec<u8>,
    ) -> Result<(), ApiError> {
        let call = SessionCall {
            id: id.to_string(),
            authorization,
            relay: String::new(),
            format: RelayFormat::Protobuf,
        };
        self.call(node, PUSH, &call, message, PUSH_TIMEOUT)
            .await
            .map(|_| ())
    }

    async fn call(
        &self,
        node: &str,
        leaf: &str,
        call: &SessionCall,
        payload: Vec<u8>,
        timeout: Duration,
    ) -> Result<Vec<u8>, ApiError> {
        let zenoh = self
            .zenoh()
            .ok_or_else(|| ApiError::unavailable("the cluster is not joined"))?;
        let gone = || {
            ApiError::unavailable(format!(
                "node {node}, which runs this session, does not answer"
            ))
        };
        let replies = zenoh
            .get(node_key(node, leaf))
            .attachment(serde_json::to_vec(call).unwrap_or_default())
            .payload(payload)
            .timeout(timeout)
            .await
            .map_err(|_| gone())?;
        let reply = replies.recv_async().await.map_err(|_| gone())?;
        match reply.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(e) => Err(refusal_of(&e.payload().to_bytes())),
        }
    }
}

/// The session a call names, as its owner sees it.
fn session_of(
    cluster: &Cluster,
    query: &zenoh::query::Query,
) -> Result<(Arc<crate::session::Session>, SessionCall), ApiError> {
    let call: SessionCall = query
        .attachment()
        .and_then(|a| serde_json::from_slice(&a.to_bytes()).ok())
        .ok_or_else(|| ApiError::bad_request("a cluster call without its session"))?;
    let token = call
        .authorization
        .as_deref()
        .and_then(crate::auth::bearer_or_bare);
    let owner: Owner = crate::auth::authenticate(&cluster.sessions.config().auth, token)?;
    let session = cluster.sessions.get(&call.id, &owner)?;
    Ok((session, call))
}

async fn reply_result(query: &zenoh::query::Query, result: Result<Vec<u8>, ApiError>) {
    let sent = match result {
        Ok(bytes) => query.reply(query.key_expr().clone(), bytes).await,
        Err(e) => {
            let refusal = Refusal {
                status: e.status,
                code: e.code.to_string(),
                message: e.message,
            };
            query
                .reply_err(serde_json::to_vec(&refusal).unwrap_or_default())
                .await
        }
    };
    if let Err(e) = sent {
        tracing::debug!("replying to a cluster call: {e}");
    }
}

/// Owner side of [`Cluster::push`].
pub(crate) async fn answer_push(cluster: Arc<Cluster>, query: zenoh::query::Query) {
    let result = async {
        let (session, _) = session_of(&cluster, &query)?;
        let payload = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        session.apply_encoded(&payload).await?;
        Ok(Vec::new())
    }
    .await;
    reply_result(&query, result).await;
}

/// Owner side of [`Cluster::watch`]: starts the relay task, then replies.
pub(crate) async fn answer_watch(cluster: Arc<Cluster>, query: zenoh::query::Query) {
    let result = async {
        let (session, call) = session_of(&cluster, &query)?;
        let prefix = format!("{CLUSTER_ROOT}/relay/");
        let valid = call.relay.strip_prefix(&prefix).is_some_and(|rest| {
            rest.split('/').count() == 2
                && rest
                    .split('/')
                    .all(|c| !c.is_empty() && !c.contains(['*', '$', '?', '#']))
        });
        if !valid {
            return Err(ApiError::bad_request(
                "a relay key outside relfusion/cluster/relay",
            ));
        }
        // Subscribe before looking at the state (an end between the two is not missed) and
        // before replying (every update after the client's 101 reaches it).
        let events = session.subscribe();
        let ended = session.info().state.is_terminal();
        if ended && call.format == RelayFormat::Protobuf {
            return Ok(END_MARKER.to_vec());
        }
        let zenoh = cluster
            .zenoh()
            .ok_or_else(|| ApiError::unavailable("the cluster is not joined"))?
            .clone();
        let publisher = zenoh
            .declare_publisher(call.relay.clone())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(|e| ApiError::internal(format!("Zenoh relay publisher: {e}")))?;
        if ended {
            // The server-sent events of an ended session: its last event, then the end.
            let last = RelayedSse::of(&crate::session::SessionEvent::last_of(session.info()));
            tokio::spawn(async move {
                let _ = publisher.put(last.bytes()).await;
                let _ = publisher
                    .put(Vec::<u8>::new())
                    .attachment(END_MARKER.to_vec())
                    .await;
                let _ = publisher.undeclare().await;
            });
        } else {
            let format = call.format;
            tokio::spawn(relay_updates(
                cluster.clone(),
                session,
                events,
                publisher,
                format,
            ));
        }
        Ok(Vec::new())
    }
    .await;
    reply_result(&query, result).await;
}

async fn relay_updates(
    cluster: Arc<Cluster>,
    session: Arc<crate::session::Session>,
    mut events: tokio::sync::broadcast::Receiver<crate::session::SessionEvent>,
    publisher: zenoh::pubsub::Publisher<'static>,
    format: RelayFormat,
) {
    let id = session.id().to_string();
    let mut tick = tokio::time::interval(RELAY_CHECK);
    let mut idle = 0;
    let deleted = session.deleted();
    tokio::pin!(deleted);
    loop {
        let received = tokio::select! {
            received = events.recv() => received,
            _ = &mut deleted => break,
            _ = tick.tick() => {
                let listening = publisher
                    .matching_status()
                    .await
                    .map(|m| m.matching())
                    .unwrap_or(false);
                idle = if listening { 0 } else { idle + 1 };
                if idle >= RELAY_IDLE_CHECKS || !cluster.sessions.holds(&id) {
                    break;
                }
                continue;
            }
        };
        let event = match received {
            Ok(event) => event,
            Err(RecvError::Lagged(skipped)) => {
                let bytes = match format {
                    RelayFormat::Protobuf => ServerMessage {
                        message: Some(server_message::Message::Error(v1::Error {
                            code: ErrorCode::ResourceExhausted as i32,
                            message: format!("{skipped} updates skipped: this client reads too slowly; the trajectory endpoint has them all"),
                        })),
                    }
                    .encode_to_vec(),
                    RelayFormat::Sse => RelayedSse {
                        event: "lagged".into(),
                        data: serde_json::json!({ "type": "lagged", "skipped": skipped })
                            .to_string(),
                    }
                    .bytes(),
                };
                let _ = publisher.put(bytes).await;
                continue;
            }
            Err(RecvError::Closed) => break,
        };
        let messages: Vec<Vec<u8>> = match format {
            RelayFormat::Protobuf => event
                .to_proto(&id)
                .iter()
                .map(|m| m.encode_to_vec())
                .collect(),
            RelayFormat::Sse => vec![RelayedSse::of(&event).bytes()],
        };
        for bytes in messages {
            if let Err(e) = publisher.put(bytes).await {
                tracing::debug!(session = %id, "relaying an update: {e}");
            }
        }
        if event.is_last() {
            break;
        }
    }
    let _ = publisher
        .put(Vec::<u8>::new())
        .attachment(END_MARKER.to_vec())
        .await;
    let _ = publisher.undeclare().await;
}
