//! Tests of the windowed bundle adjustment: analytic Jacobians against numeric differences,
//! and the joint optimisation recovering a consistent scale on rendered views.

use nalgebra::{Vector2, Vector3, Vector6};

use super::residual::{KF_PARAMS, PATTERN, Point, Vector8, View, apply_step, linearise};
use super::*;
use crate::dataset::synth::{Scene, SynthConfig, render_frame_with};
use crate::geometry::{PinholeCamera, SE3};
use crate::image::ImageF32;
use crate::image::pyramid::Pyramid;
use crate::mapping::InverseDepth;

#[test]
fn window_residual_jacobians_match_numeric_differences() {
    let (w, h) = (160usize, 120usize);
    let camera = PinholeCamera::new(130.0, 130.0, 79.5, 59.5, w as u32, h as u32).expect("camera");
    let host_pyr =
        Pyramid::build_cpu(&crate::image::smooth_test_image(w, h, 0.0), 1).expect("pyramid");
    let target_pyr =
        Pyramid::build_cpu(&crate::image::smooth_test_image(w, h, 0.4), 1).expect("pyramid");
    let host = View {
        level: &host_pyr.levels[0],
        camera,
        world_from_camera: SE3::exp(&Vector6::new(0.1, -0.05, 0.02, 0.02, -0.03, 0.01)),
        affine: (0.1, 3.0),
    };
    let target = View {
        level: &target_pyr.levels[0],
        camera,
        world_from_camera: SE3::exp(&Vector6::new(0.18, 0.02, -0.04, -0.01, 0.02, 0.03)),
        affine: (-0.05, -2.0),
    };
    let mut checked = 0;
    for (i, (u, v, rho)) in [
        (60.0, 50.0, 0.5),
        (90.0, 70.0, 0.8),
        (40.0, 30.0, 0.3),
        (100.0, 40.0, 1.1),
    ]
    .into_iter()
    .enumerate()
    {
        let point = Point {
            host: 0,
            uv: Vector2::new(u, v),
            idepth: rho,
            idepth_keyframe: rho,
            intensity: [100.0 + i as f64, 90.0, 110.0, 95.0, 105.0],
        };
        for k in 0..PATTERN.len() {
            let Some(lin) = linearise(&point, k, &host, &target) else {
                continue;
            };
            let eps = 1e-3;
            let residual_with = |dh: &Vector8, dt: &Vector8, drho: f64| -> f64 {
                let (ph, ah) = apply_step(&host, dh);
                let (pt, at) = apply_step(&target, dt);
                let hv = View {
                    world_from_camera: ph,
                    affine: ah,
                    ..host
                };
                let tv = View {
                    world_from_camera: pt,
                    affine: at,
                    ..target
                };
                let p = Point {
                    idepth: rho + drho,
                    ..point.clone()
                };
                linearise(&p, k, &hv, &tv).expect("still visible").residual
            };
            let z = Vector8::zeros();
            // Bilinear interpolation makes the residual piecewise smooth: the numeric slope
            // within a cell differs from the central-difference gradient by a few percent of
            // the Jacobian's size, which is the tolerance.
            let size = lin.d_host.amax().max(lin.d_target.amax());
            for j in 0..KF_PARAMS {
                let mut d = Vector8::zeros();
                d[j] = eps;
                let num_h =
                    (residual_with(&d, &z, 0.0) - residual_with(&-d, &z, 0.0)) / (2.0 * eps);
                let num_t =
                    (residual_with(&z, &d, 0.0) - residual_with(&z, &-d, 0.0)) / (2.0 * eps);
                for (num, ana, who) in [
                    (num_h, lin.d_host[j], "host"),
                    (num_t, lin.d_target[j], "target"),
                ] {
                    assert!(
                        (num - ana).abs() <= 0.03 * size + 0.05,
                        "point {i} pattern {k} {who} param {j}: numeric {num} analytic {ana}"
                    );
                }
            }
            let num_d = (residual_with(&z, &z, eps) - residual_with(&z, &z, -eps)) / (2.0 * eps);
            assert!(
                (num_d - lin.d_idepth).abs() <= 0.03 * num_d.abs().max(lin.d_idepth.abs()) + 0.05,
                "point {i} pattern {k} idepth: numeric {num_d} analytic {}",
                lin.d_idepth
            );
            checked += 1;
        }
    }
    assert!(
        checked >= 15,
        "only {checked} pattern residuals were visible"
    );
}

