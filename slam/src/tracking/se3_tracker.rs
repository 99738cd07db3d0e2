//! Coarse-to-fine Levenberg–Marquardt on SE(3) (LSD-SLAM ECCV 2014 §3.3, `SE3Tracker`).

use std::mem;

use nalgebra::{Matrix6, Vector6};

use super::config::TrackingConfig;
use super::reference::TrackingReference;
use super::warp::{
    InterleavedLevel, WarpBuffers, WarpParams, evaluate, left_to_right_information,
    normal_equations,
};
use crate::Result;
use crate::frame::{Frame, PYRAMID_LEVELS};
use crate::geometry::SE3;
use crate::optim::{Attempt, LmLimits, lm_level};

/// Limits beyond the schedule: no cap on tries, and a cap on the damping (λ grows as `2^k` per
/// rejected try): beyond it the step is far below `step_size_min` anyway, and `(1 + λ)` must
/// not overflow into a non-finite system.
const LIMITS: LmLimits = LmLimits {
    max_tries: u32::MAX,
    max_lambda: 1e12,
};

/// The outcome of [`SE3Tracker::track`].
#[derive(Clone, Debug, PartialEq)]
pub struct TrackingResult {
    /// The estimated pose: maps keyframe coordinates to frame coordinates (keyframe scale).
    /// On divergence, the initial guess.
    pub frame_from_keyframe: SE3,
    /// Whether tracking succeeded; false (= tracking lost) when the optimisation diverged
    /// (fewer than 1 % of the level's pixels received a point, or singular normal equations),
    /// or at the finest level `good_ratio ≤ min_good_per_good_bad` (0.5) or
    /// `good / pixels ≤ min_good_per_all` (0.04) — LSD-SLAM's `trackingWasGood` — or
    /// `correlation ≤ min_correlation` (0.5, a relfusion addition that rejects unrelated
    /// images, see [`TrackingConfig::min_correlation`]).
    pub good: bool,
    /// Final cost: mean of `w_huber · r² / σ_r²` over the warped points at the finest level
    /// (LSD-SLAM `lastResidual`).
    pub residual: f32,
    /// `good / (good + bad)` warped points at the finest level.
    pub good_ratio: f32,
    /// Share of the finest level's reference points that landed in the image, each weighted by
    /// `min(1, z_keyframe / z_frame)` (LSD-SLAM `pointUsage`, an input of keyframe selection).
    pub point_usage: f32,
    /// Number of LM iterations (normal-equation builds) over all levels.
    pub iterations: usize,
    /// Pearson correlation between keyframe intensities and frame intensities at the warped
    /// points of the finest level (≈ 1 when the frame shows the keyframe's edges where the
    /// pose puts them, ≈ 0 for an unrelated image).
    pub correlation: f32,
    /// The final normal-equation matrix `Σ w·Jᵀ·J` at the finest level (unnormalised, in units
    /// of the variance-normalised residual, Huber-weighted) with respect to a *right*
    /// perturbation `frame_from_keyframe · exp(δ)`, δ = (ρ, φ); its inverse approximates the
    /// pose covariance. Zero when tracking diverged.
    pub information: Matrix6<f64>,
}

impl TrackingResult {
    fn lost(initial: &SE3, iterations: usize) -> Self {
        Self {
            frame_from_keyframe: *initial,
            good: false,
            residual: f32::INFINITY,
            good_ratio: 0.0,
            point_usage: 0.0,
            iterations,
            correlation: 0.0,
            information: Matrix6::zeros(),
        }
    }
}

/// Direct SE(3) image alignment of frames against a keyframe's semi-dense depth.
///
/// Owns its work buffers: reuse one tracker for every frame so that tracking allocates nothing
/// once the buffers have grown to the largest point cloud.
#[derive(Debug)]
pub struct SE3Tracker {
    config: TrackingConfig,
    current: WarpBuffers,
    trial: WarpBuffers,
    frame_levels: Vec<InterleavedLevel>,
}

