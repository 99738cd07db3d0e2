//! Joining the cluster, following its members, and taking over from a node that leaves.
//!
//! [`join`] declares this node's liveliness token and queryables and follows the other nodes'
//! tokens (with history: the nodes already up count at once) and statuses. When a token goes,
//! its node is gone: its cached sessions are forgotten, WebSocket relays from it end with an
//! error ([`Cluster::departures`]), and — with a shared store — each session it ran is taken
//! over by exactly one of the nodes left, the one that ranks first for the session id by
//! rendezvous hashing over the members (every node computes the same choice from the same
//! membership, with no election): unfinished uploads re-run, unfinished live sessions fail,
//! finished sessions are served from the store again.

use std::sync::Arc;

use tokio::sync::{Semaphore, watch};
use tokio::task::JoinHandle;
use zenoh::sample::SampleKind;

use super::{CLUSTER_ROOT, Cluster, NodeLoad, alive_key, forward, handoff, lock, node_key, relay};
use crate::ServerError;

/// Cluster calls answered at once (each may wait: a frame for queue room, a download).
const CONCURRENT_CALLS: usize = 256;

/// FNV-1a, 64 bit: a hash every node computes alike (std's hasher is not promised stable).
fn fnv1a(parts: &[&str]) -> u64 {
    let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
    for part in parts {
        for byte in part.bytes().chain(std::iter::once(0)) {
            hash ^= u64::from(byte);
            hash = hash.wrapping_mul(0x0100_0000_01b3);
        }
    }
    hash
}

/// The member that takes over session `id` (rendezvous hashing).
pub fn heir<'a>(members: &'a [String], id: &str) -> Option<&'a str> {
    members
        .iter()
        .max_by_key(|node| (fnv1a(&[node.as_str(), id]), node.as_str()))
        .map(String::as_str)
}

/// Joins the cluster on `zenoh`: token, followers and queryables, until `shutdown`.
pub async fn join(
    cluster: Arc<Cluster>,
    zenoh: zenoh::Session,
    shutdown: watch::Receiver<bool>,
) -> Result<Vec<JoinHandle<()>>, ServerError> {
    let startup =
        |what: &str, e: zenoh::Error| ServerError::Startup(format!("cluster {what}: {e}"));
    let _ = cluster.zenoh.set(zenoh.clone());
    let node = cluster.node.clone();
    let token = zenoh
        .liveliness()
        .declare_token(alive_key(&node))
        .await
        .map_err(|e| startup("liveliness token", e))?;
    let members = zenoh
        .liveliness()
        .declare_subscriber(format!("{CLUSTER_ROOT}/nodes/*"))
        .history(true)
        .await
        .map_err(|e| startup("members", e))?;
    let statuses = zenoh
        .declare_subscriber("relfusion/nodes/*/status")
        .await
        .map_err(|e| startup("statuses", e))?;
    let mut tasks = Vec::new();
    {
        let cluster = cluster.clone();
        let mut shutdown = shutdown.clone();
        tasks.push(tokio::spawn(async move {
            loop {
                tokio::select! {
                    sample = members.recv_async() => match sample {
                        Ok(sample) => membership(&cluster, &sample),
                        Err(_) => break,
                    },
                    sample = statuses.recv_async() => match sample {
                        Ok(sample) => {
                            if let Ok(load) = serde_json::from_slice::<NodeLoad>(&sample.payload().to_bytes()) {
                                cluster.observe(load);
                            }
                        }
                        Err(_) => break,
                    },
                    _ = shutdown.wait_for(|stop| *stop) => break,
                }
            }
            let _ = token.undeclare().await;
        }));
    }
    let calls = Arc::new(Semaphore::new(CONCURRENT_CALLS));
    for (leaf, handler) in [
        (forward::HTTP, Handler::Http),
        (relay::PUSH, Handler::Push),
        (relay::WATCH, Handler::Watch),
        ("sessions/*", Handler::Lookup),
        (handoff::ADOPT, Handler::Adopt),
    ] {
        tasks.push(
            serve(
                cluster.clone(),
                node_key(&node, leaf),
                handler,
                calls.clone(),
                shutdown.clone(),
            )
            .await?,
        );
    }
    Ok(tasks)
}

#[derive(Clone, Copy)]
enum Handler {
    Http,
    Push,
    Watch,
    Lookup,
    Adopt,
}

