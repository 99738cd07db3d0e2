//! Scale drift: how the trajectory's scale changes along the way, from Sim(3) alignments of
//! consecutive windows. A diagnostic of monocular estimates, not an accuracy metric.
//!
//! A monocular run fixes its scale only up to a factor that drifts from keyframe to keyframe.
//! The whole-trajectory ATE ([`super::ate`]) fits one scale, so a drift shows up there as error
//! even when every stretch of the path has the right shape. Splitting the matched poses into
//! non-overlapping windows of `window` poses and aligning each on its own separates the two:
//! - `scale_ratio` of a window is its Sim(3) scale over the whole trajectory's, so 1.2 means
//!   the estimate is locally 20 % smaller than on average (the alignment scale maps estimate
//!   units to metres);
//! - `drift` is the largest ratio over the smallest: 1 for a constant scale;
//! - each window's own ATE shows how good the shape is once its scale is right.
//!
//! Figures on the shared sequences: docs/tuning.md, "Diagnostics".
//!
//! A window whose ground-truth positions hardly move (RMS spread below
//! [`MIN_WINDOW_SPREAD_M`]) has no observable scale and gets no ratio.

use serde::Serialize;

use super::associate::Matched;
use super::ate::{AlignMode, ate_matched};
use crate::{Error, Result};

/// Windows whose ground-truth camera positions spread less than this (RMS distance from
/// their centroid, metres) get no scale ratio: their scale is noise.
pub const MIN_WINDOW_SPREAD_M: f64 = 0.01;

/// One window of consecutive matched poses, aligned on its own.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ScaleWindow {
    /// Timestamps of the window's first and last estimated pose.
    pub first: f64,
    pub last: f64,
    /// Matched poses in the window.
    pub poses: usize,
    /// The window's Sim(3) scale over the whole trajectory's; `None` when the ground truth
    /// hardly moves in it.
    pub scale_ratio: Option<f64>,
    /// ATE RMSE (metres) of the window after its own Sim(3) alignment; `None` when its
    /// positions are degenerate (coincident or collinear) and cannot be aligned.
    pub ate_rmse: Option<f64>,
    /// RMS distance of the window's ground-truth positions from their centroid (metres).
    pub gt_spread: f64,
}

/// Scale drift of one estimate.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ScaleDrift {
    /// Poses per window.
    pub window: usize,
    pub windows: Vec<ScaleWindow>,
    /// Largest over smallest `scale_ratio`; `None` with fewer than two windows that have one.
    pub drift: Option<f64>,
    /// Largest window ATE RMSE (metres) over the windows that could be aligned.
    pub window_ate_rmse_max: f64,
}

