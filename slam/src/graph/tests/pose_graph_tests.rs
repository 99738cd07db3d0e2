//! Pose-graph residual Jacobians and optimisation.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::geometry::{Matrix7, SO3, Sim3, Vector7};
use crate::graph::pose_graph::{relative_residual, relative_residual_jacobians};
use crate::graph::{Constraint, PoseGraph, ScalePrior};
use relfusion_core::geometry::testing::numeric_jacobian;

fn random_sim3(rng: &mut ChaCha8Rng, rot: f64, trans: f64, log_scale: f64) -> Sim3 {
    let mut v = || rng.random_range(-1.0..1.0);
    Sim3::new(
        SO3::exp(&(Vector3::new(v(), v(), v()) * rot)),
        Vector3::new(v(), v(), v()) * trans,
        (v() * log_scale).exp(),
    )
}

#[test]
fn pose_graph_residual_jacobians_match_numeric_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for case in 0..20 {
        // Large poses, and measurements from close (small residual) to far (residual with a
        // rotation near 2 rad and scale ratio e^±1), where J_r⁻¹ differs much from I.
        let wi = random_sim3(&mut rng, 2.0, 5.0, 1.5);
        let wj = random_sim3(&mut rng, 2.0, 5.0, 1.5);
        let off = if case % 2 == 0 { 0.05 } else { 1.1 };
        let measured = wi.inverse() * wj * random_sim3(&mut rng, off, off, off);
        let (r, j_to, j_from) = relative_residual_jacobians(&measured, &wi, &wj);
        assert!((r - relative_residual(&measured, &wi, &wj)).norm() < 1e-12);
        let num_to = numeric_jacobian::<7, 7>(&|d: &Vector7| {
            relative_residual(&measured, &(wi * Sim3::exp(d)), &wj)
        });
        let num_from = numeric_jacobian::<7, 7>(&|d: &Vector7| {
            relative_residual(&measured, &wi, &(wj * Sim3::exp(d)))
        });
        for (name, analytic, numeric) in [("to", j_to, num_to), ("from", j_from, num_from)] {
            let err = (analytic - numeric).norm() / numeric.norm();
            assert!(
                err < 1e-6,
                "case {case} ∂r/∂δ_{name}: relative error {err:e}"
            );
        }
    }
}

/// Ground truth: `n` keyframes around a circle of radius 3 with varying depth scales.
fn circle(n: usize) -> Vec<Sim3> {
    (0..n)
        .map(|k| {
            let a = std::f64::consts::TAU * k as f64 / n as f64;
            Sim3::new(
                SO3::exp(&Vector3::new(0.1 * a.sin(), 0.0, a)),
                Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.2 * (2.0 * a).sin()),
                (0.3 * (3.0 * a).sin()).exp(),
            )
        })
        .collect()
}

/// Mean `|log(T_gt⁻¹ · T)|` over the vertices.
fn mean_error(graph: &PoseGraph, truth: &[Sim3]) -> f64 {
    truth
        .iter()
        .enumerate()
        .map(|(k, t)| (t.inverse() * graph.pose(k).expect("vertex")).log().norm())
        .sum::<f64>()
        / truth.len() as f64
}

/// A noisy odometry chain (with a systematic scale and rotation drift, as in monocular SLAM)
/// initialised by dead reckoning, plus the loop-closure edges `loops`.
fn drifting_chain(truth: &[Sim3], loops: &[(usize, usize)], huber: Option<f64>) -> PoseGraph {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let sigma = 0.003;
    let info = Matrix7::identity() / (sigma * sigma);
    let mut bias = Vector7::zeros();
    bias[5] = 0.02; // yaw drift, rad per edge
    bias[6] = 0.03; // scale drift per edge
    let mut graph = PoseGraph::new(huber);
    graph.add_vertex(0, truth[0]);
    for k in 1..truth.len() {
        let noise = Vector7::from_fn(|_, _| rng.random_range(-1.0..1.0) * sigma);
        // to = k − 1, from = k: measured (k−1)_from_k.
        let measured = truth[k - 1].inverse() * truth[k] * Sim3::exp(&(bias + noise));
        let initial = graph.pose(k - 1).expect("previous") * measured;
        graph.add_vertex(k, initial);
        graph
            .add_edge(Constraint {
                from: k,
                to: k - 1,
                to_from_from: measured,
                information: info.into(),
            })
            .expect("vertices exist");
    }
    for &(from, to) in loops {
        let noise = Vector7::from_fn(|_, _| rng.random_range(-1.0..1.0) * sigma);
        let measured = truth[to].inverse() * truth[from] * Sim3::exp(&noise);
        graph
            .add_edge(Constraint {
                from,
                to,
                to_from_from: measured,
                information: info.into(),
            })
            .expect("vertices exist");
    }
    graph
}

