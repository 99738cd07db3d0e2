//! Pairing estimated and ground-truth poses by timestamp.
//!
//! The rule is evo's `sync.associate_trajectories` with the `nearest_time` method (evo 1.38,
//! `matching_time_indices`), so that every figure downstream equals evo's:
//! 1. the *shorter* trajectory drives (the estimate when both have the same length), so that none
//!    of its poses is lost;
//! 2. each of its poses, in order, takes the pose of the longer trajectory with the nearest
//!    timestamp, if that is at most `max_dt` away; on a tie the earlier pose wins.
//!
//! Every pose of the shorter trajectory is used at most once. A pose of the longer one could in
//! principle serve two, when the shorter trajectory is locally denser than `max_dt` allows; this
//! cannot happen for constant-rate streams with `max_dt` below half the longer one's period,
//! and we keep evo's rule rather than a greedy global matching so that figures stay comparable.

use super::super::dataset::trajectory::StampedPose;
use crate::{Error, Result};

/// Default largest timestamp difference (seconds) for a pair: the TUM benchmark's
/// `associate.py --max_difference` default. (evo's own default, 0.01 s, is stricter; pass
/// `--t_max_diff 0.02` to evo to compare.)
pub const DEFAULT_MAX_DT: f64 = 0.02;

/// Index pairs `(gt_index, est_index)` of poses whose stamps differ by at most `max_dt`, in the
/// order of the shorter trajectory. `max_dt` must be finite and non-negative.
pub fn associate(gt_stamps: &[f64], est_stamps: &[f64], max_dt: f64) -> Vec<(usize, usize)> {
    // evo: traj_1 = reference, traj_2 = estimate; `second_longer` decides which one drives.
    let est_longer = est_stamps.len() > gt_stamps.len();
    let (short, long) = if est_longer {
        (gt_stamps, est_stamps)
    } else {
        (est_stamps, gt_stamps)
    };
    let sorted = long.windows(2).all(|w| w[1] >= w[0]);
    short
        .iter()
        .enumerate()
        .filter_map(|(i_short, &t)| {
            let i_long = if sorted {
                nearest_sorted(long, t, max_dt)
            } else {
                nearest_linear(long, t, max_dt)
            }?;
            Some(if est_longer {
                (i_short, i_long)
            } else {
                (i_long, i_short)
            })
        })
        .collect()
}

/// evo's binary-search branch: the insertion point (numpy `searchsorted(side="right")`) and its
/// left neighbour compete; the upper one must be strictly nearer to win.
fn nearest_sorted(long: &[f64], t: f64, max_dt: f64) -> Option<usize> {
    let (first, last) = (*long.first()?, *long.last()?);
    if t < first - max_dt || t > last + max_dt {
        return None;
    }
    let upper = long.partition_point(|&s| s <= t).min(long.len() - 1);
    let diff_ub = long[upper] - t;
    let diff_lb = if upper > 0 {
        t - long[upper - 1]
    } else {
        f64::INFINITY
    };
    if diff_ub <= max_dt && diff_ub < diff_lb {
        Some(upper)
    } else if diff_lb <= max_dt && diff_lb <= diff_ub {
        Some(upper - 1)
    } else {
        None
    }
}

/// evo's fallback for unsorted stamps: the first index of the smallest absolute difference.
fn nearest_linear(long: &[f64], t: f64, max_dt: f64) -> Option<usize> {
    let mut best: Option<(usize, f64)> = None;
    for (i, &s) in long.iter().enumerate() {
        let d = (s - t).abs();
        if best.is_none_or(|(_, bd)| d < bd) {
            best = Some((i, d));
        }
    }
    best.filter(|&(_, d)| d <= max_dt).map(|(i, _)| i)
}

/// Ground-truth and estimated poses paired one to one (same length, same order).
#[derive(Clone, Debug, PartialEq)]
pub struct Matched {
    pub gt: Vec<StampedPose>,
    pub est: Vec<StampedPose>,
}

impl Matched {
    /// Number of pairs.
    pub fn len(&self) -> usize {
        self.gt.len()
    }

