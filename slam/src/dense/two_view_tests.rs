//! Tests of `two_view`.

use super::*;
use crate::dense::gpu_warp::GpuWarp;
use crate::frame::Frame;
use crate::geometry::SO3;
use crate::gpu::{GpuConfig, GpuContext};
use crate::graph::points::KeyframeLevels;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use std::sync::Arc;

fn camera(w: u32, h: u32, f: f64) -> PinholeCamera {
    PinholeCamera::new(
        f,
        f,
        0.5 * (f64::from(w) - 1.0),
        0.5 * (f64::from(h) - 1.0),
        w,
        h,
    )
    .expect("valid camera")
}

/// Inverse depth of the plane `n·p = 1` seen by `camera`: `d(x) = n·K⁻¹x̃`.
fn plane_idepth(camera: &PinholeCamera, n: &Vector3<f64>) -> ImageF32 {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let q = camera.pixel_to_normalized(&Vector2::new(x as f64, y as f64));
            *out.at_mut(x, y) = (n.x * q.x + n.y * q.y + n.z) as f32;
        }
    }
    out
}

/// The plane `n·p = 1` of the source frame in the target frame of `dst_from_src`.
fn moved_plane(n: &Vector3<f64>, dst_from_src: &Sim3) -> Vector3<f64> {
    let rn = dst_from_src.rotation.act(n);
    rn / (dst_from_src.scale + rn.dot(&dst_from_src.translation))
}

/// Inverse depths in [0.3, 3] (the keyframe gauge has mean 1) with `holes` of them 0.
pub(crate) fn random_idepth(w: usize, h: usize, holes: f64, rng: &mut impl Rng) -> ImageF32 {
    let data = (0..w * h)
        .map(|_| {
            if rng.random_bool(holes) {
                0.0
            } else {
                rng.random_range(0.3f32..3.0)
            }
        })
        .collect();
    ImageF32::from_vec(w, h, data).expect("sizes match")
}

#[test]
fn identity_warp_returns_the_input() {
    let cam = camera(97, 33, 80.0);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut src = random_idepth(97, 33, 0.3, &mut rng);
    src.data[0] = f32::NAN;
    src.data[1] = -0.5;
    src.data[2] = f32::INFINITY;
    let out = warp_inverse_depth_cpu(&src, None, &cam, &Sim3::identity()).expect("warp");
    for (i, (&s, &o)) in src.data.iter().zip(&out.data).enumerate() {
        let expected = if s > 0.0 && s.is_finite() { s } else { 0.0 };
        assert_eq!(o, expected, "pixel {i}");
    }
}

#[test]
fn translated_fronto_parallel_plane_has_the_analytic_inverse_depth() {
    let cam = camera(64, 48, 50.0);
    let d0 = 1.25;
    let src = ImageF32::filled(64, 48, d0 as f32);
    // Scale included: the target's gauge is s× the source's.
    let pose = Sim3::new(SO3::identity(), Vector3::new(0.03, -0.02, 0.05), 1.1);
    let out = warp_inverse_depth_cpu(&src, None, &cam, &pose).expect("warp");
    let z_target = pose.scale / d0 + pose.translation.z;
    let expected = (1.0 / z_target) as f32;
    let (mut inside, mut outside) = (0, 0);
    for y in 0..48 {
        for x in 0..64 {
            // Back-project the target pixel onto the plane and find its source pixel.
            let p_dst = cam.unproject(&Vector2::new(f64::from(x), f64::from(y)), z_target);
            let p_src = pose.inverse().act(&p_dst);
            assert!((p_src.z - 1.0 / d0).abs() < 1e-12);
            let uv = cam.project(&p_src);
            let value = out.at(x as usize, y as usize);
            if uv.x > 1.0 && uv.y > 1.0 && uv.x < 62.0 && uv.y < 46.0 {
                inside += 1;
                // The image shrinks (magnification 0.95): every such pixel is hit.
                assert!(
                    (value - expected).abs() <= 2.0 * f32::EPSILON * expected,
                    "({x}, {y}): {value} vs {expected}"
                );
            } else if uv.x < -1.0 || uv.y < -1.0 || uv.x > 64.0 || uv.y > 48.0 {
                outside += 1;
                assert_eq!(value, 0.0, "({x}, {y}) sees no source pixel");
            }
        }
    }
    assert!(
        inside > 2000 && outside > 50,
        "{inside} inside, {outside} outside"
    );
}

