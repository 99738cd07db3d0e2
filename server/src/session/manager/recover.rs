//! Restart recovery: what a previous run left in the store becomes sessions again (see the
//! module docs of [`super`]).

use std::sync::Arc;

use super::*;

impl SessionManager {
    pub(super) fn recover(&self) -> Result<(), ServerError> {
        for key in self.store.list("expired/")? {
            let Some(id) = key
                .strip_prefix("expired/")
                .and_then(|k| k.strip_suffix(".json"))
            else {
                continue;
            };
            let owner = self
                .store
                .get(&key)?
                .and_then(|bytes| serde_json::from_slice::<Owner>(&bytes).ok());
            if let Some(owner) = owner {
                self.expired
                    .write()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert(id.to_string(), owner);
            }
        }
        let ids = session_ids(&self.store.list("sessions/")?);
        let mut resumed = Vec::new();
        for id in ids {
            let meta = match SessionMeta::load(self.store.as_ref(), &id) {
                Ok(Some(meta)) => meta,
                // With a shared store, another node may be storing that upload right now.
                Ok(None) if self.store.shared() => continue,
                Ok(None) => {
                    tracing::info!(session = %id, "removing an unacknowledged upload");
                    self.store.delete_prefix(&session_prefix(&id))?;
                    continue;
                }
                Err(e) => {
                    tracing::error!(session = %id, "unreadable metadata, skipped: {e}");
                    continue;
                }
            };
            if self.store.shared() && meta.node.as_deref().is_some_and(|n| n != self.node()) {
                continue; // another node's (it recovers its own, or the cluster takes it over)
            }
            let interrupted = "interrupted: the server stopped while this live session ran; \
                               results up to the last checkpoint are kept";
            if let Some(session) = self.revive(meta, interrupted)? {
                tracing::info!(session = %id, "re-running an unfinished upload");
                resumed.push(session);
            }
        }
        resumed.sort_by_key(|s| s.info().created_unix);
        for session in resumed {
            self.enqueue(&session);
        }
        Ok(())
    }

    /// Makes a stored session this node's again: an unfinished upload re-runs from scratch
    /// (returned: the caller queues it), an unfinished live session fails with `interrupted`
    /// (its stream is gone), a finished one is served as it is.
    fn revive(
        &self,
        mut meta: SessionMeta,
        interrupted: &str,
    ) -> Result<Option<Arc<Session>>, ServerError> {
        let id = meta.id.clone();
        let changed = !meta.state.is_terminal() || meta.node.as_deref() != Some(self.node());
        meta.node = Some(self.node().to_string());
        let mut resume = false;
        if !meta.state.is_terminal() {
            match meta.kind {
                SessionKind::Upload => {
                    // Re-run from scratch: progress restarts at zero.
                    meta.state = SessionState::Queued;
                    meta.counters = Default::default();
                    resume = true;
                }
                SessionKind::Live => {
                    meta.state = SessionState::Failed;
                    meta.error = Some(interrupted.into());
                }
            }
        }
        // A re-run must fit this server's limits, which may have changed since.
        let max_keyframes = match self.map_limit(&meta.camera, &meta.config) {
            Ok(n) => n,
            Err(e) if resume => {
                meta.state = SessionState::Failed;
                meta.error = Some(format!("cannot re-run: {}", e.message));
                resume = false;
                0
            }
            Err(_) => 0,
        };
        let session = Arc::new(self.build(meta, max_keyframes));
        if changed {
            // The store now names this node (and the new state) as the session's.
            session.meta().save(self.store.as_ref())?;
        }
        self.write_sessions().insert(id, session.clone());
        Ok(resume.then_some(session))
    }

    /// Queues a revived upload, or starts it when a slot is free.
    fn enqueue(&self, session: &Arc<Session>) {
        if self.queue_or_slot(&mut lock_admission(&self.admission), session) {
            self.start_or_release(session, self.model.clone());
        }
    }

    /// Takes over the sessions a node that left the cluster held (shared store only; see
    /// `cluster::failover`): unfinished ones as at a restart, finished ones to serve their
    /// results from the store. `pick` says, per session id, whether this node is the one to
    /// take it. Returns the ids taken.
    pub fn adopt_from(&self, left: &str, pick: impl Fn(&str) -> bool) -> Vec<String> {
        if !self.store.shared() || left == self.node() {
            return Vec::new();
        }
        let mut taken = Vec::new();
        let ids = match self.store.list("sessions/") {
            Ok(keys) => session_ids(&keys),
            Err(e) => {
                tracing::error!("listing sessions to take over from {left}: {e}");
                return taken;
            }
        };
        for id in ids {
            if !pick(&id) || self.read_sessions().contains_key(&id) {
                continue;
            }
            let meta = match SessionMeta::load(self.store.as_ref(), &id) {
                Ok(Some(meta)) => meta,
                _ => continue,
            };
            if meta.node.as_deref() != Some(left) {
                continue;
            }
            let reason = format!(
                "interrupted: node {left}, which ran this live session, left the cluster; \
                 results up to the last checkpoint are kept"
            );
            match self.revive(meta, &reason) {
                Ok(Some(session)) => {
                    tracing::warn!(session = %id, node = left, "re-running an upload of a node that left");
                    self.enqueue(&session);
                    taken.push(id);
                }
                Ok(None) => taken.push(id),
                Err(e) => tracing::error!(session = %id, "taking over from {left}: {e}"),
            }
        }
        taken
    }

    /// Runs here the stored, unfinished upload `id` whose metadata names node `from`: on the
    /// node placement chose, when the node that received the upload hands it over (`from` is
    /// this node; [`crate::cluster::Cluster::hand_off`]), or on the receiving node, when the
    /// chosen one did not answer (`from` is the chosen one).
    pub fn take_over(&self, id: &str, from: &str) -> Result<(), String> {
        if !self.store.shared() {
            return Err("this node's store is not shared".into());
        }
        if self.read_sessions().contains_key(id) {
            return Ok(()); // taken already (a repeated call)
        }
        let meta = SessionMeta::load(self.store.as_ref(), id)?
            .ok_or_else(|| format!("no stored session {id}"))?;
        if meta.kind != SessionKind::Upload || meta.state.is_terminal() {
            return Err(format!("session {id} is not an unfinished upload"));
        }
        if meta.node.as_deref() != Some(from) {
            return Err(format!(
                "session {id} is node {}'s, not {from}'s",
                meta.node.as_deref().unwrap_or("?")
            ));
        }
        match self.revive(meta, "") {
            Ok(Some(session)) => {
                self.enqueue(&session);
                Ok(())
            }
            Ok(None) => Ok(()), // failed at once (it no longer fits): its error says why
            Err(e) => Err(format!("taking session {id}: {e}")),
        }
    }
}

/// The session ids of `sessions/…` keys, each once.
fn session_ids(keys: &[String]) -> Vec<String> {
    let mut ids: Vec<String> = keys
        .iter()
        .filter_map(|k| k.strip_prefix("sessions/")?.split('/').next())
        .map(String::from)
        .collect();
    ids.dedup();
    ids
}