impl SE3Tracker {
    /// A tracker with `config` (validated).
    pub fn new(config: TrackingConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            config,
            current: WarpBuffers::default(),
            trial: WarpBuffers::default(),
            frame_levels: vec![InterleavedLevel::default(); PYRAMID_LEVELS],
        })
    }

    /// The configuration.
    pub fn config(&self) -> &TrackingConfig {
        &self.config
    }

    /// Aligns `frame` to the keyframe of `reference`, starting from
    /// `initial_frame_from_keyframe` (the previous frame's pose composed with a motion model).
    ///
    /// Per level from `max_level` down to `min_level`: LM on the 6×6 normal equations with
    /// LSD-SLAM's schedule ([`lm_level`]), the step applied on the left.
    pub fn track(
        &mut self,
        reference: &TrackingReference,
        frame: &Frame,
        initial_frame_from_keyframe: &SE3,
    ) -> TrackingResult {
        let cfg = self.config.clone();
        let mut pose = *initial_frame_from_keyframe;
        let mut affine = (1.0f32, 0.0f32);
        let mut iterations = 0usize;
        let top = cfg
            .max_level
            .min(frame.pyramid.levels.len().saturating_sub(1));
        if cfg.min_level > top {
            return TrackingResult::lost(initial_frame_from_keyframe, 0);
        }
        for level in (cfg.min_level..=top).rev() {
            let camera = frame.camera_at(level);
            self.frame_levels[level].fill(frame.level(level));
            let image = &self.frame_levels[level];
            let points = reference.level(level);
            // Level 0 uses every `level0_point_step`-th point; the pixel-count thresholds below
            // then count each used point for `point_step` pixels.
            let point_step = if level == 0 { cfg.level0_point_step } else { 1 };
            let pixels = (image.width * image.height) as f32 / point_step as f32;
            let min_warped = cfg.min_good_per_all_absmin * pixels;

            let params = WarpParams::new(&pose, &camera, affine);
            evaluate(points, image, &params, &cfg, point_step, &mut self.current);
            if (self.current.len() as f32) < min_warped || self.current.is_empty() {
                return TrackingResult::lost(initial_frame_from_keyframe, iterations);
            }
            if cfg.affine_lighting {
                affine = self.current.affine_estimate.unwrap_or(affine);
            }
            let mut last_cost = self.current.cost;
            // The normal equations of the iteration's starting point, set up on its first try.
            let mut normal = None;
            let its = cfg.lm.max_iterations[level];
            let step_level = lm_level(&cfg.lm, its, LIMITS, |lambda, tries| {
                if tries == 1 {
                    normal = Some(normal_equations(&self.current));
                    iterations += 1;
                }
                let Some((h, g)) = &normal else {
                    return Err(());
                };
                let mut a = *h;
                for i in 0..6 {
                    a[(i, i)] *= 1.0 + lambda;
                }
                // No solution: no gradient information at all (e.g. a constant image).
                let step = solve(a, g).ok_or(())?;
                let candidate = SE3::exp(&step) * pose;
                let params = WarpParams::new(&candidate, &camera, affine);
                evaluate(points, image, &params, &cfg, point_step, &mut self.trial);
                if (self.trial.len() as f32) < min_warped || self.trial.is_empty() {
                    return Err(());
                }
                let cost = self.trial.cost;
                if cost < last_cost {
                    pose = candidate;
                    mem::swap(&mut self.current, &mut self.trial);
                    if cfg.affine_lighting {
                        affine = self.current.affine_estimate.unwrap_or(affine);
                    }
                    let converged = cost / last_cost > cfg.lm.convergence_eps;
                    last_cost = cost;
                    return Ok(Attempt::Accepted { converged });
                }
                Ok(Attempt::Rejected {
                    step_norm2: step.norm_squared(),
                })
            });
            if step_level.is_err() {
                return TrackingResult::lost(initial_frame_from_keyframe, iterations);
            }

            if level == cfg.min_level {
                let used = points.len().div_ceil(point_step);
                return self.result(pose, last_cost, iterations, (used, pixels));
            }
        }
        TrackingResult::lost(initial_frame_from_keyframe, iterations)
    }

    /// The result at the finest level from its last evaluation: the pose with its cost,
    /// iterations, and the quality checks over the `used` points that stand for `pixels`
    /// pixels.
    fn result(
        &self,
        pose: SE3,
        last_cost: f64,
        iterations: usize,
        (used, pixels): (usize, f32),
    ) -> TrackingResult {
        let cfg = &self.config;
        let buffers = &self.current;
        let good = buffers.good as f32;
        let total = (buffers.good + buffers.bad) as f32;
        let good_ratio = if total > 0.0 { good / total } else { 0.0 };
        let point_usage = if used == 0 {
            0.0
        } else {
            (buffers.usage / used as f64) as f32
        };
        let (h_left, _) = normal_equations(buffers);
        let correlation = buffers.correlation();
        TrackingResult {
            frame_from_keyframe: pose,
            good: good / pixels > cfg.min_good_per_all
                && good_ratio > cfg.min_good_per_good_bad
                && correlation > cfg.min_correlation
                && last_cost.is_finite(),
            residual: last_cost as f32,
            good_ratio,
            point_usage,
            iterations,
            correlation,
            information: left_to_right_information(&pose, &h_left),
        }
    }

    /// Relocalisation / keyframe re-activation helper: tracks `frame` against every candidate
    /// keyframe from its initial guess and returns the index and result of the best good one,
    /// i.e. the largest `point_usage · good_ratio`, which must exceed
    /// `relocalization_threshold` (LSD-SLAM's `Relocalizer` test with `relocalizationTH`).
    pub fn try_relocalise(
        &mut self,
        candidates: &[(&TrackingReference, SE3)],
        frame: &Frame,
    ) -> Option<(usize, TrackingResult)> {
        let mut best: Option<(usize, TrackingResult, f32)> = None;
        for (i, (reference, guess)) in candidates.iter().enumerate() {
            let result = self.track(reference, frame, guess);
            let score = result.point_usage * result.good_ratio;
            if result.good
                && score > self.config.relocalization_threshold
                && best.as_ref().is_none_or(|(_, _, s)| score > *s)
            {
                best = Some((i, result, score));
            }
        }
        best.map(|(i, r, _)| (i, r))
    }
}

/// Solves the damped normal equations `A·δ = g` by Cholesky; `None` when `A` is not positive
/// definite (no constraint on some direction) or the step is not finite.
fn solve(a: Matrix6<f64>, g: &Vector6<f64>) -> Option<Vector6<f64>> {
    let step = a.cholesky()?.solve(g);
    step.iter().all(|v| v.is_finite()).then_some(step)
}
