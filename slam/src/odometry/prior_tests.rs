//! The per-point depth prior and the anchor enter the objective and its normal equations
//! consistently: what they add to `b` is the gradient of what they add to the energy.

use nalgebra::DVector;

use super::residual::{FRAME_PARAMS, FrameState, Linearisation, Vector8};
use super::solve::{Anchor, Priors, normal_equations, total_energy};
use super::tests::{add_keyframe, render};
use super::{DepthPrior, MarginalisationPrior, OdometryConfig, SlidingWindow, WindowPoint};

/// Energy and normal equations of `window` with `anchor`, its points' priors as they are.
fn system(
    window: &SlidingWindow,
    states: &[FrameState],
    points: &[WindowPoint],
    anchor: Option<&Anchor>,
) -> (f64, DVector<f64>, Vec<(f64, f64)>) {
    let hosts: Vec<usize> = points
        .iter()
        .map(|p| window.index_of(p.host).expect("host"))
        .collect();
    let prior = MarginalisationPrior {
        h: nalgebra::DMatrix::zeros(states.len() * FRAME_PARAMS, states.len() * FRAME_PARAMS),
        b: DVector::zeros(states.len() * FRAME_PARAMS),
    };
    let (config, frames) = (window.config(), window.frames());
    let priors = Priors {
        marginalisation: &prior,
        anchor,
    };
    let energy = total_energy(config, frames, states, points, &hosts, &priors);
    let eq = normal_equations(
        config,
        frames,
        states,
        points,
        &hosts,
        &priors,
        Linearisation::Current,
    );
    let depth = eq.points.iter().map(|p| (p.h_dd, p.b_d)).collect();
    (energy, eq.b, depth)
}

#[test]
fn depth_prior_and_anchor_add_the_gradient_of_their_energy() {
    let r = render(7, &[0, 6]);
    let mut window = SlidingWindow::new(OdometryConfig::default()).expect("config");
    add_keyframe(&mut window, &r, 0, r.poses[0], 200, || 1.0);
    // The second keyframe away from its first estimate, so that the anchor's hold on the
    // first and its charge on the second's translation are both non-zero.
    add_keyframe(&mut window, &r, 1, r.poses[1], 0, || 1.0);
    let mut states: Vec<FrameState> = window.frames().iter().map(|f| f.state).collect();
    let mut kick = Vector8::zeros();
    kick[0] = 0.001;
    kick[4] = 0.0002;
    states[0] = states[0].step(&kick);
    let plain: Vec<WindowPoint> = window.points().to_vec();
    let with_prior: Vec<WindowPoint> = plain
        .iter()
        .enumerate()
        .map(|(i, p)| WindowPoint {
            // Every other prior robust, half of those past their Huber width.
            prior: Some(DepthPrior {
                huber: match i % 4 {
                    1 => 1e-3,
                    3 => 1e3,
                    _ => f64::INFINITY,
                },
                ..DepthPrior::quadratic(p.idepth * (1.0 + 0.01 * (i % 7) as f64), 50.0 + i as f64)
            }),
            ..p.clone()
        })
        .collect();
    let anchor = Anchor {
        translation_weight: 3e4,
    };
    let (e0, b0, d0) = system(&window, &states, &plain, None);
    let (e1, b1, d1) = system(&window, &states, &with_prior, Some(&anchor));
    // Depths: the prior adds its weight w to h_dd and w·(ρ − ρ₀) to b_d, and its energy; the
    // b_d term is the energy's derivative (numeric), inside the Huber width and past it.
    let mut expected_energy = 0.0;
    let mut robust = 0;
    for ((p, a), b) in with_prior.iter().zip(&d0).zip(&d1) {
        let prior = p.prior.expect("prior");
        let w = prior.weight_at(p.idepth);
        robust += usize::from(w < prior.weight);
        assert!((b.0 - a.0 - w).abs() < 1e-6 * b.0.max(1.0));
        let gradient = w * (p.idepth - prior.idepth);
        assert!((b.1 - a.1 - gradient).abs() < 1e-6 * (b.1.abs() + gradient.abs()).max(1.0));
        let eps = 1e-7 * p.idepth;
        let numeric = (prior.energy(p.idepth + eps) - prior.energy(p.idepth - eps)) / (2.0 * eps);
        assert!(
            (numeric - gradient).abs() < 1e-4 * gradient.abs().max(1e-6),
            "prior {prior:?} at {}: numeric {numeric}, analytic {gradient}",
            p.idepth
        );
        expected_energy += prior.energy(p.idepth);
    }
    assert!(robust > 0, "no prior past its Huber width");
    // Frames: what the anchor adds to b is the numeric gradient of what it adds to E.
    let added = |s: &[FrameState]| -> f64 {
        system(&window, s, &with_prior, Some(&anchor)).0 - system(&window, s, &plain, None).0
    };
    let anchor_energy = e1 - e0 - expected_energy;
    assert!(
        (added(&states) - (e1 - e0)).abs() < 1e-9 * (e1 - e0).abs().max(1.0),
        "energies differ between calls"
    );
    assert!(
        anchor_energy > 0.0,
        "the anchor costs nothing: {anchor_energy}"
    );
    // The first keyframe is held: the pull points back to its first estimate (a stiff
    // quadratic in the offset, as DSO's prior on the first frame; its curvature hides the
    // second-order terms a numeric check would see).
    let first = window.frames()[0].first_estimate;
    let offset = states[0].delta_from(&first).fixed_rows::<6>(0).into_owned();
    let pull = (b1.rows(0, 6) - b0.rows(0, 6)).into_owned();
    let cosine = pull.dot(&offset) / (pull.norm() * offset.norm());
    assert!(
        cosine > 0.999_999,
        "the hold pulls along {pull}, offset {offset}"
    );
    // The others' translations: numeric against analytic.
    for k in 1..states.len() {
        for i in 0..6 {
            let eps = 1e-6;
            let mut d = Vector8::zeros();
            d[i] = eps;
            let (mut plus, mut minus) = (states.clone(), states.clone());
            plus[k] = states[k].step(&d);
            minus[k] = states[k].step(&(-d));
            let numeric = (added(&plus) - added(&minus)) / (2.0 * eps);
            let analytic = b1[k * FRAME_PARAMS + i] - b0[k * FRAME_PARAMS + i];
            assert!(
                (numeric - analytic).abs() < 1e-3 * analytic.abs().max(1.0),
                "keyframe {k} parameter {i}: numeric {numeric}, analytic {analytic}"
            );
        }
    }
}
