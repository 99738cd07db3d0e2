//! Levenberg–Marquardt on the window: keyframe poses, affine brightness and point depths
//! jointly, the depths eliminated by the Schur complement, the step kept out of the gauge
//! (DSO's `EnergyFunctional::solveSystemF`).

use nalgebra::{DMatrix, DVector};

use super::config::OdometryConfig;
use super::energy::{NormalEquations, depth_prior_energy, depth_step, photometric_energy};
use super::gauge;
use super::prior::MarginalisationPrior;
use super::residual::{FRAME_PARAMS, FrameState, FrameView, Linearisation};
use super::{WindowFrame, WindowPoint};

/// Holds a window whose scale and pose the photometric error cannot fix yet: the first
/// keyframe stays where it is (DSO's prior on the first frame's pose) and every other
/// keyframe's translation is pulled to zero with `translation_weight` (DSO's initialiser
/// charges `alphaW · points · |t|²` until the translation has earned its place). An anchored
/// window takes no gauge projection: the anchor fixes the gauge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Anchor {
    pub translation_weight: f64,
}

/// Weight that holds an anchored window's first keyframe (DSO: 10¹⁰ on translation, 10¹¹ on
/// rotation).
const FIXED_WEIGHT: f64 = 1e10;

impl Anchor {
    fn energy(&self, frames: &[WindowFrame], states: &[FrameState]) -> f64 {
        let mut e = 0.0;
        for (k, (f, s)) in frames.iter().zip(states).enumerate() {
            if k == 0 {
                let d = s.delta_from(&f.first_estimate);
                e += 0.5 * FIXED_WEIGHT * d.fixed_rows::<6>(0).norm_squared();
            } else {
                e += 0.5 * self.translation_weight * s.world_from_camera.translation.norm_squared();
            }
        }
        e
    }

    fn add(
        &self,
        frames: &[WindowFrame],
        states: &[FrameState],
        h: &mut DMatrix<f64>,
        b: &mut DVector<f64>,
    ) {
        for (k, (f, s)) in frames.iter().zip(states).enumerate() {
            let o = k * FRAME_PARAMS;
            if k == 0 {
                let d = s.delta_from(&f.first_estimate);
                for i in 0..6 {
                    h[(o + i, o + i)] += FIXED_WEIGHT;
                    b[o + i] += FIXED_WEIGHT * d[i];
                }
            } else {
                // The step moves the translation by R·v: gradient W·Rᵀt, Hessian W·I.
                let pose = &s.world_from_camera;
                let g = pose.rotation.inverse().act(&pose.translation) * self.translation_weight;
                for i in 0..3 {
                    h[(o + i, o + i)] += self.translation_weight;
                    b[o + i] += g[i];
                }
            }
        }
    }
}

/// The window's priors besides the affine and depth ones that live with their variables.
#[derive(Clone, Copy, Debug)]
pub struct Priors<'a> {
    pub marginalisation: &'a MarginalisationPrior,
    pub anchor: Option<&'a Anchor>,
}

/// What [`optimize`] did, energies as [`total_energy`] counts them.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SolveReport {
    pub initial_energy: f64,
    pub final_energy: f64,
    pub iterations: usize,
    /// Pattern residuals (inliers) at the last linearisation.
    pub residuals: usize,
}

/// The views of `frames` at `config.level` with `states`.
pub fn views<'a>(
    config: &OdometryConfig,
    frames: &'a [WindowFrame],
    states: &[FrameState],
) -> Vec<FrameView<'a>> {
    frames
        .iter()
        .zip(states)
        .map(|(f, s)| {
            let level = f.frame.level(config.level);
            FrameView {
                level,
                samples: &f.samples,
                camera: f.frame.camera_at(config.level),
                state: *s,
                first_estimate: f.first_estimate,
                row_twist: f.velocity * (config.rolling_shutter_readout / level.height() as f64),
            }
        })
        .collect()
}

/// Every keyframe's offset from its first estimate, stacked (`8·n`).
pub fn offsets(frames: &[WindowFrame], states: &[FrameState]) -> DVector<f64> {
    let mut d = DVector::zeros(frames.len() * FRAME_PARAMS);
    for (k, (f, s)) in frames.iter().zip(states).enumerate() {
        d.rows_mut(k * FRAME_PARAMS, FRAME_PARAMS)
            .copy_from(&s.delta_from(&f.first_estimate));
    }
    d
}

/// Adds keyframe `k`'s affine-brightness prior (`½(w_a a² + w_b b²)` at `state`) to `h`, `b`.
pub fn add_affine_prior(
    config: &OdometryConfig,
    k: usize,
    state: &FrameState,
    h: &mut DMatrix<f64>,
    b: &mut DVector<f64>,
) {
    let (ia, ib) = (k * FRAME_PARAMS + 6, k * FRAME_PARAMS + 7);
    h[(ia, ia)] += config.affine_prior_a;
    h[(ib, ib)] += config.affine_prior_b;
    b[ia] += config.affine_prior_a * state.affine.0;
    b[ib] += config.affine_prior_b * state.affine.1;
}

