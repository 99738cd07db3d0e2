//! A session's recording for Foxglove and the `mcap` tools (`GET /v1/sessions/{id}/recording.mcap`,
//! issue 38): what the session computed — every tracked pose and its transform, the keyframes'
//! trajectory and dense points, the fused mesh block by block — in the channels and schemas of
//! `relfusion stream --mcap` (`relfusion_viz::foxglove_log`). The frames' images are the
//! client's: the service does not keep them, so its recording has the camera's calibration
//! but no image messages (`relfusion stream --mcap` records both).
//!
//! It is written as the session runs to a private temporary file and put into the store with
//! the final results. Bounded: past `limits.max_recording_mb` it stops and says so in the
//! session's summary (`recording.truncated`); what it holds up to there stays readable.

use std::path::PathBuf;

use relfusion_slam::geometry::PinholeCamera;
use relfusion_viz::SessionLog;
use relfusion_viz::foxglove_log::{FoxgloveLog, FoxgloveOptions};
use relfusion_viz::session_log::LogError;

use super::events::SessionEvent;
use crate::storage::{ObjectStore, result_key};

/// The file name of the recording among a session's results.
pub const RECORDING: &str = "recording.mcap";

/// How often (in events) the file's size is checked against the limit.
const SIZE_CHECK_EVERY: u32 = 16;

/// A recording being written.
#[derive(Debug)]
pub(crate) struct Recorder {
    log: Option<FoxgloveLog>,
    file: tempfile::TempPath,
    max_bytes: u64,
    since_check: u32,
    truncated: bool,
    /// What the log held when it was closed.
    counts: Option<serde_json::Value>,
}

/// What a finished recording came to.
#[derive(Clone, Debug, serde::Serialize)]
pub(crate) struct RecordingSummary {
    pub bytes: u64,
    pub truncated: bool,
    pub poses: u64,
    pub keyframes: u64,
    pub mesh_updates: u64,
}

impl Recorder {
    /// Starts a recording for a camera, at most `max_bytes` long.
    pub fn open(camera: &PinholeCamera, max_bytes: u64) -> Result<Self, String> {
        let file = tempfile::Builder::new()
            .prefix("relfusion-recording-")
            .suffix(".mcap")
            .tempfile()
            .map_err(|e| format!("a temporary recording file: {e}"))?
            .into_temp_path();
        let options = FoxgloveOptions {
            mcap: Some(PathBuf::from(&*file)),
            ..FoxgloveOptions::default()
        };
        let log = FoxgloveLog::open(&options, camera).map_err(|e| e.to_string())?;
        Ok(Recorder {
            log: Some(log),
            file,
            max_bytes,
            since_check: 0,
            truncated: false,
            counts: None,
        })
    }

    /// Records one event of the session (events without a place in the recording are skipped).
    pub fn record(&mut self, event: &SessionEvent) {
        let Some(log) = self.log.as_mut() else {
            return;
        };
        let written = log_event(log, event);
        if let Err(e) = written {
            tracing::warn!("recording stopped: {e}");
            self.stop(true);
            return;
        }
        self.since_check += 1;
        if self.since_check >= SIZE_CHECK_EVERY {
            self.since_check = 0;
            if self.bytes() > self.max_bytes {
                self.stop(true);
            }
        }
    }

    fn bytes(&self) -> u64 {
        std::fs::metadata(&self.file).map_or(0, |m| m.len())
    }

    /// Closes the file; `truncated` when events are left out from here on.
    fn stop(&mut self, truncated: bool) {
        self.truncated |= truncated;
        if let Some(log) = self.log.take() {
            match SessionLog::finish(Box::new(log)) {
                Ok(counts) => self.counts = Some(counts),
                Err(e) => tracing::warn!("closing the recording: {e}"),
            }
        }
    }

    /// Closes the recording and puts it into the store among session `id`'s results (again,
    /// if an earlier try failed).
    pub fn finish(
        &mut self,
        store: &dyn ObjectStore,
        id: &str,
    ) -> Result<RecordingSummary, String> {
        self.stop(false);
        let bytes = std::fs::read(&self.file).map_err(|e| format!("reading the recording: {e}"))?;
        store
            .put(&result_key(id, RECORDING), &bytes)
            .map_err(|e| format!("storing the recording: {e}"))?;
        let count = |key: &str| {
            self.counts
                .as_ref()
                .and_then(|c| c[key].as_u64())
                .unwrap_or(0)
        };
        Ok(RecordingSummary {
            bytes: bytes.len() as u64,
            truncated: self.truncated,
            poses: count("poses"),
            keyframes: count("keyframes"),
            mesh_updates: count("mesh_updates"),
        })
    }
}

/// Gives `log` what `event` holds for a viewer (the pipeline's events, through
/// `relfusion_viz::pipeline_log`); the others are not a viewer's. Used by the recording and
/// the ROS 2 topics.
pub(crate) fn log_event(log: &mut dyn SessionLog, event: &SessionEvent) -> Result<(), LogError> {
    match event {
        SessionEvent::Pipeline(event) => relfusion_viz::pipeline_log::log_event(log, event),
        _ => Ok(()),
    }
}
