//! Retention (`[retention]`): finished sessions are deleted `finished_ttl_s` after they ended;
//! a tombstone keeps their owner, so their ids answer 410 Gone rather than 404.

use std::sync::Arc;

use super::*;

impl SessionManager {
    /// Starts the task that expires finished sessions every `retention.sweep_interval_s`.
    pub fn spawn_janitor(self: &Arc<Self>) -> tokio::task::JoinHandle<()> {
        let manager = self.clone();
        let every = Duration::from_secs(self.config.retention.sweep_interval_s);
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(every);
            loop {
                tick.tick().await;
                let m = manager.clone();
                let _ = tokio::task::spawn_blocking(move || m.expire_finished(now_unix())).await;
            }
        })
    }

    /// Deletes the data of sessions that ended more than `retention.finished_ttl_s` before
    /// `now` (seconds since the epoch), leaving a tombstone so that their ids answer 410.
    /// Returns how many expired.
    pub fn expire_finished(&self, now: u64) -> usize {
        let ttl = self.config.retention.finished_ttl_s;
        if ttl == 0 {
            return 0;
        }
        let due: Vec<Arc<Session>> = self
            .read_sessions()
            .values()
            .filter(|s| s.state().is_terminal())
            .filter(|s| s.ended_unix().is_some_and(|t| t.saturating_add(ttl) <= now))
            .cloned()
            .collect();
        let mut expired = 0;
        for session in due {
            let id = session.id();
            let owner = serde_json::to_vec(session.owner()).unwrap_or_default();
            if let Err(e) = self.store.put(&tombstone_key(id), &owner) {
                tracing::error!(session = %id, "cannot expire: {e}");
                continue;
            }
            self.write_sessions().remove(id);
            self.expired
                .write()
                .unwrap_or_else(|e| e.into_inner())
                .insert(id.to_string(), session.owner().clone());
            // meta.json first: once it is gone the session does not come back.
            let gone = self
                .store
                .delete_prefix(&meta_key(id))
                .and_then(|()| self.store.delete_prefix(&session_prefix(id)));
            match gone {
                Ok(()) => expired += 1,
                Err(e) => tracing::error!(session = %id, "deleting expired data: {e}"),
            }
        }
        if expired > 0 {
            tracing::info!(
                expired,
                "expired finished sessions (retention.finished_ttl_s)"
            );
        }
        expired
    }
}

/// Key of the tombstone of an expired session (its owner, so its id answers 410 to them).
fn tombstone_key(id: &str) -> String {
    format!("expired/{id}.json")
}
