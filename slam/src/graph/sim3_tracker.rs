//! Sim(3) direct alignment of two keyframes (LSD-SLAM, Engel et al. ECCV 2014, §3.4 "Direct
//! Sim(3) image alignment"; `Sim3Tracker` in tum-vision/lsd_slam).
//!
//! Two keyframes' depth maps have different, unknown scales (scale drift), so the relative
//! pose between them is a similarity. Photometric residuals alone cannot observe that scale;
//! eq. (15) adds, for every reference point, a *depth residual*: the point's inverse depth
//! predicted in the other keyframe, `1/z'`, against that keyframe's own inverse-depth map at the
//! warped position. Each residual is normalised by its propagated variance (eq. (16)), the
//! point's two normalised residuals share one Huber weight, and the 7-DoF normal equations are
//! solved by Levenberg–Marquardt coarse-to-fine.
//!
//! Conventions: the estimate is `frame_from_reference` (maps reference-keyframe coordinates to
//! frame-keyframe coordinates, in their respective depth scales); increments are applied on the
//! right, `T ← T·exp(δ)`, with δ = (ρ, φ, σ), and the returned `information` is the
//! Gauss–Newton Hessian `Σ Jᵀ W J` of that right perturbation at the final estimate (what the
//! pose-graph edge needs, see [`super::pose_graph`]).
//!
//! Deviations from LSD-SLAM, on purpose: the frame's gradient alone is used (no ESM average with
//! the rotated reference gradient), and the frame's inverse depth is interpolated
//! bilinearly over valid neighbours instead of read at the rounded position. As in LSD-SLAM the
//! depth residual's Jacobian ignores the gradient of the frame's depth map (too noisy on a
//! semi-dense map to differentiate).
//!
//! With [`BackendConfig::affine_lighting`] the photometric residual compares `a·I_ref + b` with
//! the frame (LSD-SLAM's `useAffineLightningEstimation`, the fit of the SE(3) tracker): an
//! exposure change between two keyframes otherwise biases the alignment, scale included — on a
//! synthetic path with auto-exposure alone the Sim(3) edges took the scale drift from 1.95
//! (odometry edges only) to 6.7 (docs/tuning.md, "Scale drift, issue 22").

use std::cell::Cell;

use nalgebra::{Cholesky, Matrix3, Vector2, Vector3};

use super::config::BackendConfig;
use super::points::{KeyframeLevel, KeyframeLevels, RefPoint};
use crate::Result;
use crate::frame::Frame;
use crate::geometry::{Matrix7, Sim3, Vector7};
use crate::image::pyramid::PyramidLevel;
use crate::mapping::DepthMap;
use crate::optim::{Attempt, LmLimits, lm_level};

/// Outcome of one Sim(3) alignment.
#[derive(Clone, Debug, PartialEq)]
pub struct Sim3TrackResult {
    /// The estimate, reference-keyframe coordinates → frame-keyframe coordinates.
    pub frame_from_reference: Sim3,
    /// `Σ Jᵀ W J` at the estimate, on the finest level (right perturbation of
    /// `frame_from_reference`, tangent order ρ, φ, σ). Zero when diverged.
    pub information: Matrix7,
    /// Mean Huber-weighted, variance-normalised squared residual over photometric and depth
    /// terms (LSD-SLAM's `lastResidual`).
    pub residual: f64,
    /// Mean of the photometric terms alone.
    pub residual_photometric: f64,
    /// Mean of the depth terms alone (0 without depth terms).
    pub residual_depth: f64,
    /// Share of warped points whose photometric error is small (`good / (good + bad)`).
    pub good_ratio: f64,
    /// LSD-SLAM's `pointUsage`: mean over reference points of `min(1, z_ref / z_frame)`, 0 for
    /// points warped out of the image.
    pub point_usage: f64,
    /// Number of points with a depth residual at the finest level.
    pub depth_terms: usize,
    /// The optimisation broke down (too few points in the image, or an absurd step).
    pub diverged: bool,
    /// Not diverged, finite sane scale, non-zero information, and `good_ratio` above
    /// [`BackendConfig::min_good_ratio`].
    pub good: bool,
}

/// Coarse-to-fine Sim(3) alignment between keyframes.
#[derive(Clone, Debug)]
pub struct Sim3Tracker {
    config: BackendConfig,
}