#[test]
fn pose_graph_loop_closure_removes_drift_and_keeps_the_first_vertex() {
    let truth = circle(30);
    let mut graph = drifting_chain(&truth, &[(29, 0), (15, 0)], None);
    let before = mean_error(&graph, &truth);
    let first = graph.pose(0).expect("first");
    let report = graph.optimize(100).expect("optimise");
    let after = mean_error(&graph, &truth);
    eprintln!(
        "pose graph: mean |log(T_gt⁻¹T)| {before:.4} → {after:.4}, cost {:.3e} → {:.3e} in {} \
         iterations",
        report.initial_cost, report.final_cost, report.iterations
    );
    assert_eq!(graph.pose(0), Some(first), "the fixed vertex moved");
    assert!(graph.vertex(0).expect("v0").fixed && !graph.vertex(1).expect("v1").fixed);
    assert!(after < 0.1 * before, "error {before} → {after}");
    assert!(report.final_cost < 1e-2 * report.initial_cost, "{report:?}");
    assert!((report.final_cost - graph.cost()).abs() <= 1e-9 * report.final_cost.max(1.0));
    // A second run starts at the optimum and cannot improve it materially.
    let again = graph.optimize(100).expect("optimise");
    assert!(again.final_cost >= 0.99 * report.final_cost && again.final_cost <= report.final_cost);
}

#[test]
fn pose_graph_huber_kernel_limits_a_false_loop_closure() {
    // A wrong loop edge (between keyframes 10 and 25 claiming they coincide) with the same
    // confidence as the others: least squares bends the whole loop towards it, the Huber
    // kernel of LSD-SLAM's edges keeps the damage smaller.
    let truth = circle(30);
    let wrong = |graph: &mut PoseGraph| {
        let info = Matrix7::identity() / (0.003f64 * 0.003);
        graph
            .add_edge(Constraint {
                from: 25,
                to: 10,
                to_from_from: Sim3::identity(),
                information: info.into(),
            })
            .expect("vertices");
    };
    let mut plain = drifting_chain(&truth, &[(29, 0)], None);
    wrong(&mut plain);
    plain.optimize(100).expect("optimise");
    // Huber width: √(rᵀΩr) of a correct edge is ≈ √7 ≈ 2.6; 10 keeps them all quadratic.
    let mut robust = drifting_chain(&truth, &[(29, 0)], Some(10.0));
    wrong(&mut robust);
    robust.optimize(100).expect("optimise");
    let (e_plain, e_robust) = (mean_error(&plain, &truth), mean_error(&robust, &truth));
    eprintln!("false loop: least squares {e_plain:.4}, Huber {e_robust:.4}");
    assert!(
        e_robust < 0.5 * e_plain,
        "Huber {e_robust} vs plain {e_plain}"
    );
}

#[test]
fn pose_graph_rejects_edges_to_unknown_vertices() {
    let mut graph = PoseGraph::new(None);
    graph.add_vertex(3, Sim3::identity());
    let c = Constraint {
        from: 3,
        to: 4,
        to_from_from: Sim3::identity(),
        information: Matrix7::identity().into(),
    };
    assert!(graph.add_edge(c.clone()).is_err());
    graph.add_vertex(4, Sim3::identity());
    assert!(graph.add_edge(c).is_ok());
    let report = graph.optimize(10).expect("optimise");
    assert_eq!(report.final_cost, 0.0);
}

/// Mean `|ln s − ln s_gt|` over the vertices.
fn mean_scale_error(graph: &PoseGraph, truth: &[Sim3]) -> f64 {
    truth
        .iter()
        .enumerate()
        .map(|(k, t)| (graph.pose(k).expect("vertex").scale / t.scale).ln().abs())
        .sum::<f64>()
        / truth.len() as f64
}

