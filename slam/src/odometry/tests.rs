//! Tests of the sliding window: Jacobians against numeric differences, the 7-dimensional
//! gauge under first-estimate Jacobians and marginalisation, recovery of exact poses and
//! depths on rendered views, scale carried through marginalisation, point selection.

use std::sync::Arc;

use nalgebra::{DMatrix, Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::gauge::{GAUGE_DIMENSION, basis};
use super::residual::{FRAME_PARAMS, FrameView, Interleaved, Vector8, linearise};
use super::select::select_candidates;
use super::*;
use crate::dataset::synth::{Scene, SynthConfig, render_frame_with};
use crate::eval::umeyama::umeyama;
use crate::frame::Frame;
use crate::geometry::{PinholeCamera, SE3};
use crate::image::ImageF32;
use crate::image::pyramid::Pyramid;

#[test]
fn residual_jacobians_match_numeric_differences() {
    let (w, h) = (160usize, 120usize);
    let camera = PinholeCamera::new(130.0, 130.0, 79.5, 59.5, w as u32, h as u32).expect("camera");
    let host_pyr =
        Pyramid::build_cpu(&crate::image::smooth_test_image(w, h, 0.0), 1).expect("pyramid");
    let target_pyr =
        Pyramid::build_cpu(&crate::image::smooth_test_image(w, h, 0.4), 1).expect("pyramid");
    let state = |xi: Vector6<f64>, affine| FrameState {
        world_from_camera: SE3::exp(&xi),
        affine,
    };
    let host_state = state(
        Vector6::new(0.1, -0.05, 0.02, 0.02, -0.03, 0.01),
        (0.1, 3.0),
    );
    let target_state = state(
        Vector6::new(0.18, 0.02, -0.04, -0.01, 0.02, 0.03),
        (-0.05, -2.0),
    );
    let host_samples = Interleaved::new(&host_pyr.levels[0]);
    let target_samples = Interleaved::new(&target_pyr.levels[0]);
    let view = |level, samples, s: FrameState| FrameView {
        level,
        samples,
        camera,
        state: s,
        first_estimate: s,
        row_twist: Vector6::zeros(),
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
        let uv = Vector2::new(u, v);
        let intensity = 100.0 + 3.0 * i as f64;
        for k in 0..PATTERN.len() {
            let host = view(&host_pyr.levels[0], &host_samples, host_state);
            let target = view(&target_pyr.levels[0], &target_samples, target_state);
            let Some(lin) = linearise(
                &uv,
                rho,
                intensity,
                k,
                &host,
                &target,
                Linearisation::FirstEstimate,
            ) else {
                continue;
            };
            let eps = 1e-3;
            let residual_with = |dh: &Vector8, dt: &Vector8, drho: f64| -> f64 {
                let host = view(&host_pyr.levels[0], &host_samples, host_state.step(dh));
                let target = view(
                    &target_pyr.levels[0],
                    &target_samples,
                    target_state.step(dt),
                );
                linearise(
                    &uv,
                    rho + drho,
                    intensity,
                    k,
                    &host,
                    &target,
                    Linearisation::Current,
                )
                .expect("still visible")
                .residual
            };
            let z = Vector8::zeros();
            // Bilinear interpolation makes the residual piecewise smooth: the numeric slope
            // within a cell differs from the central-difference gradient by a few percent.
            let size = lin.d_host.amax().max(lin.d_target.amax());
            for j in 0..FRAME_PARAMS {
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
        checked >= 24,
        "only {checked} pattern residuals were visible"
    );
}

/// Rendered keyframes of the synthetic room: frames, true poses and true z-depth images.
pub(super) struct Rendered {
    pub(super) frames: Vec<Arc<Frame>>,
    pub(super) poses: Vec<SE3>,
    pub(super) depths: Vec<ImageF32>,
}

pub(super) fn render(seed: u64, picks: &[usize]) -> Rendered {
    let config = SynthConfig {
        width: 320,
        height: 240,
        seed,
        frames: picks.iter().max().copied().unwrap_or(0) + 1,
        ..SynthConfig::default()
    };
    let camera = config.camera().expect("camera");
    let scene = Scene::generate(seed);
    let all = config.poses();
    let mut out = Rendered {
        frames: Vec::new(),
        poses: Vec::new(),
        depths: Vec::new(),
    };
    for (n, &i) in picks.iter().enumerate() {
        let (rgb, depth) = render_frame_with(&scene, &camera, &all[i], 2);
        let gray = ImageF32::from_rgb8(&rgb);
        let frame = Frame::new(n as u64, i as f64 / 30.0, camera, &gray, None).expect("frame");
        out.frames.push(Arc::new(frame));
        out.poses.push(all[i]);
        out.depths.push(depth);
    }
    out
}

/// Adds keyframe `n` of `r` at `pose` and up to `count` of its candidates with their true
/// inverse depth times `depth_factor(point)`.
pub(super) fn add_keyframe(
    window: &mut SlidingWindow,
    r: &Rendered,
    n: usize,
    pose: SE3,
    count: usize,
    mut depth_factor: impl FnMut() -> f64,
) {
    let state = FrameState {
        world_from_camera: pose,
        affine: (0.0, 0.0),
    };
    window
        .add_frame(n as u64, r.frames[n].clone(), state)
        .expect("new keyframe");
    for uv in select_candidates(r.frames[n].level(0), count) {
        let d = r.depths[n].at(uv.x as usize, uv.y as usize);
        if d > 0.0 {
            window.add_point(n as u64, uv, depth_factor() / f64::from(d), None);
        }
    }
}

/// A pose moved by about `cm` centimetres and `deg` degrees in a random direction.
pub(super) fn perturbed(pose: &SE3, rng: &mut ChaCha8Rng, cm: f64, deg: f64) -> SE3 {
    let mut unit = || {
        Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize()
    };
    let (t, w) = (unit() * cm / 100.0, unit() * deg.to_radians());
    *pose * SE3::exp(&Vector6::new(t.x, t.y, t.z, w.x, w.y, w.z))
}

/// `|H n| / (|H| |n|)` for every gauge direction `n` of `basis`: 0 when `H` knows nothing
/// along the gauge.
fn gauge_leak(h: &DMatrix<f64>, basis: &DMatrix<f64>) -> f64 {
    (0..basis.ncols())
        .map(|j| {
            let n = basis.column(j);
            (h * n).norm() / (h.norm() * n.norm())
        })
        .fold(0.0, f64::max)
}

fn first_estimates(window: &SlidingWindow) -> Vec<FrameState> {
    window.frames().iter().map(|f| f.first_estimate).collect()
}

#[test]
fn window_hessian_leaves_exactly_the_seven_gauge_directions_open() {
    let r = render(3, &[0, 4, 8, 12, 16]);
    let mut window = SlidingWindow::new(OdometryConfig::default()).expect("config");
    for n in 0..r.frames.len() {
        add_keyframe(&mut window, &r, n, r.poses[n], 400, || 1.0);
    }
    assert!(
        window.points().len() > 1000,
        "{} points",
        window.points().len()
    );
    let (h, _) = window.reduced_system();
    let leak = gauge_leak(&h, &basis(&first_estimates(&window)));
    assert!(
        leak < 1e-10,
        "the Hessian has information along the gauge: {leak:e}"
    );
    // Exactly seven: every other direction (brightness included, through its weak prior) is
    // observed. Eigenvalues of the Jacobi-scaled Hessian, so that metres, radians and grey
    // levels compare.
    let d = h.diagonal().map(|v| 1.0 / v.max(1e-300).sqrt());
    let scaled = DMatrix::from_fn(h.nrows(), h.ncols(), |i, j| h[(i, j)] * d[i] * d[j]);
    let mut eigen: Vec<f64> = scaled.symmetric_eigenvalues().iter().copied().collect();
    eigen.sort_by(f64::total_cmp);
    assert!(
        eigen[GAUGE_DIMENSION - 1].abs() < 1e-10,
        "{:e}",
        eigen[GAUGE_DIMENSION - 1]
    );
    assert!(
        eigen[GAUGE_DIMENSION] > 1e-6,
        "{:e}",
        eigen[GAUGE_DIMENSION]
    );
}

/// Runs a window over keyframes 0-5 from a perturbed start, marginalising the two oldest
/// after optimising; returns the window.
fn marginalised_window(linearisation: Linearisation) -> SlidingWindow {
    let r = render(4, &[0, 4, 8, 12, 16, 20]);
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut window = SlidingWindow::new(OdometryConfig {
        iterations: 10,
        ..OdometryConfig::default()
    })
    .expect("config")
    .with_linearisation(linearisation);
    for n in 0..r.frames.len() {
        let pose = if n == 0 {
            r.poses[0]
        } else {
            perturbed(&r.poses[n], &mut rng, 1.0, 0.5)
        };
        add_keyframe(&mut window, &r, n, pose, 300, || 1.0);
    }
    window.optimize();
    window.marginalize_frame(0).expect("in the window");
    window.optimize();
    window.marginalize_frame(1).expect("in the window");
    window.optimize();
    window
}

#[test]
fn first_estimate_jacobians_keep_the_gauge_through_marginalisation() {
    let fej = marginalised_window(Linearisation::FirstEstimate);
    let basis_fej = basis(&first_estimates(&fej));
    // Every frame moved away from its first estimate, yet neither the prior nor the whole
    // system knows anything along the gauge.
    let moved = fej
        .frames()
        .iter()
        .map(|f| f.state.delta_from(&f.first_estimate).norm())
        .fold(0.0, f64::max);
    assert!(moved > 1e-3, "the window did not move: {moved}");
    let prior_leak = gauge_leak(&fej.prior().h, &basis_fej);
    let (h, _) = fej.reduced_system();
    let system_leak = gauge_leak(&h, &basis_fej);
    // Measured: 1e-15 with first estimates, 2e-6 without.
    assert!(prior_leak < 1e-12, "prior: {prior_leak:e}");
    assert!(system_leak < 1e-12, "system: {system_leak:e}");

    // Linearised at the current state instead, the prior (built at two different states)
    // and the residuals (at a third) disagree on the gauge: the system then claims to know
    // the position, orientation or scale of the world.
    let current = marginalised_window(Linearisation::Current);
    let (h, _) = current.reduced_system();
    let states: Vec<FrameState> = current.frames().iter().map(|f| f.state).collect();
    let leak = gauge_leak(&h, &basis(&states));
    assert!(leak > 1e-8, "current-state Jacobians leaked only {leak:e}");
}

/// Sim(3)-aligned position errors of the window's keyframes against `truth`, and the
/// alignment's scale.
fn aligned_errors(window: &SlidingWindow, truth: &[SE3]) -> (Vec<f64>, f64) {
    let est: Vec<Vector3<f64>> = window
        .frames()
        .iter()
        .map(|f| f.state.world_from_camera.translation)
        .collect();
    let gt: Vec<Vector3<f64>> = window
        .frames()
        .iter()
        .map(|f| truth[f.id as usize].translation)
        .collect();
    let align = umeyama(&est, &gt, true).expect("alignment");
    let errors = est
        .iter()
        .zip(&gt)
        .map(|(e, g)| (align.act(e) - g).norm())
        .collect();
    (errors, align.scale)
}

#[test]
fn window_recovers_poses_and_depths_on_rendered_views() {
    let r = render(5, &[0, 3, 6, 9, 12, 15]);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut window = SlidingWindow::new(OdometryConfig {
        iterations: 40,
        ..OdometryConfig::default()
    })
    .expect("config");
    for n in 0..r.frames.len() {
        let pose = if n == 0 {
            r.poses[0]
        } else {
            perturbed(&r.poses[n], &mut rng, 1.5, 0.7)
        };
        let mut noise = ChaCha8Rng::seed_from_u64(100 + n as u64);
        add_keyframe(&mut window, &r, n, pose, 300, || {
            noise.random_range(0.85..1.15)
        });
    }
    let start = aligned_errors(&window, &r.poses).0;
    let report = window.optimize();
    assert!(report.final_energy < report.initial_energy, "{report:?}");
    let (errors, scale) = aligned_errors(&window, &r.poses);
    let worst = errors.iter().copied().fold(0.0, f64::max);
    let path: f64 = r
        .poses
        .windows(2)
        .map(|p| (p[1].translation - p[0].translation).norm())
        .sum();
    assert!(
        worst < 0.01 * path,
        "worst {worst} m on a {path} m path (start {start:?})"
    );
    // Depths: the inverse depths in the window's scale, against the truth.
    let mut rel = Vec::new();
    for p in window.points() {
        let d = f64::from(r.depths[p.host as usize].at(p.uv.x as usize, p.uv.y as usize));
        // `truth ≈ scale · estimate`, so an estimated inverse depth is `scale / d`.
        rel.push((p.idepth * d / scale - 1.0).abs());
    }
    rel.sort_by(f64::total_cmp);
    let median = rel[rel.len() / 2];
    assert!(
        median < 0.02,
        "median relative depth error {median} (started at 0.075)"
    );
}

#[test]
fn marginalisation_carries_the_scale_while_new_points_start_wrong() {
    // Twenty keyframes along the orbit; each new keyframe starts at the constant-velocity
    // guess from the window's own estimate, and its points at 1.3 × their true depth (a
    // biased depth source): the window and its prior must hold the scale anyway.
    let picks: Vec<usize> = (0..20).map(|i| 3 * i).collect();
    let r = render(6, &picks);
    let mut window = SlidingWindow::new(OdometryConfig {
        iterations: 10,
        ..OdometryConfig::default()
    })
    .expect("config");
    let mut estimates: Vec<SE3> = Vec::new();
    for n in 0..picks.len() {
        let guess = match n {
            0 | 1 => r.poses[n],
            _ => {
                let (a, b) = (estimates[n - 2], estimates[n - 1]);
                b * (a.inverse() * b)
            }
        };
        let factor = if n < 2 { 1.0 } else { 1.0 / 1.3 };
        add_keyframe(&mut window, &r, n, guess, 300, || factor);
        window.optimize();
        if window.frames().len() > window.config().max_frames {
            let oldest = window.frames()[0].id;
            window.marginalize_frame(oldest).expect("in the window");
        }
        estimates.resize(n + 1, SE3::identity());
        for f in window.frames() {
            estimates[f.id as usize] = f.state.world_from_camera;
        }
    }
    // Scale of each stretch of five keyframes against the truth.
    let stretch = |from: usize| {
        let est = (estimates[from + 4].translation - estimates[from].translation).norm();
        let gt = (r.poses[from + 4].translation - r.poses[from].translation).norm();
        est / gt
    };
    let (first, last) = (stretch(0), stretch(picks.len() - 5));
    assert!(
        (last / first - 1.0).abs() < 0.05,
        "scale {first} at the start, {last} at the end"
    );
    let est: Vec<Vector3<f64>> = estimates.iter().map(|p| p.translation).collect();
    let gt: Vec<Vector3<f64>> = r.poses.iter().map(|p| p.translation).collect();
    let align = umeyama(&est, &gt, true).expect("alignment");
    let ate = (est
        .iter()
        .zip(&gt)
        .map(|(e, g)| (align.act(e) - g).norm_squared())
        .sum::<f64>()
        / est.len() as f64)
        .sqrt();
    let path: f64 = gt.windows(2).map(|p| (p[1] - p[0]).norm()).sum();
    assert!(ate < 0.01 * path, "ATE {ate} m on a {path} m path");
}

#[test]
fn candidates_cover_the_image_near_the_target_count() {
    let r = render(7, &[0]);
    let level = r.frames[0].level(0);
    for target in [300usize, 1000] {
        let points = select_candidates(level, target);
        let n = points.len() as f64;
        assert!(
            (0.6..=1.4).contains(&(n / target as f64)),
            "{n} points for {target}"
        );
        // Every quarter-by-quarter cell of the image that has any texture gets points.
        let mut cells = [0usize; 16];
        for p in &points {
            let (cx, cy) = ((p.x / 80.0) as usize, (p.y / 60.0) as usize);
            cells[cy.min(3) * 4 + cx.min(3)] += 1;
        }
        let covered = cells.iter().filter(|&&c| c > 0).count();
        assert!(
            covered >= 14,
            "{covered} of 16 cells have points: {cells:?}"
        );
    }
}
