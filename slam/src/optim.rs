//! What the direct image alignments share: LSD-SLAM's Levenberg–Marquardt schedule
//! ([`LmSchedule`], [`lm_level`]) and its photometric residual model ([`PhotometricParams`]).
//! The SE(3) frame tracker and the Sim(3) keyframe tracker differ in their residuals (the
//! latter adds depth), their parameterisation and their stopping limits, not in these.

use serde::{Deserialize, Serialize};

use crate::frame::PYRAMID_LEVELS;
use crate::{Error, Result};

/// LSD-SLAM resets the damping to 0 (pure Gauss–Newton) once it has decayed to this, and
/// restarts it at this value after the first rejected Gauss–Newton step.
pub const LAMBDA_RESTART: f64 = 0.2;

/// The Levenberg–Marquardt schedule of a coarse-to-fine alignment (LSD-SLAM's
/// `DenseDepthTrackerSettings`). Expert level, as is [`PhotometricParams`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LmSchedule {
    /// Maximum iterations per level, finest first. Default `[5, 20, 50, 100, 100]`
    /// (`maxItsPerLvl`): cheap coarse levels may iterate long, the fine levels only refine.
    pub max_iterations: [usize; PYRAMID_LEVELS],
    /// Initial damping λ at every level. Default 0 (`lambdaInitial`): start as Gauss–Newton.
    pub lambda_initial: f64,
    /// λ ← λ·this after an accepted step (and λ ← 0 once ≤ [`LAMBDA_RESTART`]). Default 0.5
    /// (`lambdaSuccessFac`).
    pub lambda_success_factor: f64,
    /// After the k-th rejected try of an iteration λ ← λ·this^k (0 becomes
    /// [`LAMBDA_RESTART`]). Default 2 (`lambdaFailFac`).
    pub lambda_fail_factor: f64,
    /// A level ends when a rejected increment δ has `|δ|² ≤` this. Default 1e-8
    /// (`stepSizeMin`).
    pub step_size_min: f64,
    /// A level ends when an accepted step leaves `cost_new / cost_old >` this (less than 0.1 %
    /// improvement). Default 0.999 (`convergenceEps`).
    pub convergence_eps: f64,
}

impl Default for LmSchedule {
    fn default() -> Self {
        Self {
            max_iterations: [5, 20, 50, 100, 100],
            lambda_initial: 0.0,
            lambda_success_factor: 0.5,
            lambda_fail_factor: 2.0,
            step_size_min: 1e-8,
            convergence_eps: 0.999,
        }
    }
}

impl LmSchedule {
    /// Checks that every factor is positive and finite (`what` names the section in errors).
    pub fn validate(&self, what: &str) -> Result<()> {
        for (name, v, min_exclusive) in [
            ("lambda_success_factor", self.lambda_success_factor, true),
            ("lambda_fail_factor", self.lambda_fail_factor, true),
            ("convergence_eps", self.convergence_eps, true),
            ("lambda_initial", self.lambda_initial, false),
            ("step_size_min", self.step_size_min, false),
        ] {
            let ok = v.is_finite() && if min_exclusive { v > 0.0 } else { v >= 0.0 };
            if !ok {
                return Err(Error::Config(format!(
                    "{what}.lm.{name} must be {}, got {v}",
                    if min_exclusive { "> 0" } else { "≥ 0" }
                )));
            }
        }
        Ok(())
    }
}

/// The photometric residual model of a direct alignment (ECCV 2014 eqs. (13), (16)), with
/// LSD-SLAM's values.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhotometricParams {
    /// Image-noise variance (8-bit units²) in the residual variance
    /// `σ_r² = camera_pixel_noise2 + var_weight · (∂r/∂d)² · V_d` (ECCV 2014 eq. (13), where it
    /// is written `2σ_I²`). Default 16 = 4² (`cameraPixelNoise2`), added once for both images.
    pub camera_pixel_noise2: f64,
    /// Multiplier on every inverse-depth variance (LSD-SLAM calls the filter's variances
    /// over-confident). Default 1 (`var_weight`).
    pub var_weight: f64,
    /// Huber width on the variance-normalised residual. Default 3 (`huber_d`).
    pub huber_d: f64,
    /// A warped point counts as *good* when `r² < max_diff_constant + max_diff_grad_mult·|∇I|²`.
    /// Default 40² (`MAX_DIFF_CONSTANT`).
    pub max_diff_constant: f64,
    /// Gradient term of the good-point test (edges tolerate larger photometric errors).
    /// Default 0.5² (`MAX_DIFF_GRAD_MULT`).
    pub max_diff_grad_mult: f64,
}

impl Default for PhotometricParams {
    fn default() -> Self {
        Self {
            camera_pixel_noise2: 16.0,
            var_weight: 1.0,
            huber_d: 3.0,
            max_diff_constant: 40.0 * 40.0,
            max_diff_grad_mult: 0.5 * 0.5,
        }
    }
}

