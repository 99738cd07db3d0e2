//! The bounds of the service: what one session, one request, one connection and one owner may
//! take. A server faces strangers, so every resource has a limit here and every wait a
//! timeout; the defaults fit a small GPU node and are derived from the machine where that
//! matters (memory).

use serde::{Deserialize, Serialize};

/// Admission, queues, request sizes, memory and session lifetimes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Sessions processing at the same time (live and uploads); a new live session beyond it
    /// gets 503, an upload beyond it waits in the queue (state `queued`).
    pub max_sessions: usize,
    /// Acknowledged uploads waiting for a free session slot, plus uploads being received;
    /// more get 503 before their bytes are read.
    pub max_queued_uploads: usize,
    /// Decoded frames waiting per live session. Small on purpose: a live stream wants the
    /// newest frames, and a frame that waited long is stale.
    pub frame_queue: usize,
    /// Events buffered per subscriber (SSE, WebSocket, Zenoh); a slower subscriber loses the
    /// oldest ones (it is told), the pipeline never waits for it.
    pub event_buffer: usize,
    /// Largest upload archive in bytes (4 GiB).
    pub max_upload_bytes: u64,
    /// Largest total size of the files extracted from one upload, in bytes.
    pub max_extracted_bytes: u64,
    /// Largest ratio of extracted bytes to archive bytes (zip bombs): images barely compress,
    /// so a dataset extracts to little more than its archive. Archives under 1 MiB may
    /// expand to `max_expansion_ratio` MiB.
    pub max_expansion_ratio: f64,
    /// Most entries (files and folders) in one upload archive; a zip's count is read from its
    /// end record before anything else.
    pub max_upload_entries: usize,
    /// Largest single frame (encoded image) in bytes (8 MiB: a 1920×1080 PNG of noise).
    pub max_frame_bytes: u64,
    /// Largest camera in pixels (width × height; 1920×1080). Every buffer of a session scales
    /// with it, so it is checked before anything is allocated.
    pub max_image_pixels: u64,
    /// Memory the server may use in MiB; 0 = three quarters of what the machine (or its
    /// cgroup) gives the process. Each session slot gets an equal share, which sets how many
    /// keyframes its map may hold (see [`crate::memory`]).
    pub memory_budget_mb: u64,
    /// Most keyframes a session's map holds; 0 = as many as its memory share allows. A session
    /// that reaches its limit finishes, saving its results, with the reason in its info.
    pub max_keyframes: usize,
    /// Bytes of request bodies (frames, JSON) buffered at once across all requests, in MiB; a
    /// request that finds no room gets 503 at once instead of growing memory.
    pub max_buffered_body_mb: u64,
    /// GPU jobs queued per session in the worker pool; a session that has this many waiting
    /// blocks until the pool serves one (backpressure onto its pipeline thread).
    pub pool_job_queue: usize,
    /// A live session is finished as if the client had sent end-of-stream when, over the last
    /// `idle_timeout_s` seconds, it received fewer frames than `min_frame_rate` per second
    /// asks (at least one): a vanished or trickling client does not hold a slot.
    pub idle_timeout_s: u64,
    /// Frames per second below which a live session counts as idle (see `idle_timeout_s`).
    pub min_frame_rate: f64,
    /// Largest step between consecutive frame timestamps, in seconds; a larger step, or one
    /// backwards, is a 400 (a camera does not pause for an hour mid-stream).
    pub max_timestamp_step_s: f64,
    /// Results (trajectory, keyframes, point cloud) are written to the store every this many
    /// keyframe changes (new keyframes, or old ones re-activated on a revisit) while a session
    /// runs, so a crash loses little of a live session.
    pub checkpoint_keyframes: usize,
    /// Every this many seconds the allocator hands its free pages back to the system (besides
    /// after each checkpoint); 0 = only after checkpoints. Freed pages that threads touch
    /// again between two trims stay resident; every 10 s (about 30 ms of a blocking thread)
    /// made the hour's RSS slope 44 % flatter and left 372 MB, not 1.1 GB, after the session
    /// (docs/tuning.md, issue 37, "trimming on a timer").
    pub memory_trim_interval_s: u64,
    /// On shutdown, how long (seconds) live sessions get to finish their queued frames and
    /// persist their results before the process exits anyway.
    pub shutdown_grace_s: u64,
    /// WebSocket and server-sent-event streams open on one session at once (a producer, a
    /// viewer or two, a recorder; 429 beyond).
    pub max_streams_per_session: usize,
    /// Most megabytes of a session's recording (`GET /v1/sessions/{id}/recording.mcap`): the
    /// mesh is recorded block by block as it grows, which an hour-long session would repeat
    /// many times over; past the limit the recording stops and its summary says so. 0: no
    /// recordings.
    pub max_recording_mb: u64,
}

