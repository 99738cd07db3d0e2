//! What `/healthz` reports about the manager.

use super::*;

impl SessionManager {
    /// What `/healthz` reports: `Err` names the first thing that is broken — a GPU worker
    /// thread that died, a store that cannot be written, resident memory over the budget.
    pub fn health(&self) -> Result<(), String> {
        let alive = self.pool.alive_workers();
        if alive < self.pool.workers() {
            return Err(format!(
                "{} of {} GPU pool workers have stopped",
                self.pool.workers() - alive,
                self.pool.workers()
            ));
        }
        {
            let mut probe = lock(&self.store_probe);
            let stale = probe
                .as_ref()
                .is_none_or(|(at, _)| at.elapsed() > Duration::from_secs(10));
            if stale {
                let result = self
                    .store
                    .put(&format!("health/{}", self.node()), b"ok")
                    .map_err(|e| format!("the store is not writable: {e}"));
                *probe = Some((Instant::now(), result));
            }
            if let Some((_, Err(e))) = probe.as_ref() {
                return Err(e.clone());
            }
        }
        if let Some(rss) = resident_bytes()
            && rss > self.memory.budget
        {
            return Err(format!(
                "resident memory {} MiB is over the budget of {} MiB",
                rss >> 20,
                self.memory.budget >> 20
            ));
        }
        Ok(())
    }
}
