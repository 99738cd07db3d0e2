//! Tests of `densify`.

use super::testing::*;
use super::*;
use crate::dense::EnergyTerms;

/// Central differences of the f64 energy against the analytic gradient; returns the worst
/// relative error over the pixels whose gradient is not negligible and how many those are.
fn check_gradient(problem: &DensifyProblem, d: &[f32], params: &DensifyParams) -> (f64, usize) {
    let mut analytic = vec![0.0f32; problem.len()];
    gradient(problem, d, params, &mut analytic);
    let base: Vec<f64> = d.iter().map(|&v| f64::from(v)).collect();
    let numeric: Vec<f64> = (0..problem.len())
        .map(|i| {
            let h = 1e-6 * base[i];
            let mut plus = base.clone();
            plus[i] += h;
            let mut minus = base.clone();
            minus[i] -= h;
            (energy_f64(problem, &plus, params) - energy_f64(problem, &minus, params)) / (2.0 * h)
        })
        .collect();
    let largest = numeric.iter().fold(0.0f64, |m, g| m.max(g.abs()));
    assert!(largest > 0.0, "the energy does not depend on D");
    let mut worst = 0.0f64;
    let mut checked = 0;
    for (a, n) in analytic.iter().zip(&numeric) {
        if n.abs() > 1e-3 * largest {
            worst = worst.max((f64::from(*a) - n).abs() / n.abs());
            checked += 1;
        }
    }
    (worst, checked)
}

fn params_with(terms: EnergyTerms) -> DensifyParams {
    DensifyParams {
        terms,
        ..DensifyParams::default()
    }
}

/// Pixels of an iterate away from the prior: a random map in the prior's range.
fn iterate(width: usize, height: usize, seed: u64) -> Vec<f32> {
    noise(width, height, 0.3, 2.0, seed).data
}

#[test]
fn analytic_gradient_matches_numeric_differences_for_every_term_combination() {
    let (w, h) = (13, 9);
    let prior = noise(w, h, 0.3, 2.0, 1);
    let semi_full = noise(w, h, 0.3, 2.0, 2);
    let keep = noise(w, h, 0.0, 1.0, 3);
    let semi = ImageF32 {
        data: semi_full
            .data
            .iter()
            .zip(&keep.data)
            .map(|(&s, &k)| if k < 0.3 { s } else { 0.0 })
            .collect(),
        ..semi_full
    };
    let var = noise(w, h, 1e-3, 1e-2, 4);
    let intensity = noise(w, h, 0.0, 255.0, 5);
    let paper = EnergyTerms::default();
    let cases = [
        ("paper", paper.clone(), true),
        (
            "no charbonnier",
            EnergyTerms {
                charbonnier: false,
                ..paper.clone()
            },
            true,
        ),
        (
            "term 3 on",
            EnergyTerms {
                cnn_depth: true,
                ..paper.clone()
            },
            true,
        ),
        (
            "term 3 only",
            EnergyTerms {
                cnn_grad: false,
                semi_dense: false,
                charbonnier: false,
                cnn_depth: true,
            },
            true,
        ),
        ("no model", paper.clone(), false),
        (
            "no model, no charbonnier",
            EnergyTerms {
                charbonnier: false,
                ..paper
            },
            false,
        ),
    ];
    for (k, (name, terms, with_model)) in cases.into_iter().enumerate() {
        let params = params_with(terms);
        let problem = if with_model {
            DensifyProblem::with_prior(&prior, &semi, &var, &params)
        } else {
            DensifyProblem::without_prior(&intensity, &semi, &var, &params)
        }
        .expect("problem");
        let d = iterate(w, h, 100 + k as u64);
        let (worst, checked) = check_gradient(&problem, &d, &params);
        assert!(
            checked >= w * h / 2,
            "{name}: only {checked} pixels with a gradient"
        );
        assert!(worst < 1e-3, "{name}: relative gradient error {worst:.2e}");
    }
    // The random problem exercises every map at once (term 3 with its own weights).
    let problem = random_problem(w, h, 9);
    let params = DensifyParams::default();
    let (worst, _) = check_gradient(&problem, &iterate(w, h, 10), &params);
    assert!(worst < 1e-3, "random problem: relative error {worst:.2e}");
}

#[test]
fn term_switches_zero_their_weights() {
    let (w, h) = (6, 5);
    let prior = noise(w, h, 0.5, 1.5, 1);
    let semi = noise(w, h, 0.5, 1.5, 2);
    let var = ImageF32::filled(w, h, 1e-3);
    let paper = DensifyParams::default();
    let p = DensifyProblem::with_prior(&prior, &semi, &var, &paper).expect("paper");
    let i = 2 * w + 3;
    assert!((p.wx[i] - prior.data[i] * prior.data[i]).abs() < 1e-6);
    assert!((p.tx[i] - (prior.data[i + 1].ln() - prior.data[i].ln())).abs() < 1e-6);
    assert_eq!(p.wx[w - 1], 0.0, "no forward difference at the last column");
    assert_eq!(
        p.wy[(h - 1) * w],
        0.0,
        "no forward difference at the last row"
    );
    assert!((p.semi_scale - paper.lambda / (w * h) as f32).abs() < 1e-9);
    assert!(p.cnn_weight.iter().all(|&c| c == 0.0));
    let ablated = DensifyParams {
        terms: EnergyTerms {
            cnn_grad: false,
            semi_dense: false,
            charbonnier: true,
            cnn_depth: true,
        },
        ..paper.clone()
    };
    let q = DensifyProblem::with_prior(&prior, &semi, &var, &ablated).expect("ablated");
    assert!(q.wx.iter().chain(&q.wy).all(|&v| v == 0.0));
    assert_eq!(q.semi_scale, 0.0);
    let expected = ablated.cnn_depth_weight * prior.data[i] * prior.data[i];
    assert!((q.cnn_weight[i] - expected).abs() < 1e-9);
    // Mismatched sizes are refused, naming the map.
    let small = ImageF32::filled(w - 1, h, 1.0);
    match DensifyProblem::with_prior(&prior, &small, &var, &paper) {
        Err(Error::Shape(msg)) => assert!(msg.contains("semi-dense"), "{msg}"),
        other => panic!("expected a shape error, got {other:?}"),
    }
}

