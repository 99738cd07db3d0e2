//! The bounded frame queue between a live session's producers (async request handlers) and
//! its pipeline thread (a plain std thread).
//!
//! Two ways in: [`FrameQueue::push_drop_oldest`] never waits and, when full, evicts the oldest
//! waiting item (a live camera wants fresh frames; the eviction is returned so it is counted);
//! [`FrameQueue::push_wait`] awaits room (replays and uploads lose nothing). One way out:
//! [`FrameQueue::pop_timeout`] blocks the consumer thread. After [`FrameQueue::close`] pushes
//! fail and the consumer drains what is left, then sees [`Pop::Closed`].

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

/// The queue was closed (end of stream or session stopped); the item comes back.
#[derive(Debug)]
pub struct Closed<T>(pub T);

/// What the consumer got.
#[derive(Debug)]
pub enum Pop<T> {
    Item(T),
    /// Nothing arrived within the timeout.
    TimedOut,
    /// Closed and empty: no item will ever come.
    Closed,
}

#[derive(Debug)]
struct State<T> {
    items: VecDeque<T>,
    closed: bool,
}

/// A bounded multi-producer, single-consumer queue.
#[derive(Debug)]
pub struct FrameQueue<T> {
    state: Mutex<State<T>>,
    capacity: usize,
    /// Wakes the consumer thread.
    available: Condvar,
    /// Wakes async producers waiting for room.
    space: Notify,
}

impl<T> FrameQueue<T> {
    /// A queue holding at most `capacity` (≥ 1) items.
    pub fn new(capacity: usize) -> Self {
        Self {
            state: Mutex::new(State {
                items: VecDeque::with_capacity(capacity.max(1)),
                closed: false,
            }),
            capacity: capacity.max(1),
            available: Condvar::new(),
            space: Notify::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Items waiting now.
    pub fn len(&self) -> usize {
        self.lock().items.len()
    }

    /// Whether no item waits.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The bound.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Queues `item`; when full, the oldest waiting item is removed and returned.
    pub fn push_drop_oldest(&self, item: T) -> Result<Option<T>, Closed<T>> {
        let mut state = self.lock();
        if state.closed {
            return Err(Closed(item));
        }
        let dropped = if state.items.len() >= self.capacity {
            state.items.pop_front()
        } else {
            None
        };
        state.items.push_back(item);
        drop(state);
        self.available.notify_one();
        Ok(dropped)
    }

    /// Queues `item`, waiting (asynchronously) while the queue is full.
    pub async fn push_wait(&self, item: T) -> Result<(), Closed<T>> {
        loop {
            // Register for the wake-up before looking, so a pop between the look and the
            // await is not missed.
            let notified = self.space.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let mut state = self.lock();
                if state.closed {
                    return Err(Closed(item));
                }
                if state.items.len() < self.capacity {
                    state.items.push_back(item);
                    drop(state);
                    self.available.notify_one();
                    return Ok(());
                }
            }
            notified.await;
        }
    }

    /// Takes the oldest item, waiting up to `timeout` for one.
    pub fn pop_timeout(&self, timeout: Duration) -> Pop<T> {
        let deadline = Instant::now() + timeout;
        let mut state = self.lock();
        loop {
            if let Some(item) = state.items.pop_front() {
                drop(state);
                self.space.notify_waiters();
                return Pop::Item(item);
            }
            if state.closed {
                return Pop::Closed;
            }
            let now = Instant::now();
            if now >= deadline {
                return Pop::TimedOut;
            }
            state = self
                .available
                .wait_timeout(state, deadline - now)
                .map(|(s, _)| s)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    /// No more pushes; the consumer drains the rest. Waiting producers get `Closed`.
    pub fn close(&self) {
        self.lock().closed = true;
        self.available.notify_all();
        self.space.notify_waiters();
    }

    /// Closes and discards every waiting item (a cancelled session); returns how many.
    pub fn close_and_clear(&self) -> usize {
        let n = {
            let mut state = self.lock();
            state.closed = true;
            let n = state.items.len();
            state.items.clear();
            n
        };
        self.available.notify_all();
        self.space.notify_waiters();
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    const SHORT: Duration = Duration::from_millis(10);

    #[test]
    fn drop_oldest_keeps_the_newest_and_returns_the_evicted() {
        let q = FrameQueue::new(3);
        for i in 0..3 {
            assert!(q.push_drop_oldest(i).expect("open").is_none());
        }
        assert_eq!(q.push_drop_oldest(3).expect("open"), Some(0));
        assert_eq!(q.push_drop_oldest(4).expect("open"), Some(1));
        assert_eq!(q.len(), 3);
        let got: Vec<i32> = (0..3)
            .map(|_| match q.pop_timeout(SHORT) {
                Pop::Item(i) => i,
                other => panic!("{other:?}"),
            })
            .collect();
        assert_eq!(got, [2, 3, 4]);
        assert!(matches!(q.pop_timeout(SHORT), Pop::TimedOut));
    }

    #[test]
    fn close_drains_then_reports_closed() {
        let q = FrameQueue::new(2);
        q.push_drop_oldest(1).expect("open");
        q.close();
        assert!(q.push_drop_oldest(2).is_err());
        assert!(matches!(q.pop_timeout(SHORT), Pop::Item(1)));
        assert!(matches!(q.pop_timeout(SHORT), Pop::Closed));
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn wait_blocks_until_the_consumer_makes_room_and_loses_nothing() {
        let q = Arc::new(FrameQueue::new(2));
        let consumer = {
            let q = q.clone();
            std::thread::spawn(move || {
                let mut got = Vec::new();
                loop {
                    match q.pop_timeout(Duration::from_secs(5)) {
                        Pop::Item(i) => {
                            got.push(i);
                            std::thread::sleep(Duration::from_millis(2));
                        }
                        Pop::Closed => return got,
                        Pop::TimedOut => panic!("producer stalled"),
                    }
                }
            })
        };
        for i in 0..50 {
            q.push_wait(i).await.expect("open");
            assert!(q.len() <= 2, "bound exceeded");
        }
        q.close();
        let got = tokio::task::spawn_blocking(move || consumer.join().expect("consumer"))
            .await
            .expect("join");
        assert_eq!(got, (0..50).collect::<Vec<_>>());
    }

    #[tokio::test]
    async fn wait_fails_when_closed_while_waiting() {
        let q = Arc::new(FrameQueue::new(1));
        q.push_wait(1).await.expect("room");
        let waiter = {
            let q = q.clone();
            tokio::spawn(async move { q.push_wait(2).await.is_err() })
        };
        tokio::time::sleep(SHORT).await;
        assert!(!waiter.is_finished(), "must wait while full");
        assert_eq!(q.close_and_clear(), 1);
        assert!(
            waiter.await.expect("join"),
            "closed while waiting is an error"
        );
    }
}