#[test]
fn nearest_surface_wins_and_exclusion_and_disocclusion_leave_holes() {
    // A 20×1 scan line: background at depth 1, pixels 10..=12 at depth 0.5. Moving the
    // points by 0.1 along x shifts the background by fx·0.1·d = 1 pixel and the near strip
    // by 2 pixels.
    let cam = camera(20, 1, 10.0);
    let mut src = ImageF32::filled(20, 1, 1.0);
    for x in 10..=12 {
        src.data[x] = 2.0;
    }
    let pose = Sim3::new(SO3::identity(), Vector3::new(0.1, 0.0, 0.0), 1.0);
    let out = warp_inverse_depth_cpu(&src, None, &cam, &pose).expect("warp");
    let mut expected = vec![1.0f32; 20];
    expected[0] = 0.0; // nothing lands left of the first pixel's target
    expected[11] = 0.0; // disoccluded: behind the near strip's old place
    expected[12..=14].fill(2.0); // near strip; 13 and 14 also receive the background
    for (x, (&o, &e)) in out.data.iter().zip(&expected).enumerate() {
        assert!((o - e).abs() < 1e-6, "x = {x}: {o} vs {e}");
    }
    // Excluding near pixel 12: background pixel 13 is the only one left on target 14.
    let mut exclude = ImageF32::filled(20, 1, 0.0);
    exclude.data[12] = 1.0;
    let out = warp_inverse_depth_cpu(&src, Some(&exclude), &cam, &pose).expect("warp");
    assert!((out.data[14] - 1.0).abs() < 1e-6, "{}", out.data[14]);
    assert!((out.data[13] - 2.0).abs() < 1e-6, "{}", out.data[13]);
}

#[test]
fn points_behind_or_at_the_camera_are_dropped() {
    let cam = camera(16, 12, 12.0);
    let src = ImageF32::filled(16, 12, 1.0);
    for tz in [-1.5, -0.9995] {
        let pose = Sim3::new(SO3::identity(), Vector3::new(0.0, 0.0, tz), 1.0);
        let out = warp_inverse_depth_cpu(&src, None, &cam, &pose).expect("warp");
        assert!(out.data.iter().all(|&v| v == 0.0), "tz = {tz}");
    }
    let wrong = ImageF32::filled(15, 12, 1.0);
    assert!(matches!(
        warp_inverse_depth_cpu(&wrong, None, &cam, &Sim3::identity()),
        Err(Error::Shape(_))
    ));
}

#[test]
fn idepth_jacobian_matches_numeric_differences() {
    let cam = PinholeCamera::new(260.0, 255.0, 158.3, 121.7, 320, 240).expect("camera");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    for _ in 0..50 {
        let (x, y) = (rng.random_range(0.0..320.0), rng.random_range(0.0..240.0));
        let d = rng.random_range(0.2..4.0);
        // Any keyframe pose: the derivative is taken in the keyframe's tangent space.
        let world_from_kf = Sim3::exp(&Vector7::from_fn(|_, _| rng.random_range(-1.0..1.0)));
        let p_world = world_from_kf.act(&cam.unproject(&Vector2::new(x, y), 1.0 / d));
        let idepth_after = |delta: &Vector7| {
            let moved = world_from_kf * Sim3::exp(delta);
            1.0 / moved.inverse().act(&p_world).z
        };
        const H: f64 = 1e-6;
        let numeric = Vector7::from_fn(|k, _| {
            let mut e = Vector7::zeros();
            e[k] = H;
            (idepth_after(&e) - idepth_after(&-e)) / (2.0 * H)
        });
        let analytic = idepth_pose_jacobian(&cam, x, y, d);
        let err = (numeric - analytic).norm();
        assert!(
            err < 1e-6 * (1.0 + analytic.norm()),
            "pixel ({x}, {y}), d = {d}: analytic {analytic:?} numeric {numeric:?}"
        );
    }
}

