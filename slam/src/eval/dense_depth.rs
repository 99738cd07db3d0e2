//! Per-stage depth accuracy of a whole run (`relfusion eval depth --dataset DIR --run OUT`):
//! the paper's percentage of correct depth (§V.A, Tables II–III) over the densified keyframes
//! that `relfusion run` stored in `OUT/keyframes/` ([`crate::dense::store`]).
//!
//! The protocol, per the paper §V.A:
//! - **Scale.** A monocular run has no metric scale. The keyframe trajectory `OUT/keyframes.txt`
//!   is aligned to `DIR/groundtruth.txt` with Sim(3) Umeyama (the association and alignment of
//!   `relfusion eval traj`), and its scale `s` (metres per map unit) is the one factor applied to
//!   every keyframe's depth. Keyframe maps live in each keyframe's own gauge; the keyframe's
//!   final Sim(3) scale `s_kf` brings them into the map's units, so metric depth is
//!   `s · s_kf / D` for an inverse depth `D`.
//! - **Ground truth.** The dataset's depth image of the frame with the keyframe's timestamp
//!   (nearest within [`GT_MAX_DT`]), brought to the working resolution by nearest sampling:
//!   each working pixel's ray (undistorted working camera) is projected into the dataset camera
//!   (with its lens distortion, when the dataset has one) and takes the nearest depth pixel.
//!   Without distortion and with the working camera the scaled dataset camera this is plain
//!   pixel-centre nearest resampling.
//! - **Stages.**
//!   1. `prior_gt_fit` — the raw prior with scale and shift fitted per keyframe to the ground
//!      truth's inverse depth, unconstrained least squares over pixels with gt > 0.1 m (shared
//!      data README §1.4; the paper's Table III baseline "CNN depth, scale/shift fitted"); an
//!      inverted fit is scored, not skipped.
//!   2. `prior_aligned` — `D'_CNN` as the pipeline aligned it to the semi-dense map (eq. 3).
//!   3. `semidense_raw` / 4. `semidense_filtered` — over the pixels where the map has a value.
//!   5. `dense` — `OUT/keyframes/<ts>.depth.npy` over every pixel.
//!   6. `dense_keyframe_scale` — the same maps, each at its own best scale (the median of
//!      ground truth over estimate) instead of the trajectory's: a probe, not a result. Its
//!      gap to `dense` is what the disagreement between each keyframe's depth scale and the
//!      trajectory's costs (scale drift, depth maps propagated in an older unit); the ratio
//!      of each keyframe's best scale to the trajectory's is listed (1 = they agree).
//!
//! Stages 1, 2 and 5 count over every pixel with a valid ground truth (a pixel the stage leaves
//! without depth is wrong, [`percent_correct_depth`]); the semi-dense stages count over their
//! own pixels only, as the paper does for semi-dense maps. Each stage reports the mean of the
//! per-keyframe percentages (the paper's figure) and the percentage pooled over all pixels.

use std::path::Path;

use serde::Serialize;

use super::associate::{DEFAULT_MAX_DT, associate_poses};
use super::ate::{AlignMode, AteResult, ate_matched};
use super::depth::{DepthAccuracy, percent_correct_depth};
use super::depth_slope::{KeyframeSlopes, depth_range_slope};
use crate::dataset::trajectory::read_tum_trajectory;
use crate::dataset::tum::TumSequence;
use crate::dense::store::{DenseStore, StoredKeyframe, depth_from_idepth};
use crate::geometry::PinholeCamera;
use crate::image::ImageF32;
use crate::scale_shift::{aligned_depth, fit_scale_shift_unconstrained, inverse_depth_target};
use crate::{Error, Result};
use nalgebra::Vector2;

/// Largest difference (seconds) between a keyframe's timestamp and its ground-truth depth
/// frame's (TUM's `associate.py` default).
pub const GT_MAX_DT: f64 = 0.02;

/// Ground-truth pixels below this depth (metres) are left out of the prior's scale/shift fit
/// (shared data README §1.4); they are still scored.
pub const GT_FIT_MIN_DEPTH: f32 = 0.1;

/// Folder of the stored keyframes inside a run's output folder.
pub const KEYFRAMES_DIR: &str = "keyframes";

/// Keyframe trajectory file inside a run's output folder.
pub const KEYFRAMES_TRAJECTORY: &str = "keyframes.txt";