/// One queryable of this node; each query is answered in its own task.
async fn serve(
    cluster: Arc<Cluster>,
    key: String,
    handler: Handler,
    calls: Arc<Semaphore>,
    mut shutdown: watch::Receiver<bool>,
) -> Result<JoinHandle<()>, ServerError> {
    let zenoh = cluster
        .zenoh()
        .cloned()
        .ok_or_else(|| ServerError::Startup("no Zenoh".into()))?;
    let queryable = zenoh
        .declare_queryable(key.clone())
        .await
        .map_err(|e| ServerError::Startup(format!("declaring {key}: {e}")))?;
    Ok(tokio::spawn(async move {
        loop {
            let query = tokio::select! {
                query = queryable.recv_async() => match query {
                    Ok(query) => query,
                    Err(_) => break,
                },
                _ = shutdown.wait_for(|stop| *stop) => break,
            };
            let Ok(permit) = calls.clone().acquire_owned().await else {
                break;
            };
            let cluster = cluster.clone();
            tokio::spawn(async move {
                match handler {
                    Handler::Http => forward::answer(cluster, query).await,
                    Handler::Push => relay::answer_push(cluster, query).await,
                    Handler::Watch => relay::answer_watch(cluster, query).await,
                    Handler::Lookup => answer_lookup(&cluster, query).await,
                    Handler::Adopt => handoff::answer_adopt(cluster, query).await,
                }
                drop(permit);
            });
        }
    }))
}

/// Answers `…/nodes/<me>/sessions/<id>` when this node holds session `id`.
async fn answer_lookup(cluster: &Cluster, query: zenoh::query::Query) {
    let id = query
        .key_expr()
        .as_str()
        .rsplit('/')
        .next()
        .unwrap_or_default()
        .to_string();
    if !id.is_empty() && !id.contains('*') && cluster.sessions.holds(&id) {
        let key = node_key(&cluster.node, &format!("sessions/{id}"));
        if let Err(e) = query.reply(key, Vec::<u8>::new()).await {
            tracing::debug!("answering a session lookup: {e}");
        }
    }
}

/// A member's token appeared or went.
fn membership(cluster: &Arc<Cluster>, sample: &zenoh::sample::Sample) {
    let Some(node) = sample
        .key_expr()
        .as_str()
        .strip_prefix(&format!("{CLUSTER_ROOT}/nodes/"))
        .filter(|n| !n.contains('/'))
        .map(String::from)
    else {
        return;
    };
    if node == cluster.node {
        return;
    }
    match sample.kind() {
        SampleKind::Put => {
            tracing::info!(node = %node, "a node joined the cluster");
            lock(&cluster.alive).insert(node);
        }
        SampleKind::Delete => {
            tracing::warn!(node = %node, "a node left the cluster");
            lock(&cluster.alive).remove(&node);
            lock(&cluster.peers).remove(&node);
            lock(&cluster.owners).retain(|_, (n, _)| *n != node);
            let _ = cluster.left.send(node.clone());
            let cluster = cluster.clone();
            tokio::task::spawn_blocking(move || {
                let members = cluster.members();
                let me = cluster.node.clone();
                let taken = cluster
                    .sessions
                    .adopt_from(&node, |id| heir(&members, id) == Some(me.as_str()));
                if !taken.is_empty() {
                    tracing::warn!(node = %node, sessions = ?taken, "took over sessions of a node that left");
                }
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_session_has_one_heir_and_heirs_spread() {
        let members: Vec<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
        let mut counts = std::collections::HashMap::new();
        for i in 0..300 {
            let id = format!("s-{i:024x}");
            let heir = heir(&members, &id).expect("an heir");
            assert_eq!(
                heir,
                super::heir(&members, &id).expect("an heir"),
                "deterministic"
            );
            *counts.entry(heir.to_string()).or_insert(0) += 1;
        }
        assert_eq!(counts.len(), 3, "{counts:?}");
        assert!(counts.values().all(|&n| n > 60), "{counts:?}");
        // Removing a member moves only its sessions.
        let fewer: Vec<String> = ["a", "c"].iter().map(|s| s.to_string()).collect();
        for i in 0..300 {
            let id = format!("s-{i:024x}");
            let before = heir(&members, &id).expect("an heir");
            if before != "b" {
                assert_eq!(heir(&fewer, &id).expect("an heir"), before);
            }
        }
        assert!(heir(&[], "s-1").is_none());
    }
}