impl PhotometricParams {
    /// Checks that every value is positive and finite.
    pub fn validate(&self, what: &str) -> Result<()> {
        for (name, v, min_exclusive) in [
            ("camera_pixel_noise2", self.camera_pixel_noise2, true),
            ("huber_d", self.huber_d, true),
            ("max_diff_constant", self.max_diff_constant, true),
            ("var_weight", self.var_weight, false),
            ("max_diff_grad_mult", self.max_diff_grad_mult, false),
        ] {
            let ok = v.is_finite() && if min_exclusive { v > 0.0 } else { v >= 0.0 };
            if !ok {
                return Err(Error::Config(format!(
                    "{what}.photometric.{name} must be {}, got {v}",
                    if min_exclusive { "> 0" } else { "≥ 0" }
                )));
            }
        }
        Ok(())
    }
}

/// The result of one damped try of an iteration ([`lm_level`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Attempt {
    /// The step lowered the cost and was taken; `converged` when it improved it by less than
    /// `convergence_eps` asks.
    Accepted { converged: bool },
    /// The step raised the cost and was not taken; `step_norm2` is `|δ|²` (NaN when there
    /// was no step).
    Rejected { step_norm2: f64 },
}

/// How a [`lm_level`] run may be cut short beyond the schedule.
#[derive(Clone, Copy, Debug)]
pub struct LmLimits {
    /// Rejected tries of one iteration after which the level ends.
    pub max_tries: u32,
    /// Damping beyond which the level ends (`(1 + λ)` must stay finite).
    pub max_lambda: f64,
}

/// One pyramid level of Levenberg–Marquardt with LSD-SLAM's schedule: `iterations` at most;
/// per iteration, tries at growing damping until one step is accepted. `attempt(λ, try)` builds
/// and evaluates the step damped by `(1 + λ)` on the diagonal (`try` counts from 1 within an
/// iteration, so the caller can set up the iteration's normal equations on the first) and
/// takes it when it is better; an `Err` ends the level at once and is returned. After an
/// accepted step `λ ← 0 if λ ≤ 0.2 else λ·lambda_success_factor`; after the k-th rejected try
/// `λ ← 0.2 if λ = 0 else λ·lambda_fail_factor^k`. The level ends after `iterations`, on a
/// converged step, or when a rejected step is tiny (`step_size_min`) or a limit is reached.
pub fn lm_level<E>(
    schedule: &LmSchedule,
    iterations: usize,
    limits: LmLimits,
    mut attempt: impl FnMut(f64, u32) -> std::result::Result<Attempt, E>,
) -> std::result::Result<(), E> {
    let mut lambda = schedule.lambda_initial;
    'iterations: for _ in 0..iterations {
        let mut tries = 0u32;
        loop {
            tries += 1;
            match attempt(lambda, tries)? {
                Attempt::Accepted { converged } => {
                    lambda = if lambda <= LAMBDA_RESTART {
                        0.0
                    } else {
                        lambda * schedule.lambda_success_factor
                    };
                    if converged {
                        break 'iterations;
                    }
                    break;
                }
                Attempt::Rejected { step_norm2 } => {
                    if step_norm2.is_nan()
                        || step_norm2 <= schedule.step_size_min
                        || tries >= limits.max_tries
                        || lambda >= limits.max_lambda
                    {
                        break 'iterations;
                    }
                    lambda = if lambda == 0.0 {
                        LAMBDA_RESTART
                    } else {
                        lambda * schedule.lambda_fail_factor.powi(tries as i32)
                    };
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Minimises `(x − 3)²` by damped Newton steps from 0: converges to 3 within the
    /// iterations, and the damping follows the schedule.
    #[test]
    fn lm_level_converges_on_a_parabola_and_follows_the_schedule() {
        let schedule = LmSchedule::default();
        let mut x = 0.0f64;
        let mut lambdas = Vec::new();
        let limits = LmLimits {
            max_tries: 60,
            max_lambda: 1e12,
        };
        lm_level::<()>(&schedule, 20, limits, |lambda, _| {
            lambdas.push(lambda);
            let (g, h) = (2.0 * (x - 3.0), 2.0);
            let step = -g / (h * (1.0 + lambda));
            let (old, new) = ((x - 3.0).powi(2), (x + step - 3.0).powi(2));
            if new < old {
                x += step;
                Ok(Attempt::Accepted {
                    converged: new / old > schedule.convergence_eps,
                })
            } else {
                Ok(Attempt::Rejected {
                    step_norm2: step * step,
                })
            }
        })
        .expect("no error");
        assert!((x - 3.0).abs() < 1e-9, "{x}");
        assert_eq!(lambdas[0], 0.0, "starts as Gauss–Newton");

        // A step that never helps: λ restarts at 0.2 and grows 2^k per try until the step
        // is tiny; one iteration, then the level ends.
        let mut tries_seen = Vec::new();
        lm_level::<()>(&schedule, 5, limits, |lambda, tries| {
            tries_seen.push((lambda, tries));
            Ok(Attempt::Rejected {
                step_norm2: 1.0 / (1.0 + lambda).powi(2),
            })
        })
        .expect("no error");
        assert_eq!(tries_seen[1], (LAMBDA_RESTART, 2));
        assert_eq!(tries_seen[2], (LAMBDA_RESTART * 4.0, 3));
        assert!(tries_seen.iter().all(|&(_, t)| t >= 1));
        let aborted = lm_level(&schedule, 5, limits, |_, _| Err::<Attempt, _>("stop"));
        assert_eq!(aborted, Err("stop"));
    }
}