#[test]
fn pose_variance_propagates_the_covariance() {
    let cam = PinholeCamera::new(200.0, 190.0, 40.3, 30.1, 80, 60).expect("camera");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    let idepth = random_idepth(80, 60, 0.2, &mut rng);
    let a = Matrix7::from_fn(|_, _| rng.random_range(-0.01..0.01));
    let sigma = a * a.transpose() + Matrix7::identity() * 1e-6;
    let var = pose_variance(&idepth, &cam, &sigma);
    for y in 0..60 {
        for x in 0..80 {
            let d = idepth.at(x, y);
            let v = var.at(x, y);
            if d == 0.0 {
                assert_eq!(v, 0.0);
                continue;
            }
            let j = idepth_pose_jacobian(&cam, x as f64, y as f64, f64::from(d));
            let expected = j.dot(&(sigma * j));
            assert!(v > 0.0 && (f64::from(v) - expected).abs() <= 1e-6 * expected);
        }
    }
    // Pure scale uncertainty σ_s: the inverse depth's relative standard deviation is σ_s.
    let mut scale_only = Matrix7::zeros();
    scale_only[(6, 6)] = 0.01f64.powi(2);
    let var = pose_variance(&idepth, &cam, &scale_only);
    for (&d, &v) in idepth.data.iter().zip(&var.data) {
        let expected = (0.01 * d) * (0.01 * d);
        assert!(
            (v - expected).abs() <= 1e-5 * expected.max(1e-12),
            "{v} vs {expected}"
        );
    }
}

/// Two views of the slanted plane `n·p = 1` (prev) with exact dense maps, and semi-dense
/// pixels on a grid of lines painted on the plane (the same 3-D lines in both views).
struct PlaneScene {
    camera: PinholeCamera,
    cur_from_prev: Sim3,
    prev_semi: ImageF32,
    prev_dense: ImageF32,
    cur_semi: ImageF32,
    cur_semi_var: ImageF32,
    cur_dense: ImageF32,
}

fn plane_scene() -> PlaneScene {
    let camera = camera(320, 240, 260.0);
    let n_prev = Vector3::new(0.1, -0.05, 1.0);
    let cur_from_prev = Sim3::new(
        SO3::exp(&Vector3::new(0.02, -0.03, 0.01)),
        Vector3::new(0.05, -0.02, 0.03),
        1.05,
    );
    let n_cur = moved_plane(&n_prev, &cur_from_prev);
    let prev_dense = plane_idepth(&camera, &n_prev);
    let cur_dense = plane_idepth(&camera, &n_cur);
    // Lines 1/12 apart, 30 % of the plane.
    let on_line = |p: &Vector3<f64>| {
        (p.x * 12.0).rem_euclid(1.0) < 0.15 || (p.y * 12.0).rem_euclid(1.0) < 0.15
    };
    let semi = |dense: &ImageF32, prev_from_view: &Sim3| {
        let mut out = ImageF32::filled(320, 240, 0.0);
        for y in 0..240 {
            for x in 0..320 {
                let d = f64::from(dense.at(x, y));
                let p = camera.unproject(&Vector2::new(x as f64, y as f64), 1.0 / d);
                if on_line(&prev_from_view.act(&p)) {
                    *out.at_mut(x, y) = dense.at(x, y);
                }
            }
        }
        out
    };
    let prev_semi = semi(&prev_dense, &Sim3::identity());
    let cur_semi = semi(&cur_dense, &cur_from_prev.inverse());
    let cur_semi_var = ImageF32::from_vec(
        320,
        240,
        cur_semi
            .data
            .iter()
            .map(|&d| if d > 0.0 { 1e-3 } else { 0.0 })
            .collect(),
    )
    .expect("size");
    PlaneScene {
        camera,
        cur_from_prev,
        prev_semi,
        prev_dense,
        cur_semi,
        cur_semi_var,
        cur_dense,
    }
}