/// Residual sums and normal equations at one pose.
#[derive(Clone, Debug)]
struct Evaluation {
    warped: usize,
    sum_p: f64,
    sum_d: f64,
    num_p: usize,
    num_d: usize,
    good: usize,
    bad: usize,
    usage: f64,
    /// `Σ Jᵀ W J` and `Σ Jᵀ W r` (unnormalised).
    hessian: Matrix7,
    gradient: Vector7,
    /// Huber-weighted moments `(Σw, Σw·c1, Σw·c2, Σw·c1², Σw·c2²)` of the corrected reference
    /// intensity `c1 = a·I_ref + b` and the frame's `c2`, for the affine fit.
    moments: [f64; 5],
}

impl Evaluation {
    /// LSD-SLAM's affine fit `c2 ≈ α·c1 + β` (α the ratio of the robust standard deviations, β
    /// matching the means) composed with the current `(a, b)`; `None` when degenerate.
    fn affine_estimate(&self, (a, b): (f64, f64)) -> Option<(f64, f64)> {
        let [sw, sx, sy, sxx, syy] = self.moments;
        let alpha = ((syy - sy * sy / sw) / (sxx - sx * sx / sw)).sqrt();
        let beta = (sy - alpha * sx) / sw;
        (alpha.is_finite() && beta.is_finite() && alpha > 0.0)
            .then_some((alpha * a, alpha * b + beta))
            .filter(|(a, _)| (0.25..4.0).contains(a))
    }
}

impl Evaluation {
    fn mean(&self) -> f64 {
        let n = self.num_p + self.num_d;
        if n == 0 {
            f64::INFINITY
        } else {
            (self.sum_p + self.sum_d) / n as f64
        }
    }
}

/// Scales outside `(ε, 1/ε)` mean the alignment collapsed (LSD-SLAM's `tryTrackSim3`).
const SCALE_EPS: f64 = 1e-6;

/// Limits beyond the schedule: give up an iteration after this many rejected damped steps (the
/// step-size test normally ends it far earlier); no cap on the damping.
const LIMITS: LmLimits = LmLimits {
    max_tries: 60,
    max_lambda: f64::INFINITY,
};

impl Sim3Tracker {
    /// A tracker with `config`'s tracking parameters (the config is assumed validated).
    pub fn new(config: BackendConfig) -> Self {
        Self { config }
    }

    /// The configuration in use.
    pub fn config(&self) -> &BackendConfig {
        &self.config
    }

    /// Aligns `frame` to `reference` from `initial_frame_from_reference`, coarse-to-fine from
    /// [`BackendConfig::max_level`] to [`BackendConfig::min_level`]. Builds both keyframes'
    /// depth pyramids; use [`Sim3Tracker::track_levels`] to reuse them.
    pub fn track(
        &self,
        reference: &Frame,
        reference_depth: &DepthMap,
        frame: &Frame,
        frame_depth: &DepthMap,
        initial_frame_from_reference: &Sim3,
    ) -> Result<Sim3TrackResult> {
        let reference_levels = KeyframeLevels::new(reference, reference_depth)?;
        let frame_levels = KeyframeLevels::new(frame, frame_depth)?;
        Ok(self.track_levels(
            &reference_levels,
            frame,
            &frame_levels,
            initial_frame_from_reference,
            self.config.max_level,
            self.config.min_level,
        ))
    }

