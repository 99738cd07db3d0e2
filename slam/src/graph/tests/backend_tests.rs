//! The back end, synchronous and threaded, on a synthetic loop.

use std::collections::HashMap;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use super::{DepthScale, SynthKeyframe, render, view};
use crate::geometry::{Matrix7, Sim3, Vector7};
use crate::graph::{
    Backend, BackendCommand, BackendConfig, BackendLink, Constraint, KeyframeData, KeyframeId,
    KeyframeMaps, NewKeyframe, ParentEdge, Thumbnail,
};

/// Keyframes around a horizontal circle of radius 0.25 m (the last one 36° before the first,
/// 15 cm away), yaw oscillating ±8°, each depth map normalised to mean inverse depth 1.
const LOOP_KEYFRAMES: usize = 10;

fn loop_keyframes() -> &'static [SynthKeyframe] {
    static KEYFRAMES: OnceLock<Vec<SynthKeyframe>> = OnceLock::new();
    KEYFRAMES.get_or_init(|| {
        (0..LOOP_KEYFRAMES)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / LOOP_KEYFRAMES as f64;
                let offset = Vector3::new(0.25 * (a.cos() - 1.0), 0.25 * a.sin(), 0.0);
                render(
                    k as u64,
                    view(8.0 * a.sin(), offset),
                    DepthScale::Normalised,
                )
            })
            .collect()
    })
}

/// The front end's view: parent edges measured with a systematic drift (1.5° of yaw and 5 %
/// of scale per keyframe, like monocular odometry) and poses by dead reckoning.
fn drifting_inputs(keyframes: &[SynthKeyframe]) -> Vec<NewKeyframe> {
    let mut bias = Vector7::zeros();
    bias[4] = 1.5f64.to_radians(); // about the camera's y (down) axis: yaw
    bias[6] = 0.05f64.ln_1p();
    let mut world_from_keyframe = keyframes[0].world_from_keyframe();
    keyframes
        .iter()
        .enumerate()
        .map(|(k, kf)| {
            let parent = (k > 0).then(|| {
                let truth =
                    keyframes[k - 1].world_from_keyframe().inverse() * kf.world_from_keyframe();
                let measured = truth * Sim3::exp(&bias);
                world_from_keyframe = world_from_keyframe * measured;
                ParentEdge {
                    id: k - 1,
                    parent_from_keyframe: measured,
                    information: (Matrix7::identity() * 1e6).into(),
                    trusted: false,
                }
            });
            NewKeyframe {
                id: k,
                maps: KeyframeMaps::Held {
                    frame: Arc::clone(&kf.frame),
                    depth: Arc::clone(&kf.depth),
                    data: None,
                },
                world_from_keyframe,
                parent,
                handover: None,
                thumbnail: None,
            }
        })
        .collect()
}

fn test_config() -> BackendConfig {
    // Ten keyframes only: none is "initialisation" here.
    BackendConfig {
        skip_initial_keyframes: 0,
        ..BackendConfig::default()
    }
}

/// Mean camera-centre error (m), mean rotation error (°) and mean |scale ratio − 1|.
fn errors(poses: &HashMap<KeyframeId, Sim3>, keyframes: &[SynthKeyframe]) -> (f64, f64, f64) {
    let n = keyframes.len() as f64;
    let (mut dt, mut dr, mut ds) = (0.0, 0.0, 0.0);
    for (k, kf) in keyframes.iter().enumerate() {
        let (est, gt) = (poses[&k], kf.world_from_keyframe());
        dt += (est.translation - gt.translation).norm() / n;
        dr += (est.rotation * gt.rotation.inverse())
            .log()
            .norm()
            .to_degrees()
            / n;
        ds += (est.scale / gt.scale - 1.0).abs() / n;
    }
    (dt, dr, ds)
}