/// The accuracy of one stage over the keyframes it exists for.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct StageScore {
    /// Mean over keyframes of the per-keyframe percentage (the paper's figure).
    pub percent_mean: f64,
    /// 100 · correct / pixels, over all keyframes' pixels together.
    pub percent_pooled: f64,
    /// Pixels counted (the denominator): valid ground truth, and for semi-dense stages a value
    /// in the map.
    pub pixels: usize,
    /// Of those, pixels where the stage has a depth.
    pub evaluated: usize,
    /// Of those, pixels within the threshold.
    pub correct: usize,
    /// Keyframes that contributed at least one pixel.
    pub keyframes: usize,
}

/// Running sums behind a [`StageScore`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTally {
    percent_sum: f64,
    keyframes: usize,
    pixels: usize,
    evaluated: usize,
    correct: usize,
}

impl StageTally {
    /// Adds one keyframe's accuracy.
    pub fn add(&mut self, acc: &DepthAccuracy) {
        self.percent_sum += acc.percent;
        self.keyframes += 1;
        self.pixels += acc.valid_gt;
        self.evaluated += acc.evaluated;
        self.correct += acc.correct;
    }

    /// The score, or `None` when no keyframe contributed (the stage's maps are absent).
    pub fn score(&self) -> Option<StageScore> {
        (self.keyframes > 0).then(|| StageScore {
            percent_mean: self.percent_sum / self.keyframes as f64,
            percent_pooled: 100.0 * self.correct as f64 / self.pixels as f64,
            pixels: self.pixels,
            evaluated: self.evaluated,
            correct: self.correct,
            keyframes: self.keyframes,
        })
    }
}

/// Percentage of correct depth of `est_depth · scale` against `gt_depth`, counted only over
/// the pixels where `mask` is true (all pixels without a mask). `None` when no pixel has both
/// the mask and a valid ground truth.
pub fn score_depth(
    est_depth: &ImageF32,
    gt_depth: &ImageF32,
    scale: f64,
    threshold: f64,
    mask: Option<&[bool]>,
) -> Result<Option<DepthAccuracy>> {
    let restricted;
    let gt = match mask {
        None => gt_depth,
        Some(m) => {
            if m.len() != gt_depth.data.len() {
                return Err(Error::Shape(format!(
                    "mask has {} values for {} pixels",
                    m.len(),
                    gt_depth.data.len()
                )));
            }
            restricted = ImageF32 {
                width: gt_depth.width,
                height: gt_depth.height,
                data: gt_depth
                    .data
                    .iter()
                    .zip(m)
                    .map(|(&g, &keep)| if keep { g } else { 0.0 })
                    .collect(),
            };
            &restricted
        }
    };
    if !gt.data.iter().any(|&g| g.is_finite() && g > 0.0) {
        return Ok(None);
    }
    percent_correct_depth(est_depth, gt, scale, threshold).map(Some)
}

/// Pixels where an inverse-depth map has a value (finite, > 0).
pub fn has_value(map: &ImageF32) -> Vec<bool> {
    map.data.iter().map(|&d| d.is_finite() && d > 0.0).collect()
}

/// A run's stored keyframes opened against its dataset: the pieces every whole-run depth
/// evaluation (this module, [`super::ablation`]) needs.
#[derive(Debug)]
pub struct DenseRun {
    pub store: DenseStore,
    pub sequence: TumSequence,
    /// ATE of `keyframes.txt` after Sim(3) alignment; its `scale` is the trajectory scale `s`
    /// (metres per map unit).
    pub ate: AteResult,
    /// Per working pixel, the index of the dataset depth pixel it samples (None: outside).
    gt_lookup: Vec<Option<usize>>,
}

impl DenseRun {
    /// Opens `run/keyframes/`, aligns `run/keyframes.txt` to `dataset/groundtruth.txt` and
    /// prepares the ground-truth resampling. Errors say which file is missing or wrong.
    pub fn open(dataset: &Path, run: &Path) -> Result<Self> {
        let kf_dir = run.join(KEYFRAMES_DIR);
        if !kf_dir.join(crate::dense::store::INDEX_FILE).is_file() {
            return Err(Error::Eval(format!(
                "{} holds no densified keyframes (no {}): run `relfusion run` with the dense \
                 layer on, into {}",
                kf_dir.display(),
                crate::dense::store::INDEX_FILE,
                run.display()
            )));
        }
        let store = DenseStore::open(&kf_dir)?;
        let sequence = TumSequence::open(dataset, None)?;
        let gt_path = dataset.join("groundtruth.txt");
        if !gt_path.is_file() {
            return Err(Error::Eval(format!(
                "{} is missing: the trajectory scale needs ground truth",
                gt_path.display()
            )));
        }
        let gt = read_tum_trajectory(&gt_path)?;
        let est = read_tum_trajectory(&run.join(KEYFRAMES_TRAJECTORY))?;
        let ate = ate_matched(
            &associate_poses(&gt, &est, DEFAULT_MAX_DT)?,
            AlignMode::Sim3,
        )?;
        if !(ate.scale.is_finite() && ate.scale > 0.0) {
            return Err(Error::Eval(format!(
                "Sim(3) alignment of {} gave scale {}: too few or degenerate keyframe poses",
                KEYFRAMES_TRAJECTORY, ate.scale
            )));
        }
        let gt_lookup = if store.keyframes.is_empty() {
            Vec::new()
        } else {
            ground_truth_lookup(&store.pinhole()?, &sequence.camera)
        };
        Ok(Self {
            store,
            sequence,
            ate,
            gt_lookup,
        })
    }

