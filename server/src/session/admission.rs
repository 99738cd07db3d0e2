//! Admission: session slots, the upload queue, and what each owner may hold (`[quotas]`).
//!
//! Everything is decided under one lock ([`Admission`]) and reserved before any work starts,
//! so that two requests racing for the last slot, queue place or quota unit cannot both get
//! it: an upload reserves its queue place and its owner's quota with an [`UploadTicket`]
//! before its first byte is read, and gives them back when it fails or becomes a session.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};

use super::handle::Session;
use super::types::{Owner, SessionState};
use crate::ApiError;
use crate::config::Config;

/// Slots and queues, under one lock.
#[derive(Debug, Default)]
pub(crate) struct Admission {
    /// Sessions holding one of the `limits.max_sessions` slots.
    pub active: usize,
    /// Acknowledged uploads waiting for a slot.
    pub queued: VecDeque<Arc<Session>>,
    /// Uploads being received, per owner.
    receiving: HashMap<Owner, usize>,
}

pub(crate) type SharedAdmission = Arc<Mutex<Admission>>;

pub(crate) fn lock(admission: &SharedAdmission) -> MutexGuard<'_, Admission> {
    admission.lock().unwrap_or_else(|e| e.into_inner())
}

impl Admission {
    fn receiving_total(&self) -> usize {
        self.receiving.values().sum()
    }

    fn receiving_of(&self, owner: &Owner) -> usize {
        self.receiving.get(owner).copied().unwrap_or(0)
    }
}

/// What one owner holds now (from the session table, counted under the admission lock).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct OwnerHoldings {
    /// Sessions processing (holding a slot).
    pub active: usize,
    /// Uploads waiting for a slot.
    pub queued: usize,
    /// Sessions in the store, any state.
    pub stored: usize,
    /// Their bytes on disk.
    pub stored_bytes: u64,
}

impl OwnerHoldings {
    /// The holdings of `owner` among `sessions`.
    pub fn of<'a>(owner: &Owner, sessions: impl Iterator<Item = &'a Arc<Session>>) -> Self {
        let mut h = Self::default();
        for s in sessions.filter(|s| s.owner() == owner) {
            h.stored += 1;
            h.stored_bytes += s.disk_bytes();
            match s.state() {
                SessionState::Queued => h.queued += 1,
                SessionState::Running | SessionState::Finishing => h.active += 1,
                SessionState::Finished | SessionState::Failed => {}
            }
        }
        h
    }
}

/// What a new session of an owner would be.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum NewSession {
    /// A live session: it needs a slot now.
    Live,
    /// An upload: it arrives, then waits for a slot.
    Upload,
}

/// Whether `owner` may hold one more slot: fewer than `quotas.max_active_sessions`.
pub(crate) fn under_active_quota(config: &Config, holdings: OwnerHoldings) -> bool {
    holdings.active
        < config
            .quotas
            .active_sessions(config.limits.max_sessions, config.auth.enabled())
}

/// Refuses a new session of `owner` (`adding_bytes` on disk) beyond its quotas (429), counting
/// the uploads it is sending now.
pub(crate) fn check_quota(
    config: &Config,
    admission: &Admission,
    owner: &Owner,
    holdings: OwnerHoldings,
    new: NewSession,
    adding_bytes: u64,
) -> Result<(), ApiError> {
    let q = &config.quotas;
    let receiving = admission.receiving_of(owner);
    match new {
        NewSession::Live if !under_active_quota(config, holdings) => {
            return Err(ApiError::quota(format!(
                "this token has {} sessions processing (quotas.max_active_sessions = {}); \
                 finish or delete one first",
                holdings.active,
                q.active_sessions(config.limits.max_sessions, config.auth.enabled())
            )));
        }
        NewSession::Upload if receiving + holdings.queued >= q.max_uploads_in_flight => {
            return Err(ApiError::quota(format!(
                "this token has {} uploads arriving or waiting for a slot \
                 (quotas.max_uploads_in_flight = {})",
                receiving + holdings.queued,
                q.max_uploads_in_flight
            )));
        }
        _ => {}
    }
    if holdings.stored + receiving >= q.max_stored_sessions {
        return Err(ApiError::quota(format!(
            "this token keeps {} sessions (quotas.max_stored_sessions = {}); delete some first",
            holdings.stored + receiving,
            q.max_stored_sessions
        )));
    }
    let max_bytes = (q.max_stored_gb * (1u64 << 30) as f64) as u64;
    if holdings.stored_bytes.saturating_add(adding_bytes) > max_bytes {
        return Err(ApiError::quota(format!(
            "this token's sessions take {} MiB on disk and this one may add {} MiB \
             (quotas.max_stored_gb = {}); delete some first",
            holdings.stored_bytes >> 20,
            adding_bytes >> 20,
            q.max_stored_gb
        )));
    }
    Ok(())
}

/// An upload's reserved place: counted in the upload queue and in its owner's quotas from
/// before its body is read; released when dropped, unless [`UploadTicket::redeem`]ed.
#[derive(Debug)]
pub struct UploadTicket {
    admission: SharedAdmission,
    owner: Owner,
    redeemed: bool,
}

impl UploadTicket {
    /// Reserves an upload of `owner` if the queue and the owner's quotas have room (checked
    /// by `check`, under the lock, with the owner's holdings).
    pub(crate) fn reserve(
        admission: &SharedAdmission,
        config: &Config,
        owner: &Owner,
        check: impl FnOnce(&Admission) -> Result<(), ApiError>,
    ) -> Result<Self, ApiError> {
        let mut a = lock(admission);
        let waiting = a.queued.len() + a.receiving_total();
        if waiting >= config.limits.max_queued_uploads {
            return Err(ApiError::unavailable(format!(
                "{waiting} uploads are already waiting or arriving (limits.max_queued_uploads); \
                 retry later"
            )));
        }
        check(&a)?;
        *a.receiving.entry(owner.clone()).or_insert(0) += 1;
        Ok(Self {
            admission: admission.clone(),
            owner: owner.clone(),
            redeemed: false,
        })
    }

    /// The owner it was reserved for.
    pub fn owner(&self) -> &Owner {
        &self.owner
    }

    /// The upload became a session: its place moves from "receiving" to whatever `then`
    /// does with the lock held (queue it or give it a slot), atomically.
    pub(crate) fn redeem<T>(mut self, then: impl FnOnce(&mut Admission) -> T) -> T {
        let mut a = lock(&self.admission);
        release(&mut a, &self.owner);
        self.redeemed = true;
        then(&mut a)
    }
}

fn release(a: &mut Admission, owner: &Owner) {
    if let Some(n) = a.receiving.get_mut(owner) {
        *n = n.saturating_sub(1);
        if *n == 0 {
            a.receiving.remove(owner);
        }
    }
}

impl Drop for UploadTicket {
    fn drop(&mut self) {
        if !self.redeemed {
            release(&mut lock(&self.admission), &self.owner);
        }
    }
}
