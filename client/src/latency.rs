//! Frame-to-pose latency figures of the service benchmarks (`relfusion bench serve`, `bench
//! cluster`, `bench long`): nearest-rank percentiles and the pass/fail of one step of a sessions
//! ramp. In the library rather than the binary so that their unit tests do not compile the whole
//! command line a second time as a test harness (issue 36: about 50 s of every cold build).

use serde_json::{Value, json};

/// p99 frame-to-pose latency above which a number of sessions is not "sustained".
pub const MAX_P99_MS: f64 = 1000.0;
/// Fraction of dropped frames above which a number of sessions is not "sustained".
pub const MAX_DROP_FRACTION: f64 = 0.05;

/// One paced live session's outcome.
#[derive(Debug, Default)]
pub struct LiveRun {
    /// Frames sent.
    pub sent: u64,
    /// Frame-to-pose latency of every frame that got a pose.
    pub latencies_ms: Vec<f64>,
    /// Frames the server reported as dropped.
    pub server_dropped: u64,
    /// Why the session failed, if it did.
    pub error: Option<String>,
}

/// One step of a sessions ramp as JSON: its latency percentiles and drops, and whether it
/// passed ([`MAX_P99_MS`], [`MAX_DROP_FRACTION`]). Sorts `run`'s latencies.
pub fn step_json(k: usize, run: &mut LiveRun, fps: f64) -> Value {
    run.latencies_ms.sort_by(f64::total_cmp);
    let poses = run.latencies_ms.len() as u64;
    let drop_fraction = if run.sent == 0 {
        1.0
    } else {
        1.0 - poses as f64 / run.sent as f64
    };
    let p50 = percentile(&run.latencies_ms, 0.50);
    let p99 = percentile(&run.latencies_ms, 0.99);
    let ok = run.error.is_none()
        && p99.is_some_and(|p| p <= MAX_P99_MS)
        && drop_fraction <= MAX_DROP_FRACTION;
    json!({
        "sessions": k,
        "fps": fps,
        "frames_sent": run.sent,
        "poses": poses,
        "drop_fraction": drop_fraction,
        "server_frames_dropped": run.server_dropped,
        "p50_ms": p50,
        "p99_ms": p99,
        "max_ms": run.latencies_ms.last(),
        "ok": ok,
        "error": run.error,
    })
}

/// Nearest-rank percentile of sorted `v`.
pub fn percentile(v: &[f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let rank = (q * v.len() as f64).ceil() as usize;
    Some(v[rank.clamp(1, v.len()) - 1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentiles() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), Some(50.0));
        assert_eq!(percentile(&v, 0.99), Some(99.0));
        assert_eq!(percentile(&[3.0], 0.99), Some(3.0));
        assert_eq!(percentile(&[], 0.5), None);
    }

    #[test]
    fn a_step_fails_on_drops_or_latency() {
        let mut good = LiveRun {
            sent: 100,
            latencies_ms: vec![50.0; 100],
            ..LiveRun::default()
        };
        assert_eq!(step_json(1, &mut good, 30.0)["ok"], true);
        let mut dropping = LiveRun {
            sent: 100,
            latencies_ms: vec![50.0; 90],
            ..LiveRun::default()
        };
        assert_eq!(step_json(1, &mut dropping, 30.0)["ok"], false);
        let mut slow = LiveRun {
            sent: 100,
            latencies_ms: vec![1500.0; 100],
            ..LiveRun::default()
        };
        assert_eq!(step_json(1, &mut slow, 30.0)["ok"], false);
    }
}