/// An odometry chain along `truth` with no loop: each edge measures the true relative pose with
/// its log scale off by `drift`, claims scale information `scale_information` (0.003 σ on the
/// rest), and the graph has the edge scale floor `floor`.
fn scale_drifting_chain(
    truth: &[Sim3],
    scale_information: f64,
    drift: f64,
    floor: Option<f64>,
) -> PoseGraph {
    let mut info = Matrix7::identity() / (0.003 * 0.003);
    info[(6, 6)] = scale_information;
    let mut bias = Vector7::zeros();
    bias[6] = drift;
    let mut graph = PoseGraph::new(None);
    graph.set_edge_scale_sigma(floor).expect("valid floor");
    graph.add_vertex(0, truth[0]);
    for k in 1..truth.len() {
        let measured = truth[k - 1].inverse() * truth[k] * Sim3::exp(&bias);
        let initial = graph.pose(k - 1).expect("previous") * measured;
        graph.add_vertex(k, initial);
        let edge = Constraint {
            from: k,
            to: k - 1,
            to_from_from: measured,
            information: info.into(),
        };
        graph.add_edge(edge).expect("vertices exist");
    }
    graph
}

#[test]
fn pose_graph_scale_priors_bound_scale_drift_and_tolerate_an_outlier() {
    // An odometry chain whose scale drifts 3 % per edge (scale σ 0.03 in its information,
    // the rest 0.003), no loop: only unary scale factors (a metric prior, σ 0.1, votes noisy
    // by ±0.05) can hold the scale. One factor is wildly wrong (e³). The first vertex is fixed
    // but has a factor too, so its scale is free.
    let truth = circle(30);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut graph = scale_drifting_chain(&truth, 1.0 / (0.03 * 0.03), 0.03, None);
    let before = mean_scale_error(&graph, &truth);
    let outlier = 17;
    for (k, t) in truth.iter().enumerate() {
        let noise = if k == outlier {
            3.0
        } else {
            rng.random_range(-0.05..0.05)
        };
        let prior = ScalePrior {
            log_scale: t.scale.ln() + noise,
            sigma: 0.1,
            huber: 2.0,
        };
        graph.set_scale_prior(k, Some(prior)).expect("vertex");
    }
    assert!(graph.set_scale_prior(99, None).is_err(), "unknown vertex");
    let bad = ScalePrior {
        log_scale: 0.0,
        sigma: 0.0,
        huber: 2.0,
    };
    assert!(graph.set_scale_prior(1, Some(bad)).is_err(), "σ = 0");
    let first = graph.pose(0).expect("first");
    graph.optimize(100).expect("optimise");
    let after = mean_scale_error(&graph, &truth);
    let at_outlier = (graph.pose(outlier).expect("v").scale / truth[outlier].scale).ln();
    eprintln!(
        "scale priors: mean |ln s error| {before:.3} → {after:.3}, at the outlier {at_outlier:.3}"
    );
    let moved = graph.pose(0).expect("first");
    assert_eq!(
        (moved.rotation, moved.translation),
        (first.rotation, first.translation),
        "the fixed vertex may only change its scale"
    );
    assert!(after < 0.15 * before, "scale error {before} → {after}");
    assert!(
        at_outlier.abs() < 0.2,
        "the outlier pulled its vertex: {at_outlier}"
    );
    assert_eq!(graph.scale_priors().len(), truth.len());
}

/// Largest minus smallest `ln(s_k / s_true,k)`: the scale drift along the chain (a common
/// scale error is not drift).
fn scale_error_range(graph: &PoseGraph, truth: &[Sim3]) -> f64 {
    let errors = truth
        .iter()
        .enumerate()
        .map(|(k, t)| (graph.pose(k).expect("vertex").scale / t.scale).ln());
    let (lo, hi) = errors.fold((f64::MAX, f64::MIN), |(lo, hi), e| (lo.min(e), hi.max(e)));
    hi - lo
}