fn inputs<'a>(
    s: &'a PlaneScene,
    cur_semi: &'a ImageF32,
    cur_dense: &'a ImageF32,
) -> TwoViewInputs<'a> {
    let mut pose_covariance = Matrix7::identity() * 1e-6;
    pose_covariance[(6, 6)] = 1e-4;
    TwoViewInputs {
        camera: &s.camera,
        prev_semi: &s.prev_semi,
        prev_dense: &s.prev_dense,
        cur_semi,
        cur_semi_var: &s.cur_semi_var,
        cur_dense,
        cur_from_prev: s.cur_from_prev,
        pose_covariance,
    }
}

/// (semi-dense pixels with a warped counterpart, dense ones) of the current keyframe,
/// restricted to `region`.
fn overlapping(s: &PlaneScene, region: &dyn Fn(usize) -> bool) -> (usize, usize) {
    let warped_semi =
        warp_inverse_depth_cpu(&s.prev_semi, None, &s.camera, &s.cur_from_prev).expect("warp");
    let warped_dense = warp_inverse_depth_cpu(
        &s.prev_dense,
        Some(&s.prev_semi),
        &s.camera,
        &s.cur_from_prev,
    )
    .expect("warp");
    let (mut semi, mut dense) = (0, 0);
    for i in (0..320 * 240).filter(|&i| region(i)) {
        if s.cur_semi.data[i] > 0.0 {
            semi += usize::from(warped_semi.data[i] > 0.0);
        } else {
            dense += usize::from(warped_dense.data[i] > 0.0);
        }
    }
    (semi, dense)
}

fn check_plane_result(s: &PlaneScene, result: &TwoViewResult) {
    let (semi, dense) = overlapping(s, &|_| true);
    let semi_total = s.cur_semi.data.iter().filter(|&&d| d > 0.0).count();
    assert!(
        semi > semi_total / 2 && dense > 320 * 240 / 3,
        "overlap: {semi} of {semi_total} semi-dense, {dense} dense"
    );
    assert!(
        result.consistent_semi as f64 >= 0.95 * semi as f64
            && result.consistent_dense as f64 >= 0.95 * dense as f64,
        "kept {}/{semi} semi-dense and {}/{dense} dense",
        result.consistent_semi,
        result.consistent_dense
    );
    let expected_var = pose_variance(
        &s.cur_dense,
        &s.camera,
        &inputs(s, &s.cur_semi, &s.cur_dense).pose_covariance,
    );
    assert_eq!(result.dense_variance, expected_var);
    for i in 0..320 * 240 {
        let d = result.idepth.data[i];
        if d == 0.0 {
            assert_eq!(result.variance.data[i], 0.0);
        } else if s.cur_semi.data[i] > 0.0 {
            assert_eq!((d, result.variance.data[i]), (s.cur_semi.data[i], 1e-3));
        } else {
            assert_eq!(
                (d, result.variance.data[i]),
                (s.cur_dense.data[i], expected_var.data[i])
            );
        }
    }
}

