//! Placing sessions on another node.
//!
//! A Zenoh create placed elsewhere is relayed whole to the chosen node's own create queryable
//! (`relfusion/cluster/nodes/<node>/create/<tenant>`), whose reply goes back as it is.
//!
//! An upload is received and stored by the node it was sent to (its bytes
//! stay in one HTTP request, not a Zenoh message), which then hands the stored session to
//! the node placement chose with one query, `relfusion/cluster/nodes/<node>/adopt` (payload:
//! the session id). The chosen node reads the metadata from the shared store and queues the
//! upload; when it does not answer in time, the receiving node runs it itself. Either way
//! the upload was acknowledged once, from the store, before any of this.

use std::time::Duration;

use super::{Cluster, node_key};
use crate::session::types::valid_session_id;

/// The queryable's leaf.
pub const ADOPT: &str = "adopt";

/// How long a create relayed to the node placement chose may take before this node creates
/// the session itself.
const PLACED_TIMEOUT: Duration = Duration::from_secs(5);

/// How long the receiving node waits for the chosen one to take an upload (it only reads
/// one small object and queues the session).
const HANDOFF_TIMEOUT: Duration = Duration::from_secs(10);

impl Cluster {
    /// Relays a Zenoh create of `tenant` (its payload and token attachment) to `node`'s own
    /// create queryable: the reply or refusal as it is; `None` when `node` did not answer in
    /// [`PLACED_TIMEOUT`].
    pub async fn relay_create(
        &self,
        node: &str,
        tenant: &str,
        payload: Vec<u8>,
        attachment: Option<zenoh::bytes::ZBytes>,
    ) -> Option<Result<Vec<u8>, Vec<u8>>> {
        let mut get = self
            .zenoh()?
            .get(node_key(node, &format!("create/{tenant}")))
            .payload(payload)
            .timeout(PLACED_TIMEOUT);
        if let Some(token) = attachment {
            get = get.attachment(token);
        }
        let reply = match get.await {
            Ok(replies) => replies.recv_async().await.ok(),
            Err(_) => None,
        }?;
        Some(match reply.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(error) => Err(error.payload().to_bytes().into_owned()),
        })
    }

    /// Asks `node` to run the stored upload `id` (its metadata names `node`). `Err` says why
    /// it did not take it; the caller then runs it itself
    /// ([`crate::session::SessionManager::take_over`]).
    pub async fn hand_off(&self, node: &str, id: &str) -> Result<(), String> {
        let zenoh = self.zenoh().ok_or("no Zenoh session")?;
        let replies = zenoh
            .get(node_key(node, ADOPT))
            .payload(id.as_bytes().to_vec())
            .timeout(HANDOFF_TIMEOUT)
            .await
            .map_err(|e| format!("asking node {node}: {e}"))?;
        match replies.recv_async().await {
            Ok(reply) => match reply.result() {
                Ok(_) => Ok(()),
                Err(e) => Err(format!(
                    "node {node} refused: {}",
                    String::from_utf8_lossy(&e.payload().to_bytes())
                )),
            },
            Err(_) => Err(format!(
                "node {node} did not answer in {} s",
                HANDOFF_TIMEOUT.as_secs()
            )),
        }
    }
}

/// Answers `…/nodes/<me>/adopt`: takes the upload named in the payload, if the store says it
/// is this node's to run.
pub(crate) async fn answer_adopt(cluster: std::sync::Arc<Cluster>, query: zenoh::query::Query) {
    let id = query
        .payload()
        .map(|p| String::from_utf8_lossy(&p.to_bytes()).into_owned())
        .unwrap_or_default();
    let outcome = if valid_session_id(&id) {
        let sessions = cluster.sessions.clone();
        let me = cluster.node().to_string();
        let taking = id.clone();
        tokio::task::spawn_blocking(move || sessions.take_over(&taking, &me))
            .await
            .unwrap_or_else(|e| Err(format!("taking the upload failed: {e}")))
    } else {
        Err("not a session id".to_string())
    };
    let sent = match outcome {
        Ok(()) => {
            tracing::info!(session = %id, "took an upload placed on this node");
            query
                .reply(query.key_expr().clone(), Vec::<u8>::new())
                .await
        }
        Err(e) => {
            tracing::warn!(session = %id, "refused an upload placed on this node: {e}");
            query.reply_err(e.into_bytes()).await
        }
    };
    if let Err(e) = sent {
        tracing::debug!("answering an upload hand-off: {e}");
    }
}
