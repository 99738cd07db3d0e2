//! Tests of the depth filter on the synthetic orbit with exact depth and poses.

use std::time::Instant;

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::test_scene::{SynthScene, median, orbit_320, relative_errors, share_above};
use super::{DepthFilter, InverseDepth, MappingConfig, keyframe_score, needs_new_keyframe};
use crate::dataset::synth::Motion;
use crate::geometry::{SE3, SO3};
use crate::image::ImageF32;

/// Observes frames `range` (with regularisation after each, as LSD's mapping thread does).
fn observe_frames(
    f: &mut DepthFilter,
    s: &SynthScene,
    kf: usize,
    range: std::ops::RangeInclusive<usize>,
) {
    for i in range {
        f.observe(&s.frames[i], &s.relative(kf, i))
            .expect("observe");
        f.regularize();
    }
}

fn ground_truth_filter(s: &SynthScene, kf: usize) -> DepthFilter {
    let mut f = DepthFilter::new(s.frames[kf].clone(), MappingConfig::default()).expect("filter");
    let var = f.config().var_gt_init_initial;
    f.init_from_depth(&s.idepth(kf), var).expect("init");
    f
}

#[test]
fn mapping_random_init_converges_with_true_poses() {
    let s = orbit_320();
    let mut f = DepthFilter::new(s.frames[0].clone(), MappingConfig::default()).expect("filter");
    f.init_random(7);
    // Monocular scale is a gauge: LSD's tracking expresses poses in the scale of the random
    // map (mean inverse depth ≈ 1). Emulate that with true poses whose translations are
    // scaled by the scene's mean inverse depth.
    let gt_metric = s.idepth(0);
    let k = mean_idepth_where_estimated(&f, &gt_metric);
    let gt = scaled_image(&gt_metric, 1.0 / k as f32);
    let initial = relative_errors(&f.depth_map(), &gt);
    for i in 1..s.frames.len() {
        let mut pose = s.relative(0, i);
        pose.translation *= k;
        f.observe(&s.frames[i], &pose).expect("observe");
        f.regularize();
    }
    let map = f.depth_map();
    let errs = relative_errors(&map, &gt);
    let coverage = errs.len() as f64 / (map.width * map.height) as f64;
    let med = median(errs.clone());
    eprintln!(
        "random init (scale {k:.3}): median rel err {:.3} -> {med:.4}, coverage {coverage:.3}, >10%: {:.3}",
        median(initial),
        share_above(&errs, 0.1)
    );
    assert!(med < 0.05, "median relative inverse-depth error {med}");
    assert!(coverage >= 0.10, "only {coverage} of the pixels estimated");
    // Hypotheses never observed (gradient parallel to every epipolar line of this orbit)
    // keep their random value but also their large variance; the confident ones are right.
    let confident: Vec<f64> = map
        .pixels
        .iter()
        .zip(&gt.data)
        .filter_map(|(p, &g)| {
            p.estimate()
                .filter(|&(_, v)| v < 1e-3)
                .map(|(d, _)| f64::from((d - g).abs() / g))
        })
        .collect();
    eprintln!(
        "confident (var < 1e-3): {} estimates, median {:.4}, >10%: {:.4}",
        confident.len(),
        median(confident.clone()),
        share_above(&confident, 0.1)
    );
    assert!(
        confident.len() > errs.len() / 3,
        "most observed hypotheses become confident"
    );
    assert!(share_above(&confident, 0.1) < 0.05, "confident outliers");
}

/// Mean of `gt` over the pixels holding a hypothesis.
fn mean_idepth_where_estimated(f: &DepthFilter, gt: &ImageF32) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for y in 0..f.height() {
        for x in 0..f.width() {
            if f.raw_estimate(x, y).is_some() {
                sum += f64::from(gt.at(x, y));
                n += 1;
            }
        }
    }
    sum / n.max(1) as f64
}

