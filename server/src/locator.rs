//! Where a session runs, as the transports see it: here ([`Located::Here`]) or on another
//! node of the cluster ([`Located::Elsewhere`]), behind one interface.
//!
//! HTTP and Zenoh ask the locator; they never name the cluster. A session found here is
//! served as it is; one held elsewhere is reached through a [`Remote`]: a plain request is
//! forwarded whole, a stream of updates is followed ([`Remote::follow`]), a client message is
//! pushed ([`Remote::push`]). New sessions go where placement says ([`Locator::place`]).
//! Without Zenoh the cluster is inert and every session is here.

use std::sync::Arc;

use axum::extract::Request;
use axum::http::HeaderMap;
use axum::response::Response;
use tokio::sync::broadcast;
use tokio::task::JoinHandle;

use crate::auth::Owner;
use crate::cluster::relay::{Relay, Relayed, relayed};
use crate::cluster::{Cluster, NodeLoad, forward::FORWARDED, node_key};
use crate::session::admission::UploadTicket;
use crate::session::types::SessionInfo;
use crate::session::{NewUpload, Session, SessionManager};
use crate::{ApiError, ServerError};

pub use crate::cluster::relay::{RelayFormat, RelayedSse};

/// Where a session is.
#[derive(Debug)]
pub enum Located {
    Here(Arc<Session>),
    Elsewhere(Remote),
}

/// Who sent a request: a client, or another node forwarding a client's request (which is
/// served here or refused, never forwarded again: no loops).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Hop {
    FromClient,
    FromNode,
}

impl Hop {
    /// The hop of an HTTP request (a forwarded one carries the forwarding node's name).
    pub fn of(headers: &HeaderMap) -> Self {
        if headers.contains_key(FORWARDED) {
            Self::FromNode
        } else {
            Self::FromClient
        }
    }
}

/// The sessions of this node and of the cluster it belongs to.
#[derive(Debug)]
pub struct Locator {
    sessions: Arc<SessionManager>,
    cluster: Arc<Cluster>,
}

impl Locator {
    pub fn new(cluster: Arc<Cluster>) -> Self {
        Self {
            sessions: cluster.sessions.clone(),
            cluster,
        }
    }

    /// This node's sessions.
    pub fn sessions(&self) -> &Arc<SessionManager> {
        &self.sessions
    }

    /// This node's name.
    pub fn node(&self) -> &str {
        self.cluster.node()
    }

    /// Session `id` of `owner`: here, or (for a client's request) on the node that holds it.
    /// Not found anywhere: this node's error (404, or 410 when it expired here).
    pub async fn locate(&self, id: &str, owner: &Owner, hop: Hop) -> Result<Located, ApiError> {
        match self.sessions.get(id, owner) {
            Ok(session) => Ok(Located::Here(session)),
            Err(e) if e.status == 404 && hop == Hop::FromClient => {
                // The owner checks the token when it is reached.
                self.elsewhere(id).await.map(Located::Elsewhere).ok_or(e)
            }
            Err(e) => Err(e),
        }
    }

    /// Session `id` on another node, when this one does not hold it and another answers for
    /// it (whoever asks: the owner checks the caller).
    pub async fn elsewhere(&self, id: &str) -> Option<Remote> {
        if self.sessions.holds(id) {
            return None;
        }
        let node = self.cluster.owner_of(id).await?;
        Some(Remote {
            node: Node {
                cluster: self.cluster.clone(),
                name: node,
            },
            id: id.to_string(),
        })
    }

    /// The node a new session should run on: `None` for this one (single node, or no member
    /// has more room).
    pub fn place(&self) -> Option<Node> {
        let name = self.cluster.place()?;
        Some(Node {
            cluster: self.cluster.clone(),
            name,
        })
    }

    /// Whether this node is part of a cluster (its Zenoh session is up).
    pub fn joined(&self) -> bool {
        self.cluster.zenoh().is_some()
    }

    /// `GET path` on every other member with the caller's `authorization`: the 200 bodies.
    pub async fn gather(&self, path: &str, authorization: Option<&str>) -> Vec<Vec<u8>> {
        self.cluster.gather(path, authorization).await
    }

    /// The members alive and their load, sorted by name (this node included).
    pub fn members(&self) -> Vec<NodeLoad> {
        self.cluster.loads()
    }

    /// This node's load, as placement reads it.
    pub fn local_load(&self) -> NodeLoad {
        self.cluster.local_load()
    }

    /// Stores an upload as a session, here or, with a store the cluster shares, on the node
    /// placement chose (handed to it; run here when it does not answer). The upload is
    /// acknowledged from the store either way.
    pub async fn store_upload(
        &self,
        ticket: UploadTicket,
        upload: NewUpload<'_>,
    ) -> Result<SessionInfo, ApiError> {
        let placed = if self.sessions.shares_store() {
            self.place()
        } else {
            None
        };
        let Some(node) = placed else {
            return Ok(self.sessions.create_upload(ticket, upload).await?.info());
        };
        let node = node.name;
        let mut info = self
            .sessions
            .create_upload_for(&node, ticket, upload)
            .await?;
        if let Err(e) = self.cluster.hand_off(&node, &info.id).await {
            // Acknowledged already: run it here instead. Should this fail too, the metadata
            // still names `node`, which runs it at its next start, or its heir when it leaves.
            tracing::warn!(session = %info.id, "handing the upload to {node}: {e}; running it here");
            let (sessions, id) = (self.sessions.clone(), info.id.clone());
            let taken = tokio::task::spawn_blocking(move || sessions.take_over(&id, &node)).await;
            match taken {
                Ok(Ok(())) => info.node = Some(self.sessions.node().to_string()),
                Ok(Err(e)) => tracing::error!(session = %info.id, "taking the upload back: {e}"),
                Err(e) => tracing::error!(session = %info.id, "taking the upload back: {e}"),
            }
        }
        Ok(info)
    }