/// Runs the in-step back end as the pipeline does: one `process` per new keyframe.
fn run_in_step(inputs: &[NewKeyframe]) -> (HashMap<KeyframeId, Sim3>, Vec<Constraint>) {
    let mut backend = Backend::new(test_config()).expect("valid config");
    for input in inputs {
        backend.add_keyframe(input.clone()).expect("add");
        backend.process().expect("process");
    }
    (backend.poses(), backend.constraints().to_vec())
}

#[test]
fn backend_in_step_closes_the_loop_and_is_deterministic() {
    let keyframes = loop_keyframes();
    let inputs = drifting_inputs(keyframes);
    let dead_reckoning: HashMap<KeyframeId, Sim3> = inputs
        .iter()
        .map(|k| (k.id, k.world_from_keyframe))
        .collect();
    let start = Instant::now();
    let (poses, constraints) = run_in_step(&inputs);
    let elapsed = start.elapsed();
    let before = errors(&dead_reckoning, keyframes);
    let after = errors(&poses, keyframes);
    eprintln!(
        "backend loop ({LOOP_KEYFRAMES} keyframes, {} edges, {:.1} s): dead reckoning {:.4} m / \
         {:.2}° / scale {:.3} → optimised {:.4} m / {:.3}° / scale {:.4}",
        constraints.len(),
        elapsed.as_secs_f64(),
        before.0,
        before.1,
        before.2,
        after.0,
        after.1,
        after.2
    );
    assert_eq!(poses.len(), LOOP_KEYFRAMES);
    assert_eq!(
        poses[&0],
        keyframes[0].world_from_keyframe(),
        "first keyframe is the gauge"
    );
    let closes_loop = constraints.iter().any(|c| {
        let (lo, hi) = (c.from.min(c.to), c.from.max(c.to));
        lo <= 1 && hi >= LOOP_KEYFRAMES - 2
    });
    assert!(
        closes_loop,
        "no edge between the loop's ends: {:?}",
        constraints
            .iter()
            .map(|c| (c.from, c.to))
            .collect::<Vec<_>>()
    );
    assert!(
        after.0 < 0.2 * before.0,
        "position error {} → {}",
        before.0,
        after.0
    );
    assert!(
        after.1 < 0.2 * before.1,
        "rotation error {} → {}",
        before.1,
        after.1
    );
    assert!(
        after.2 < 0.2 * before.2,
        "scale error {} → {}",
        before.2,
        after.2
    );
    assert!(
        after.0 < 0.01 && after.1 < 0.5 && after.2 < 0.01,
        "{after:?}"
    );

    // Same inputs, same outputs, bit for bit.
    let (poses_again, constraints_again) = run_in_step(&inputs);
    assert_eq!(poses, poses_again);
    assert_eq!(constraints, constraints_again);
}

#[test]
fn a_queued_keyframe_whose_maps_the_front_end_let_go_of_is_rebuilt_identical() {
    // A back end fallen behind gets keyframes whose full maps the front end has dropped: it
    // rebuilds them from their compact form, and nothing it computes changes.
    let keyframes = &loop_keyframes()[..6];
    let held = drifting_inputs(keyframes);
    let shared: Vec<NewKeyframe> = held
        .iter()
        .map(|new| {
            let KeyframeMaps::Held { frame, depth, .. } = &new.maps else {
                panic!("held");
            };
            let data = KeyframeData::new(
                &crate::spill::Spill::default(),
                frame.compact(),
                crate::mapping::CompactDepth::of(depth),
            );
            // Weak references to copies nobody holds: the front end let go of them.
            let (frame, depth) = (
                Arc::new(data.frame().expect("frame")),
                Arc::new((**depth).clone()),
            );
            let maps = KeyframeMaps::Shared {
                frame: Arc::downgrade(&frame),
                depth: Arc::downgrade(&depth),
                data,
            };
            NewKeyframe {
                maps,
                ..new.clone()
            }
        })
        .collect();
    let KeyframeMaps::Shared { frame, depth, .. } = &shared[0].maps else {
        panic!("shared");
    };
    assert!(frame.upgrade().is_none() && depth.upgrade().is_none());
    assert_eq!(run_in_step(&shared), run_in_step(&held));

    // While the front end holds them, the back end uses the same maps, not a copy.
    let frame = Arc::clone(&keyframes[0].frame);
    let maps = KeyframeMaps::Shared {
        frame: Arc::downgrade(&frame),
        depth: Arc::downgrade(&keyframes[0].depth),
        data: KeyframeData::new(
            &crate::spill::Spill::default(),
            frame.compact(),
            crate::mapping::CompactDepth::of(&keyframes[0].depth),
        ),
    };
    let (resolved, _, data) = maps.resolve().expect("resolve");
    assert!(Arc::ptr_eq(&resolved, &frame) && data.is_some());
}