#[test]
fn edge_scale_floor_lets_scale_factors_correct_an_overconfident_chain() {
    // As on real video: every edge claims its relative scale to 3·10⁻⁴ (information 10⁷) but
    // the chain drifts 2 % per edge. Without the floor the factors (σ 0.2) only shift the
    // whole chain; with q = 0.02 they reduce its drift. A graph without factors keeps its
    // edges' own information.
    let truth = circle(30);
    let build = |floor| scale_drifting_chain(&truth, 1e7, 0.02, floor);
    let mut plain = build(Some(0.02));
    let untouched = plain.cost();
    plain.optimize(20).expect("optimise");
    assert!(
        (plain.cost() - untouched).abs() <= 1e-9 * untouched.max(1.0),
        "without factors the floor changes nothing"
    );
    let mut errors = Vec::new();
    for floor in [None, Some(0.02)] {
        let mut graph = build(floor);
        for (k, t) in truth.iter().enumerate() {
            let prior = ScalePrior {
                log_scale: t.scale.ln(),
                sigma: 0.2,
                huber: 2.0,
            };
            graph.set_scale_prior(k, Some(prior)).expect("vertex");
        }
        let before = scale_error_range(&graph, &truth);
        graph.optimize(100).expect("optimise");
        errors.push((before, scale_error_range(&graph, &truth)));
    }
    eprintln!(
        "edge scale floor: drift without {:?}, with {:?}",
        errors[0], errors[1]
    );
    // A drift of one floor σ per edge is still plausible to the edges: the factors take
    // about 40 % of it out.
    let ((before, without), (_, with)) = (errors[0], errors[1]);
    assert!(
        without > 0.95 * before,
        "without the floor the chain keeps its drift"
    );
    assert!(
        with < 0.7 * before,
        "with the floor the factors pull: {before} → {with}"
    );
    assert!(
        PoseGraph::new(None)
            .set_edge_scale_sigma(Some(0.0))
            .is_err()
    );
}

/// The 60-keyframe drifting chain of [`circle`]`(61)` optimised, then keyframe 60 added with
/// its parent edge to 59 and a second edge to `other`, from a perturbed initial pose.
fn chain_with_a_new_keyframe(other: usize) -> (PoseGraph, Vec<Sim3>) {
    let truth = circle(61);
    let mut graph = drifting_chain(&truth[..60], &[], None);
    graph.optimize(100).expect("optimise");
    let info = Matrix7::identity() / (0.003f64 * 0.003);
    let guess = graph.pose(59).expect("59") * truth[59].inverse() * truth[60];
    let nudge = Vector7::from_fn(|i, _| 0.02 * (i as f64 + 1.0));
    graph.add_vertex(60, guess * Sim3::exp(&nudge));
    for to in [59, other] {
        // Measured from the optimised chain, so that only keyframe 60 is off.
        let world_from_to = graph.pose(to).expect("vertex");
        let measured = world_from_to.inverse() * guess;
        graph
            .add_edge(Constraint {
                from: 60,
                to,
                to_from_from: measured * Sim3::exp(&(nudge * 0.01)),
                information: info.into(),
            })
            .expect("vertices exist");
    }
    (graph, truth)
}

#[test]
fn bounded_optimisation_moves_only_the_neighbourhood_of_a_new_keyframe() {
    // Keyframe 60 closes a small loop (59 … 55) inside its neighbourhood of 10 vertices.
    let (mut graph, _) = chain_with_a_new_keyframe(55);
    let before = graph.poses();
    let report = graph.optimize_bounded(10, 100).expect("optimise");
    assert!(report.bounded && report.vertices == 10, "{report:?}");
    assert!(report.final_cost < 0.01 * report.initial_cost, "{report:?}");
    // Vertices 51-60 may move; everything older stays exactly where it was.
    let moved: Vec<usize> = (0..=60)
        .filter(|k| graph.pose(*k) != before.get(k).copied())
        .collect();
    assert!(
        moved.contains(&60) && moved.iter().all(|&k| k > 50),
        "{moved:?}"
    );
    // Nothing changed since: a second bounded call has nothing to start from and runs whole.
    assert!(!graph.optimize_bounded(10, 100).expect("again").bounded);
}

#[test]
fn a_loop_beyond_the_neighbourhood_moves_the_whole_graph() {
    // Keyframe 60 is joined to keyframe 0: the loop runs through all 60 keyframes, and a
    // bounded optimisation could not spread its correction.
    let (mut graph, _) = chain_with_a_new_keyframe(0);
    let mut exact = graph.clone();
    let report = graph.optimize_bounded(10, 100).expect("optimise");
    assert!(!report.bounded && report.vertices == 60, "{report:?}");
    // Beyond the bound its steps come from conjugate gradients, and it reaches the optimum of
    // the exact solver.
    let reference = exact.optimize(100).expect("optimise");
    assert!(report.iterative && !reference.iterative, "{report:?}");
    let excess = (report.final_cost - reference.final_cost) / report.initial_cost;
    assert!(excess < 1e-9, "{report:?} against {reference:?}");
    for (k, pose) in exact.poses() {
        let apart = (graph.pose(k).expect("vertex").inverse() * pose)
            .log()
            .norm();
        assert!(apart < 1e-4, "keyframe {k} {apart}");
    }
    // Two fragments joined by a new edge: also whole.
    let truth = circle(30);
    let mut graph = drifting_chain(&truth[..20], &[], None);
    graph.optimize(100).expect("optimise");
    graph.add_vertex(20, truth[20]);
    for k in 21..30 {
        graph.add_vertex(k, truth[k]);
        let measured = truth[k - 1].inverse() * truth[k];
        let information = Matrix7::identity().into();
        let edge = Constraint {
            from: k,
            to: k - 1,
            to_from_from: measured,
            information,
        };
        graph.add_edge(edge).expect("vertices exist");
    }
    graph.optimize(100).expect("optimise");
    let measured = truth[19].inverse() * truth[29];
    let edge = Constraint {
        from: 29,
        to: 19,
        to_from_from: measured,
        information: Matrix7::identity().into(),
    };
    graph.add_edge(edge).expect("vertices exist");
    assert!(!graph.optimize_bounded(5, 100).expect("optimise").bounded);
}