    /// Aligns on levels `coarsest` down to `finest` (clamped to what both keyframes have).
    pub fn track_levels(
        &self,
        reference: &KeyframeLevels,
        frame: &Frame,
        frame_levels: &KeyframeLevels,
        initial_frame_from_reference: &Sim3,
        coarsest: usize,
        finest: usize,
    ) -> Sim3TrackResult {
        let available = reference
            .levels
            .len()
            .min(frame_levels.levels.len())
            .min(frame.pyramid.levels.len());
        let coarsest = coarsest.min(available.saturating_sub(1));
        let finest = finest.min(coarsest);
        let cfg = &self.config;
        let mut pose = *initial_frame_from_reference;
        let mut affine = (1.0, 0.0);
        let mut last: Option<(usize, Evaluation)> = None;

        for level in (finest..=coarsest).rev() {
            let its = cfg.lm.max_iterations.get(level).copied().unwrap_or(0);
            if its == 0 && level != finest {
                continue;
            }
            let ctx = LevelContext {
                reference: &reference.levels[level],
                image: frame.level(level),
                frame: &frame_levels.levels[level],
                config: cfg,
                affine: Cell::new(affine),
            };
            let Some(mut eval) = ctx.evaluate(&pose) else {
                return self.diverged(pose, reference, level, last);
            };
            let refit = |eval: &Evaluation| {
                if cfg.affine_lighting
                    && let Some(fit) = eval.affine_estimate(ctx.affine.get())
                {
                    ctx.affine.set(fit);
                }
            };
            refit(&eval);
            let step_level = lm_level(&cfg.lm, its, LIMITS, |lambda, _| {
                let n = (eval.num_p + eval.num_d).max(1) as f64;
                let mut a = eval.hessian / n;
                for i in 0..7 {
                    a[(i, i)] *= 1.0 + lambda;
                }
                let b = -eval.gradient / n;
                let inc = solve7(a, &b);
                let step2 = inc.map_or(f64::NAN, |v| v.norm_squared());
                // An increment of unit size (≈ the scene depth, or a radian) is absurd.
                let Some(inc) = inc.filter(|_| step2 < 1.0) else {
                    return Err(());
                };
                let candidate = pose * Sim3::exp(&inc);
                let new_eval = ctx.evaluate(&candidate).ok_or(())?;
                if new_eval.mean() < eval.mean() {
                    let converged = new_eval.mean() / eval.mean() > cfg.lm.convergence_eps;
                    pose = candidate;
                    eval = new_eval;
                    refit(&eval);
                    return Ok(Attempt::Accepted { converged });
                }
                Ok(Attempt::Rejected { step_norm2: step2 })
            });
            if step_level.is_err() {
                return self.diverged(pose, reference, level, Some((level, eval)));
            }
            affine = ctx.affine.get();
            last = Some((level, eval));
        }

        match last {
            Some((level, eval)) => self.result(pose, reference, level, &eval),
            None => self.diverged(pose, reference, finest, None),
        }
    }

    /// The result from the finest level's last evaluation: the pose, its information, the
    /// residuals and the quality checks.
    fn result(
        &self,
        pose: Sim3,
        reference: &KeyframeLevels,
        level: usize,
        eval: &Evaluation,
    ) -> Sim3TrackResult {
        let cfg = &self.config;
        let total_points = reference.levels[level].points.len().max(1) as f64;
        let good_ratio = eval.good as f64 / (eval.good + eval.bad).max(1) as f64;
        let information = eval.hessian;
        let sane = pose.scale.is_finite()
            && pose.scale > SCALE_EPS
            && pose.scale < 1.0 / SCALE_EPS
            && pose.translation.iter().all(|v| v.is_finite())
            && information.iter().all(|v| v.is_finite())
            && information[(0, 0)] > 0.0
            && information[(6, 6)] > 0.0;
        Sim3TrackResult {
            frame_from_reference: pose,
            information,
            residual: eval.mean(),
            residual_photometric: eval.sum_p / eval.num_p.max(1) as f64,
            residual_depth: eval.sum_d / eval.num_d.max(1) as f64,
            good_ratio,
            point_usage: eval.usage / total_points,
            depth_terms: eval.num_d,
            diverged: false,
            good: sane && good_ratio >= cfg.min_good_ratio,
        }
    }

    fn diverged(
        &self,
        pose: Sim3,
        reference: &KeyframeLevels,
        level: usize,
        last: Option<(usize, Evaluation)>,
    ) -> Sim3TrackResult {
        let total = reference
            .levels
            .get(level)
            .map_or(1, |l| l.points.len().max(1)) as f64;
        let (residual, usage) = last.map_or((f64::INFINITY, 0.0), |(_, e)| (e.mean(), e.usage));
        Sim3TrackResult {
            frame_from_reference: pose,
            information: Matrix7::zeros(),
            residual,
            residual_photometric: f64::INFINITY,
            residual_depth: f64::INFINITY,
            good_ratio: 0.0,
            point_usage: usage / total,
            depth_terms: 0,
            diverged: true,
            good: false,
        }
    }
}

/// Solves the damped 7×7 system (Cholesky, LU as fallback for a semi-definite matrix).
fn solve7(a: Matrix7, b: &Vector7) -> Option<Vector7> {
    match Cholesky::new(a) {
        Some(c) => Some(c.solve(b)),
        None => a.lu().solve(b),
    }
    .filter(|v| v.iter().all(|x| x.is_finite()))
}