    /// The trajectory scale `s`: metres per map unit.
    pub fn trajectory_scale(&self) -> f64 {
        self.ate.scale
    }

    /// Metric ground-truth depth of `kf` at the working resolution (0 = none), or `None` when
    /// the dataset has no depth frame within [`GT_MAX_DT`] of its timestamp.
    pub fn ground_truth_depth(&self, kf: &StoredKeyframe) -> Result<Option<ImageF32>> {
        let nearest = self
            .sequence
            .frames
            .iter()
            .enumerate()
            .map(|(i, f)| (i, (f.timestamp - kf.timestamp).abs()))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let Some((i, _)) = nearest.filter(|&(_, dt)| dt <= GT_MAX_DT) else {
            return Ok(None);
        };
        let Some(full) = self.sequence.load_depth(i)? else {
            return Ok(None);
        };
        let data = self
            .gt_lookup
            .iter()
            .map(|src| src.map_or(0.0, |j| full.data[j]))
            .collect();
        ImageF32::from_vec(self.store.width, self.store.height, data)
            .map(Some)
            .map_err(Into::into)
    }

    /// Depth in map units from one of `kf`'s inverse-depth maps (`s_kf / D`); multiply by
    /// [`Self::trajectory_scale`] for metres.
    pub fn map_depth(&self, kf: &StoredKeyframe, idepth: &ImageF32) -> ImageF32 {
        depth_from_idepth(idepth, kf.scale)
    }
}

/// For each pixel of `working` (undistorted), the nearest pixel of the dataset image: the
/// working pixel's ray, distorted by the dataset lens if it has one, projected with the
/// dataset intrinsics.
fn ground_truth_lookup(working: &PinholeCamera, dataset: &PinholeCamera) -> Vec<Option<usize>> {
    let (w, h) = (working.width as usize, working.height as usize);
    let (dw, dh) = (dataset.width as usize, dataset.height as usize);
    (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let ray = working.pixel_to_normalized(&Vector2::new(x as f64, y as f64));
            let uv = dataset.normalized_to_pixel(&dataset.distort_normalized(&ray));
            let (u, v) = ((uv.x + 0.5).floor(), (uv.y + 0.5).floor());
            (u >= 0.0 && v >= 0.0 && u < dw as f64 && v < dh as f64)
                .then(|| v as usize * dw + u as usize)
        })
        .collect()
}

/// Every stage's score; `None` for a stage no keyframe has.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StageScores {
    pub prior_gt_fit: Option<StageScore>,
    pub prior_aligned: Option<StageScore>,
    pub semidense_raw: Option<StageScore>,
    pub semidense_filtered: Option<StageScore>,
    pub dense: Option<StageScore>,
    pub dense_keyframe_scale: Option<StageScore>,
}

/// One keyframe's depth scale against the trajectory's: its densified depth's best scale
/// (median ground truth over estimate) divided by the trajectory's Sim(3) scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct KeyframeScaleRatio {
    pub timestamp: f64,
    pub ratio: f64,
}

/// The JSON `relfusion eval depth --dataset --run` prints.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DenseDepthReport {
    /// Relative error bound of a correct pixel.
    pub threshold: f64,
    /// Sim(3) scale of the keyframe trajectory alignment (metres per map unit).
    pub trajectory_scale: f64,
    /// ATE RMSE (metres) of `keyframes.txt` after Sim(3) alignment, and its matched poses.
    pub ate_rmse_m: f64,
    pub ate_matched: usize,
    /// Keyframes in the store.
    pub keyframes: usize,
    /// Of those, keyframes with a ground-truth depth frame (the ones scored).
    pub keyframes_evaluated: usize,
    pub keyframes_without_gt: usize,
    /// Keyframes densified without the prior (mode `no_model`).
    pub no_model_keyframes: usize,
    /// Keyframes whose prior could not be fitted to the ground truth at all (constant prior,
    /// too few pixels); scored as 0 % in `prior_gt_fit`.
    pub prior_gt_fit_failures: usize,
    pub stages: StageScores,
    /// Per scored keyframe, the depth-range slopes of its raw semi-dense map and raw prior
    /// ([`super::depth_slope`]; 1 = depth ratios right).
    pub depth_range_slopes: Vec<KeyframeSlopes>,
    /// Per scored keyframe, its depth scale against the trajectory's (stage 6).
    pub dense_scale_ratios: Vec<KeyframeScaleRatio>,
}

