//! Depth-range slope: whether a map's depth *ratios* match the ground truth's, independently of
//! its scale. Over the pixels where both have a depth, it is the least-squares slope `b` of
//!
//! ```text
//! log ρ_est = a + b · log ρ_gt        (ρ = inverse depth)
//! ```
//!
//! `b = 1`: near and far are in the right proportion (whatever the scale `a`); `b < 1`: the map
//! is compressed (near surfaces too far, far ones too near); `b > 1`: stretched.
//!
//! Why it is worth printing: a monocular map can be wrong in this way while its percentage of
//! correct depth hardly says why, and the error couples into the poses. Over a narrow field of
//! view, rotation and translation explain nearly the same image motion (the rotation–translation
//! ambiguity of two-view geometry), and the depths of the map decide the split
//! ([`super::rotation_gain`]). Figures on the shared sequences: docs/tuning.md, "Diagnostics".

use serde::Serialize;

use crate::image::ImageF32;
use crate::{Error, Result};

/// Fewest pixels with both depths for a slope.
pub const MIN_SLOPE_PIXELS: usize = 100;

/// Below this variance of `log ρ_gt` the view has no depth range (a fronto-parallel wall) and
/// the slope is not defined.
pub const MIN_LOG_DEPTH_VARIANCE: f64 = 1e-4;

/// The depth-range slope of the inverse-depth map `est_idepth` against the metric depth
/// `gt_depth` (same size; 0 or non-finite = none), or `None` when fewer than
/// [`MIN_SLOPE_PIXELS`] pixels have both or the ground truth spans no depth range.
pub fn depth_range_slope(est_idepth: &ImageF32, gt_depth: &ImageF32) -> Result<Option<f64>> {
    if (est_idepth.width, est_idepth.height) != (gt_depth.width, gt_depth.height)
        || est_idepth.data.len() != gt_depth.data.len()
    {
        return Err(Error::Shape(format!(
            "estimate {}x{}, ground truth {}x{}",
            est_idepth.width, est_idepth.height, gt_depth.width, gt_depth.height
        )));
    }
    let pairs: Vec<(f64, f64)> = est_idepth
        .data
        .iter()
        .zip(&gt_depth.data)
        .filter(|(e, g)| e.is_finite() && **e > 0.0 && g.is_finite() && **g > 0.0)
        .map(|(&e, &g)| (-f64::from(g).ln(), f64::from(e).ln()))
        .collect();
    if pairs.len() < MIN_SLOPE_PIXELS {
        return Ok(None);
    }
    Ok(log_slope(&pairs))
}

/// The least-squares slope of `(log ρ_gt, log ρ_est)` pairs, or `None` when the ground truth
/// spans no depth range ([`MIN_LOG_DEPTH_VARIANCE`]).
pub fn log_slope(pairs: &[(f64, f64)]) -> Option<f64> {
    let n = pairs.len() as f64;
    let (mx, my) = pairs
        .iter()
        .fold((0.0, 0.0), |(sx, sy), (x, y)| (sx + x / n, sy + y / n));
    let (sxx, sxy) = pairs.iter().fold((0.0, 0.0), |(sxx, sxy), (x, y)| {
        (sxx + (x - mx) * (x - mx), sxy + (x - mx) * (y - my))
    });
    (n > 0.0 && sxx / n >= MIN_LOG_DEPTH_VARIANCE).then(|| sxy / sxx)
}

/// Depth-range slopes of one stored keyframe's maps.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct KeyframeSlopes {
    pub timestamp: f64,
    /// Of the raw semi-dense map (the one tracking and the back end use).
    pub semidense: Option<f64>,
    /// Of the raw depth prior.
    pub prior: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 40×30 ground truth spanning 0.5–4 m with every 7th pixel missing.
    fn ground_truth() -> ImageF32 {
        let data = (0..1200)
            .map(|i| {
                if i % 7 == 3 {
                    0.0
                } else {
                    0.5 + 3.5 * (i as f32 / 1199.0)
                }
            })
            .collect();
        ImageF32::from_vec(40, 30, data).expect("40×30 image")
    }

    fn power_law(gt: &ImageF32, scale: f32, slope: f32) -> ImageF32 {
        let data = gt
            .data
            .iter()
            .map(|&g| {
                if g > 0.0 {
                    scale * g.recip().powf(slope)
                } else {
                    0.0
                }
            })
            .collect();
        ImageF32::from_vec(gt.width, gt.height, data).expect("same size")
    }

    #[test]
    fn depth_slope_recovers_the_power_at_any_scale() {
        let gt = ground_truth();
        for (scale, slope) in [(1.0, 1.0), (3.7, 0.7), (0.2, 1.4)] {
            let b = depth_range_slope(&power_law(&gt, scale, slope), &gt)
                .expect("same size")
                .expect("enough pixels");
            assert!((b - f64::from(slope)).abs() < 1e-4, "{b} vs {slope}");
        }
    }

    #[test]
    fn depth_slope_skips_pixels_without_either_depth() {
        let gt = ground_truth();
        let mut est = power_law(&gt, 2.0, 0.8);
        // Outliers hidden behind missing or invalid values must not count.
        for i in (0..1200).step_by(5) {
            est.data[i] = if i % 2 == 0 { 0.0 } else { f32::NAN };
        }
        let b = depth_range_slope(&est, &gt)
            .expect("same size")
            .expect("enough pixels");
        assert!((b - 0.8).abs() < 1e-4, "{b}");
    }

    #[test]
    fn depth_slope_needs_pixels_and_a_depth_range() {
        let gt = ground_truth();
        let flat = ImageF32::filled(40, 30, 2.0);
        assert_eq!(
            depth_range_slope(&power_law(&flat, 1.0, 1.0), &flat).expect("same size"),
            None
        );
        let mut sparse = power_law(&gt, 1.0, 1.0);
        for v in sparse.data.iter_mut().skip(MIN_SLOPE_PIXELS) {
            *v = 0.0;
        }
        assert_eq!(depth_range_slope(&sparse, &gt).expect("same size"), None);
        assert!(depth_range_slope(&ImageF32::filled(30, 40, 1.0), &gt).is_err());
    }
}