#[test]
fn consistent_plane_is_kept_and_corrupted_depth_is_rejected() {
    let s = plane_scene();
    let params = TwoViewParams::default();
    let result = two_view_consistency(&inputs(&s, &s.cur_semi, &s.cur_dense), &params, &CpuWarp)
        .expect("two-view");
    check_plane_result(&s, &result);

    // 1 % inverse-depth error in a block of the current keyframe (both maps).
    let in_block = |i: usize| (100..180).contains(&(i % 320)) && (60..140).contains(&(i / 320));
    let corrupt = |m: &ImageF32| {
        let mut m = m.clone();
        for (i, v) in m.data.iter_mut().enumerate() {
            if in_block(i) {
                *v *= 1.01;
            }
        }
        m
    };
    let (bad_semi, bad_dense) = (corrupt(&s.cur_semi), corrupt(&s.cur_dense));
    let result = two_view_consistency(&inputs(&s, &bad_semi, &bad_dense), &params, &CpuWarp)
        .expect("two-view");
    let kept_in_block = (0..320 * 240)
        .filter(|&i| in_block(i) && result.idepth.data[i] > 0.0)
        .count();
    assert_eq!(kept_in_block, 0, "corrupted pixels kept");
    let (semi_out, dense_out) = overlapping(&s, &|i| !in_block(i));
    let kept_out = (0..320 * 240)
        .filter(|&i| !in_block(i) && result.idepth.data[i] > 0.0)
        .count();
    assert!(
        kept_out as f64 >= 0.95 * (semi_out + dense_out) as f64,
        "outside the block: kept {kept_out} of {}",
        semi_out + dense_out
    );
    // The block's pixels did overlap, so the test above could have failed.
    let (semi_in, dense_in) = overlapping(&s, &in_block);
    assert!(semi_in + dense_in > 4000, "{semi_in} + {dense_in}");
}

#[test]
fn consistency_on_the_gpu_matches_the_cpu() {
    let ctx = Arc::new(
        GpuContext::new(&GpuConfig::default()).unwrap_or_else(|e| panic!("no GPU context: {e}")),
    );
    let gpu = GpuWarp::new(ctx).expect("kernel compiles");
    let s = plane_scene();
    let params = TwoViewParams::default();
    let inputs = inputs(&s, &s.cur_semi, &s.cur_dense);
    let cpu = two_view_consistency(&inputs, &params, &CpuWarp).expect("cpu");
    let on_gpu = two_view_consistency(&inputs, &params, &gpu).expect("gpu");
    check_plane_result(&s, &on_gpu);
    let differ = cpu
        .idepth
        .data
        .iter()
        .zip(&on_gpu.idepth.data)
        .filter(|(a, b)| a != b)
        .count();
    assert!(differ <= 320 * 240 / 1000, "{differ} pixels differ");
}