/// Splits `matched` into windows of `window` poses (a last window shorter than half of it
/// joins the one before) and aligns each with Sim(3). Needs at least two windows.
pub fn scale_drift(matched: &Matched, window: usize) -> Result<ScaleDrift> {
    if window < 3 || matched.len() < 2 * window {
        return Err(Error::Eval(format!(
            "scale drift over {window}-pose windows needs windows of at least 3 poses and two \
             windows of matched poses, got {}",
            matched.len()
        )));
    }
    let global = ate_matched(matched, AlignMode::Sim3)?.scale;
    let mut starts: Vec<usize> = (0..matched.len()).step_by(window).collect();
    if matched.len() - starts[starts.len() - 1] < window.div_ceil(2) {
        starts.pop();
    }
    starts.push(matched.len());
    let mut windows = Vec::with_capacity(starts.len() - 1);
    for w in starts.windows(2) {
        let part = Matched {
            gt: matched.gt[w[0]..w[1]].to_vec(),
            est: matched.est[w[0]..w[1]].to_vec(),
        };
        let n = part.len() as f64;
        let centroid = part
            .gt
            .iter()
            .map(|p| p.world_from_camera.translation)
            .sum::<nalgebra::Vector3<f64>>()
            / n;
        let gt_spread = (part
            .gt
            .iter()
            .map(|p| (p.world_from_camera.translation - centroid).norm_squared())
            .sum::<f64>()
            / n)
            .sqrt();
        // Umeyama's only failure is degenerate geometry, which a still window may have.
        let ate = ate_matched(&part, AlignMode::Sim3).ok();
        windows.push(ScaleWindow {
            first: part.est[0].timestamp,
            last: part.est[part.len() - 1].timestamp,
            poses: part.len(),
            scale_ratio: ate
                .as_ref()
                .filter(|_| gt_spread >= MIN_WINDOW_SPREAD_M)
                .map(|a| a.scale / global),
            ate_rmse: ate.map(|a| a.rmse),
            gt_spread,
        });
    }
    let ratios: Vec<f64> = windows.iter().filter_map(|w| w.scale_ratio).collect();
    let drift = (ratios.len() >= 2).then(|| {
        let max = ratios.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let min = ratios.iter().copied().fold(f64::INFINITY, f64::min);
        max / min
    });
    let window_ate_rmse_max = windows
        .iter()
        .filter_map(|w| w.ate_rmse)
        .fold(0.0, f64::max);
    Ok(ScaleDrift {
        window,
        windows,
        drift,
        window_ate_rmse_max,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::trajectory::StampedPose;
    use crate::geometry::{SE3, SO3};
    use nalgebra::Vector3;

    /// A curved path of `n` poses; the estimate covers each step `scale(i)` times as far.
    fn path(n: usize, scale: impl Fn(usize) -> f64) -> Matched {
        let (mut gt_pos, mut est_pos) = (Vector3::zeros(), Vector3::zeros());
        let (mut gt, mut est) = (Vec::new(), Vec::new());
        for i in 0..n {
            let t = i as f64;
            let pose = |p: Vector3<f64>| StampedPose {
                timestamp: t,
                world_from_camera: SE3::new(SO3::exp(&Vector3::new(0.0, 0.01 * t, 0.0)), p),
            };
            gt.push(pose(gt_pos));
            est.push(pose(est_pos));
            let step =
                Vector3::new((0.1 * t).cos(), 0.3 * (0.05 * t).sin(), (0.1 * t).sin()) * 0.01;
            gt_pos += step;
            est_pos += step * scale(i);
        }
        Matched { gt, est }
    }

    #[test]
    fn eval_scale_drift_is_one_for_a_constant_scale() {
        let m = path(200, |_| 2.0);
        let d = scale_drift(&m, 50).expect("drift");
        assert_eq!(d.windows.len(), 4);
        assert!((d.drift.expect("ratios") - 1.0).abs() < 1e-9, "{d:?}");
        assert!(d.window_ate_rmse_max < 1e-9, "{d:?}");
    }

    #[test]
    fn eval_scale_drift_finds_a_scale_change() {
        // The estimate's steps halve after pose 100: its second half is half as large, so
        // that window's alignment scale is twice the first's.
        let m = path(200, |i| if i < 100 { 1.0 } else { 0.5 });
        let d = scale_drift(&m, 100).expect("drift");
        let r: Vec<f64> = d
            .windows
            .iter()
            .map(|w| w.scale_ratio.expect("moves"))
            .collect();
        assert!((r[1] / r[0] - 2.0).abs() < 1e-6, "{d:?}");
        assert!((d.drift.expect("two") - 2.0).abs() < 1e-6, "{d:?}");
        // Each half alone has the right shape; the whole trajectory does not.
        assert!(d.window_ate_rmse_max < 1e-9, "{d:?}");
        assert!(ate_matched(&m, AlignMode::Sim3).expect("ate").rmse > 0.01);
    }

    #[test]
    fn eval_scale_drift_windows_and_still_stretches() {
        // 230 poses in windows of 100: the last 30 join the second window.
        let d = scale_drift(&path(230, |_| 1.0), 100).expect("drift");
        assert_eq!(
            d.windows.iter().map(|w| w.poses).collect::<Vec<_>>(),
            [100, 130]
        );
        // A ground truth standing still in the second window has no scale there.
        let mut m = path(200, |_| 1.0);
        for i in 100..200 {
            m.gt[i].world_from_camera = m.gt[99].world_from_camera;
        }
        let d = scale_drift(&m, 100).expect("drift");
        assert!(
            d.windows[1].scale_ratio.is_none() && d.drift.is_none(),
            "{d:?}"
        );
        assert!(scale_drift(&m, 2).is_err());
        assert!(scale_drift(&m, 101).is_err());
    }
}