    /// This node's Zenoh key where another node creates a session placed here
    /// (`relfusion/cluster/nodes/<node>/create/<tenant>`).
    pub fn placed_create_key(&self, tenant: &str) -> String {
        node_key(self.cluster.node(), &format!("create/{tenant}"))
    }

    /// Makes this node a member of the cluster on `zenoh` (token, followers, queryables)
    /// until `shutdown`.
    pub async fn join(
        &self,
        zenoh: zenoh::Session,
        shutdown: tokio::sync::watch::Receiver<bool>,
    ) -> Result<Vec<JoinHandle<()>>, ServerError> {
        crate::cluster::failover::join(self.cluster.clone(), zenoh, shutdown).await
    }

    /// The HTTP application that serves requests forwarded by other nodes.
    pub fn serve_forwarded_with(&self, router: axum::Router) {
        self.cluster.set_router(router);
    }
}

/// Another node of the cluster.
#[derive(Clone, Debug)]
pub struct Node {
    cluster: Arc<Cluster>,
    name: String,
}

impl Node {
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Runs `request` on that node; its response (502 when it does not answer).
    pub async fn forward(&self, request: Request) -> Response {
        self.cluster.forward(&self.name, request).await
    }

    /// Runs a Zenoh create on that node's own create queryable: its reply or refusal as it
    /// is; `None` when it did not answer in time (then this node creates the session).
    pub async fn create(
        &self,
        tenant: &str,
        payload: Vec<u8>,
        attachment: Option<zenoh::bytes::ZBytes>,
    ) -> Option<Result<Vec<u8>, Vec<u8>>> {
        self.cluster
            .relay_create(&self.name, tenant, payload, attachment)
            .await
    }
}

/// A session another node holds.
#[derive(Clone, Debug)]
pub struct Remote {
    node: Node,
    id: String,
}

impl Remote {
    /// The node that holds it.
    pub fn node(&self) -> &str {
        &self.node.name
    }

    pub fn id(&self) -> &str {
        &self.id
    }

    /// Runs `request` (about this session) on its node.
    pub async fn forward(&self, request: Request) -> Response {
        self.node.forward(request).await
    }

    /// Follows the session's updates in `format` (`authorization`: the caller's, checked
    /// by the owner); `capacity` updates are buffered.
    pub async fn follow(
        &self,
        authorization: Option<String>,
        capacity: usize,
        format: RelayFormat,
    ) -> Result<Feed, ApiError> {
        let cluster = &self.node.cluster;
        // Departures first: a node that leaves while the relay starts is not missed.
        let departures = cluster.departures();
        let relay = cluster
            .watch(&self.node.name, &self.id, authorization, capacity, format)
            .await?;
        Ok(Feed {
            relay,
            departures,
            node: self.node.name.clone(),
        })
    }

    /// Hands one client message (protobuf `ClientMessage` bytes) to the session; returns
    /// once its node took it (a `wait` policy pushes back through both nodes).
    pub async fn push(
        &self,
        authorization: Option<String>,
        message: Vec<u8>,
    ) -> Result<(), ApiError> {
        let cluster = &self.node.cluster;
        cluster
            .push(&self.node.name, &self.id, authorization, message)
            .await
    }
}

/// The updates of a session another node holds.
#[derive(Debug)]
pub struct Feed {
    relay: Relay,
    departures: broadcast::Receiver<String>,
    node: String,
}

/// One thing a [`Feed`] says.
#[derive(Debug)]
pub enum Update {
    /// One update in the feed's format.
    Message(Vec<u8>),
    /// The session ended normally; nothing follows.
    End,
    /// The session's node left the cluster (the reason, for the client); nothing follows.
    NodeLeft(String),
    /// The relay broke off.
    Lost,
}

impl Feed {
    /// The session had ended before the feed started.
    pub fn already_ended(&self) -> bool {
        self.relay.ended
    }

    /// The next update.
    pub async fn next(&mut self) -> Update {
        loop {
            tokio::select! {
                sample = self.relay.subscriber.recv_async() => {
                    return match sample.as_ref().map(relayed) {
                        Ok(Relayed::Message(bytes)) => Update::Message(bytes),
                        Ok(Relayed::End) => Update::End,
                        Err(_) => Update::Lost,
                    };
                }
                node = next_departure(&mut self.departures) => {
                    if node == self.node {
                        return Update::NodeLeft(format!(
                            "node {node} running this session left the cluster: the session \
                             ended (results up to its last checkpoint are kept)"
                        ));
                    }
                }
            }
        }
    }
}

/// The next node to leave the cluster (departures missed by a slow reader are skipped); never,
/// once the cluster is gone.
async fn next_departure(departures: &mut broadcast::Receiver<String>) -> String {
    loop {
        match departures.recv().await {
            Ok(node) => return node,
            Err(broadcast::error::RecvError::Lagged(_)) => {}
            Err(broadcast::error::RecvError::Closed) => std::future::pending().await,
        }
    }
}
