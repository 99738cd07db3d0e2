//! Sim(3) alignment: residual Jacobians, recovery of a known similarity, the reciprocal test.

use std::sync::Arc;

use nalgebra::{Vector2, Vector3};

use super::{DepthScale, SynthKeyframe, render, sim3_errors, view};
use crate::frame::Frame;
use crate::geometry::{SO3, Sim3, Vector7};
use crate::graph::points::{KeyframeLevels, RefPoint};
use crate::graph::sim3_tracker::LevelContext;
use crate::graph::{BackendConfig, Keyframe, Sim3Tracker, reciprocal_test};
use crate::image::ImageF32;
use crate::mapping::{DepthMap, InverseDepth};

/// Keyframe A (metric depth) and B (depth × 1.3, moved 10 cm sideways, 4 cm forward, yawed
/// 4°), rendered once for all tests of this file.
fn pair() -> &'static (SynthKeyframe, SynthKeyframe) {
    static PAIR: std::sync::OnceLock<(SynthKeyframe, SynthKeyframe)> = std::sync::OnceLock::new();
    PAIR.get_or_init(|| {
        let a = render(0, view(0.0, Vector3::zeros()), DepthScale::Fixed(1.0));
        let b = render(
            1,
            view(4.0, Vector3::new(0.04, -0.10, 0.03)),
            DepthScale::Fixed(1.3),
        );
        (a, b)
    })
}

/// Central differences of a scalar function of a Sim(3) tangent with step `h` (the image
/// pipeline is f32, so the geometry crate's 1e-6 step would be dominated by rounding).
fn numeric_gradient(f: &dyn Fn(&Vector7) -> f64, h: f64) -> Vector7 {
    Vector7::from_fn(|i, _| {
        let mut d = Vector7::zeros();
        d[i] = h;
        (f(&d) - f(&-d)) / (2.0 * h)
    })
}

/// Mean metric depth of the estimates of a keyframe.
fn mean_depth(kf: &SynthKeyframe) -> f64 {
    let (sum, n) = kf
        .depth
        .pixels
        .iter()
        .filter_map(|p| p.estimate())
        .fold((0.0, 0usize), |(s, n), (d, _)| {
            (s + 1.0 / f64::from(d), n + 1)
        });
    sum / n as f64 / kf.depth_scale
}

#[test]
fn sim3_residual_jacobians_match_numeric_differences() {
    // A frame whose intensity is linear in (x, y): bilinear interpolation and central
    // differences are then exact, so the photometric Jacobian must match to rounding; the
    // frame's inverse-depth map is constant, so the depth residual's Jacobian is exact too.
    let cam = super::camera();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let gray = ImageF32::from_vec(
        w,
        h,
        (0..w * h)
            .map(|i| 40.0 + 0.3 * (i % w) as f32 + 0.2 * (i / w) as f32)
            .collect(),
    )
    .expect("size");
    let frame = Frame::new(7, 0.0, cam, &gray, None).expect("frame");
    let mut depth = DepthMap::unknown(w, h);
    depth.pixels.fill(InverseDepth::Estimate {
        idepth: 0.6,
        var: 0.01,
    });
    let frame_levels = KeyframeLevels::new(&frame, &depth).expect("levels");
    let config = BackendConfig::default();
    let level = 1;
    let cam1 = frame.camera_at(level);
    let point = RefPoint {
        point: cam1.unproject(&Vector2::new(61.3, 47.8), 1.7),
        idepth: 1.0 / 1.7,
        var: 0.003,
        intensity: 90.0,
    };
    let reference_level = crate::graph::points::KeyframeLevel {
        camera: cam1,
        points: vec![point],
        depth: frame_levels.levels[level].depth.clone(),
    };
    let ctx = LevelContext {
        reference: &reference_level,
        image: frame.level(level),
        frame: &frame_levels.levels[level],
        config: &config,
        affine: std::cell::Cell::new((1.0, 0.0)),
    };
    let poses = [
        Sim3::new(
            SO3::exp(&Vector3::new(0.02, -0.05, 0.01)),
            Vector3::new(0.05, -0.02, 0.1),
            1.3,
        ),
        Sim3::new(
            SO3::exp(&Vector3::new(-0.1, 0.03, 0.2)),
            Vector3::new(-0.1, 0.04, -0.2),
            0.8,
        ),
    ];
    for pose in poses {
        let base = ctx.warp(&pose, &point).expect("point lands inside");
        let (_, j_d, _) = base.depth.expect("constant depth map everywhere");
        let num_p = numeric_gradient(
            &|d| {
                ctx.warp(&(pose * Sim3::exp(d)), &point)
                    .expect("inside")
                    .r_p
            },
            1e-3,
        );
        let num_d = numeric_gradient(
            &|d| {
                ctx.warp(&(pose * Sim3::exp(d)), &point)
                    .expect("inside")
                    .depth
                    .expect("d")
                    .0
            },
            1e-4,
        );
        let err_p = (num_p - base.j_p).norm() / base.j_p.norm();
        let err_d = (num_d - j_d).norm() / j_d.norm();
        assert!(
            err_p < 1e-3,
            "photometric Jacobian off by {err_p:e}: {} vs {num_p}",
            base.j_p
        );
        assert!(
            err_d < 1e-6,
            "depth Jacobian off by {err_d:e}: {j_d} vs {num_d}"
        );
    }
}

