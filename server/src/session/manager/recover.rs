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
        let keys = self.store.list("sessions/")?;
        let mut ids: Vec<String> = keys
            .iter()
            .filter_map(|k| k.strip_prefix("sessions/")?.split('/').next())
            .map(String::from)
            .collect();
        ids.dedup();
        let mut resumed = Vec::new();
        for id in ids {
            let meta = match SessionMeta::load(self.store.as_ref(), &id) {
                Ok(Some(meta)) => meta,
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
            let mut meta = meta;
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
                        meta.error = Some(
                            "interrupted: the server stopped while this live session ran; \
                             results up to the last checkpoint are kept"
                                .into(),
                        );
                        meta.save(self.store.as_ref())?;
                    }
                }
            }
            // A re-run must fit this server's limits, which may have changed since.
            let max_keyframes = match self.map_limit(&meta.camera, &meta.config) {
                Ok(n) => n,
                Err(e) if resume => {
                    meta.state = SessionState::Failed;
                    meta.error = Some(format!("cannot re-run: {}", e.message));
                    meta.save(self.store.as_ref())?;
                    resume = false;
                    0
                }
                Err(_) => 0,
            };
            let session = Arc::new(self.build(meta, max_keyframes));
            if resume {
                tracing::info!(session = %id, "re-running an unfinished upload");
                resumed.push(session.clone());
            }
            self.write_sessions().insert(id, session);
        }
        resumed.sort_by_key(|s| s.info().created_unix);
        for session in resumed {
            let start = self.queue_or_slot(&mut lock_admission(&self.admission), &session);
            if start {
                self.start_or_release(&session, self.model.clone());
            }
        }
        Ok(())
    }
}