fn scaled_image(img: &ImageF32, k: f32) -> ImageF32 {
    ImageF32::from_vec(
        img.width,
        img.height,
        img.data.iter().map(|v| v * k).collect(),
    )
    .expect("size")
}

#[test]
fn mapping_noisy_depth_init_improves_with_observations() {
    let s = orbit_320();
    let gt = s.idepth(0);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    // 10 % multiplicative Gaussian noise (Box–Muller).
    let noisy: Vec<f32> = gt
        .data
        .iter()
        .map(|&d| {
            let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
            let n = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
            d * (1.0 + 0.1 * n as f32)
        })
        .collect();
    let noisy = ImageF32::from_vec(gt.width, gt.height, noisy).expect("size");
    let mean_gt = gt.data.iter().map(|&d| f64::from(d)).sum::<f64>() / gt.data.len() as f64;
    let mut f = DepthFilter::new(s.frames[0].clone(), MappingConfig::default()).expect("filter");
    f.init_from_depth(&noisy, (0.1 * mean_gt as f32).powi(2))
        .expect("init");
    let before = median(relative_errors(&f.depth_map(), &gt));
    let n_before = f.num_estimates();
    observe_frames(&mut f, s, 0, 1..=20);
    let errs = relative_errors(&f.depth_map(), &gt);
    let after = median(errs.clone());
    eprintln!(
        "noisy init: median rel err {before:.4} -> {after:.4}, {n_before} -> {} estimates",
        errs.len()
    );
    assert!(
        before > 0.05,
        "the noise must be visible before observing ({before})"
    );
    assert!(
        after < 0.5 * before,
        "observations must at least halve the error: {before} -> {after}"
    );
    assert!(
        errs.len() as f64 > 0.5 * n_before as f64,
        "most estimates must survive"
    );
}

#[test]
fn mapping_propagation_keeps_estimates_consistent_with_new_keyframe() {
    let s = orbit_320();
    let mut f = ground_truth_filter(s, 0);
    observe_frames(&mut f, s, 0, 1..=5);
    let n_old = f.num_estimates();
    let new_kf = 15;
    let t0 = Instant::now();
    let mut g = f
        .propagate_to(s.frames[new_kf].clone(), &s.relative(new_kf, 0))
        .expect("propagate");
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let errs = relative_errors(&g.depth_map(), &s.idepth(new_kf));
    let med = median(errs.clone());
    eprintln!(
        "propagation: {n_old} -> {} estimates, median rel err {med:.4}, >5%: {:.3}, {ms:.1} ms",
        errs.len(),
        share_above(&errs, 0.05)
    );
    assert!(med < 0.02, "median relative error after propagation {med}");
    assert!(share_above(&errs, 0.1) < 0.05, "propagated outliers");
    assert!(
        errs.len() as f64 > 0.4 * n_old as f64,
        "too few estimates survive propagation"
    );
    // The new map keeps fusing observations consistently with its own ground truth.
    observe_frames(&mut g, s, new_kf, new_kf + 1..=new_kf + 5);
    let med2 = median(relative_errors(&g.depth_map(), &s.idepth(new_kf)));
    assert!(med2 < 0.02, "after observing on the new keyframe {med2}");

    // Scale normalisation: mean published inverse depth becomes 1 and all values scale alike.
    let before = g.depth_map();
    let factor = g.normalize_scale();
    let after = g.depth_map();
    let mean = after.mean_idepth().expect("estimates");
    assert!(
        (mean - 1.0).abs() < 0.02,
        "mean inverse depth after normalisation {mean}"
    );
    assert!((factor * before.mean_idepth().expect("estimates") - 1.0).abs() < 0.02);
    for (a, b) in before.pixels.iter().zip(&after.pixels) {
        if let (Some((da, va)), Some((db, vb))) = (a.estimate(), b.estimate()) {
            assert!((f64::from(db) - factor * f64::from(da)).abs() < 1e-4 * f64::from(db).max(1.0));
            assert!(
                (f64::from(vb) - factor * factor * f64::from(va)).abs()
                    <= 1e-4 * f64::from(vb).max(1e-6)
            );
        }
    }
}