#[test]
fn sim3_tracker_recovers_relative_similarity_with_scaled_depth() {
    let (a, b) = pair();
    let truth = b.world_from_keyframe().inverse() * a.world_from_keyframe();
    let tracker = Sim3Tracker::new(BackendConfig::default());
    // From the identity: 10 cm, 4° and a 30 % scale change away.
    let result = tracker
        .track(&a.frame, &a.depth, &b.frame, &b.depth, &Sim3::identity())
        .expect("same sizes");
    let (angle, scale, dt) = sim3_errors(&result.frame_from_reference, &truth);
    let depth_b = mean_depth(a) * b.depth_scale;
    eprintln!(
        "sim3 A→B: rot {angle:.4}°, scale {:.4} %, translation {:.4} % of depth; good {:.3}, \
         residual {:.3}, depth terms {}",
        100.0 * scale,
        100.0 * dt.norm() / depth_b,
        result.good_ratio,
        result.residual,
        result.depth_terms
    );
    assert!(result.good && !result.diverged, "{result:?}");
    assert!(angle < 0.3, "rotation error {angle}°");
    assert!(scale.abs() < 0.01, "scale error {scale}");
    assert!(
        dt.norm() < 0.01 * depth_b,
        "translation error {} vs depth {depth_b}",
        dt.norm()
    );
    assert!(result.depth_terms > 100);
    let info = result.information;
    assert!(
        info.symmetric_eigen().eigenvalues.min() > 0.0,
        "information not positive definite"
    );

    // The other direction estimates the inverse.
    let back = tracker
        .track(&b.frame, &b.depth, &a.frame, &a.depth, &Sim3::identity())
        .expect("same sizes");
    let (angle, scale, _) = sim3_errors(&back.frame_from_reference, &truth.inverse());
    assert!(back.good && angle < 0.3 && scale.abs() < 0.01, "{back:?}");
}