#[test]
fn backend_appearance_search_links_a_keyframe_with_a_wrong_pose() {
    // Keyframe 3 revisits keyframe 0's view but arrives without a parent and with a pose 5 m
    // and 90° off: only the appearance thumbnail can propose the candidate, and the Sim(3)
    // test from the identity must verify it.
    let keyframes = loop_keyframes();
    let revisit = render(
        33,
        view(2.0, Vector3::new(0.03, 0.04, 0.0)),
        DepthScale::Normalised,
    );
    let mut inputs: Vec<NewKeyframe> = drifting_inputs(&keyframes[..3]);
    let wrong = Sim3::new(
        crate::geometry::SO3::exp(&Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2)),
        Vector3::new(5.0, -3.0, 1.0),
        2.0,
    );
    inputs.push(NewKeyframe {
        id: 3,
        maps: KeyframeMaps::Held {
            frame: Arc::clone(&revisit.frame),
            depth: Arc::clone(&revisit.depth),
            data: None,
        },
        world_from_keyframe: wrong,
        parent: None,
        handover: None,
        thumbnail: None,
    });
    let mut backend = Backend::new(test_config()).expect("config");
    for input in inputs {
        backend.add_keyframe(input).expect("add");
        backend.process().expect("process");
    }
    let linked: Vec<_> = backend
        .constraints()
        .iter()
        .filter(|c| c.from == 3 || c.to == 3)
        .map(|c| (c.from, c.to))
        .collect();
    assert!(
        linked.contains(&(3, 0)),
        "revisit not linked to keyframe 0: {linked:?}"
    );
    let estimate = backend.poses()[&3];
    let gt = revisit.world_from_keyframe();
    let dt = (estimate.translation - gt.translation).norm();
    let dr = (estimate.rotation * gt.rotation.inverse())
        .log()
        .norm()
        .to_degrees();
    let ds = estimate.scale / gt.scale - 1.0;
    eprintln!(
        "revisit after optimisation: {dt:.4} m, {dr:.3}°, scale {:.3} %",
        100.0 * ds
    );
    assert!(
        dt < 0.02 && dr < 0.5 && ds.abs() < 0.02,
        "{dt} m {dr}° {ds}"
    );
}

