//! Prometheus metrics of the service (`GET /metrics`, OpenMetrics text format).
//!
//! Counters: `frames_received_total`, `frames_dropped_total`, `frames_processed_total`,
//! `gpu_jobs_total`. Gauges: `sessions_active`, `frame_queue_depth` (frames waiting in all
//! sessions' queues), `gpu_queue_depth` (jobs waiting in the GPU pool), `resident_memory_bytes`
//! (the process's RSS when scraped), `heap_in_use_bytes` (what the program holds of the heap
//! when scraped; RSS beyond it is code, stacks, libraries' mappings, the allocator's slack),
//! `heap_free_bytes` (free in the heap's arenas: the slack's upper bound).
//! Histogram: `stage_latency_seconds{stage="decode|tracking|mapping|frame_to_pose|prior"}`.
//! Names carry no prefix so that they read the same in the API docs and in dashboards.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

/// A pipeline stage whose latency is recorded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Stage {
    /// Decoding an incoming JPEG/PNG.
    Decode,
    /// Tracking a frame (the pipeline's tracking time for it).
    Tracking,
    /// Mapping work done for a frame (depth filter, keyframe creation).
    Mapping,
    /// From the frame's arrival at the server to its pose event (queueing included).
    FrameToPose,
    /// One depth-prior inference on the GPU pool (queueing in the pool included).
    Prior,
}

impl Stage {
    fn label(self) -> &'static str {
        match self {
            Stage::Decode => "decode",
            Stage::Tracking => "tracking",
            Stage::Mapping => "mapping",
            Stage::FrameToPose => "frame_to_pose",
            Stage::Prior => "prior",
        }
    }
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StageLabels {
    stage: &'static str,
}

/// 0.5 ms … ~16 s in factors of 2: covers a PNG decode and a stalled GPU queue alike.
fn latency_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.0005, 2.0, 16))
}

/// Every metric of the process; shared (`Arc`) by the session manager, the GPU pool and the
/// HTTP layer.
pub struct Metrics {
    registry: Registry,
    pub frames_received: Counter,
    pub frames_dropped: Counter,
    pub frames_processed: Counter,
    pub gpu_jobs: Counter,
    pub sessions_active: Gauge,
    pub frame_queue_depth: Gauge,
    pub gpu_queue_depth: Gauge,
    /// The process's resident memory, read when the metrics are rendered.
    resident_memory: Gauge,
    /// Heap bytes in use, read when the metrics are rendered.
    heap_in_use: Gauge,
    heap_free: Gauge,
    stage_latency: Family<StageLabels, Histogram, fn() -> Histogram>,
}

impl std::fmt::Debug for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Metrics")
            .field("frames_received", &self.frames_received.get())
            .field("frames_dropped", &self.frames_dropped.get())
            .field("sessions_active", &self.sessions_active.get())
            .finish_non_exhaustive()
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    /// All metrics registered, at zero.
    pub fn new() -> Self {
        let mut registry = Registry::default();
        let frames_received = Counter::default();
        let frames_dropped = Counter::default();
        let frames_processed = Counter::default();
        let gpu_jobs = Counter::default();
        let sessions_active = Gauge::default();
        let frame_queue_depth = Gauge::default();
        let gpu_queue_depth = Gauge::default();
        let resident_memory = Gauge::default();
        let heap_in_use = Gauge::default();
        let heap_free = Gauge::default();
        let stage_latency =
            Family::<StageLabels, Histogram, fn() -> Histogram>::new_with_constructor(
                latency_histogram,
            );
        registry.register(
            "frames_received",
            "Frames accepted by live sessions (decoded and queued)",
            frames_received.clone(),
        );
        registry.register(
            "frames_dropped",
            "Queued frames dropped because a live stream outran its pipeline",
            frames_dropped.clone(),
        );
        registry.register(
            "frames_processed",
            "Frames that went through a pipeline (live and uploads)",
            frames_processed.clone(),
        );
        registry.register(
            "gpu_jobs",
            "Jobs completed by the GPU worker pool",
            gpu_jobs.clone(),
        );
        registry.register(
            "sessions_active",
            "Sessions processing frames now",
            sessions_active.clone(),
        );
        registry.register(
            "frame_queue_depth",
            "Frames waiting in all live sessions' queues",
            frame_queue_depth.clone(),
        );
        registry.register(
            "gpu_queue_depth",
            "Jobs waiting in the GPU worker pool",
            gpu_queue_depth.clone(),
        );
        registry.register(
            "resident_memory_bytes",
            "Resident memory of the process (what the memory budget bounds)",
            resident_memory.clone(),
        );
        registry.register(
            "heap_in_use_bytes",
            "Heap memory the program holds (glibc only)",
            heap_in_use.clone(),
        );
        registry.register(
            "heap_free_bytes",
            "Bytes free in the heap's arenas, resident or handed back (glibc only)",
            heap_free.clone(),
        );
        registry.register(
            "stage_latency_seconds",
            "Latency of pipeline stages",
            stage_latency.clone(),
        );
        Self {
            registry,
            frames_received,
            frames_dropped,
            frames_processed,
            gpu_jobs,
            sessions_active,
            frame_queue_depth,
            gpu_queue_depth,
            resident_memory,
            heap_in_use,
            heap_free,
            stage_latency,
        }
    }

    /// Records one latency sample of `stage`.
    pub fn observe_stage(&self, stage: Stage, seconds: f64) {
        self.stage_latency
            .get_or_create(&StageLabels {
                stage: stage.label(),
            })
            .observe(seconds);
    }

    /// The text exposition served at `/metrics`.
    pub fn render(&self) -> String {
        if let Some(bytes) = crate::memory::resident_bytes() {
            self.resident_memory
                .set(i64::try_from(bytes).unwrap_or(i64::MAX));
        }
        for (gauge, bytes) in [
            (&self.heap_in_use, crate::memory::heap_in_use_bytes()),
            (&self.heap_free, crate::memory::heap_free_bytes()),
        ] {
            if let Some(bytes) = bytes {
                gauge.set(i64::try_from(bytes).unwrap_or(i64::MAX));
            }
        }
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut out, &self.registry);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_every_metric() {
        let m = Metrics::new();
        m.frames_received.inc_by(3);
        m.frames_dropped.inc();
        m.sessions_active.set(2);
        m.observe_stage(Stage::FrameToPose, 0.02);
        let text = m.render();
        for needle in [
            "frames_received_total 3",
            "frames_dropped_total 1",
            "frames_processed_total 0",
            "gpu_jobs_total 0",
            "sessions_active 2",
            "frame_queue_depth 0",
            "gpu_queue_depth 0",
            "stage_latency_seconds_count{stage=\"frame_to_pose\"} 1",
        ] {
            assert!(text.contains(needle), "{needle} missing in\n{text}");
        }
        let rss: u64 = text
            .lines()
            .find_map(|l| l.strip_prefix("resident_memory_bytes "))
            .and_then(|v| v.trim().parse().ok())
            .expect("resident_memory_bytes");
        assert!(rss > 1 << 20, "{rss}");
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        {
            let heap: u64 = text
                .lines()
                .find_map(|l| l.strip_prefix("heap_in_use_bytes "))
                .and_then(|v| v.trim().parse().ok())
                .expect("heap_in_use_bytes");
            assert!(heap > 0, "heap {heap}");
            assert!(text.contains("heap_free_bytes "), "{text}");
        }
    }
}