#[test]
fn mapping_regularize_removes_injected_outlier_and_isolated_points() {
    let s = orbit_320();
    let mut f = ground_truth_filter(s, 0);
    f.regularize();
    let (w, h) = (f.width(), f.height());
    // A pixel whose whole 5×5 neighbourhood holds estimates.
    let full = |x: usize, y: usize| {
        (y - 2..=y + 2).all(|ny| (x - 2..=x + 2).all(|nx| f.raw_estimate(nx, ny).is_some()))
    };
    let (ox, oy) = (10..h - 10)
        .flat_map(|y| (10..w - 10).map(move |x| (x, y)))
        .find(|&(x, y)| full(x, y))
        .expect("a fully estimated 5x5 patch");
    // And an empty 5×5 region for an isolated point.
    let empty = |x: usize, y: usize| {
        (y - 2..=y + 2).all(|ny| (x - 2..=x + 2).all(|nx| f.raw_estimate(nx, ny).is_none()))
    };
    let (ix, iy) = (10..h - 10)
        .flat_map(|y| (10..w - 10).map(move |x| (x, y)))
        .find(|&(x, y)| empty(x, y))
        .expect("an empty 5x5 patch");
    let gt = s.idepth(0);
    let true_d = gt.at(ox, oy);
    f.set_estimate(ox, oy, 3.0 * true_d, 1e-4, 20);
    f.set_estimate(ix, iy, 0.7, 1e-4, 5);
    f.regularize();
    let map = f.depth_map();
    assert_eq!(
        map.at(ox, oy),
        InverseDepth::Unknown,
        "the outlier must be removed"
    );
    assert_eq!(
        map.at(ix, iy),
        InverseDepth::Unknown,
        "the isolated point must be removed"
    );
    // Its neighbours were not dragged towards it.
    for ny in oy - 2..=oy + 2 {
        for nx in ox - 2..=ox + 2 {
            if (nx, ny) == (ox, oy) {
                continue;
            }
            let (d, _) = map.at(nx, ny).estimate().expect("neighbours survive");
            let g = gt.at(nx, ny);
            assert!(
                (d - g).abs() < 0.02 * g,
                "neighbour ({nx},{ny}): {d} vs {g}"
            );
        }
    }
}

#[test]
fn mapping_tiny_baseline_observations_do_not_move_estimates() {
    let s = orbit_320();
    let mut f = ground_truth_filter(s, 0);
    observe_frames(&mut f, s, 0, 1..=3);
    let snapshot: Vec<_> = (0..f.height())
        .flat_map(|y| (0..f.width()).map(move |x| (x, y)))
        .map(|(x, y)| f.raw_estimate(x, y))
        .collect();
    let tiny = [
        SE3::identity(),
        SE3::new(
            SO3::exp(&Vector3::new(0.0, 0.01, 0.0)),
            Vector3::new(1e-4, 0.0, 0.0),
        ),
        SE3::new(SO3::identity(), Vector3::new(0.0, 2e-4, 1e-4)),
    ];
    // Frames with ids after the ones observed; the keyframe image itself (no parallax).
    for (k, pose) in tiny.iter().enumerate() {
        let frame = crate::frame::Frame::new(
            100 + k as u64,
            0.0,
            s.camera,
            &s.frames[0].level(0).image,
            None,
        )
        .expect("frame");
        let stats = f.observe(&frame, pose).expect("observe");
        assert_eq!(
            stats.updated + stats.created + stats.inconsistent + stats.failed,
            0,
            "{stats:?}"
        );
        assert!(stats.skipped_epl > 0);
    }
    let after: Vec<_> = (0..f.height())
        .flat_map(|y| (0..f.width()).map(move |x| (x, y)))
        .map(|(x, y)| f.raw_estimate(x, y))
        .collect();
    assert_eq!(snapshot, after);
}

