//! The map's depth shape and scale against the sensor's depth, one sample per keyframe (issue
//! 35's probes, printed by `bench odometry` and `bench accuracy`): the slope of log estimated
//! over log true inverse depth ([`log_slope`]; 1 = the depth ratios are right, below 1 a
//! flattened map, negative an inverted one) and the median ratio of estimated to true inverse
//! depth, whose changes over a run are the map's scale drift. A trajectory's ATE says that a
//! run went wrong; these say whether the map's shape or its scale went first.

use relfusion_slam::eval::depth_slope::{MIN_SLOPE_PIXELS, log_slope};
use relfusion_slam::image::ImageF32;
use relfusion_slam::mapping::DepthMap;
use serde::Serialize;

/// Seconds after the first frame from which the shape is judged (issue 35: "depth-shape slope
/// within 0.85-1.15 after 1 s"; before that the initialisation is still settling).
const SETTLE_S: f64 = 1.0;

/// The samples of one run.
#[derive(Debug, Default)]
pub struct DepthProbe {
    /// `(timestamp, slope, scale)` per keyframe; the slope is `None` when the true depths
    /// hardly vary (a wall seen head-on has no shape to measure).
    pub samples: Vec<(f64, Option<f64>, f64)>,
}

impl DepthProbe {
    /// Adds the keyframe at `timestamp` from `(ln true, ln estimated)` inverse-depth pairs;
    /// nothing when there are fewer than [`MIN_SLOPE_PIXELS`].
    pub fn add(&mut self, timestamp: f64, pairs: &[(f64, f64)]) {
        if pairs.len() < MIN_SLOPE_PIXELS {
            return;
        }
        let mut ratios: Vec<f64> = pairs.iter().map(|(x, y)| y - x).collect();
        ratios.sort_by(f64::total_cmp);
        let scale = ratios[ratios.len() / 2].exp();
        self.samples.push((timestamp, log_slope(pairs), scale));
    }

    /// The slope at the first keyframe [`SETTLE_S`] after `start`, the slopes' range from
    /// then on, and the largest over the smallest scale over the same keyframes.
    pub fn summary(&self, start: f64) -> ShapeSummary {
        let later: Vec<&(f64, Option<f64>, f64)> = self
            .samples
            .iter()
            .filter(|s| s.0 >= start + SETTLE_S)
            .collect();
        let slopes: Vec<f64> = later.iter().filter_map(|s| s.1).collect();
        let (lo, hi) = later.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), s| {
            (lo.min(s.2), hi.max(s.2))
        });
        ShapeSummary {
            slope_after_1s: later.first().and_then(|s| s.1),
            slope_range: (!slopes.is_empty()).then(|| {
                slopes
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &s| {
                        (a.min(s), b.max(s))
                    })
            }),
            scale_ratio: (lo > 0.0 && lo.is_finite()).then(|| hi / lo),
        }
    }
}

/// What [`DepthProbe::summary`] reports for one run.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct ShapeSummary {
    pub slope_after_1s: Option<f64>,
    pub slope_range: Option<(f64, f64)>,
    /// Largest over smallest scale of the keyframes' depth against the sensor's.
    pub scale_ratio: Option<f64>,
}

impl ShapeSummary {
    /// The range as `lo–hi`, or `-`.
    pub fn range_text(&self) -> String {
        self.slope_range
            .map_or_else(|| "-".into(), |(a, b)| format!("{a:.2}–{b:.2}"))
    }
}

/// `(ln true, ln estimated)` inverse depth at every pixel where the semi-dense `map` has an
/// estimate and the `sensor` (depth in metres, 0 = none, possibly another resolution) a
/// reading.
pub fn map_pairs(map: &DepthMap, sensor: &ImageF32) -> Vec<(f64, f64)> {
    let (sx, sy) = (
        sensor.width as f64 / map.width as f64,
        sensor.height as f64 / map.height as f64,
    );
    let mut pairs = Vec::new();
    for y in 0..map.height {
        for x in 0..map.width {
            let Some((idepth, _)) = map.at(x, y).estimate() else {
                continue;
            };
            let (u, v) = ((x as f64 * sx) as usize, (y as f64 * sy) as usize);
            if u >= sensor.width || v >= sensor.height {
                continue;
            }
            let d = f64::from(sensor.at(u, v));
            if d > 0.0 && idepth > 0.0 {
                pairs.push((-d.ln(), f64::from(idepth).ln()));
            }
        }
    }
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;
    use relfusion_slam::mapping::InverseDepth;

    /// A map whose inverse depth is `k · (1/d)^slope` of a sensor depth ramp.
    fn ramp(k: f32, slope: f32) -> (DepthMap, ImageF32) {
        let (w, h) = (40, 30);
        let mut sensor = ImageF32::filled(w, h, 0.0);
        let mut map = DepthMap::unknown(w, h);
        for y in 0..h {
            for x in 0..w {
                let d = 0.5 + 0.1 * x as f32 + 0.02 * y as f32;
                sensor.data[y * w + x] = d;
                if (x + y) % 2 == 0 {
                    map.pixels[y * w + x] = InverseDepth::Estimate {
                        idepth: k * (1.0 / d).powf(slope),
                        var: 0.01,
                    };
                }
            }
        }
        (map, sensor)
    }

    #[test]
    fn probe_reads_shape_and_scale_drift_from_keyframe_maps() {
        let mut probe = DepthProbe::default();
        let (map, sensor) = ramp(2.0, 1.0);
        probe.add(0.0, &map_pairs(&map, &sensor));
        let (map, sensor) = ramp(2.0, 0.5);
        probe.add(1.5, &map_pairs(&map, &sensor));
        let (map, sensor) = ramp(3.0, 1.0);
        probe.add(2.0, &map_pairs(&map, &sensor));
        assert_eq!(probe.samples.len(), 3);
        assert!(
            (probe.samples[0].2 - 2.0).abs() < 1e-4,
            "{:?}",
            probe.samples
        );
        let s = probe.summary(0.0);
        let first = s.slope_after_1s.expect("slope after 1 s");
        assert!((first - 0.5).abs() < 1e-3, "slope after 1 s {first}");
        let (lo, hi) = s.slope_range.expect("range");
        assert!(
            (lo - 0.5).abs() < 1e-3 && (hi - 1.0).abs() < 1e-3,
            "{lo} {hi}"
        );
        // Only the keyframes after 1 s: the flattened one and the one at scale 3.
        let ratio = s.scale_ratio.expect("scale ratio");
        assert!(ratio > 1.0, "scale ratio {ratio}");
        assert_eq!(s.range_text(), "0.50–1.00");
    }

    #[test]
    fn probe_skips_keyframes_without_enough_sensor_depth() {
        let (map, mut sensor) = ramp(1.0, 1.0);
        sensor.data.iter_mut().for_each(|d| *d = 0.0);
        let mut probe = DepthProbe::default();
        probe.add(0.0, &map_pairs(&map, &sensor));
        assert!(probe.samples.is_empty());
        assert!(probe.summary(0.0).slope_after_1s.is_none());
        assert_eq!(probe.summary(0.0).range_text(), "-");
    }
}
