//! Keyframe re-activation on a camera that comes back: a dolly towards the far wall and back
//! over the same poses (the synthetic `forward` motion). On the way back the old keyframes
//! must be made current again instead of new ones being made, without losing accuracy, with
//! the hand-over edges in the pose graph, and with the same results when the old keyframes
//! come back from the session's store.

use std::sync::{Mutex, MutexGuard, OnceLock};

use super::*;
use crate::dataset::Motion;
use crate::dataset::synth::{Scene, SynthConfig, path_length, render_frame};
use crate::dataset::trajectory::StampedPose;
use crate::eval::{AlignMode, ate};

type Sequence = (PinholeCamera, Vec<FrameInput>, Vec<StampedPose>);

/// The middle of the `forward` motion at 320×240 with ground truth: frames 150-449, the
/// second half of the dolly towards the far wall and the first half of the way back over the
/// same poses. Rendered once per test binary.
fn forward_and_back() -> &'static Sequence {
    static SEQUENCE: OnceLock<Sequence> = OnceLock::new();
    SEQUENCE.get_or_init(render_forward_and_back)
}

fn render_forward_and_back() -> Sequence {
    let synth = SynthConfig {
        frames: 450,
        seed: 3,
        motion: Motion::Forward,
        width: 320,
        height: 240,
        ..Default::default()
    };
    let camera = synth.camera().expect("camera");
    let scene = Scene::generate(synth.seed);
    let (mut frames, mut gt) = (Vec::new(), Vec::new());
    for (i, pose) in synth.poses().iter().enumerate().skip(150) {
        let timestamp = i as f64 / synth.fps;
        let (rgb, _) = render_frame(&scene, &camera, pose);
        frames.push(FrameInput {
            frame_id: None,
            timestamp,
            rgb,
            depth: None,
        });
        gt.push(StampedPose {
            timestamp,
            world_from_camera: *pose,
        });
    }
    (camera, frames, gt)
}

/// Runs the sequence in step with `candidates` re-activation candidates, spilling every
/// keyframe but the current one into `spill` when given.
fn run(sequence: &Sequence, candidates: usize, spill: Option<&std::path::Path>) -> Pipeline {
    let (camera, frames, _) = sequence;
    let mut config = Config::default();
    config.pipeline.deterministic = true;
    config.pipeline.init = DepthInit::Random;
    config.pipeline.reactivation_candidates = candidates;
    // Tracking, mapping and the pose graph are what re-activation changes.
    config.dense.enabled = false;
    if spill.is_some() {
        config.backend.resident_keyframes = 0;
        config.backend.held_keyframes = 0;
    }
    let mut pipeline = Pipeline::new(config, *camera, None).expect("pipeline");
    if let Some(dir) = spill {
        let store = crate::spill::FolderStore::new(dir).expect("spill folder");
        pipeline.spill().attach(Arc::new(store)).expect("attach");
    }
    for frame in frames {
        pipeline.push(frame.clone()).expect("push");
    }
    pipeline.finish().expect("finish");
    pipeline
}

/// The run with three candidates, every keyframe held: both tests read it, and it is
/// deterministic, so it runs once per test binary (issue 36).
fn reactivating() -> MutexGuard<'static, Pipeline> {
    static RUN: OnceLock<Mutex<Pipeline>> = OnceLock::new();
    RUN.get_or_init(|| Mutex::new(run(forward_and_back(), 3, None)))
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[test]
fn a_camera_that_comes_back_reactivates_old_keyframes_instead_of_making_new_ones() {
    let sequence = forward_and_back();
    let gt = &sequence.2;
    let path = path_length(&gt.iter().map(|p| p.world_from_camera).collect::<Vec<_>>());
    let on = reactivating();
    let off = run(sequence, 0, None);
    let ate_of = |p: &Pipeline| {
        ate(
            gt,
            &stamped(&p.trajectory().expect("trajectory")),
            AlignMode::Sim3,
        )
        .expect("ate")
        .rmse
    };
    let (ate_on, ate_off) = (ate_of(&on), ate_of(&off));
    println!(
        "forward and back: path {path:.2} m; re-activation on: {} keyframes, {} re-activations, \
         ATE {ate_on:.4} m; off: {} keyframes, ATE {ate_off:.4} m",
        on.stats().keyframes,
        on.stats().keyframes_reactivated,
        off.stats().keyframes,
    );
    assert_eq!(off.stats().keyframes_reactivated, 0);
    assert!(on.stats().keyframes_reactivated > 0, "nothing re-activated");
    assert!(
        on.stats().keyframes < off.stats().keyframes,
        "re-activation must save keyframes on the way back"
    );
    assert_eq!(
        on.trajectory().expect("trajectory").len(),
        gt.len(),
        "every frame keeps a pose"
    );
    // The same bound as the orbit's (tests.rs): re-activation may not cost accuracy.
    assert!(ate_on <= 0.025 * path, "ATE {ate_on} > 2.5% of {path} m");

    // Every hand-over edge reached the pose graph: the keyframe left is joined to the one
    // re-activated, by the reciprocal Sim(3) test or by the tracking estimate.
    let backend = on.backend.backend().expect("in step");
    let handovers: Vec<(KeyframeId, KeyframeId)> = on
        .keyframes
        .iter()
        .enumerate()
        .filter_map(|(id, k)| Some((id, k.handover.as_ref()?.id)))
        .collect();
    assert!(!handovers.is_empty(), "no hand-over edge");
    for (left, old) in handovers {
        assert!(
            backend
                .constraints_of(left)
                .any(|c| (c.from, c.to) == (left, old) || (c.from, c.to) == (old, left)),
            "no edge between keyframe {left} and the re-activated {old}"
        );
    }
}

#[test]
fn reactivated_keyframes_read_back_from_the_store_give_the_same_results() {
    let sequence = forward_and_back();
    let dir = std::env::temp_dir().join(format!("relfusion-reactivate-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let spilled = run(sequence, 3, Some(&dir));
    let held = reactivating();
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        spilled.keyframe_memory().spill.loads > 0,
        "nothing read back"
    );
    assert!(spilled.stats().keyframes_reactivated > 0);
    assert_eq!(
        held.stats().keyframes_reactivated,
        spilled.stats().keyframes_reactivated
    );
    assert_eq!(
        held.trajectory().expect("trajectory"),
        spilled.trajectory().expect("trajectory")
    );
    assert_eq!(held.keyframe_trajectory(), spilled.keyframe_trajectory());
}

fn stamped(poses: &[(f64, Sim3)]) -> Vec<StampedPose> {
    crate::dataset::trajectory::stamped_se3(poses)
}