#[test]
fn sim3_tracker_needs_depth_residuals_to_observe_scale() {
    // Photometric residuals depend on π(sR·p + t) = π(R·p + t/s) only, so scaling the frame's
    // coordinates — the right-perturbation direction n = (Rᵀt/s, 0, 1) — is invisible to them.
    // Without the frame's depth map the information along n (nearly) vanishes; with it, it
    // does not.
    let (a, b) = pair();
    // Without the affine brightness fit: with it, the depth-less alignment diverges (zero
    // information; checked), which says nothing about the geometry this test reads.
    let tracker = Sim3Tracker::new(BackendConfig {
        affine_lighting: false,
        ..BackendConfig::default()
    });
    let full = tracker
        .track(&a.frame, &a.depth, &b.frame, &b.depth, &Sim3::identity())
        .expect("sizes");
    let mut sparse = (*b.depth).clone();
    // Keep one estimate so the map is not empty; nearly no depth terms remain.
    let keep = sparse
        .pixels
        .iter()
        .position(|p| p.estimate().is_some())
        .expect("estimates");
    for (i, p) in sparse.pixels.iter_mut().enumerate() {
        if i != keep {
            *p = InverseDepth::Unknown;
        }
    }
    let photometric = tracker
        .track(
            &a.frame,
            &a.depth,
            &b.frame,
            &sparse,
            &full.frame_from_reference,
        )
        .expect("sizes");
    assert!(photometric.depth_terms < 10, "{}", photometric.depth_terms);
    let t = &full.frame_from_reference;
    let rho = t.rotation.inverse().act(&t.translation) / t.scale;
    let mut n = Vector7::zeros();
    n.fixed_rows_mut::<3>(0).copy_from(&rho);
    n[6] = 1.0;
    let along = |info: &crate::geometry::Matrix7| n.dot(&(info * n)) / info.trace();
    let ratio = along(&photometric.information) / along(&full.information);
    eprintln!("scale-direction information, photometric-only / full: {ratio:.2e}");
    assert!(
        ratio < 1e-2,
        "scale direction observed without depth: ratio {ratio}"
    );
}

#[test]
fn reciprocal_test_accepts_overlapping_and_rejects_unrelated_keyframes() {
    let (a, b) = pair();
    let config = BackendConfig::default();
    let tracker = Sim3Tracker::new(config.clone());
    let ka = Keyframe::new(0, Arc::clone(&a.frame), Arc::clone(&a.depth)).expect("a");
    let kb = Keyframe::new(1, Arc::clone(&b.frame), Arc::clone(&b.depth)).expect("b");
    let good = reciprocal_test(
        &tracker,
        &ka,
        &kb,
        &Sim3::identity(),
        config.loop_closure_strictness,
    );
    eprintln!("overlapping pair: consistency {:.2}", good.consistency);
    let (forward, backward) = good
        .constraints
        .clone()
        .expect("overlapping views are accepted");
    assert_eq!(
        (forward.from, forward.to, backward.from, backward.to),
        (0, 1, 1, 0)
    );
    let truth = b.world_from_keyframe().inverse() * a.world_from_keyframe();
    let (angle, scale, _) = sim3_errors(&forward.to_from_from, &truth);
    assert!(angle < 0.3 && scale.abs() < 0.01, "{angle}° {scale}");

    // Unrelated views: the same viewpoint in a differently furnished and textured room (seed
    // 1), and the opposite wall of the same room. Both must be rejected, also when the
    // good-pixel test is disabled. (Measured: both fail at stage 0, where the first
    // Gauss–Newton step on level 4 is absurd, |δ|² ≥ 1, i.e. LSD-SLAM's divergence test.)
    let other_room = crate::dataset::synth::Scene::generate(1);
    let lenient = BackendConfig {
        min_good_ratio: 0.0,
        ..config.clone()
    };
    let lenient_tracker = Sim3Tracker::new(lenient.clone());
    for (id, yaw, room) in [(2, 0.0, &other_room), (3, 180.0, super::scene())] {
        let c = super::render_in(
            room,
            id,
            view(yaw, Vector3::new(0.0, 0.1, 0.0)),
            DepthScale::Normalised,
        );
        let kc = Keyframe::new(id as usize, Arc::clone(&c.frame), Arc::clone(&c.depth)).expect("c");
        for (name, t) in [
            ("default", &tracker),
            ("no good-ratio test", &lenient_tracker),
        ] {
            let bad = reciprocal_test(
                t,
                &ka,
                &kc,
                &Sim3::identity(),
                config.loop_closure_strictness,
            );
            eprintln!(
                "unrelated pair (yaw {yaw}°, {name}): stage {:?}, consistency {:.1}, good ratios \
                 {:?} / {:?}, diverged {:?}",
                bad.failed_stage,
                bad.consistency,
                bad.forward.as_ref().map(|r| r.good_ratio),
                bad.backward.as_ref().map(|r| r.good_ratio),
                bad.forward.as_ref().map(|r| r.diverged),
            );
            assert!(
                bad.constraints.is_none(),
                "unrelated views accepted ({name}): {bad:?}"
            );
            assert!(bad.failed_stage.is_some());
        }
    }
}