#[test]
fn mapping_init_from_depth_uses_only_textured_pixels() {
    let s = orbit_320();
    let mut f = DepthFilter::new(s.frames[0].clone(), MappingConfig::default()).expect("filter");
    let gt = s.idepth(0);
    f.init_from_depth(&gt, 1e-4).expect("init");
    let grad = &s.frames[0].level(0).grad_mag;
    let (w, h) = (f.width(), f.height());
    let mut textured = 0;
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let max = (y - 1..=y + 1)
                .flat_map(|ny| (x - 1..=x + 1).map(move |nx| grad.at(nx, ny)))
                .fold(0.0f32, f32::max);
            let has = f.raw_estimate(x, y).is_some();
            assert_eq!(has, max >= f.config().min_use_grad, "({x},{y}) grad {max}");
            textured += usize::from(has);
        }
    }
    assert!(textured > w * h / 10, "the synthetic room is textured");
    assert!(
        f.init_from_depth(&ImageF32::filled(4, 4, 1.0), 1e-4)
            .is_err()
    );
    assert!(f.init_from_depth(&gt, 0.0).is_err());
}

#[test]
fn mapping_config_roundtrips_and_rejects_unknown_fields() {
    let cfg = MappingConfig::default();
    assert_eq!((cfg.kf_dist_weight, cfg.kf_usage_weight), (7.5, 7.5));
    assert_eq!(
        (cfg.min_use_grad, cfg.max_var, cfg.var_random_init_initial),
        (5.0, 0.25, 0.125)
    );
    let json = serde_json::to_string(&cfg).expect("serialise");
    let back: MappingConfig = serde_json::from_str(&json).expect("deserialise");
    assert_eq!(back, cfg);
    let partial: MappingConfig = toml::from_str("min_use_grad = 1.0").expect("partial config");
    assert_eq!(partial.min_use_grad, 1.0);
    assert_eq!(partial.max_error_stereo, cfg.max_error_stereo);
    assert!(toml::from_str::<MappingConfig>("min_use_gradient = 1.0").is_err());
    let bad = MappingConfig {
        max_var: -1.0,
        ..cfg
    };
    assert!(bad.validate().is_err());
    let s = orbit_320();
    assert!(DepthFilter::new(s.frames[0].clone(), bad).is_err());
}

#[test]
fn mapping_keyframe_selection_on_the_orbit() {
    let s = orbit_320();
    let cfg = MappingConfig::default();
    let mean = ground_truth_filter(s, 0)
        .depth_map()
        .mean_idepth()
        .expect("estimates");
    let score = |i: usize| keyframe_score(&cfg, &s.relative(0, i), mean, 1.0);
    let fired: Vec<bool> = (0..s.frames.len())
        .map(|i| needs_new_keyframe(&cfg, &s.relative(0, i), mean, 1.0, 10, 20))
        .collect();
    let first = fired
        .iter()
        .position(|&b| b)
        .expect("the orbit moves far enough");
    eprintln!(
        "orbit: mean idepth {mean:.3}, first new keyframe at frame {first} (score {:.3})",
        score(first)
    );
    assert!(first > 10, "a keyframe after {first} frames is too early");
    assert!(score(first - 1) <= 1.0 && score(first) > 1.0);
    // Half the overlap lost triggers immediately, but not while the keyframe is young.
    assert!(needs_new_keyframe(
        &cfg,
        &s.relative(0, 1),
        mean,
        0.5,
        10,
        20
    ));
    assert!(!needs_new_keyframe(
        &cfg,
        &s.relative(0, 1),
        mean,
        0.5,
        10,
        3
    ));
}

