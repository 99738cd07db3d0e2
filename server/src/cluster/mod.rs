//! Many relfusiond nodes as one service, over the Zenoh network they all join (a `zenohd`
//! router, or peers): no cluster protocol of our own, only Zenoh queryables, pub/sub and
//! liveliness.
//!
//! - Membership: each node holds a liveliness token, `relfusion/cluster/nodes/<node>`, and
//!   publishes its load on `relfusion/nodes/<node>/status` (every 2 s); every node follows both
//!   ([`failover`]). A node that dies (`kill -9`, a lost link) loses its token at once.
//! - Placement ([`Cluster::place`]): a session created on any node goes to the node with a real
//!   GPU, then the most free slots (this node on a tie: no hop); the session info names it.
//!   A live session's creation is forwarded there; an upload is stored by the node that
//!   received it and handed over ([`handoff`]).
//! - Routing ([`forward`]): a request for a session this node does not hold is forwarded to
//!   the node that answers for it (`relfusion/cluster/nodes/*/sessions/<id>`) as one Zenoh
//!   query, `relfusion/cluster/nodes/<node>/http`, which the owner runs through its own HTTP
//!   router (auth included: the owner checks the bearer token as if it were called directly).
//!   The reply comes back only when the owner answered, so a frame waiting for queue room on the
//!   owner holds its sender's request: backpressure is kept end to end.
//! - WebSocket streams through any node ([`relay`]): frames go to the owner as queries (one at
//!   a time, the next read only when the owner took the last), updates come back on a
//!   per-stream key the owner publishes.
//! - Failover ([`failover`]): with a shared store (S3), when a node's token goes, the nodes
//!   left take over its sessions (each by rendezvous hashing of the session id over the nodes
//!   alive): unfinished uploads re-run from the store, unfinished live sessions end with an
//!   error (WebSocket clients streaming through another node get it and a close), finished
//!   sessions' results are served again.
//!
//! Zenoh access control confines tenants to `relfusion/tenants/<tenant>/**` (and reading node
//! status), so the `relfusion/cluster/**` keys, which carry bearer tokens between nodes, are
//! for nodes only.

pub mod failover;
pub mod forward;
pub mod handoff;
pub mod relay;

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tokio::sync::broadcast;

use crate::session::SessionManager;

/// Prefix of the node-to-node keys.
pub const CLUSTER_ROOT: &str = "relfusion/cluster";

/// `relfusion/cluster/nodes/<node>`: the node's liveliness token.
pub fn alive_key(node: &str) -> String {
    format!("{CLUSTER_ROOT}/nodes/{node}")
}

/// `relfusion/cluster/nodes/<node>/<leaf>`: one of the node's queryables.
pub fn node_key(node: &str, leaf: &str) -> String {
    format!("{CLUSTER_ROOT}/nodes/{node}/{leaf}")
}

/// How long a lookup of a session's node waits for an answer.
const LOOKUP_TIMEOUT: Duration = Duration::from_secs(2);
/// A node's status older than this is not used for placement (3 missed publications).
const STATUS_STALE: Duration = Duration::from_secs(7);
/// Session → node answers are kept this long (a session does not move unless its node goes).
const OWNER_CACHE_TTL: Duration = Duration::from_secs(30);
/// Bound of the session → node cache.
const OWNER_CACHE_MAX: usize = 10_000;

/// What a node publishes about itself (`relfusion/nodes/<node>/status`), as placement reads it.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct NodeLoad {
    pub node: String,
    #[serde(default)]
    pub sessions_active: usize,
    #[serde(default)]
    pub max_sessions: usize,
    #[serde(default)]
    pub accepting: bool,
    /// Real GPUs of the node (0: its kernels run on the CPU fallback).
    #[serde(default)]
    pub gpus: usize,
    /// Its HTTP address for clients (`[zenoh] advertise`), if given.
    #[serde(default)]
    pub advertise: String,
}

impl NodeLoad {
    fn free(&self) -> usize {
        self.max_sessions.saturating_sub(self.sessions_active)
    }
}