impl Limits {
    /// What reading an uploaded dataset may cost: no list longer than an archive may have
    /// entries (a longer one names files again and again), no image file larger than a frame,
    /// no text file over 64 MiB (a 20 000-frame list with 100 Hz ground truth is ~30 MB).
    pub fn sequence_limits(&self) -> relfusion_slam::dataset::SequenceLimits {
        relfusion_slam::dataset::SequenceLimits {
            max_frames: self.max_upload_entries,
            max_text_bytes: 64 << 20,
            max_image_bytes: self.max_frame_bytes,
        }
    }
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_sessions: 4,
            max_queued_uploads: 16,
            frame_queue: 8,
            event_buffer: 1024,
            max_upload_bytes: 4 << 30,
            max_extracted_bytes: 8 << 30,
            max_expansion_ratio: 20.0,
            max_upload_entries: 20_000,
            max_frame_bytes: 8 << 20,
            max_image_pixels: 1920 * 1080,
            memory_budget_mb: 0,
            max_keyframes: 0,
            max_buffered_body_mb: 256,
            pool_job_queue: 4,
            idle_timeout_s: 60,
            min_frame_rate: 0.5,
            max_timestamp_step_s: 3600.0,
            checkpoint_keyframes: 10,
            memory_trim_interval_s: 10,
            shutdown_grace_s: 30,
            max_streams_per_session: 8,
            max_recording_mb: 256,
        }
    }
}

/// Connections and the time a request may take.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HttpLimits {
    /// Open connections at once; further ones wait in the kernel's backlog.
    pub max_connections: usize,
    /// A request's headers must arrive within this many seconds (slowloris); the clock runs
    /// from when the connection is ready for a request, so an idle HTTP/1 keep-alive
    /// connection is closed after it too. HTTP/2 connections are pinged at this interval and
    /// closed when a ping goes unanswered as long.
    pub header_timeout_s: u64,
    /// A buffered request body (a frame, JSON) must arrive whole within this many seconds;
    /// an upload is aborted when no byte arrives for this long.
    pub body_timeout_s: u64,
    /// An upload must arrive at this average rate at least (KiB/s), after a first
    /// `body_timeout_s`: its whole deadline grows with its size, so a trickle cannot hold an
    /// upload place for ever.
    pub min_upload_kib_per_s: u64,
    /// A write to a client (a response, a stream's message) that makes no progress for this
    /// many seconds ends the connection: a client that stops reading cannot hold its
    /// connection, its task and its send queue.
    pub write_timeout_s: u64,
    /// A WebSocket is pinged every third of this and closed when its peer said nothing (not
    /// even a pong) for this many seconds.
    pub stream_idle_timeout_s: u64,
}

impl Default for HttpLimits {
    fn default() -> Self {
        Self {
            max_connections: 1024,
            header_timeout_s: 10,
            body_timeout_s: 30,
            min_upload_kib_per_s: 16,
            write_timeout_s: 30,
            stream_idle_timeout_s: 60,
        }
    }
}

/// What one owner (bearer token name) may hold, so that one tenant cannot take the server
/// from the others. With auth off everyone is one owner.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Quotas {
    /// Sessions processing at once (live sessions and running uploads: the slots an owner
    /// holds); 0 = half of `limits.max_sessions` (rounded up) when auth is on, all of them
    /// when it is off. Queued uploads of an owner at its quota wait for its own sessions.
    pub max_active_sessions: usize,
    /// Uploads being received or waiting for a slot at once.
    pub max_uploads_in_flight: usize,
    /// Sessions kept in the store (any state); more are refused until some are deleted or
    /// expire.
    pub max_stored_sessions: usize,
    /// Bytes on disk (uploads and results) in GiB.
    pub max_stored_gb: f64,
    /// Saved maps (`POST /v1/maps`) one token keeps; more are refused until some are deleted.
    pub max_maps: usize,
    /// MiB of request bodies one token may have buffered at once (its share of
    /// `limits.max_buffered_body_mb`; 0 = a quarter of it with auth on, all of it when off).
    pub max_buffered_body_mb: u64,
    /// WebSocket and server-sent-event streams one token may hold open at once.
    pub max_streams: usize,
}