/// The data one level's evaluation reads.
pub(crate) struct LevelContext<'a> {
    pub reference: &'a KeyframeLevel,
    pub image: &'a PyramidLevel,
    pub frame: &'a KeyframeLevel,
    pub config: &'a BackendConfig,
    /// Affine brightness `(a, b)`: the reference intensity `I` appears as `a·I + b` in the frame.
    pub affine: Cell<(f64, f64)>,
}

/// One reference point warped into the frame: residuals, their Jacobians with respect to a
/// right perturbation of `frame_from_reference`, and their variance weights.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WarpedPoint {
    /// `r_p = a·I_ref + b − I_frame(π(T·p))`.
    pub r_p: f64,
    /// The frame's intensity at the warped position (the affine fit's `c2`).
    pub frame_intensity: f64,
    pub j_p: Vector7,
    /// `1 / σ_p²`.
    pub w_p: f64,
    /// `(r_d, ∂r_d/∂δ, 1/σ_d²)` with `r_d = 1/z' − D_frame(π(T·p))`, when the frame has depth
    /// there.
    pub depth: Option<(f64, Vector7, f64)>,
    /// `|∇I_frame|²` at the warped position.
    pub grad2: f64,
    /// `min(1, z_ref / z')`.
    pub usage: f64,
}

impl LevelContext<'_> {
    /// Warps one reference point; `None` when it lands outside the frame (1-pixel margin) or
    /// behind the camera.
    #[cfg(test)]
    pub(crate) fn warp(&self, frame_from_reference: &Sim3, pt: &RefPoint) -> Option<WarpedPoint> {
        self.warp_with(
            frame_from_reference,
            &frame_from_reference.act_jacobian_wrt_point(),
            pt,
        )
    }

    /// [`LevelContext::warp`] with `sR` of `frame_from_reference` computed once per evaluation.
    #[inline]
    fn warp_with(
        &self,
        frame_from_reference: &Sim3,
        sr: &Matrix3<f64>,
        pt: &RefPoint,
    ) -> Option<WarpedPoint> {
        let cfg = self.config;
        let cam = &self.frame.camera;
        let (w, h) = (f64::from(cam.width), f64::from(cam.height));
        let pw = frame_from_reference.act(&pt.point);
        if pw.z.is_nan() || pw.z <= 1e-9 {
            return None;
        }
        let uv = cam.project(&pw);
        // Strictly inside with a margin for the central-difference gradients.
        if !(uv.x > 1.0 && uv.y > 1.0 && uv.x < w - 2.0 && uv.y < h - 2.0) {
            return None;
        }
        // The image and its gradients have one size: one lookup serves all three.
        let at = self.image.image.bilinear_at(uv.x as f32, uv.y as f32)?;
        let intensity = self.image.image.sample(&at);
        let grad = Vector2::new(
            f64::from(self.image.gx.sample(&at)),
            f64::from(self.image.gy.sample(&at)),
        );
        // ∂I/∂p' (3-vector) through the projection.
        let grad_point: Vector3<f64> = cam.project_jacobian(&pw).transpose() * grad;
        let (a, b) = self.affine.get();
        let r_p = a * pt.intensity + b - f64::from(intensity);
        // Sensitivity of the warped point to the reference inverse depth d: p = p̂/d, so
        // ∂p'/∂d = −sR·p/d = −(p' − t)/d. Propagated into both residual variances (eq. (16)).
        let dpw_dd = -(pw - frame_from_reference.translation) / pt.idepth;
        let var_ref = cfg.photometric.var_weight * pt.var;
        let drp_dd = -grad_point.dot(&dpw_dd);
        let w_p = 1.0 / (cfg.photometric.camera_pixel_noise2 + var_ref * drp_dd * drp_dd);
        let j_act = Sim3::act_jacobian_with(sr, &pt.point);
        // ∂r_p/∂δ = −∇I·∂π/∂p'·∂p'/∂δ.
        let j_p: Vector7 = -(j_act.transpose() * grad_point);
        let inv_z = 1.0 / pw.z;
        let depth = self.frame.depth.sample(&uv).map(|(d_f, v_f)| {
            let r_d = inv_z - d_f;
            let drd_dd = -inv_z * inv_z * dpw_dd.z;
            let w_d = 1.0 / (cfg.photometric.var_weight * v_f + var_ref * drd_dd * drd_dd);
            // The frame map's own gradient is neglected (module docs).
            let j_d: Vector7 = j_act.row(2).transpose() * (-inv_z * inv_z);
            (r_d, j_d, w_d)
        });
        Some(WarpedPoint {
            r_p,
            frame_intensity: f64::from(intensity),
            j_p,
            w_p,
            depth,
            grad2: grad.norm_squared(),
            usage: (pt.point.z / pw.z).min(1.0),
        })
    }

    /// Residuals, weights and normal equations at `frame_from_reference`; `None` when too few
    /// points land in the frame (diverged).
    fn evaluate(&self, frame_from_reference: &Sim3) -> Option<Evaluation> {
        let cfg = self.config;
        let cam = &self.frame.camera;
        let mut e = Evaluation {
            warped: 0,
            sum_p: 0.0,
            sum_d: 0.0,
            num_p: 0,
            num_d: 0,
            good: 0,
            bad: 0,
            usage: 0.0,
            hessian: Matrix7::zeros(),
            gradient: Vector7::zeros(),
            moments: [0.0; 5],
        };
        let (a, b) = self.affine.get();
        let sr = frame_from_reference.act_jacobian_wrt_point();
        for pt in &self.reference.points {
            let Some(wp) = self.warp_with(frame_from_reference, &sr, pt) else {
                continue;
            };
            e.warped += 1;
            // One Huber weight per point on the sum of its normalised residuals.
            let norm_abs =
                wp.r_p.abs() * wp.w_p.sqrt() + wp.depth.map_or(0.0, |(r, _, w)| r.abs() * w.sqrt());
            let huber = if norm_abs < cfg.photometric.huber_d {
                1.0
            } else {
                cfg.photometric.huber_d / norm_abs
            };
            let weight_p = huber * wp.w_p;
            add_outer_upper(&mut e.hessian, &wp.j_p, weight_p);
            e.gradient += wp.j_p * (weight_p * wp.r_p);
            e.sum_p += weight_p * wp.r_p * wp.r_p;
            e.num_p += 1;
            if let Some((r_d, j_d, w_d)) = wp.depth {
                let weight_d = huber * w_d;
                add_outer_upper(&mut e.hessian, &j_d, weight_d);
                e.gradient += j_d * (weight_d * r_d);
                e.sum_d += weight_d * r_d * r_d;
                e.num_d += 1;
            }
            if wp.r_p * wp.r_p
                < cfg.photometric.max_diff_constant + cfg.photometric.max_diff_grad_mult * wp.grad2
            {
                e.good += 1;
            } else {
                e.bad += 1;
            }
            e.usage += wp.usage;
            let (c1, c2) = (a * pt.intensity + b, wp.frame_intensity);
            let m = &mut e.moments;
            m[0] += huber;
            m[1] += huber * c1;
            m[2] += huber * c2;
            m[3] += huber * c1 * c1;
            m[4] += huber * c2 * c2;
        }
        e.hessian.fill_lower_triangle_with_upper_triangle();
        let (w, h) = (f64::from(cam.width), f64::from(cam.height));
        let min_warped = (0.5 * cfg.min_warped_share * w * h).max(10.0);
        (e.warped as f64 >= min_warped).then_some(e)
    }
}