/// Scores every stage of a run's stored keyframes; see the module docs for the protocol.
pub fn evaluate_dense_depth(
    dataset: &Path,
    run: &Path,
    threshold: f64,
) -> Result<DenseDepthReport> {
    if !(threshold.is_finite() && threshold > 0.0) {
        return Err(Error::Eval(format!(
            "threshold must be finite and > 0, got {threshold}"
        )));
    }
    let run = DenseRun::open(dataset, run)?;
    let s = run.trajectory_scale();
    let mut tally: [StageTally; 6] = Default::default();
    let mut ratios = Vec::new();
    let (mut evaluated, mut without_gt, mut fit_failures) = (0, 0, 0);
    let mut slopes = Vec::new();
    for kf in &run.store.keyframes {
        let Some(gt) = run.ground_truth_depth(kf)? else {
            without_gt += 1;
            continue;
        };
        evaluated += 1;
        let store = &run.store;
        let mut kf_slopes = KeyframeSlopes {
            timestamp: kf.timestamp,
            semidense: None,
            prior: None,
        };

        if let Some(prior) = store.read_map(kf, "prior")? {
            kf_slopes.prior = depth_range_slope(&prior, &gt)?;
            // Table III baseline: the best scale/shift for this frame, metric by construction.
            let (target, mask) = inverse_depth_target(&gt, GT_FIT_MIN_DEPTH);
            let est = match fit_scale_shift_unconstrained(&prior, &target, Some(&mask)) {
                Ok(fit) => aligned_depth(&prior, &fit),
                Err(_) => {
                    fit_failures += 1;
                    ImageF32::filled(gt.width, gt.height, 0.0)
                }
            };
            add(&mut tally[0], score_depth(&est, &gt, 1.0, threshold, None)?);
        }
        if let Some(aligned) = store.read_map(kf, "prior_aligned")? {
            let est = run.map_depth(kf, &aligned);
            add(&mut tally[1], score_depth(&est, &gt, s, threshold, None)?);
        }
        for (stage, name) in [(2, "semidense"), (3, "filtered")] {
            if let Some(semi) = store.read_map(kf, name)? {
                if name == "semidense" {
                    kf_slopes.semidense = depth_range_slope(&semi, &gt)?;
                }
                let est = run.map_depth(kf, &semi);
                let mask = has_value(&semi);
                add(
                    &mut tally[stage],
                    score_depth(&est, &gt, s, threshold, Some(&mask))?,
                );
            }
        }
        if let Some(dense) = store.read_map(kf, "depth")? {
            add(&mut tally[4], score_depth(&dense, &gt, s, threshold, None)?);
            if let Some(best) = best_scale(&dense, &gt) {
                add(
                    &mut tally[5],
                    score_depth(&dense, &gt, best, threshold, None)?,
                );
                ratios.push(KeyframeScaleRatio {
                    timestamp: kf.timestamp,
                    ratio: best / s,
                });
            }
        }
        slopes.push(kf_slopes);
    }
    let [
        prior_gt_fit,
        prior_aligned,
        semidense_raw,
        semidense_filtered,
        dense,
        dense_keyframe_scale,
    ] = tally.map(|t| t.score());
    Ok(DenseDepthReport {
        threshold,
        trajectory_scale: s,
        ate_rmse_m: run.ate.rmse,
        ate_matched: run.ate.matched,
        keyframes: run.store.keyframes.len(),
        keyframes_evaluated: evaluated,
        keyframes_without_gt: without_gt,
        no_model_keyframes: run
            .store
            .keyframes
            .iter()
            .filter(|k| k.is_no_model())
            .count(),
        prior_gt_fit_failures: fit_failures,
        stages: StageScores {
            prior_gt_fit,
            prior_aligned,
            semidense_raw,
            semidense_filtered,
            dense,
            dense_keyframe_scale,
        },
        depth_range_slopes: slopes,
        dense_scale_ratios: ratios,
    })
}

