//! The pipeline with the DSO-class odometry as its front end, on the rendered orbit of
//! [`super::tests::sequence`]: every frame posed, the odometry's keyframes are the pipeline's,
//! each densified, and the trajectory within a bound the LSD front end does not reach there.

use super::tests::sequence;
use super::*;
use crate::dataset::synth::path_length;
use crate::dataset::trajectory::stamped_se3;
use crate::eval::{AlignMode, ate};

fn dso() -> Config {
    let mut config = Config::default();
    config.pipeline.deterministic = true;
    config.pipeline.frontend = Frontend::Dso;
    config
}

#[test]
fn the_odometry_front_end_poses_every_frame_and_gives_each_keyframe_its_dense_map() {
    let (camera, frames, gt) = sequence();
    let mut pipeline = Pipeline::new(dso(), *camera, None).expect("pipeline");
    let mut events = Vec::new();
    for frame in frames {
        events.extend(pipeline.push(frame.clone()).expect("push"));
    }
    pipeline.finish().expect("finish");
    events.extend(pipeline.take_events());

    let states: Vec<TrackingState> = events
        .iter()
        .filter_map(|e| match e {
            Event::Pose(p) => Some(p.state),
            _ => None,
        })
        .collect();
    assert_eq!(states.len(), frames.len(), "one pose event per frame");
    let initialising = states
        .iter()
        .take_while(|s| **s == TrackingState::Initializing)
        .count();
    assert!(
        initialising > 0 && initialising < frames.len() / 4,
        "the odometry initialises early on the orbit ({initialising} frames)"
    );
    assert!(
        states[initialising..]
            .iter()
            .all(|s| *s == TrackingState::Tracking),
        "after the initialisation every frame is tracked"
    );
    let stats = pipeline.stats().clone();
    assert_eq!(stats.frames_lost, 0);
    assert!(stats.keyframes >= 5, "{} keyframes", stats.keyframes);
    let announced = events
        .iter()
        .filter(|e| matches!(e, Event::Keyframe(_)))
        .count();
    assert_eq!(
        announced, stats.keyframes,
        "one keyframe event per keyframe"
    );
    assert_eq!(
        stats.keyframes_densified, stats.keyframes,
        "in step the dense layer densifies every keyframe"
    );

    let path = path_length(&gt.iter().map(|p| p.world_from_camera).collect::<Vec<_>>());
    let trajectory = pipeline.trajectory().expect("trajectory");
    let traj = ate(gt, &stamped_se3(&trajectory), AlignMode::Sim3).expect("ate");
    let keyframes = stamped_se3(&pipeline.keyframe_trajectory());
    let kfs = ate(gt, &keyframes, AlignMode::Sim3).expect("ate");
    println!(
        "odometry front end: path {path:.3} m, {} keyframes, ATE frames {:.4} m, keyframes {:.4} m",
        stats.keyframes, traj.rmse, kfs.rmse
    );
    assert_eq!(traj.matched, frames.len());
    assert!(traj.rmse <= 0.005 * path, "frame ATE {} m", traj.rmse);
    assert!(kfs.rmse <= 0.005 * path, "keyframe ATE {} m", kfs.rmse);
}

#[test]
fn extending_a_map_with_the_odometry_front_end_is_refused() {
    let (camera, _, _) = sequence();
    let backend = crate::graph::Backend::new(crate::graph::BackendConfig::default());
    let error = Pipeline::build(
        dso(),
        *camera,
        None,
        None,
        Some(backend.expect("backend")),
        crate::spill::Spill::default(),
    )
    .expect_err("extending needs the LSD front end");
    assert!(error.to_string().contains("frontend"), "{error}");
}