/// The best node for a new session among `candidates` (this node first): accepting with a
/// free slot; a real GPU before none; then the most free slots; the first listed on a tie.
pub fn best_node(candidates: &[NodeLoad]) -> Option<&NodeLoad> {
    let mut best: Option<&NodeLoad> = None;
    for c in candidates.iter().filter(|c| c.accepting && c.free() > 0) {
        let better = best.is_none_or(|b| ((c.gpus > 0), c.free()) > ((b.gpus > 0), b.free()));
        if better {
            best = Some(c);
        }
    }
    best
}

/// A peer as this node knows it.
#[derive(Debug)]
struct Peer {
    load: NodeLoad,
    seen: Instant,
}

/// This node's view of the cluster and its Zenoh session (set once Zenoh is up).
#[derive(Debug)]
pub struct Cluster {
    node: String,
    advertise: String,
    gpus: usize,
    pub(crate) sessions: Arc<SessionManager>,
    zenoh: OnceLock<zenoh::Session>,
    /// The HTTP application forwarded requests run through (set by `run`).
    router: OnceLock<axum::Router>,
    /// Nodes whose liveliness token is up (this one excluded).
    alive: Mutex<HashSet<String>>,
    peers: Mutex<HashMap<String, Peer>>,
    owners: Mutex<HashMap<String, (String, Instant)>>,
    /// Names of nodes as they leave (WebSocket relays end their streams).
    left: broadcast::Sender<String>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Cluster {
    /// The cluster side of this node; inert until [`Cluster::join`].
    pub fn new(sessions: Arc<SessionManager>) -> Arc<Self> {
        let config = sessions.config();
        let gpus =
            relfusion_slam::gpu::gpu_adapter_count(&relfusion_slam::gpu::GpuConfig::default());
        Arc::new(Self {
            node: config.zenoh.node.clone(),
            advertise: config.zenoh.advertise.clone(),
            gpus,
            sessions,
            zenoh: OnceLock::new(),
            router: OnceLock::new(),
            alive: Mutex::default(),
            peers: Mutex::default(),
            owners: Mutex::default(),
            left: broadcast::channel(64).0,
        })
    }

    pub fn node(&self) -> &str {
        &self.node
    }

    /// The Zenoh session, once the node has joined.
    pub fn zenoh(&self) -> Option<&zenoh::Session> {
        self.zenoh.get()
    }

    /// Sets the HTTP application forwarded requests are served by.
    pub fn set_router(&self, router: axum::Router) {
        let _ = self.router.set(router);
    }

    /// This node's load, as its status publishes it.
    pub fn local_load(&self) -> NodeLoad {
        let (sessions_active, max_sessions) = self.sessions.load();
        NodeLoad {
            node: self.node.clone(),
            sessions_active,
            max_sessions,
            accepting: self.sessions.is_accepting(),
            gpus: self.gpus,
            advertise: self.advertise.clone(),
        }
    }

    /// Records a peer's published status.
    pub(crate) fn observe(&self, load: NodeLoad) {
        if load.node == self.node {
            return;
        }
        lock(&self.peers).insert(
            load.node.clone(),
            Peer {
                load,
                seen: Instant::now(),
            },
        );
    }

    /// The node a new session should run on: `None` for this one (also when Zenoh is down or
    /// no peer is better).
    pub fn place(&self) -> Option<String> {
        self.zenoh.get()?;
        let alive = lock(&self.alive).clone();
        let mut candidates = vec![self.local_load()];
        {
            let peers = lock(&self.peers);
            let mut names: Vec<&String> = peers.keys().collect();
            names.sort();
            for name in names {
                let peer = &peers[name];
                if alive.contains(name) && peer.seen.elapsed() < STATUS_STALE {
                    candidates.push(peer.load.clone());
                }
            }
        }
        let best = best_node(&candidates)?.node.clone();
        if best == self.node {
            return None;
        }
        // Count the session at once: the next status is up to 2 s away, and a burst of
        // creates must spread, not all land on the node that looked emptiest.
        if let Some(peer) = lock(&self.peers).get_mut(&best) {
            peer.load.sessions_active += 1;
        }
        Some(best)
    }

    /// The node that holds session `id` (not this one), asked over Zenoh; `None` when no node
    /// answers (unknown session).
    pub async fn owner_of(&self, id: &str) -> Option<String> {
        let zenoh = self.zenoh.get()?;
        if let Some((node, at)) = lock(&self.owners).get(id)
            && at.elapsed() < OWNER_CACHE_TTL
            && lock(&self.alive).contains(node)
        {
            return Some(node.clone());
        }
        let key = format!("{CLUSTER_ROOT}/nodes/*/sessions/{id}");
        let replies = zenoh
            .get(&key)
            .target(zenoh::query::QueryTarget::All)
            .timeout(LOOKUP_TIMEOUT)
            .await
            .ok()?;
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else { continue };
            let node = sample
                .key_expr()
                .as_str()
                .strip_prefix(&format!("{CLUSTER_ROOT}/nodes/"))
                .and_then(|rest| rest.split('/').next())
                .map(String::from);
            if let Some(node) = node.filter(|n| *n != self.node) {
                let mut owners = lock(&self.owners);
                if owners.len() >= OWNER_CACHE_MAX {
                    owners.retain(|_, (_, at)| at.elapsed() < OWNER_CACHE_TTL);
                    if owners.len() >= OWNER_CACHE_MAX {
                        owners.clear();
                    }
                }
                owners.insert(id.to_string(), (node.clone(), Instant::now()));
                return Some(node);
            }
        }
        None
    }

