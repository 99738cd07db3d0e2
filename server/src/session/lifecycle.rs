//! [`Lifecycle`]: where a session is in its life, and the one signal its tasks stop on.
//!
//! Everything a session's tasks need to know about its life lives in one watch channel: the
//! state with its error and notice, whether it still takes frames, and whether it was told to
//! stop (deleted, or the server shutting down). Transitions are the methods below and nothing
//! else writes the status; a task that must stop when the session is deleted selects on
//! [`Lifecycle::deleted`] (as mini-redis's tasks select on one `Shutdown`) instead of polling.

use std::time::{Duration, Instant};

use tokio::sync::watch;

use super::types::SessionState;

/// Why a session was told to stop before it ended by itself.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Stop {
    /// The server shuts down: an upload stops where it is (it re-runs on restart).
    Shutdown,
    /// Deleted: every task stops, the worker discards everything, the metadata is never
    /// written again. Overrides [`Stop::Shutdown`].
    Deleted,
}

/// What the watch channel publishes.
#[derive(Clone, Debug)]
pub(crate) struct Status {
    pub state: SessionState,
    pub error: Option<String>,
    /// Why it ended without failing, or what it waits for (`SessionInfo::notice`).
    pub notice: Option<String>,
    /// It takes no more frames (end of stream, or its worker ended).
    pub input_closed: bool,
    pub stop: Option<Stop>,
}

/// The session's status and its transitions.
#[derive(Debug)]
pub(crate) struct Lifecycle {
    status: watch::Sender<Status>,
}

impl Lifecycle {
    /// A session in `state` (a terminal one takes no frames).
    pub fn new(state: SessionState, error: Option<String>, notice: Option<String>) -> Self {
        let (status, _) = watch::channel(Status {
            input_closed: state.is_terminal(),
            state,
            error,
            notice,
            stop: None,
        });
        Self { status }
    }

    /// The status now.
    pub fn status(&self) -> Status {
        self.status.borrow().clone()
    }

    pub fn state(&self) -> SessionState {
        self.status.borrow().state
    }

    pub fn input_closed(&self) -> bool {
        self.status.borrow().input_closed
    }

    pub fn is_deleted(&self) -> bool {
        self.status.borrow().stop == Some(Stop::Deleted)
    }

    /// Deleted or shutting down.
    pub fn is_stopped(&self) -> bool {
        self.status.borrow().stop.is_some()
    }

    /// End of stream: closes the input and, if it runs, moves it to `Finishing`. Returns
    /// whether the input was open (the first end of stream acts, repeats do nothing).
    pub fn end_of_stream(&self) -> bool {
        let mut was_open = false;
        self.status.send_if_modified(|s| {
            was_open = !s.input_closed;
            s.input_closed = true;
            let running = s.state == SessionState::Running;
            if was_open && running {
                s.state = SessionState::Finishing;
            }
            was_open
        });
        was_open
    }

    /// The worker ended: no more frames are accepted.
    pub fn close_input(&self) {
        self.status
            .send_if_modified(|s| !std::mem::replace(&mut s.input_closed, true));
    }

    /// Tells every task of the session to stop (`Deleted` overrides `Shutdown`); closes the
    /// input.
    pub fn stop(&self, why: Stop) {
        self.status.send_if_modified(|s| {
            let stop = s.stop.max(Some(why));
            let changed = stop != s.stop || !s.input_closed;
            s.stop = stop;
            s.input_closed = true;
            changed
        });
    }

    /// Changes the state and error.
    pub fn set_state(&self, state: SessionState, error: Option<String>) {
        self.status.send_modify(|s| {
            s.state = state;
            s.error = error;
        });
    }

    pub fn set_notice(&self, notice: Option<String>) {
        self.status.send_modify(|s| s.notice = notice);
    }

    /// Records the final state without waking anyone; [`Self::announce`] wakes them (the
    /// session sends its last event in between).
    pub fn record_end(&self, state: SessionState, error: Option<String>) {
        self.status.send_if_modified(|s| {
            s.state = state;
            s.error = error;
            false
        });
    }