    /// True when no pose could be paired.
    pub fn is_empty(&self) -> bool {
        self.gt.is_empty()
    }
}

/// Pairs the poses of two trajectories with [`associate`]; fails when nothing pairs (a wrong
/// file or a time offset between clocks) or `max_dt` is not a finite non-negative number.
pub fn associate_poses(gt: &[StampedPose], est: &[StampedPose], max_dt: f64) -> Result<Matched> {
    if !(max_dt.is_finite() && max_dt >= 0.0) {
        return Err(Error::Eval(format!(
            "max_dt must be finite and >= 0, got {max_dt}"
        )));
    }
    let gt_t: Vec<f64> = gt.iter().map(|p| p.timestamp).collect();
    let est_t: Vec<f64> = est.iter().map(|p| p.timestamp).collect();
    let pairs = associate(&gt_t, &est_t, max_dt);
    if pairs.is_empty() {
        let range = |t: &[f64]| match (t.first(), t.last()) {
            (Some(a), Some(b)) => format!("{} poses, {a}..{b} s", t.len()),
            _ => "no poses".to_string(),
        };
        return Err(Error::Eval(format!(
            "no timestamps match within {max_dt} s (ground truth: {}; estimate: {})",
            range(&gt_t),
            range(&est_t)
        )));
    }
    Ok(Matched {
        gt: pairs.iter().map(|&(g, _)| gt[g]).collect(),
        est: pairs.iter().map(|&(_, e)| est[e]).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eval_associate_shorter_estimate_drives() {
        let gt = [0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06];
        // -0.5 is out of range, 0.024 → 0.02; 0.0625 and 0.061 both take 0.06 (evo's rule lets a
        // pose of the longer trajectory serve twice).
        let est = [-0.5, 0.024, 0.0625, 0.061];
        let pairs = associate(&gt, &est, 0.02);
        assert_eq!(pairs, vec![(2, 1), (6, 2), (6, 3)]);
        // A tighter window drops 0.024 (4 ms away) and 0.0625 (2.5 ms) but keeps 0.061.
        // (Every expectation in these tests was checked with evo's `matching_time_indices`.)
        assert_eq!(associate(&gt, &est, 0.002), vec![(6, 3)]);
    }

    #[test]
    fn eval_associate_tie_takes_the_earlier_pose() {
        let gt = [0.0, 0.5, 1.0];
        assert_eq!(associate(&gt, &[0.25, 0.75], 0.3), vec![(0, 0), (1, 1)]);
        // Unsorted long side: the linear fallback keeps the same tie rule.
        let gt_unsorted = [1.0, 0.5, 0.0, 2.0];
        assert_eq!(
            associate(&gt_unsorted, &[0.25, 0.75, 9.0], 0.3),
            vec![(1, 0), (0, 1)]
        );
    }

    #[test]
    fn eval_associate_longer_estimate_is_searched() {
        let gt = [1.0, 2.0];
        let est = [0.9, 0.99, 1.02, 1.5, 2.05, 3.0];
        assert_eq!(associate(&gt, &est, 0.02), vec![(0, 1)]);
        assert_eq!(associate(&gt, &est, 0.06), vec![(0, 1), (1, 4)]);
    }

    #[test]
    fn eval_associate_poses_reports_no_overlap() {
        use crate::geometry::SE3;
        let pose = |t| StampedPose {
            timestamp: t,
            world_from_camera: SE3::identity(),
        };
        let err = associate_poses(&[pose(0.0), pose(1.0)], &[pose(5.0)], 0.02)
            .expect_err("disjoint stamps");
        assert!(err.to_string().contains("no timestamps match"), "{err}");
        assert!(associate_poses(&[pose(0.0)], &[pose(0.0)], f64::NAN).is_err());
        let m = associate_poses(&[pose(0.0), pose(1.0)], &[pose(1.01)], 0.02).expect("one pair");
        assert_eq!(
            (m.len(), m.gt[0].timestamp, m.est[0].timestamp),
            (1, 1.0, 1.01)
        );
    }
}
