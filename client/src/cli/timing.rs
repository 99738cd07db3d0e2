//! The figures benchmarks print: medians of timings.

use std::time::{Duration, Instant};

/// Median in milliseconds (`samples` must be non-empty).
pub fn median_ms(samples: &mut [Duration]) -> f64 {
    samples.sort_unstable();
    let mid = samples.len() / 2;
    let m = if samples.len() % 2 == 1 {
        samples[mid]
    } else {
        (samples[mid - 1] + samples[mid]) / 2
    };
    m.as_secs_f64() * 1e3
}

/// Median of per-item figures (the upper median; NaN for none).
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Milliseconds since `t`.
pub fn ms(t: Instant) -> f64 {
    1e3 * t.elapsed().as_secs_f64()
}