#[test]
fn densification_lowers_the_energy_and_beats_the_prior_on_a_synthetic_scene() {
    let (w, h) = (160, 120);
    let (truth, prior, semi, var) = synthetic_scene(w, h, 42);
    let params = DensifyParams::default();
    let problem = DensifyProblem::with_prior(&prior, &semi, &var, &params).expect("problem");
    let start = problem.start(&params);
    let dense = densify_cpu(&problem, &params).expect("densify");
    let e0 = energy(&problem, &start, &params);
    let e1 = energy(&problem, &dense.data, &params);
    assert!(
        e1 < 0.5 * e0,
        "energy {e0:.4e} → {e1:.4e}: Adam did not minimise it"
    );
    // Every intermediate iterate too: the energy falls over the 30 iterations overall,
    // and is lower after 30 than after 10.
    let early = densify_cpu(
        &problem,
        &DensifyParams {
            iterations: 10,
            ..params.clone()
        },
    )
    .expect("10 iterations");
    assert!(energy(&problem, &early.data, &params) > e1);
    let before = within_10_percent(&prior.data, &truth.data);
    let after = within_10_percent(&dense.data, &truth.data);
    // Measured: 0.62 → 1.00.
    assert!(
        after > before + 0.2 && after > 0.9,
        "within 10%: prior {before:.3} → densified {after:.3}"
    );
    assert!(
        dense
            .data
            .iter()
            .all(|v| v.is_finite() && *v >= params.min_idepth)
    );
}

#[test]
fn without_prior_fills_every_hole_and_refuses_an_empty_map() {
    let (w, h) = (37, 23);
    let intensity = noise(w, h, 0.0, 255.0, 1);
    let values = noise(w, h, 0.5, 1.5, 2);
    let keep = noise(w, h, 0.0, 1.0, 3);
    let mut semi = ImageF32::filled(w, h, 0.0);
    for i in 0..w * h {
        if keep.data[i] < 0.05 {
            semi.data[i] = values.data[i];
        }
    }
    // One NaN depth and one NaN variance: neither may leak into the result.
    semi.data[0] = f32::NAN;
    let mut var = ImageF32::filled(w, h, 1e-3);
    let nan_var_pixel = (0..w * h).find(|&i| semi.data[i] > 0.0).expect("a pixel");
    var.data[nan_var_pixel] = f32::NAN;
    let params = DensifyParams::default();
    let p = DensifyProblem::without_prior(&intensity, &semi, &var, &params).expect("problem");
    let (lo, hi) = (0.5, 1.5);
    assert!(
        p.init
            .iter()
            .all(|v| v.is_finite() && (lo..=hi).contains(v)),
        "filled map leaves the range of the semi-dense values or has holes"
    );
    for i in 0..w * h {
        if p.semi[i] > 0.0 {
            assert_eq!(p.init[i], semi.data[i], "a valid pixel moved");
        }
    }
    assert_eq!(p.semi[nan_var_pixel], 0.0);
    assert!(p.wx.iter().all(|&v| (0.0..=1.0).contains(&v)));
    assert_eq!(p.wx[w - 1], 0.0);
    let dense = densify_cpu(&p, &params).expect("densify");
    assert!(dense.data.iter().all(|v| v.is_finite()));
    // A single valid pixel fills the whole map with its value.
    let mut single = ImageF32::filled(w, h, 0.0);
    single.data[5 * w + 7] = 0.8;
    let one = DensifyProblem::without_prior(&intensity, &single, &var, &params).expect("one");
    assert!(one.init.iter().all(|&v| (v - 0.8).abs() < 1e-6));
    // Edges get small weights: a step of 100 across σ_edge = 10.
    let mut step = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in w / 2..w {
            *step.at_mut(x, y) = 100.0;
        }
    }
    let edged = DensifyProblem::without_prior(&step, &semi, &var, &params).expect("edges");
    assert!(edged.wx[w / 2 - 1] < 1e-4 && (edged.wx[0] - 1.0).abs() < 1e-6);
    let empty = ImageF32::filled(w, h, 0.0);
    assert!(matches!(
        DensifyProblem::without_prior(&intensity, &empty, &var, &params),
        Err(Error::Shape(_))
    ));
}

#[test]
fn adam_matches_a_hand_computed_first_step() {
    // One pixel, semi term only, no Charbonnier: g = semi_scale·2(D − s)/V; the first Adam
    // step is lr·sign(g) (bias-corrected m/sqrt(v) = g/|g|).
    let params = DensifyParams {
        iterations: 1,
        terms: EnergyTerms {
            charbonnier: false,
            ..EnergyTerms::default()
        },
        ..DensifyParams::default()
    };
    let one = |v: f32| ImageF32::filled(1, 1, v);
    let p = DensifyProblem::with_prior(&one(1.0), &one(0.5), &one(0.01), &params).expect("problem");
    let out = densify_cpu(&p, &params).expect("densify");
    assert!((out.data[0] - (1.0 - params.learning_rate)).abs() < 1e-6);
    let none = DensifyParams {
        iterations: 0,
        ..params
    };
    assert_eq!(densify_cpu(&p, &none).expect("zero").data, vec![1.0]);
}