#[test]
fn backend_thread_processes_commands_and_publishes_poses() {
    let keyframes = loop_keyframes();
    let inputs = drifting_inputs(&keyframes[..4]);
    let mut handle = BackendLink::new(test_config(), true).expect("spawn");
    for input in &inputs {
        handle.add_keyframe(input.clone()).expect("queued");
    }
    // A duplicate id is reported, not fatal.
    handle.add_keyframe(inputs[1].clone()).expect("queued");
    handle.send(BackendCommand::Optimize).expect("queued");
    let deadline = Instant::now() + Duration::from_secs(120);
    while handle.handled_commands() < inputs.len() as u64 + 2 {
        assert!(Instant::now() < deadline, "back end did not finish");
        std::thread::sleep(Duration::from_millis(20));
    }
    let published = handle.poses();
    assert_eq!(published.len(), inputs.len());
    assert!(
        handle
            .last_error()
            .is_some_and(|e| e.contains("added twice"))
    );
    let (dt, dr, ds) = errors(&published, &keyframes[..4]);
    eprintln!("threaded back end: {dt:.4} m, {dr:.3}°, scale {ds:.4}");
    assert!(dt < 0.01 && dr < 0.5 && ds < 0.01, "{dt} m {dr}° {ds}");

    // A fifth keyframe, then the end of the session: `finish` processes it, optimises, stops.
    let fifth = drifting_inputs(&keyframes[..5]).pop().expect("five inputs");
    handle.add_keyframe(fifth).expect("queued");
    let final_poses = handle.finish().expect("clean finish");
    assert_eq!(final_poses.len(), 5);
    assert_eq!(
        handle.poses(),
        final_poses,
        "the snapshot is the final state"
    );
    assert!(
        handle.send(BackendCommand::Optimize).is_err(),
        "the thread has stopped"
    );

    // After `finish` the back end itself is at hand.
    let backend = handle.backend().expect("the back end after finish");
    assert_eq!(backend.poses().len(), 5);
    assert!(backend.pending().is_empty());
}

#[test]
fn se3_parent_information_is_embedded_with_a_weak_scale_term() {
    let info6 =
        nalgebra::Matrix6::from_fn(|i, j| if i == j { 100.0 * (i + 1) as f64 } else { 1.0 });
    let edge = ParentEdge::from_se3_information(4, Sim3::identity(), &info6);
    let information = edge.information.matrix();
    assert_eq!(information.fixed_view::<6, 6>(0, 0).into_owned(), info6);
    assert_eq!(
        information.fixed_view::<1, 6>(6, 0).into_owned(),
        nalgebra::RowVector6::zeros()
    );
    let expected = crate::graph::backend::SE3_EDGE_SCALE_INFORMATION_RATIO * 200.0;
    assert!((information[(6, 6)] - expected).abs() < 1e-12);
    assert!(information.cholesky().is_some(), "positive definite");
}

#[test]
fn thumbnail_scores_a_revisit_above_unrelated_views() {
    let keyframes = loop_keyframes();
    let revisit = render(
        33,
        view(2.0, Vector3::new(0.03, 0.04, 0.0)),
        DepthScale::Normalised,
    );
    let opposite = render(34, view(180.0, Vector3::zeros()), DepthScale::Normalised);
    let other_room = super::render_in(
        &crate::dataset::synth::Scene::generate(1),
        35,
        view(0.0, Vector3::zeros()),
        DepthScale::Normalised,
    );
    let t = Thumbnail::new(&revisit.frame);
    let same = t.score(&Thumbnail::new(&keyframes[0].frame));
    let unrelated = [&opposite, &other_room].map(|k| t.score(&Thumbnail::new(&k.frame)));
    eprintln!("thumbnail scores: revisit {same:.3}, unrelated {unrelated:.3?}");
    let threshold = BackendConfig::default().appearance_min_score;
    assert!(same > 0.9, "{same}");
    assert!(unrelated.iter().all(|&u| u < threshold), "{unrelated:?}");
    assert!((t.score(&t) - 1.0).abs() < 1e-6);
}

