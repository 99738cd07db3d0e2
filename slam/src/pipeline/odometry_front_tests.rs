//! The pipeline with the DSO-class odometry as its front end, on the rendered orbit of
//! [`super::tests::sequence`]: every frame posed, the odometry's keyframes are the pipeline's,
//! each densified, and the trajectory within a bound the LSD front end does not reach there.

use super::tests::{run, sequence};
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
    let (_, frames, gt) = sequence();
    let (pipeline, events) = run(dso());

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

/// The lens goes black for 2.3 s (nothing to track: the odometry has no relocalisation and
/// would stay lost) and then shows the orbit again where it was left: after
/// `new_fragment_after_lost_s` a new odometry starts in a new map fragment and the frames
/// after the gap are tracked again.
#[test]
fn a_lost_odometry_starts_again_in_a_new_fragment() {
    let (camera, frames, _) = sequence();
    let black = ::image::RgbImage::new(camera.width, camera.height);
    let shown = frames[..90]
        .iter()
        .map(|f| f.rgb.clone())
        .chain(std::iter::repeat_n(black, 70))
        .chain(frames[90..].iter().map(|f| f.rgb.clone()));
    let mut pipeline = Pipeline::new(dso(), *camera, None).expect("pipeline");
    let mut states = Vec::new();
    for (k, rgb) in shown.enumerate() {
        let input = FrameInput {
            frame_id: None,
            timestamp: k as f64 / 30.0,
            rgb,
            depth: None,
        };
        for event in pipeline.push(input).expect("push") {
            if let Event::Pose(p) = event {
                states.push(p.state);
            }
        }
    }
    pipeline.finish().expect("finish");
    let stats = pipeline.stats().clone();
    let after = &states[160..];
    let tracked = after
        .iter()
        .filter(|s| **s == TrackingState::Tracking)
        .count();
    println!(
        "black lens: {} lost, {} fragment(s), {} apart, {tracked} of {} frames after it tracked",
        stats.frames_lost,
        stats.fragments,
        stats.fragments_apart,
        after.len()
    );
    assert_eq!(stats.fragments, 1, "{stats:?}");
    assert!(
        stats.frames_lost > 0 && stats.frames_lost <= 70,
        "{stats:?}"
    );
    assert!(
        tracked >= after.len() * 3 / 4,
        "{tracked} of {}",
        after.len()
    );
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