impl Default for Quotas {
    fn default() -> Self {
        Self {
            max_active_sessions: 0,
            max_uploads_in_flight: 4,
            max_stored_sessions: 200,
            max_stored_gb: 20.0,
            max_maps: 20,
            max_buffered_body_mb: 0,
            max_streams: 16,
        }
    }
}

impl Quotas {
    /// The effective `max_buffered_body_mb` (see its doc) under a server budget of
    /// `server_mb`.
    pub fn buffered_body_mb(&self, server_mb: u64, auth_on: bool) -> u64 {
        match (self.max_buffered_body_mb, auth_on) {
            (0, true) => (server_mb / 4).max(1),
            (0, false) => server_mb,
            (n, _) => n.min(server_mb),
        }
    }

    /// The effective `max_active_sessions` (see its doc).
    pub fn active_sessions(&self, max_sessions: usize, auth_on: bool) -> usize {
        match (self.max_active_sessions, auth_on) {
            (0, true) => max_sessions.div_ceil(2),
            (0, false) => max_sessions,
            (n, _) => n,
        }
    }
}

/// How long finished sessions are kept.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Retention {
    /// A finished or failed session's data is deleted this many seconds after it ended (7
    /// days); its id then answers 410 Gone. 0 keeps sessions until they are deleted.
    pub finished_ttl_s: u64,
    /// How often expired sessions are looked for, in seconds.
    pub sweep_interval_s: u64,
}

impl Default for Retention {
    fn default() -> Self {
        Self {
            finished_ttl_s: 7 * 24 * 3600,
            sweep_interval_s: 60,
        }
    }
}

/// Checks values serde cannot: positive limits and finite rates.
pub(super) fn validate(
    l: &Limits,
    h: &HttpLimits,
    q: &Quotas,
    r: &Retention,
) -> Result<(), String> {
    for (name, v) in [
        ("limits.max_sessions", l.max_sessions as u64),
        ("limits.frame_queue", l.frame_queue as u64),
        ("limits.event_buffer", l.event_buffer as u64),
        ("limits.max_upload_bytes", l.max_upload_bytes),
        ("limits.max_extracted_bytes", l.max_extracted_bytes),
        ("limits.max_upload_entries", l.max_upload_entries as u64),
        ("limits.max_frame_bytes", l.max_frame_bytes),
        ("limits.max_image_pixels", l.max_image_pixels),
        ("limits.max_buffered_body_mb", l.max_buffered_body_mb),
        ("limits.pool_job_queue", l.pool_job_queue as u64),
        ("limits.idle_timeout_s", l.idle_timeout_s),
        ("limits.checkpoint_keyframes", l.checkpoint_keyframes as u64),
        ("http.max_connections", h.max_connections as u64),
        ("http.header_timeout_s", h.header_timeout_s),
        ("http.body_timeout_s", h.body_timeout_s),
        ("http.min_upload_kib_per_s", h.min_upload_kib_per_s),
        ("http.write_timeout_s", h.write_timeout_s),
        ("http.stream_idle_timeout_s", h.stream_idle_timeout_s),
        (
            "limits.max_streams_per_session",
            l.max_streams_per_session as u64,
        ),
        (
            "quotas.max_uploads_in_flight",
            q.max_uploads_in_flight as u64,
        ),
        ("quotas.max_stored_sessions", q.max_stored_sessions as u64),
        ("quotas.max_streams", q.max_streams as u64),
        ("retention.sweep_interval_s", r.sweep_interval_s),
    ] {
        if v == 0 {
            return Err(format!("{name} must be > 0"));
        }
    }
    for (name, v, min) in [
        ("limits.max_expansion_ratio", l.max_expansion_ratio, 1.0),
        ("limits.min_frame_rate", l.min_frame_rate, 0.0),
        ("limits.max_timestamp_step_s", l.max_timestamp_step_s, 1e-3),
        ("quotas.max_stored_gb", q.max_stored_gb, 1e-3),
    ] {
        if !(v.is_finite() && v >= min) {
            return Err(format!("{name} must be a number ≥ {min}, got {v}"));
        }
    }
    Ok(())
}