/// The scale that brings `depth` onto `gt` at the median pixel (both positive and finite);
/// `None` when no pixel has both.
fn best_scale(depth: &ImageF32, gt: &ImageF32) -> Option<f64> {
    let mut ratios: Vec<f64> = (depth.data.iter().zip(&gt.data))
        .filter(|(d, g)| d.is_finite() && g.is_finite() && **d > 0.0 && **g > 0.0)
        .map(|(d, g)| f64::from(*g) / f64::from(*d))
        .collect();
    crate::metric_scale::median(&mut ratios)
}

fn add(tally: &mut StageTally, acc: Option<DepthAccuracy>) {
    if let Some(acc) = acc {
        tally.add(&acc);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eval_dense_tally_means_and_pools() {
        let mut t = StageTally::default();
        assert_eq!(t.score(), None);
        // 1 of 2 pixels right, then 9 of 18: mean of 50 and 50; pooled 10 / 20.
        t.add(&DepthAccuracy {
            percent: 50.0,
            valid_gt: 2,
            evaluated: 2,
            correct: 1,
        });
        t.add(&DepthAccuracy {
            percent: 100.0,
            valid_gt: 18,
            evaluated: 18,
            correct: 18,
        });
        let s = t.score().expect("score");
        assert_eq!(s.percent_mean, 75.0);
        assert!((s.percent_pooled - 95.0).abs() < 1e-12);
        assert_eq!((s.pixels, s.correct, s.keyframes), (20, 19, 2));
    }

    #[test]
    fn eval_dense_best_scale_is_the_median_ratio_over_pixels_both_have() {
        // The estimate is 1.25× the truth on every pixel but one outlier; holes either side.
        let gt = ImageF32::from_vec(6, 1, vec![1.0, 2.0, 0.0, 3.0, 4.0, 5.0]).expect("gt");
        let est =
            ImageF32::from_vec(6, 1, vec![1.25, 2.5, 7.0, f32::NAN, 5.0, 60.0]).expect("estimate");
        let best = best_scale(&est, &gt).expect("pixels");
        assert!((best - 0.8).abs() < 1e-6, "{best}");
        let empty = ImageF32::filled(6, 1, 0.0);
        assert!(best_scale(&empty, &gt).is_none());
    }

    #[test]
    fn eval_dense_score_counts_only_masked_pixels() {
        let gt = ImageF32::from_vec(4, 1, vec![1.0, 2.0, 0.0, 4.0]).expect("size");
        // Right, wrong (+50 %), no gt, no estimate.
        let est = ImageF32::from_vec(4, 1, vec![0.5, 1.5, 1.0, 0.0]).expect("size");
        let all = score_depth(&est, &gt, 2.0, 0.1, None)
            .expect("score")
            .expect("some");
        assert_eq!((all.valid_gt, all.evaluated, all.correct), (3, 2, 1));
        let mask = [true, false, true, false];
        let only = score_depth(&est, &gt, 2.0, 0.1, Some(&mask))
            .expect("score")
            .expect("some");
        assert_eq!((only.valid_gt, only.correct, only.percent), (1, 1, 100.0));
        // No overlap between the mask and the ground truth: nothing to score.
        let none = score_depth(&est, &gt, 2.0, 0.1, Some(&[false, false, true, false]));
        assert_eq!(none.expect("score"), None);
        assert!(score_depth(&est, &gt, 2.0, 0.1, Some(&[true])).is_err());
    }

    #[test]
    fn eval_dense_ground_truth_lookup_is_pixel_centre_nearest() {
        // Working camera = dataset camera halved (PinholeCamera::scaled): pixel x takes the
        // dataset pixel nearest to its centre 2x + 0.5, i.e. 2x or 2x + 1.
        let full = PinholeCamera::new(100.0, 100.0, 7.5, 5.5, 16, 12).expect("camera");
        let half = full.scaled(1);
        let lut = ground_truth_lookup(&half, &full);
        assert_eq!(lut.len(), 8 * 6);
        for (i, src) in lut.iter().enumerate() {
            let (x, y) = (i % 8, i / 8);
            let j = src.expect("inside");
            let (u, v) = (j % 16, j / 16);
            assert!(u == 2 * x || u == 2 * x + 1, "x {x} -> u {u}");
            assert!(v == 2 * y || v == 2 * y + 1, "y {y} -> v {v}");
        }
        // Same camera: identity.
        let same = ground_truth_lookup(&full, &full);
        assert!(same.iter().enumerate().all(|(i, s)| *s == Some(i)));
        // A working camera wider than the dataset's sees outside it.
        let wide = PinholeCamera::new(50.0, 50.0, 7.5, 5.5, 16, 12).expect("camera");
        let lut = ground_truth_lookup(&wide, &full);
        assert_eq!(lut[0], None);
        assert!(lut[6 * 16 + 8].is_some());
    }
}