    /// The members alive with their last published load (this node's current one), sorted.
    pub fn loads(&self) -> Vec<NodeLoad> {
        let alive = lock(&self.alive).clone();
        let peers = lock(&self.peers);
        let mut loads = vec![self.local_load()];
        for name in alive {
            let load = peers.get(&name).map_or_else(
                || NodeLoad {
                    node: name.clone(),
                    ..NodeLoad::default()
                },
                |p| p.load.clone(),
            );
            loads.push(load);
        }
        loads.sort_by(|a, b| a.node.cmp(&b.node));
        loads
    }

    /// Whether `node` holds a liveliness token now.
    pub fn is_alive(&self, node: &str) -> bool {
        node == self.node || lock(&self.alive).contains(node)
    }

    /// Nodes leaving, from now on.
    pub fn departures(&self) -> broadcast::Receiver<String> {
        self.left.subscribe()
    }

    /// The nodes alive now, this one included, sorted.
    pub fn members(&self) -> Vec<String> {
        let mut nodes: Vec<String> = lock(&self.alive).iter().cloned().collect();
        nodes.push(self.node.clone());
        nodes.sort();
        nodes.dedup();
        nodes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load(node: &str, active: usize, max: usize, gpus: usize) -> NodeLoad {
        NodeLoad {
            node: node.into(),
            sessions_active: active,
            max_sessions: max,
            accepting: true,
            gpus,
            advertise: String::new(),
        }
    }

    #[test]
    fn placement_prefers_a_gpu_then_free_slots_then_the_first_listed() {
        let a = load("a", 1, 3, 0);
        let b = load("b", 0, 3, 0);
        let c = load("c", 2, 3, 1);
        assert_eq!(
            best_node(&[a.clone(), b.clone()]).map(|n| &*n.node),
            Some("b")
        );
        assert_eq!(
            best_node(&[a.clone(), b.clone(), c.clone()]).map(|n| &*n.node),
            Some("c")
        );
        let a_tie = load("a", 0, 3, 0);
        assert_eq!(best_node(&[a_tie, b.clone()]).map(|n| &*n.node), Some("a"));
        let full = load("f", 3, 3, 1);
        let mut closed = load("x", 0, 9, 1);
        closed.accepting = false;
        assert!(
            best_node(&[full, closed]).is_none(),
            "no free slot anywhere"
        );
    }
}
