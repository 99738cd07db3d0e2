//! Long-lived streams (WebSocket, server-sent events) and what bounds them beyond a
//! connection's own limits:
//! - **caps**: one owner holds at most `quotas.max_streams` streams, one session has at most
//!   `limits.max_streams_per_session` (429 beyond), so no tenant fills the connection slots
//!   that the others and `/healthz` need;
//! - **liveness**: a WebSocket is pinged every third of `http.stream_idle_timeout_s` and closed
//!   when nothing (a pong, a frame) came back for that long: a vanished peer does not keep
//!   its socket, its task and its send queue.
//!
//! A client that stops reading is cut by the connection's write deadline
//! ([`super::serve`]), which the upgraded socket keeps.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::session::Owner;
use crate::{ApiError, AppState};

#[derive(Debug, Default)]
struct Counts {
    owners: HashMap<Owner, usize>,
    sessions: HashMap<String, usize>,
}

/// The streams open on this node, per owner and per session.
#[derive(Debug, Default)]
pub struct StreamCounts {
    counts: Mutex<Counts>,
}

/// One open stream, counted until dropped.
#[derive(Debug)]
pub struct StreamSlot {
    counts: Arc<StreamCounts>,
    owner: Owner,
    session: String,
}

impl StreamCounts {
    /// Counts a new stream of `owner` on `session`: 429 when either is at its cap.
    pub fn open(
        self: &Arc<Self>,
        owner: &Owner,
        session: &str,
        max_per_owner: usize,
        max_per_session: usize,
    ) -> Result<StreamSlot, ApiError> {
        let mut counts = self.counts.lock().unwrap_or_else(|e| e.into_inner());
        let by_owner = counts.owners.get(owner).copied().unwrap_or(0);
        if by_owner >= max_per_owner {
            return Err(ApiError::quota(format!(
                "this token has {by_owner} streams open (quotas.max_streams); close one first"
            )));
        }
        let by_session = counts.sessions.get(session).copied().unwrap_or(0);
        if by_session >= max_per_session {
            return Err(ApiError::quota(format!(
                "session {session} has {by_session} streams open \
                 (limits.max_streams_per_session); close one first"
            )));
        }
        *counts.owners.entry(owner.clone()).or_default() += 1;
        *counts.sessions.entry(session.to_string()).or_default() += 1;
        Ok(StreamSlot {
            counts: self.clone(),
            owner: owner.clone(),
            session: session.to_string(),
        })
    }

    /// Streams open now.
    #[cfg(test)]
    fn open_now(&self) -> usize {
        let counts = self.counts.lock().unwrap_or_else(|e| e.into_inner());
        counts.owners.values().sum()
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        let mut counts = self.counts.counts.lock().unwrap_or_else(|e| e.into_inner());
        decrement(&mut counts.owners, &self.owner);
        decrement(&mut counts.sessions, &self.session);
    }
}

fn decrement<K: std::hash::Hash + Eq>(map: &mut HashMap<K, usize>, key: &K) {
    if let Some(n) = map.get_mut(key) {
        *n -= 1;
        if *n == 0 {
            map.remove(key);
        }
    }
}

/// A place for one more stream of `owner` on session `id` under this server's caps (429 at
/// a cap). Call it once the session is found: a cap must not tell whether another tenant's
/// session exists.
pub fn open_stream(state: &AppState, owner: &Owner, id: &str) -> Result<StreamSlot, ApiError> {
    state.streams.open(
        owner,
        id,
        state.config.quotas.max_streams,
        state.config.limits.max_streams_per_session,
    )
}

/// When the peer of a WebSocket was last heard from (shared by its receiving and sending
/// tasks).
#[derive(Clone, Debug)]
pub struct LastHeard {
    start: Instant,
    millis: Arc<AtomicU64>,
}

impl LastHeard {
    pub fn now() -> Self {
        Self {
            start: Instant::now(),
            millis: Arc::new(AtomicU64::new(0)),
        }
    }

    /// The peer said something (any message, a pong included).
    pub fn heard(&self) {
        let ms = self.start.elapsed().as_millis() as u64;
        self.millis.store(ms, Ordering::Relaxed);
    }

    fn silent_for(&self) -> Duration {
        let ms = self.start.elapsed().as_millis() as u64;
        Duration::from_millis(ms.saturating_sub(self.millis.load(Ordering::Relaxed)))
    }
}

/// What the sending task does at a keep-alive tick.
#[derive(Debug, PartialEq, Eq)]
pub enum KeepAlive {
    Ping,
    /// Nothing came back for the idle timeout: close.
    Expired,
}

/// The keep-alive clock of one WebSocket (see the module docs).
#[derive(Debug)]
pub struct KeepAliveClock {
    interval: tokio::time::Interval,
    heard: LastHeard,
    idle: Duration,
}

impl KeepAliveClock {
    pub fn new(heard: LastHeard, idle: Duration) -> Self {
        let period = (idle / 3).max(Duration::from_millis(100));
        let mut interval = tokio::time::interval_at(tokio::time::Instant::now() + period, period);
        interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        Self {
            interval,
            heard,
            idle,
        }
    }

    /// Waits for the next tick.
    pub async fn tick(&mut self) -> KeepAlive {
        self.interval.tick().await;
        if self.heard.silent_for() >= self.idle {
            KeepAlive::Expired
        } else {
            KeepAlive::Ping
        }
    }

    /// The idle timeout (for the close reason).
    pub fn idle(&self) -> Duration {
        self.idle
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caps_hold_per_owner_and_per_session_and_free_on_drop() {
        let counts = Arc::new(StreamCounts::default());
        let bob = Owner(Some("bob".into()));
        let alice = Owner(Some("alice".into()));
        let a = counts.open(&bob, "s1", 2, 3).expect("first");
        let _b = counts.open(&bob, "s2", 2, 3).expect("second");
        assert_eq!(
            counts.open(&bob, "s3", 2, 3).map_err(|e| e.status).err(),
            Some(429)
        );
        let _c = counts
            .open(&alice, "s1", 2, 2)
            .expect("alice has her own cap");
        assert_eq!(
            counts.open(&alice, "s1", 2, 2).map_err(|e| e.status).err(),
            Some(429)
        );
        drop(a);
        let _d = counts.open(&bob, "s1", 2, 3).expect("freed");
        assert_eq!(counts.open_now(), 3);
    }
}