#[test]
fn depth_map_upsampling_round_trips_and_feeds_the_back_end_pyramid() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
    let idepth = random_idepth(320, 240, 0.4, &mut rng);
    let mut variance = ImageF32::from_vec(
        320,
        240,
        (0..320 * 240)
            .map(|_| rng.random_range(1e-5f32..1e-2))
            .collect(),
    )
    .expect("size");
    // Some kept depths without a usable variance: they must become Unknown.
    for i in (0..320 * 240).step_by(97) {
        variance.data[i] = if i % 2 == 0 { 0.0 } else { f32::NAN };
    }
    let valid =
        |i: usize| idepth.data[i] > 0.0 && variance.data[i] > 0.0 && variance.data[i].is_finite();

    for (w, h) in [(640, 480), (320, 240)] {
        let map = to_depth_map(&idepth, &variance, w, h).expect("upsample");
        assert_eq!((map.width, map.height, map.pixels.len()), (w, h, w * h));
        let (fx, fy) = (w / 320, h / 240);
        for y in 0..h {
            for x in 0..w {
                let i = (y / fy) * 320 + x / fx;
                let expected = if valid(i) {
                    InverseDepth::Estimate {
                        idepth: idepth.data[i],
                        var: variance.data[i],
                    }
                } else {
                    InverseDepth::Unknown
                };
                assert_eq!(map.at(x, y), expected, "{w}x{h} at ({x}, {y})");
            }
        }
        let n_valid = (0..320 * 240).filter(|&i| valid(i)).count();
        assert_eq!(map.num_estimates(), n_valid * fx * fy);
    }

    // The back end's depth pyramid of a 640×480 keyframe: level 1 is the working map again.
    let full_cam = camera(640, 480, 520.0);
    let gray = ImageF32::from_vec(
        640,
        480,
        (0..640 * 480)
            .map(|_| rng.random_range(0.0f32..255.0))
            .collect(),
    )
    .expect("size");
    let frame = Frame::new(0, 0.0, full_cam, &gray, None).expect("frame");
    let map = to_depth_map(&idepth, &variance, 640, 480).expect("upsample");
    let levels = KeyframeLevels::new(&frame, &map).expect("levels");
    let level1 = &levels.levels[1].depth;
    assert_eq!((level1.width, level1.height), (320, 240));
    for i in 0..320 * 240 {
        if valid(i) {
            let (d, v) = (level1.idepth[i], level1.var[i]);
            assert!(
                (d - idepth.data[i]).abs() <= f32::EPSILON * d
                    && (v - variance.data[i]).abs() <= f32::EPSILON * v,
                "pixel {i}: ({d}, {v}) vs ({}, {})",
                idepth.data[i],
                variance.data[i]
            );
        } else {
            assert!(level1.var[i] <= 0.0, "pixel {i} should hold no estimate");
        }
    }

    assert!(matches!(
        to_depth_map(&idepth, &ImageF32::filled(320, 239, 1.0), 640, 480),
        Err(Error::Shape(_))
    ));
    assert!(matches!(
        to_depth_map(&idepth, &variance, 0, 480),
        Err(Error::Shape(_))
    ));
}

#[test]
fn sensor_depth_takes_the_keyframe_gauge_and_the_sensor_shape() {
    let (w, h) = (32, 24);
    let depth = ImageF32::from_vec(
        w,
        h,
        (0..w * h)
            .map(|i| {
                if i % 11 == 0 {
                    0.0
                } else {
                    0.5 + (i % 97) as f32 * 0.03
                }
            })
            .collect(),
    )
    .expect("depth");
    // Semi-dense estimates on every third pixel: the truth in a gauge 2.5× the metric
    // inverse depth, with a few gross outliers that the median ignores.
    let gauge = 2.5;
    let mut semi = DepthMap::unknown(w, h);
    for (i, p) in semi.pixels.iter_mut().enumerate() {
        let d = depth.data[i];
        if i % 3 == 0 && d > 0.0 {
            let idepth = if i % 30 == 0 { 40.0 } else { gauge / d };
            *p = InverseDepth::Estimate { idepth, var: 0.1 };
        }
    }
    let map = sensor_depth_map(&semi, &depth)
        .expect("same size")
        .expect("enough pixels");
    for (p, &d) in map.pixels.iter().zip(&depth.data) {
        match p.estimate() {
            Some((idepth, var)) => {
                assert!(
                    (idepth - gauge / d).abs() < 1e-5 * idepth,
                    "{idepth} vs {d}"
                );
                let sd = SENSOR_DEPTH_REL_SD * idepth;
                assert!((var - sd * sd).abs() < 1e-6 * var);
            }
            None => assert!(d < MIN_SENSOR_DEPTH, "pixel with depth {d} left out"),
        }
    }

    // Too little overlap gives no map; a wrong size is an error.
    let mut sparse = DepthMap::unknown(w, h);
    sparse.pixels[1] = InverseDepth::Estimate {
        idepth: 1.0,
        var: 0.1,
    };
    assert!(
        sensor_depth_map(&sparse, &depth)
            .expect("same size")
            .is_none()
    );
    let small = ImageF32::filled(w - 1, h, 1.0);
    assert!(matches!(
        sensor_depth_map(&semi, &small),
        Err(Error::Shape(_))
    ));
}
