//! The odometry loop end to end on a rendered sequence: initialisation without a prior,
//! tracking, tracing, activation, keyframes and marginalisation, judged against the truth.

use std::sync::Arc;

use nalgebra::Vector3;

use super::{Odometry, OdometryConfig};
use crate::dataset::synth::{Scene, SynthConfig, render_frame_with};
use crate::eval::umeyama::umeyama;
use crate::frame::Frame;
use crate::image::ImageF32;

/// The frames of `config`'s rendered sequence, numbered from 0 at 30 Hz.
pub(super) fn rendered_frames(config: &SynthConfig) -> Vec<Arc<Frame>> {
    let camera = config.camera().expect("camera");
    let scene = Scene::generate(config.seed);
    config
        .poses()
        .iter()
        .enumerate()
        .map(|(i, pose)| {
            let (rgb, _) = render_frame_with(&scene, &camera, pose, 1);
            let gray = ImageF32::from_rgb8(&rgb);
            Arc::new(Frame::new(i as u64, i as f64 / 30.0, camera, &gray, None).expect("frame"))
        })
        .collect()
}

/// RMSE after a Sim(3) alignment, and the alignment's scale.
fn aligned(est: &[Vector3<f64>], gt: &[Vector3<f64>]) -> (f64, f64) {
    let align = umeyama(est, gt, true).expect("alignment");
    let sum: f64 = est
        .iter()
        .zip(gt)
        .map(|(e, g)| (align.act(e) - g).norm_squared())
        .sum();
    ((sum / est.len() as f64).sqrt(), align.scale)
}

#[test]
fn odometry_poses_a_rendered_orbit_at_a_consistent_scale() {
    let config = SynthConfig {
        // 640×480: at 320×240 the loop does not yet work (issue 35's note).
        width: 640,
        height: 480,
        seed: 11,
        frames: 120,
        ..SynthConfig::default()
    };
    let truth = config.poses();
    let mut odometry = Odometry::new(OdometryConfig::default()).expect("config");
    let mut tracked = 0;
    for frame in rendered_frames(&config) {
        tracked += usize::from(odometry.push(frame).expect("push").tracked);
    }
    let trajectory = odometry.trajectory();
    assert_eq!(trajectory.len(), truth.len(), "every frame has a pose");
    assert!(tracked >= 105, "{tracked} of 120 frames tracked");
    assert!(
        odometry.keyframe_count() >= 5,
        "{} keyframes",
        odometry.keyframe_count()
    );
    let est: Vec<Vector3<f64>> = trajectory.iter().map(|(_, p)| p.translation).collect();
    let gt: Vec<Vector3<f64>> = trajectory
        .iter()
        .map(|(id, _)| truth[*id as usize].translation)
        .collect();
    let path: f64 = gt.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    let (ate, _) = aligned(&est, &gt);
    assert!(ate < 0.005 * path, "ATE {ate} m on a {path} m path");
    // The scale of the first and the second half agree (no drift).
    let half = est.len() / 2;
    let (_, s1) = aligned(&est[..half], &gt[..half]);
    let (_, s2) = aligned(&est[half..], &gt[half..]);
    assert!((s2 / s1 - 1.0).abs() < 0.1, "scale {s1} then {s2}");
}

#[test]
fn threaded_window_that_catches_up_computes_what_the_window_in_step_does() {
    let config = SynthConfig {
        width: 640,
        height: 480,
        seed: 12,
        frames: 50,
        ..SynthConfig::default()
    };
    let frames = rendered_frames(&config);
    let run = |threaded: bool| {
        let mut odometry =
            Odometry::start(OdometryConfig::default(), 0, threaded).expect("odometry");
        let mut outcomes = Vec::new();
        for f in &frames {
            outcomes.push(odometry.push(f.clone()).expect("push"));
            // Given the time, the thread stands where the window in step does.
            odometry
                .catch_up(std::time::Duration::from_secs(120))
                .expect("catch up");
        }
        odometry.finish().expect("finish");
        (outcomes, odometry.trajectory(), odometry.keyframe_count())
    };
    let (in_step, in_step_trajectory, keyframes) = run(false);
    assert!(keyframes >= 3, "{keyframes} keyframes in 50 frames");
    let (threaded, threaded_trajectory, threaded_keyframes) = run(true);
    assert_eq!(threaded_keyframes, keyframes);
    assert_eq!(threaded, in_step, "frame outcomes differ");
    assert_eq!(threaded_trajectory.len(), in_step_trajectory.len());
    for ((a, p), (b, q)) in threaded_trajectory.iter().zip(&in_step_trajectory) {
        assert_eq!(a, b);
        assert!(
            (p.translation - q.translation).norm() < 1e-12,
            "frame {a}: {p:?} vs {q:?}"
        );
    }
}

#[test]
fn a_first_map_replaces_the_initialisers_before_the_window_starts() {
    let frames = rendered_frames(&SynthConfig {
        width: 320,
        height: 240,
        seed: 4,
        frames: 30,
        ..SynthConfig::default()
    });
    // Keep the first 100 points, every one at inverse depth 0.5.
    let first_map = super::FirstMap(Arc::new(
        |_: &Frame, points: &[(nalgebra::Vector2<f64>, f64)]| {
            points.iter().take(100).map(|(uv, _)| (*uv, 0.5)).collect()
        },
    ));
    let mut odometry = Odometry::new(OdometryConfig::default())
        .expect("odometry")
        .with_first_map(first_map);
    for f in &frames {
        if odometry.push(f.clone()).expect("push").keyframe {
            break;
        }
    }
    let window = odometry.window().expect("the first keyframe");
    assert_eq!(window.frames.len(), 1);
    assert_eq!(
        window.points.len(),
        100,
        "the window starts from the given map"
    );
    for p in &window.points {
        assert!((p.idepth - 0.5).abs() < 1e-12, "inverse depth {}", p.idepth);
    }
}