#[test]
fn backend_depth_update_re_estimates_the_constraints() {
    // Keyframe 2 first arrives with a warped depth map (inverse depth × 1 + 0.4·x/width, as a
    // biased prior would give), which biases its constraints; the corrected map, sent as a
    // depth update, must replace them and pull the pose back.
    let keyframes = loop_keyframes();
    let mut inputs = drifting_inputs(&keyframes[..4]);
    let good_depth = Arc::clone(&keyframes[2].depth);
    let mut warped = (*good_depth).clone();
    let width = warped.width;
    for (i, p) in warped.pixels.iter_mut().enumerate() {
        if let crate::mapping::InverseDepth::Estimate { idepth, var } = *p {
            let f = 1.0 + 0.4 * (i % width) as f32 / width as f32;
            *p = crate::mapping::InverseDepth::Estimate {
                idepth: idepth * f,
                var,
            };
        }
    }
    inputs[2].maps = KeyframeMaps::Held {
        frame: Arc::clone(&keyframes[2].frame),
        depth: Arc::new(warped),
        data: None,
    };
    let mut backend = Backend::new(test_config()).expect("config");
    for input in inputs {
        backend.add_keyframe(input).expect("add");
        backend.process().expect("process");
    }
    let edges_before = backend.constraints().len();
    let pose_error = |b: &Backend| {
        let (est, gt) = (b.poses()[&2], keyframes[2].world_from_keyframe());
        (
            (est.translation - gt.translation).norm(),
            (est.scale / gt.scale - 1.0).abs(),
        )
    };
    let before = pose_error(&backend);
    let neighbours = backend.constraints_of(2).count();
    backend
        .update_keyframe_depth(2, good_depth)
        .expect("known keyframe");
    let report = backend.process().expect("process");
    let after = pose_error(&backend);
    eprintln!(
        "depth update: keyframe 2 error {:.4} m / scale {:.4} → {:.4} m / {:.4}, {} pairs \
         refreshed of {}",
        before.0,
        before.1,
        after.0,
        after.1,
        report.constraints_refreshed,
        neighbours / 2
    );
    assert!(
        report.constraints_refreshed > 0 && report.optimize.is_some(),
        "{report:?}"
    );
    assert_eq!(
        backend.constraints().len(),
        edges_before,
        "edges replaced, not added"
    );
    assert!(
        after.0 < 0.5 * before.0 && after.1 < 0.5 * before.1,
        "{before:?} → {after:?}"
    );
    assert!(
        backend
            .update_keyframe_depth(99, Arc::clone(&keyframes[0].depth))
            .is_err()
    );
}

#[test]
fn backend_window_runs_per_keyframe_and_replaces_its_edges() {
    let keyframes = loop_keyframes();
    let inputs = drifting_inputs(keyframes);
    let window = crate::window::WindowConfig {
        enabled: true,
        keyframes: 4,
        ..crate::window::WindowConfig::default()
    };
    let mut backend = Backend::new(BackendConfig {
        window: window.clone(),
        ..test_config()
    })
    .expect("valid config");
    let mut runs = 0;
    for input in &inputs {
        backend.add_keyframe(input.clone()).expect("add");
        let report = backend.process().expect("process");
        if let Some(w) = report.window {
            runs += 1;
            assert!(w.final_cost <= w.initial_cost * 1.5, "{w:?}");
        }
    }
    // One window per keyframe from the fourth on.
    assert_eq!(runs, LOOP_KEYFRAMES - window.keyframes + 1);
    // Each consecutive pair keeps one window edge: later windows replace, never add.
    let (_, without) = run_in_step(&inputs);
    assert_eq!(
        backend.constraints().len(),
        without.len() + LOOP_KEYFRAMES - 1,
        "window edges: one per consecutive pair"
    );
    for k in 1..LOOP_KEYFRAMES {
        assert!(
            backend
                .constraints()
                .iter()
                .any(|c| c.from == k && c.to == k - 1),
            "pair {k}"
        );
    }
    // The window holds the map together at least as well as the Sim(3) edges alone.
    let (with_t, _, with_s) = errors(&backend.poses(), keyframes);
    let (poses, _) = run_in_step(&inputs);
    let (base_t, _, base_s) = errors(&poses, keyframes);
    assert!(
        with_t < base_t + 0.01,
        "position error {with_t} m vs {base_t} m"
    );
    assert!(with_s < base_s + 0.02, "scale error {with_s} vs {base_s}");
}