#[test]
fn reciprocal_consistency_is_chi_square_with_seven_degrees_of_freedom() {
    // Draw the two estimates from their own Gaussians around mutually inverse truths: with the
    // covariance propagated correctly (adjoint of the right transform) the Mahalanobis
    // distance of T_ba·T_ab from the identity is χ²(7), mean 7.
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut gauss = move || {
        let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let truth = Sim3::new(
        SO3::exp(&Vector3::new(0.4, -0.7, 1.1)),
        Vector3::new(0.8, -1.5, 0.6),
        2.5,
    );
    // Two different, correlated informations (A·Aᵀ + I scaled).
    let make_info = |seed: f64| {
        let a = crate::geometry::Matrix7::from_fn(|i, j| ((i * 7 + j) as f64 * seed).sin());
        (a * a.transpose() + crate::geometry::Matrix7::identity()) * 1e4
    };
    let (info_ba, info_ab) = (make_info(0.37), make_info(1.91));
    let chol_cov = |info: &crate::geometry::Matrix7| {
        info.try_inverse()
            .expect("invertible")
            .cholesky()
            .expect("SPD")
            .l()
    };
    let (l_ba, l_ab) = (chol_cov(&info_ba), chol_cov(&info_ab));
    let n = 4000;
    let mut sum = 0.0;
    for _ in 0..n {
        let d1 = l_ba * Vector7::from_fn(|_, _| gauss());
        let d2 = l_ab * Vector7::from_fn(|_, _| gauss());
        let b_from_a = truth * Sim3::exp(&d1);
        let a_from_b = truth.inverse() * Sim3::exp(&d2);
        sum += crate::graph::reciprocal_consistency(&b_from_a, &info_ba, &a_from_b, &info_ab)
            .expect("invertible");
    }
    let mean = sum / n as f64;
    // Standard error of the mean of χ²(7): sqrt(14 / 4000) ≈ 0.06.
    assert!((mean - 7.0).abs() < 0.3, "mean Mahalanobis distance {mean}");
}

/// Issue 37: the back end's working set holds the most recently used keyframes in full and
/// rebuilds the others from their compact form, identical to what was inserted.
#[test]
fn resident_set_evicts_the_least_recently_used_and_rebuilds_it_identical() {
    use crate::graph::resident::Resident;
    let (a, b) = pair();
    let ka = Keyframe::new(0, Arc::clone(&a.frame), Arc::clone(&a.depth)).expect("a");
    let kb = Keyframe::new(1, Arc::clone(&b.frame), Arc::clone(&b.depth)).expect("b");
    let (ca, cb) = (ka.compact(), kb.compact());
    assert!(
        ka.heap_bytes() > 3 * ca.heap_bytes(),
        "the compact form is small"
    );

    let mut resident = Resident::new(1);
    resident.insert(ka.clone());
    resident.insert(kb.clone());
    assert_eq!((resident.len(), resident.rebuilds()), (1, 0));
    // b is resident: no rebuild. a was evicted: rebuilt, and now b is out.
    assert!(Arc::ptr_eq(
        &resident.get(&cb).expect("b"),
        &resident.get(&cb).expect("b")
    ));
    assert_eq!(resident.rebuilds(), 0);
    let again = resident.get(&ca).expect("a");
    assert_eq!(resident.rebuilds(), 1);
    assert_eq!(*again.frame, *ka.frame);
    assert_eq!(again.levels, ka.levels);
    assert_eq!(again.thumbnail, ka.thumbnail);
    assert_eq!(resident.heap_bytes(), ka.heap_bytes());
    resident.get(&cb).expect("b");
    assert_eq!(resident.rebuilds(), 2);

    // Capacity 0 holds nothing and rebuilds on every use.
    let mut none = Resident::new(0);
    none.insert(ka);
    assert!(none.is_empty());
    none.get(&ca).expect("a");
    none.get(&ca).expect("a");
    assert_eq!((none.len(), none.rebuilds()), (0, 2));
}