/// The objective: half the photometric energy, the marginalisation prior, the affine prior
/// and the points' depth priors (the normal equations of [`NormalEquations`] are those of
/// this function).
pub fn total_energy(
    config: &OdometryConfig,
    frames: &[WindowFrame],
    states: &[FrameState],
    points: &[WindowPoint],
    hosts: &[usize],
    priors: &Priors<'_>,
) -> f64 {
    let views = views(config, frames, states);
    let (photometric, _) = photometric_energy(config, points, hosts, &views);
    let affine: f64 = states
        .iter()
        .map(|s| {
            config.affine_prior_a * s.affine.0.powi(2) + config.affine_prior_b * s.affine.1.powi(2)
        })
        .sum();
    0.5 * photometric
        + priors.marginalisation.energy(&offsets(frames, states))
        + 0.5 * affine
        + depth_prior_energy(points)
        + priors.anchor.map_or(0.0, |a| a.energy(frames, states))
}

/// The full normal equations at `states`: photometric, marginalisation prior and affine prior.
pub fn normal_equations(
    config: &OdometryConfig,
    frames: &[WindowFrame],
    states: &[FrameState],
    points: &[WindowPoint],
    hosts: &[usize],
    priors: &Priors<'_>,
    mode: Linearisation,
) -> NormalEquations {
    let views = views(config, frames, states);
    let mut eq = NormalEquations::build(config, points, hosts, &views, mode);
    eq.h += &priors.marginalisation.h;
    eq.b += priors.marginalisation.gradient(&offsets(frames, states));
    for (k, state) in states.iter().enumerate() {
        add_affine_prior(config, k, state, &mut eq.h, &mut eq.b);
    }
    if let Some(anchor) = priors.anchor {
        anchor.add(frames, states, &mut eq.h, &mut eq.b);
    }
    eq
}

/// Minimises [`total_energy`] over every keyframe's state and every point's inverse depth,
/// updating `frames` and `points` in place.
pub fn optimize(
    config: &OdometryConfig,
    frames: &mut [WindowFrame],
    points: &mut [WindowPoint],
    hosts: &[usize],
    priors: &Priors<'_>,
    mode: Linearisation,
) -> SolveReport {
    let mut states: Vec<FrameState> = frames.iter().map(|f| f.state).collect();
    let mut current = total_energy(config, frames, &states, points, hosts, priors);
    let mut report = SolveReport {
        initial_energy: current,
        final_energy: current,
        ..SolveReport::default()
    };
    if frames.len() < 2 || points.is_empty() {
        return report;
    }
    let first: Vec<FrameState> = frames.iter().map(|f| f.first_estimate).collect();
    let gauge_basis = gauge::basis(&first);
    let mut lambda = 1e-4;
    for _ in 0..config.iterations {
        report.iterations += 1;
        let eq = normal_equations(config, frames, &states, points, hosts, priors, mode);
        report.residuals = eq.residuals;
        let mut accepted = false;
        let mut converged = false;
        for _ in 0..6 {
            let (mut h, b) = eq.reduced(lambda);
            for i in 0..h.nrows() {
                h[(i, i)] += lambda * eq.h[(i, i)] + 1e-9;
            }
            let Some(chol) = h.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let mut step = chol.solve(&(-b));
            if priors.anchor.is_none() {
                gauge::project_out(&gauge_basis, &mut step);
            }
            let trial_states: Vec<FrameState> = states
                .iter()
                .enumerate()
                .map(|(k, s)| {
                    s.step(
                        &step
                            .fixed_rows::<FRAME_PARAMS>(k * FRAME_PARAMS)
                            .into_owned(),
                    )
                })
                .collect();
            let mut trial_points = points.to_vec();
            for (p, sys) in trial_points.iter_mut().zip(&eq.points) {
                if let Some(d) = depth_step(sys, lambda, &step) {
                    // Keep the inverse depth positive: at most halve or double it per step.
                    p.idepth = (p.idepth + d).clamp(0.5 * p.idepth, 2.0 * p.idepth);
                }
            }
            let trial = total_energy(config, frames, &trial_states, &trial_points, hosts, priors);
            if trial < current {
                let gain = (current - trial) / current.max(1e-12);
                states = trial_states;
                points.clone_from_slice(&trial_points);
                current = trial;
                lambda = (lambda * 0.5).max(1e-6);
                accepted = true;
                converged = gain < 1e-5;
                break;
            }
            lambda *= 10.0;
        }
        if !accepted || converged {
            break;
        }
    }
    for (f, s) in frames.iter_mut().zip(&states) {
        f.state = *s;
    }
    report.final_energy = current;
    report
}