#[test]
fn a_back_end_behind_defers_full_searches_and_catches_up_to_the_same_loop() {
    use crate::graph::Budget;
    let keyframes = loop_keyframes();
    let inputs = drifting_inputs(keyframes);
    let mut backend = Backend::new(test_config()).expect("valid config");
    for input in &inputs {
        backend.add_keyframe(input.clone()).expect("add");
    }
    // All ten queued at once: only the two newest are searched in full.
    let behind = Budget::for_pass(inputs.len(), 2);
    assert_eq!(behind, Budget::Behind(2));
    let report = backend.process_within(behind).expect("behind");
    assert_eq!(report.keyframes_searched, LOOP_KEYFRAMES);
    assert_eq!(report.searches_deferred, LOOP_KEYFRAMES - 2);
    let deferred: Vec<KeyframeId> = backend.deferred().collect();
    assert_eq!(deferred, (0..LOOP_KEYFRAMES - 2).collect::<Vec<_>>());
    let edges_behind = backend.constraints().len();

    // A caught-up pass takes the two oldest deferred searches.
    let report = backend
        .process_within(Budget::for_pass(0, 2))
        .expect("caught up");
    assert_eq!(report.keyframes_searched, 2);
    assert_eq!(backend.deferred().count(), LOOP_KEYFRAMES - 4);

    // The final pass does the rest and closes the loop as well as searching in step does.
    backend.process().expect("final");
    assert_eq!(backend.deferred().count(), 0);
    assert!(backend.constraints().len() > edges_behind);
    let (in_step, _) = run_in_step(&inputs);
    let (late, timely) = (
        errors(&backend.poses(), keyframes),
        errors(&in_step, keyframes),
    );
    eprintln!("deferred searches: {late:?}; in step: {timely:?}");
    assert!(late.0 < 0.01 && late.1 < 0.5 && late.2 < 0.01, "{late:?}");
}

#[test]
fn a_caught_up_pass_refreshes_a_few_depth_updates_oldest_first() {
    use crate::graph::Budget;
    let keyframes = loop_keyframes();
    let mut backend = Backend::new(test_config()).expect("valid config");
    for input in drifting_inputs(keyframes) {
        backend.add_keyframe(input).expect("add");
    }
    backend.process().expect("searched");
    for id in [4, 1, 6, 3, 1] {
        let depth = Arc::clone(&keyframes[id].depth);
        backend.update_keyframe_depth(id, depth).expect("update");
    }
    // Queued once each, in the order of their first update.
    assert_eq!(backend.refreshes().collect::<Vec<_>>(), vec![4, 1, 6, 3]);
    // Behind: refreshes wait.
    backend.process_within(Budget::Behind(2)).expect("behind");
    assert_eq!(backend.refreshes().count(), 4);
    // Caught up: the two oldest, their neighbours re-tested.
    let report = backend
        .process_within(Budget::CaughtUp(2))
        .expect("caught up");
    assert!(report.candidates_tested > 0);
    assert_eq!(backend.refreshes().collect::<Vec<_>>(), vec![6, 3]);
    // The final pass does the rest.
    backend.process().expect("final");
    assert_eq!(backend.refreshes().count(), 0);
}

#[test]
fn deferred_searches_past_their_limit_are_given_up() {
    use crate::graph::Budget;
    let inputs = drifting_inputs(loop_keyframes());
    let config = BackendConfig {
        deferred_max: 3,
        ..test_config()
    };
    let mut backend = Backend::new(config).expect("valid config");
    for input in &inputs {
        backend.add_keyframe(input.clone()).expect("add");
    }
    let report = backend.process_within(Budget::Behind(1)).expect("behind");
    assert_eq!(report.searches_deferred, LOOP_KEYFRAMES - 1);
    assert_eq!(report.searches_dropped, LOOP_KEYFRAMES - 1 - 3);
    let memory = backend.memory();
    assert_eq!(
        (memory.searches_deferred, memory.searches_given_up),
        (3, LOOP_KEYFRAMES - 1 - 3)
    );
    // The newest deferred ones are kept.
    let kept: Vec<KeyframeId> = backend.deferred().collect();
    assert_eq!(
        kept,
        vec![LOOP_KEYFRAMES - 4, LOOP_KEYFRAMES - 3, LOOP_KEYFRAMES - 2]
    );
}