/// Times observe / regularise / propagate on a converging map of `w × h` frames.
fn time_filter(s: &SynthScene) -> (f64, f64, f64, usize) {
    let mut f = DepthFilter::new(s.frames[0].clone(), MappingConfig::default()).expect("filter");
    f.init_random(1);
    let (mut t_obs, mut t_reg, mut n) = (0.0, 0.0, 0usize);
    for i in 1..s.frames.len() {
        let t = Instant::now();
        f.observe(&s.frames[i], &s.relative(0, i)).expect("observe");
        let t1 = Instant::now();
        f.regularize();
        // The first observations run on the random initialisation; time the steady state.
        if i > 3 {
            t_obs += (t1 - t).as_secs_f64();
            t_reg += t1.elapsed().as_secs_f64();
            n += 1;
        }
    }
    let last = s.frames.len() - 1;
    let t = Instant::now();
    let _g = f
        .propagate_to(s.frames[last].clone(), &s.relative(last, 0))
        .expect("propagate");
    let t_prop = t.elapsed().as_secs_f64();
    let k = n.max(1) as f64;
    (
        t_obs / k * 1e3,
        t_reg / k * 1e3,
        t_prop * 1e3,
        f.num_estimates(),
    )
}

#[test]
fn mapping_timing_320x240() {
    let (obs, reg, prop, n) = time_filter(orbit_320());
    eprintln!(
        "320x240: observe {obs:.2} ms, regularize {reg:.2} ms, propagate {prop:.2} ms, {n} hypotheses"
    );
    assert!(n > 0);
}

/// 640×480 timing (renders 12 frames, ~30 s): `cargo test -p relfusion-slam --
/// --ignored mapping_timing_640x480 --nocapture`.
#[test]
#[ignore]
fn mapping_timing_640x480() {
    let s = SynthScene::render(Motion::Orbit, 12, 640, 480);
    let (obs, reg, prop, n) = time_filter(&s);
    eprintln!(
        "640x480: observe {obs:.2} ms, regularize {reg:.2} ms, propagate {prop:.2} ms, {n} hypotheses"
    );
    assert!(n > 0);
}

/// CPU time of the calling thread, ns (Linux `schedstat`): unaffected by other processes.
fn thread_cpu_ns() -> u64 {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").expect("schedstat");
    s.split_whitespace()
        .next()
        .and_then(|v| v.parse().ok())
        .expect("run time in ns")
}

/// Single-thread CPU cost per hypothesis / per search (Linux only): `cargo test -p
/// relfusion-slam -- --ignored mapping_bench_cpu_time --nocapture`.
#[test]
#[ignore]
fn mapping_bench_cpu_time() {
    let s = orbit_320();
    let cfg = MappingConfig {
        threads: 1,
        ..MappingConfig::default()
    };
    let mut f = DepthFilter::new(s.frames[0].clone(), cfg).expect("filter");
    f.init_from_depth(&s.idepth(0), 1e-4).expect("init");
    let n = f.num_estimates() as f64;
    let reps = 30;
    let t0 = thread_cpu_ns();
    for _ in 0..reps {
        f.regularize();
    }
    let per_reg = (thread_cpu_ns() - t0) as f64 / f64::from(reps);
    let mut g = f.clone();
    g.init_random(3);
    let (mut cpu, mut searches) = (0u64, 0usize);
    for i in 1..20 {
        let t = thread_cpu_ns();
        let st = g.observe(&s.frames[i], &s.relative(0, i)).expect("observe");
        cpu += thread_cpu_ns() - t;
        searches += st.update_attempted + st.create_attempted;
        g.regularize();
    }
    eprintln!(
        "1 thread: regularize {:.2} ms ({:.1} ns/hypothesis, {n} hypotheses); observe {:.0} ns/search, \
         {:.2} ms/frame ({} searches/frame)",
        per_reg / 1e6,
        per_reg / n,
        cpu as f64 / searches as f64,
        cpu as f64 / 19.0 / 1e6,
        searches / 19
    );
    assert!(searches > 0);
}
