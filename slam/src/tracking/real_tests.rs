//! Tracking on the real 7-Scenes sequence (shared data, skipped when absent), with the
//! sensor depth of the keyframe as its "semi-dense map".

use super::*;
use crate::dataset::TumSequence;
use crate::frame::Frame;
use crate::geometry::{SE3, UndistortMap};
use crate::image::ImageF32;
use crate::mapping::{DepthMap, InverseDepth};

fn sequence(name: &str) -> Option<TumSequence> {
    crate::dataset::shared_sequence(name)
}

fn frame(seq: &TumSequence, i: usize) -> Frame {
    crate::dataset::shared_frame(seq, i)
}

/// Sensor depth at pixels with gradient above `min_grad` (LSD-SLAM `minUseGrad` = 5).
fn sensor_map(frame: &Frame, depth: &ImageF32, min_grad: f32) -> DepthMap {
    let level = frame.level(0);
    let mut map = DepthMap::unknown(level.width(), level.height());
    for i in 0..map.pixels.len() {
        let d = depth.data[i];
        if level.grad_mag.data[i] > min_grad && d > 0.1 {
            map.pixels[i] = InverseDepth::Estimate {
                idepth: 1.0 / d,
                // ~1 % depth noise, as a Kinect at 1–3 m.
                var: (0.01 / d).powi(2),
            };
        }
    }
    map
}

fn pose_error(estimate: &SE3, truth: &SE3) -> (f64, f64) {
    let e = truth.inverse() * *estimate;
    (e.translation.norm(), e.rotation.log().norm().to_degrees())
}

/// Tracks frames `indices` (loaded by `load`) one after the other against the keyframe 0
/// `reference`, each starting from the previous result as LSD-SLAM does; asserts every frame
/// is tracked and returns the worst (translation m, rotation °) error against ground truth.
fn track_chain(
    label: &str,
    seq: &TumSequence,
    reference: &TrackingReference,
    indices: impl IntoIterator<Item = usize>,
    load: impl Fn(usize) -> Frame,
) -> (f64, f64) {
    let w_kf = seq.frames[0].world_from_camera.expect("gt");
    let mut tracker = SE3Tracker::new(TrackingConfig::default()).expect("tracker");
    let mut guess = SE3::identity();
    let mut worst = (0.0f64, 0.0f64);
    for i in indices {
        let f = load(i);
        let result = tracker.track(reference, &f, &guess);
        let truth = seq.frames[i].world_from_camera.expect("gt").inverse() * w_kf;
        let (et, er) = pose_error(&result.frame_from_keyframe, &truth);
        let (mt, mr) = pose_error(&SE3::identity(), &truth);
        eprintln!(
            "{label} {i:2}: motion {mt:.3} m {mr:.2}°, error {et:.4} m {er:.3}°, good {} ({:.2}), usage {:.2}, residual {:.2}, its {}, corr {:.3}",
            result.good,
            result.good_ratio,
            result.point_usage,
            result.residual,
            result.iterations,
            result.correlation
        );
        assert!(result.good, "{label} frame {i} lost");
        worst = (worst.0.max(et), worst.1.max(er));
        guess = result.frame_from_keyframe;
    }
    worst
}

#[test]
fn tracking_real_7scenes_against_sensor_depth() {
    let Some(seq) = sequence("7scenes_redkitchen_f0000-0299") else {
        return;
    };
    let key = frame(&seq, 0);
    let depth = seq.load_depth(0).expect("depth").expect("has depth");
    let map = sensor_map(&key, &depth, 5.0);
    let reference = TrackingReference::new(&key, &map).expect("reference");
    let worst = track_chain("7scenes", &seq, &reference, (2..=40).step_by(2), |i| {
        frame(&seq, i)
    });
    eprintln!("7scenes worst error {:.4} m {:.3}°", worst.0, worst.1);
    // Colour and depth of 7-Scenes are not registered (a few pixels apart) and the ground truth
    // is KinectFusion's: centimetre-level agreement is what the data supports.
    assert!(worst.0 < 0.03 && worst.1 < 1.0, "worst error {worst:?}");
}

/// fr1/rpy: distorted images (undistorted on input, depth by nearest neighbour), fast
/// rotation (up to 4° per frame) and motion blur.
#[test]
fn tracking_real_fr1_rpy_against_sensor_depth() {
    let Some(seq) = sequence("tum_fr1_rpy_f0000-0249") else {
        return;
    };
    let undistort = UndistortMap::new(&seq.camera);
    let camera = undistort.undistorted_camera();
    let load = |i: usize| {
        let gray = undistort
            .apply(&seq.load_gray(i).expect("image"))
            .expect("undistort");
        Frame::new(i as u64, seq.frames[i].timestamp, camera, &gray, None).expect("frame")
    };
    let raw = seq.load_depth(0).expect("depth").expect("has depth");
    let mut depth = ImageF32::filled(raw.width, raw.height, 0.0);
    for y in 0..raw.height {
        for x in 0..raw.width {
            if let Some(s) = undistort.source(x as u32, y as u32) {
                let (u, v) = ((s.x + 0.5) as usize, (s.y + 0.5) as usize);
                *depth.at_mut(x, y) = raw.at(u.min(raw.width - 1), v.min(raw.height - 1));
            }
        }
    }
    let key = load(0);
    let map = sensor_map(&key, &depth, 5.0);
    let reference = TrackingReference::new(&key, &map).expect("reference");
    let worst = track_chain("fr1", &seq, &reference, 1..=10, load);
    let mut tracker = SE3Tracker::new(TrackingConfig::default()).expect("tracker");
    // The sensor depth is captured up to ~20 ms apart from the colour image while the camera
    // turns at ~120°/s, so the "map" itself is off by up to a few degrees at edges.
    assert!(worst.0 < 0.03 && worst.1 < 2.0, "worst error {worst:?}");
    // Frames of another scene (7-Scenes kitchen) are lost.
    if let Some(kitchen) = sequence("7scenes_redkitchen_f0000-0299") {
        for i in [0, 100, 200] {
            let gray = kitchen.load_gray(i).expect("image");
            let f = Frame::new(0, 0.0, camera, &gray, None).expect("frame");
            let result = tracker.track(&reference, &f, &SE3::identity());
            eprintln!(
                "fr1 keyframe vs kitchen {i}: good {} ({:.2}), usage {:.2}, residual {:.2} corr {:.3}",
                result.good,
                result.good_ratio,
                result.point_usage,
                result.residual,
                result.correlation
            );
            assert!(!result.good, "kitchen frame {i} tracked on an fr1 keyframe");
        }
    }
}