    /// Wakes every waiter after [`Self::record_end`].
    pub fn announce(&self) {
        self.status.send_modify(|_| {});
    }

    /// Resolves once the session is finished or failed.
    pub async fn terminal(&self) {
        let mut rx = self.status.subscribe();
        let _ = rx.wait_for(|s| s.state.is_terminal()).await;
    }

    /// Resolves once the session is deleted (never, otherwise): the signal its tasks select
    /// on.
    pub async fn deleted(&self) {
        let mut rx = self.status.subscribe();
        let _ = rx.wait_for(|s| s.stop == Some(Stop::Deleted)).await;
    }

    /// Sleeps `duration` on a worker thread, waking early when the session is told to stop;
    /// returns whether it was.
    pub fn sleep_unless_stopped(&self, duration: Duration) -> bool {
        const STEP: Duration = Duration::from_millis(100);
        let until = Instant::now() + duration;
        while Instant::now() < until {
            if self.is_stopped() {
                return true;
            }
            std::thread::sleep(STEP.min(until.saturating_duration_since(Instant::now())));
        }
        self.is_stopped()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn end_of_stream_acts_once_and_moves_a_running_session_to_finishing() {
        let l = Lifecycle::new(SessionState::Running, None, None);
        assert!(!l.input_closed());
        assert!(l.end_of_stream());
        assert_eq!(l.state(), SessionState::Finishing);
        assert!(l.input_closed());
        l.set_state(SessionState::Running, None);
        assert!(!l.end_of_stream(), "a repeated end of stream does nothing");
        assert_eq!(l.state(), SessionState::Running);
    }

    #[test]
    fn a_terminal_session_takes_no_frames_and_deletion_overrides_shutdown() {
        assert!(Lifecycle::new(SessionState::Finished, None, None).input_closed());
        let l = Lifecycle::new(SessionState::Running, None, None);
        l.stop(Stop::Deleted);
        l.stop(Stop::Shutdown);
        assert!(l.is_deleted() && l.is_stopped() && l.input_closed());
    }

    #[tokio::test]
    async fn deleted_wakes_its_waiters_and_nothing_else_does() {
        let l = std::sync::Arc::new(Lifecycle::new(SessionState::Running, None, None));
        let waiter = tokio::spawn({
            let l = l.clone();
            async move { l.deleted().await }
        });
        l.stop(Stop::Shutdown);
        l.set_state(SessionState::Finished, None);
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert!(
            !waiter.is_finished(),
            "shutdown and the end are not deletion"
        );
        l.stop(Stop::Deleted);
        tokio::time::timeout(Duration::from_secs(5), waiter)
            .await
            .expect("woken")
            .expect("joined");
    }

    #[tokio::test]
    async fn an_ending_is_seen_only_once_announced() {
        let l = std::sync::Arc::new(Lifecycle::new(SessionState::Running, None, None));
        let mut rx = l.status.subscribe();
        rx.mark_unchanged();
        l.record_end(SessionState::Failed, Some("boom".into()));
        assert!(!rx.has_changed().expect("open"), "not announced yet");
        l.announce();
        assert!(rx.has_changed().expect("open"));
        assert_eq!(l.status().error.as_deref(), Some("boom"));
        tokio::time::timeout(Duration::from_secs(5), l.terminal())
            .await
            .expect("terminal");
    }

    #[test]
    fn sleep_wakes_early_when_stopped() {
        let l = std::sync::Arc::new(Lifecycle::new(SessionState::Running, None, None));
        let stopper = {
            let l = l.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(50));
                l.stop(Stop::Shutdown);
            })
        };
        let t0 = Instant::now();
        assert!(l.sleep_unless_stopped(Duration::from_secs(30)));
        assert!(t0.elapsed() < Duration::from_secs(10));
        stopper.join().expect("joined");
        assert!(
            !Lifecycle::new(SessionState::Running, None, None).sleep_unless_stopped(Duration::ZERO)
        );
    }
}