#[test]
fn a_loops_whole_pass_waits_for_the_graph_to_grow() {
    // As above, but a whole pass is owed only once the graph has grown by 5 % since its last
    // one (60 vertices then: due at 63).
    let (mut graph, _) = chain_with_a_new_keyframe(0);
    graph.set_loop_pass_growth(0.05).expect("growth");
    let before = graph.poses();
    let report = graph.optimize_bounded(10, 100).expect("optimise");
    assert!(report.bounded && report.vertices == 10, "{report:?}");
    assert!(report.final_cost < report.initial_cost, "{report:?}");
    assert_eq!(
        graph.pose(30),
        before.get(&30).copied(),
        "the loop's far side is held"
    );
    // More keyframes, each on its parent alone: the owed whole pass comes at 63 vertices
    // (keyframe 62); once paid, a chain edge alone stays bounded again.
    let step = Sim3::exp(&Vector7::from_element(0.01));
    for k in 61..64 {
        let parent = graph.pose(k - 1).expect("parent");
        graph.add_vertex(k, parent * step);
        let edge = Constraint {
            from: k,
            to: k - 1,
            to_from_from: step,
            information: Matrix7::identity().into(),
        };
        graph.add_edge(edge).expect("vertices exist");
        let report = graph.optimize_bounded(10, 100).expect("optimise");
        if k == 62 {
            let whole = !report.bounded && report.iterative && report.vertices > 60;
            assert!(whole, "keyframe {k}: {report:?}");
        } else {
            assert!(report.bounded, "keyframe {k}: {report:?}");
        }
    }
    assert!(graph.set_loop_pass_growth(-0.1).is_err());
    assert!(graph.set_loop_pass_growth(f64::NAN).is_err());
}

#[test]
fn a_graph_within_the_bound_is_optimised_exactly_as_a_whole() {
    let (graph, _) = chain_with_a_new_keyframe(30);
    let (mut whole, mut bounded) = (graph.clone(), graph);
    let a = whole.optimize(100).expect("optimise");
    let b = bounded.optimize_bounded(60, 100).expect("optimise");
    assert_eq!(a, b);
    assert!(!b.bounded && !b.iterative && b.vertices == 60);
    assert_eq!(whole.poses(), bounded.poses());
}

#[test]
fn replacing_or_doubling_an_edge_of_a_chain_stays_bounded() {
    // In a chain every edge is a bridge; re-estimating one (a depth update) or adding a second
    // edge over the same pair (the window's) joins nothing that was not joined before.
    let truth = circle(61);
    let mut graph = drifting_chain(&truth[..60], &[], None);
    graph.optimize(100).expect("optimise");
    let old = graph
        .edges()
        .iter()
        .find(|e| e.from == 50)
        .expect("edge 50 → 49")
        .clone();
    assert!(graph.remove_edge(&old));
    let nudge = Vector7::from_element(1e-3);
    let replaced = Constraint {
        to_from_from: old.to_from_from * Sim3::exp(&nudge),
        ..old.clone()
    };
    graph.add_edge(replaced).expect("vertices exist");
    let report = graph.optimize_bounded(10, 100).expect("optimise");
    assert!(report.bounded && report.vertices == 10, "{report:?}");
    let doubled = Constraint {
        to_from_from: old.to_from_from * Sim3::exp(&-nudge),
        ..old
    };
    graph.add_edge(doubled).expect("vertices exist");
    let report = graph.optimize_bounded(10, 100).expect("optimise");
    assert!(report.bounded && report.vertices == 10, "{report:?}");
}