/// `h += j·jᵀ·w` on and above the diagonal only (the normal equations' hot loop; the lower
/// triangle is copied from the upper one at the end). Each element is `(jᵢ·jₖ)·w`, as the full
/// product computes it, so the sums are bit for bit those of `h += j * j.transpose() * w`.
#[inline]
fn add_outer_upper(h: &mut Matrix7, j: &Vector7, w: f64) {
    for k in 0..7 {
        for i in 0..=k {
            h[(i, k)] += j[i] * j[k] * w;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The normal equations are bit for bit those of the full outer products, so that
    /// deterministic runs give the same trajectories and meshes as before the change.
    #[test]
    fn upper_triangle_accumulation_equals_the_full_outer_products_bit_for_bit() {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 10f64.powi((state % 7) as i32 - 3)
        };
        let (mut full, mut upper) = (Matrix7::zeros(), Matrix7::zeros());
        for _ in 0..1000 {
            let j = Vector7::from_fn(|_, _| next());
            let w = next().abs();
            full += j * j.transpose() * w;
            add_outer_upper(&mut upper, &j, w);
        }
        upper.fill_lower_triangle_with_upper_triangle();
        for (a, b) in full.iter().zip(upper.iter()) {
            assert_eq!(a.to_bits(), b.to_bits());
        }
    }
}