/// Rendered views of the synthetic room along the orbit, with their exact depth as the
/// semi-dense maps (in keyframe units of a different scale each).
#[test]
fn window_recovers_a_consistent_scale_from_drifted_poses() {
    let config = SynthConfig {
        width: 320,
        height: 240,
        seed: 5,
        frames: 61,
        ..SynthConfig::default()
    };
    let camera = config.camera().expect("camera");
    let scene = Scene::generate(config.seed);
    let poses = config.poses();
    let picks = [0usize, 10, 20, 30, 40, 50, 60];
    let mut frames = Vec::new();
    let mut depths = Vec::new();
    // Each keyframe's depth map in its own units: true depth divided by its scale.
    let scales: [f64; 7] = [1.0, 1.0, 0.8, 1.25, 0.9, 1.1, 0.7];
    for (n, &i) in picks.iter().enumerate() {
        let (rgb, depth) = render_frame_with(&scene, &camera, &poses[i], 1);
        let gray = ImageF32::from_rgb8(&rgb);
        frames.push(
            crate::frame::Frame::new(n as u64, i as f64 / 30.0, camera, &gray, None)
                .expect("frame"),
        );
        let mut map = DepthMap::unknown(depth.width, depth.height);
        for (px, &d) in map.pixels.iter_mut().zip(&depth.data) {
            if d > 0.0 {
                *px = InverseDepth::Estimate {
                    idepth: scales[n] as f32 / d,
                    var: 1e-3,
                };
            }
        }
        depths.push(map);
    }
    // Drifted start: the free keyframes' positions shrink towards the second one by 7 %
    // and their scales are the (wrong) ones of the depth maps; the first two are exact.
    let start: Vec<Sim3> = picks
        .iter()
        .enumerate()
        .map(|(n, &i)| {
            let truth = poses[i];
            let t = if n < 2 {
                truth.translation
            } else {
                poses[picks[1]].translation
                    + 0.93 * (truth.translation - poses[picks[1]].translation)
            };
            Sim3::new(
                truth.rotation,
                t + Vector3::new(0.0, 0.005, 0.0),
                scales[n] * if n < 2 { 1.0 } else { 0.93 },
            )
        })
        .collect();
    let keyframes: Vec<WindowKeyframe<'_>> = (0..picks.len())
        .map(|n| WindowKeyframe {
            id: n,
            frame: &frames[n],
            depth: &depths[n],
            world_from_keyframe: start[n],
        })
        .collect();
    let window = WindowConfig {
        enabled: true,
        iterations: 20,
        points_per_keyframe: 300,
        ..WindowConfig::default()
    };
    let result = optimize_window(&window, &keyframes).expect("window ran");
    assert!(
        result.report.final_cost < result.report.initial_cost,
        "{:?}",
        result.report
    );
    for (n, (_, pose)) in result.poses.iter().enumerate() {
        let truth = poses[picks[n]];
        let err = (pose.translation - truth.translation).norm();
        let start_err = (start[n].translation - truth.translation).norm();
        assert!(
            err < 0.01 || n < 2,
            "keyframe {n}: {err} m (started {start_err} m)"
        );
        // The scale of each depth map against the world: exactly scales[n].
        let ratio = pose.scale / scales[n];
        assert!(
            (ratio - 1.0).abs() < 0.03,
            "keyframe {n}: scale ratio {ratio}"
        );
    }
}
