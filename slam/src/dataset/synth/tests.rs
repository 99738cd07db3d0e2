//! Tests of the synthetic sequence renderer: determinism, exact depth, the TUM round trip,
//! texture statistics and the motion presets' bounds.

use super::*;
use crate::dataset::tum::TumSequence;
use nalgebra::Vector2;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("relfusion-synth-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn small(seed: u64, frames: usize) -> SynthConfig {
    SynthConfig {
        frames,
        seed,
        width: 160,
        height: 120,
        ..SynthConfig::default()
    }
}

/// All files under `dir` (relative path → bytes), sorted.
fn tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).expect("read_dir") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let bytes = std::fs::read(&path).expect("read");
                out.push((path.strip_prefix(dir).expect("prefix").to_path_buf(), bytes));
            }
        }
    }
    out.sort();
    out
}

/// Share of pixels whose central-difference gradient magnitude exceeds `above`, and share
/// below `below` (8-bit grey units).
fn gradient_shares(gray: &ImageF32, above: f32, below: f32) -> (f64, f64) {
    let (mut hi, mut lo, mut n) = (0usize, 0usize, 0usize);
    for y in 1..gray.height - 1 {
        for x in 1..gray.width - 1 {
            let gx = 0.5 * (gray.at(x + 1, y) - gray.at(x - 1, y));
            let gy = 0.5 * (gray.at(x, y + 1) - gray.at(x, y - 1));
            let g = gx.hypot(gy);
            hi += usize::from(g > above);
            lo += usize::from(g < below);
            n += 1;
        }
    }
    (hi as f64 / n as f64, lo as f64 / n as f64)
}

/// Relative differences between frame j's depth and frame i's depth warped into j, over
/// pixels of i (stride 3) that land on a surface visible in j. Inverse depth is interpolated
/// bilinearly, which is exact on planes (inverse depth is affine in pixel coordinates there);
/// neighbourhoods straddling a depth edge are skipped. Returns (diffs, pixels tried).
fn warp_differences(
    camera: &PinholeCamera,
    (pose_i, depth_i): (&SE3, &ImageF32),
    (pose_j, depth_j): (&SE3, &ImageF32),
) -> (Vec<f64>, usize) {
    let j_from_i = pose_j.inverse() * *pose_i;
    let (mut diffs, mut tried) = (Vec::new(), 0);
    for y in (0..depth_i.height).step_by(3) {
        for x in (0..depth_i.width).step_by(3) {
            let d = f64::from(depth_i.at(x, y));
            if d <= 0.0 {
                continue;
            }
            tried += 1;
            let p = j_from_i.act(&camera.unproject(&Vector2::new(x as f64, y as f64), d));
            if p.z <= 0.0 {
                continue;
            }
            let uv = camera.project(&p);
            let (x0, y0) = (uv.x.floor(), uv.y.floor());
            if x0 < 0.0
                || y0 < 0.0
                || x0 + 1.0 >= f64::from(camera.width)
                || y0 + 1.0 >= f64::from(camera.height)
            {
                continue;
            }
            let (xi, yi) = (x0 as usize, y0 as usize);
            let n = [
                depth_j.at(xi, yi),
                depth_j.at(xi + 1, yi),
                depth_j.at(xi, yi + 1),
                depth_j.at(xi + 1, yi + 1),
            ]
            .map(f64::from);
            let (lo, hi) = n
                .iter()
                .fold((f64::MAX, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
            if lo <= 0.0 || hi / lo > 1.02 {
                continue;
            }
            let (fx, fy) = (uv.x - x0, uv.y - y0);
            let inv = (1.0 / n[0]) * (1.0 - fx) * (1.0 - fy)
                + (1.0 / n[1]) * fx * (1.0 - fy)
                + (1.0 / n[2]) * (1.0 - fx) * fy
                + (1.0 / n[3]) * fx * fy;
            let rel = (p.z * inv - 1.0).abs();
            // Much farther in j than predicted: the point is occluded there.
            if rel < 0.05 {
                diffs.push(rel);
            }
        }
    }
    (diffs, tried)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
fn dataset_synth_is_deterministic_per_seed() {
    let (a, b, c) = (temp_dir("det-a"), temp_dir("det-b"), temp_dir("det-c"));
    let sa = render_sequence(&small(5, 4), &a).expect("render a");
    let sb = render_sequence(
        &SynthConfig {
            threads: 1,
            ..small(5, 4)
        },
        &b,
    )
    .expect("render b");
    render_sequence(&small(6, 4), &c).expect("render c");
    assert_eq!(sa, sb);
    let (ta, tb, tc) = (tree(&a), tree(&b), tree(&c));
    assert_eq!(ta.len(), 4 * 2 + 5, "4 rgb + 4 depth + 5 text files");
    assert!(
        ta == tb,
        "same seed, different thread count: identical bytes"
    );
    let rgb0 = |t: &[(PathBuf, Vec<u8>)]| {
        t.iter()
            .find(|(p, _)| p.starts_with("rgb") && p.ends_with("0.000000.png"))
            .map(|(_, b)| b.clone())
    };
    assert!(rgb0(&ta).is_some());
    assert_ne!(
        rgb0(&ta),
        rgb0(&tc),
        "a different seed gives a different room"
    );
    for d in [a, b, c] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn dataset_synth_depth_is_exact_across_views() {
    let config = SynthConfig {
        seed: 3,
        ..SynthConfig::default()
    };
    let camera = config.camera().expect("camera");
    let scene = Scene::generate(config.seed);
    let traj = Trajectory::new(config.motion, config.seed);
    let (pi, pj) = (traj.world_from_camera(0.0), traj.world_from_camera(1.0));
    let baseline = (pi.translation - pj.translation).norm();
    assert!(baseline > 0.1, "a real baseline, got {baseline} m");
    let (_, di) = render_frame_with(&scene, &camera, &pi, 1);
    let (_, dj) = render_frame_with(&scene, &camera, &pj, 1);
    assert!(
        di.data.iter().all(|&d| d > 0.1 && d < 6.0),
        "every ray hits the closed room"
    );
    let (diffs, tried) = warp_differences(&camera, (&pi, &di), (&pj, &dj));
    assert!(
        diffs.len() > tried / 2,
        "{} of {tried} pixels compared",
        diffs.len()
    );
    let compared = diffs.len();
    let med = median(diffs);
    eprintln!(
        "baseline {baseline:.3} m: {compared}/{tried} pixels compared, median rel. diff {med:.2e}"
    );
    assert!(med < 1e-4, "median relative depth difference {med}");
}

#[test]
fn dataset_synth_sequence_loads_as_tum() {
    let dir = temp_dir("tum");
    let config = SynthConfig {
        frames: 12,
        seed: 11,
        width: 320,
        height: 240,
        ..SynthConfig::default()
    };
    let summary = render_sequence(&config, &dir).expect("render");
    assert_eq!(summary.frames, 12);
    let seq = TumSequence::open(&dir, None).expect("open as TUM");
    assert_eq!(seq.len(), 12);
    let cam = &seq.camera;
    assert_eq!(
        (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height),
        (262.5, 262.5, 159.5, 119.5, 320, 240)
    );
    assert!(cam.distortion.is_none());
    let poses = config.poses();
    for (f, p) in seq.frames.iter().zip(&poses) {
        assert!(f.depth.is_some());
        let gt = f.world_from_camera.expect("ground truth for every frame");
        assert!((gt.translation - p.translation).norm() < 1e-8);
        assert!((gt.rotation.inverse() * p.rotation).log().norm() < 1e-8);
    }
    // Stored depth = rendered depth up to the 1/5000 m quantisation.
    let scene = Scene::generate(config.seed);
    let (_, rendered) = render_frame_with(&scene, cam, &poses[0], 1);
    let stored = seq.load_depth(0).expect("depth").expect("associated");
    let worst = rendered
        .data
        .iter()
        .zip(&stored.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst <= 0.5 / 5000.0 + 1e-6, "quantisation error {worst} m");
    // Depth read back from the files is still consistent between the first and last frame.
    let last = seq.len() - 1;
    let dl = seq.load_depth(last).expect("depth").expect("associated");
    let (pose0, posel) = (
        seq.frames[0].world_from_camera.expect("gt"),
        seq.frames[last].world_from_camera.expect("gt"),
    );
    let (diffs, tried) = warp_differences(cam, (&pose0, &stored), (&posel, &dl));
    assert!(diffs.len() > tried / 2);
    let med = median(diffs);
    eprintln!("from the PNG files: median rel. diff {med:.2e}");
    assert!(med < 1e-3, "median relative difference from files {med}");
    let gray = seq.load_gray(3).expect("gray");
    assert_eq!((gray.width, gray.height), (320, 240));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn dataset_synth_has_texture_and_textureless_areas() {
    for seed in [0u64, 1, 2] {
        let config = SynthConfig {
            seed,
            ..SynthConfig::default()
        };
        let camera = config.camera().expect("camera");
        let scene = Scene::generate(seed);
        let (rgb, _) = render_frame(&scene, &camera, &config.poses()[0]);
        let gray = ImageF32::from_rgb8(&rgb);
        let (strong, flat) = gradient_shares(&gray, 5.0, 1.0);
        assert!(
            strong > 0.18,
            "seed {seed}: {strong} of pixels with |grad| > 5"
        );
        assert!(flat > 0.02, "seed {seed}: {flat} of pixels with |grad| < 1");
        let (lo, hi) = rgb
            .pixels()
            .fold((255u8, 0u8), |(lo, hi), p| (lo.min(p[1]), hi.max(p[1])));
        assert!(lo < 50 && hi > 150, "seed {seed}: green range {lo}..{hi}");
        let saturated = rgb.pixels().filter(|p| p[1] == 255).count() as f64 / (640.0 * 480.0);
        assert!(saturated < 0.05, "seed {seed}: {saturated} saturated");
    }
}

#[test]
fn dataset_synth_views_stay_textured_along_every_preset() {
    let seed = 4;
    let scene = Scene::generate(seed);
    for motion in Motion::ALL {
        let config = SynthConfig {
            seed,
            motion,
            width: 160,
            height: 120,
            ..SynthConfig::default()
        };
        let camera = config.camera().expect("camera");
        for (i, pose) in config.poses().iter().enumerate().step_by(30) {
            let (rgb, depth) = render_frame_with(&scene, &camera, pose, 1);
            let (strong, _) = gradient_shares(&ImageF32::from_rgb8(&rgb), 5.0, 1.0);
            assert!(
                strong > 0.18,
                "{motion} frame {i}: only {strong} of pixels with |grad| > 5"
            );
            let near = depth.data.iter().cloned().fold(f32::MAX, f32::min);
            assert!(near > 0.3, "{motion} frame {i}: surface at {near} m");
        }
    }
}

#[test]
fn dataset_synth_motion_presets_within_bounds() {
    for seed in 0..6u64 {
        let scene = Scene::generate(seed);
        assert!(
            scene.blocks.len() >= 4,
            "seed {seed}: {} blocks",
            scene.blocks.len()
        );
        for motion in Motion::ALL {
            let poses = SynthConfig {
                seed,
                motion,
                ..SynthConfig::default()
            }
            .poses();
            assert!(
                poses.iter().all(|p| scene.is_free(&p.translation, 0.3)),
                "{motion} seed {seed}"
            );
            let (len, rot) = (path_length(&poses), max_rotation_deg(&poses));
            let (len_range, rot_range) = match motion {
                Motion::Orbit => (1.5..4.0, 10.0..60.0),
                Motion::Forward => (1.5..2.5, 2.0..25.0),
                Motion::Rotation => (0.0..0.3, 20.0..80.0),
                Motion::Shake => (0.5..4.0, 1.0..15.0),
                Motion::Handheld => (1.0..4.0, 5.0..80.0),
                Motion::Loop => (0.8..3.0, 5.0..60.0),
            };
            assert!(
                len_range.contains(&len),
                "{motion} seed {seed}: path {len} m"
            );
            assert!(
                rot_range.contains(&rot),
                "{motion} seed {seed}: rotation {rot} deg"
            );
            // Smooth: no frame-to-frame jump larger than 3 cm or 2 degrees.
            for w in poses.windows(2) {
                assert!((w[1].translation - w[0].translation).norm() < 0.03);
                assert!(
                    (w[0].rotation.inverse() * w[1].rotation)
                        .log()
                        .norm()
                        .to_degrees()
                        < 2.0
                );
            }
        }
    }
}

#[test]
fn dataset_synth_config_serde_and_validation() {
    let c: SynthConfig =
        serde_json::from_str(r#"{"frames": 7, "motion": "shake"}"#).expect("parse");
    assert_eq!(
        (c.frames, c.motion, c.width, c.seed),
        (7, Motion::Shake, 640, 0)
    );
    assert!(
        serde_json::from_str::<SynthConfig>(r#"{"frame": 7}"#).is_err(),
        "unknown field"
    );
    assert_eq!(
        "rotation".parse::<Motion>().expect("parse"),
        Motion::Rotation
    );
    assert!("spin".parse::<Motion>().is_err());
    let dir = temp_dir("invalid");
    assert!(
        render_sequence(
            &SynthConfig {
                frames: 0,
                ..SynthConfig::default()
            },
            &dir
        )
        .is_err()
    );
    assert!(
        render_sequence(
            &SynthConfig {
                supersample: 0,
                ..SynthConfig::default()
            },
            &dir
        )
        .is_err()
    );
    let camera = SynthConfig::default().camera().expect("camera");
    assert_eq!(
        (camera.fx, camera.fy, camera.cx, camera.cy),
        (525.0, 525.0, 319.5, 239.5)
    );
}

#[test]
fn dataset_synth_long_presets_stay_free_and_the_loop_comes_back() {
    for seed in 0..4u64 {
        let scene = Scene::generate(seed);
        for motion in [Motion::Handheld, Motion::Loop] {
            let poses = SynthConfig {
                seed,
                motion,
                frames: 1200,
                ..SynthConfig::default()
            }
            .poses();
            assert!(
                poses.iter().all(|p| scene.is_free(&p.translation, 0.3)),
                "{motion} seed {seed}"
            );
            let len = path_length(&poses);
            assert!(
                (4.0..12.0).contains(&len),
                "{motion} seed {seed}: {len} m over 1200 frames"
            );
            for w in poses.windows(2) {
                assert!((w[1].translation - w[0].translation).norm() < 0.03);
            }
            // 900 frames = the loop's 30 s period: back at the start up to the tremor.
            let back = poses[0].inverse() * poses[900];
            let (dt, dr) = (
                back.translation.norm(),
                back.rotation.log().norm().to_degrees(),
            );
            match motion {
                Motion::Loop => assert!(dt < 0.015 && dr < 2.0, "seed {seed}: {dt} m {dr} deg"),
                _ => assert!(dt > 0.1 || dr > 10.0, "seed {seed}: handheld came back"),
            }
        }
    }
}

#[test]
fn dataset_synth_nuisances_are_deterministic_and_do_what_they_say() {
    let nuisy = SynthConfig {
        nuisances: Nuisances::CAMERA,
        motion: Motion::Handheld,
        ..small(3, 4)
    };
    let (a, b) = (temp_dir("nuis-a"), temp_dir("nuis-b"));
    render_sequence(
        &SynthConfig {
            threads: 1,
            ..nuisy.clone()
        },
        &a,
    )
    .expect("render a");
    render_sequence(
        &SynthConfig {
            threads: 3,
            ..nuisy.clone()
        },
        &b,
    )
    .expect("render b");
    let (ta, tb) = (tree(&a), tree(&b));
    assert_eq!(ta, tb, "same seed, different threads: identical files");
    assert!(
        ta.iter()
            .any(|(p, _)| p.extension().is_some_and(|e| e == "jpg"))
    );
    let seq = TumSequence::open(&a, None).expect("open");
    assert_eq!(seq.len(), 4);
    let img = seq.load_gray(0).expect("jpeg frame decodes");

    // Against the ideal camera: the corners are darker (vignetting 0.3 on top of the gain)
    // and the image differs everywhere by about the noise.
    let scene = Scene::generate(3);
    let camera = nuisy.camera().expect("camera");
    let (ideal, _) = render_frame_with(&scene, &camera, &nuisy.poses()[0], 2);
    let ideal = ImageF32::from_rgb8(&ideal);
    let gain = Nuisances::CAMERA.gain(3, 0.0) as f32;
    let mean_ratio = |x0: usize, y0: usize| {
        let (mut n, mut d) = (0.0f32, 0.0f32);
        for y in y0..y0 + 12 {
            for x in x0..x0 + 16 {
                n += img.at(x, y);
                d += ideal.at(x, y);
            }
        }
        n / d / gain
    };
    let centre = mean_ratio(72, 54);
    let corner = mean_ratio(0, 0);
    assert!(centre > 0.9 && centre < 1.1, "centre ratio {centre}");
    assert!(corner < 0.85 * centre, "corner {corner} vs centre {centre}");

    // The gain wanders within exp(±0.22) and really changes over a few seconds.
    let gains: Vec<f64> = (0..300)
        .map(|i| Nuisances::CAMERA.gain(3, i as f64 / 30.0))
        .collect();
    let (lo, hi) = gains
        .iter()
        .fold((f64::MAX, 0.0f64), |(l, h), &g| (l.min(g), h.max(g)));
    assert!(lo >= (-0.22f64).exp() - 1e-9 && hi <= 0.22f64.exp() + 1e-9);
    assert!(hi / lo > 1.2, "gain range {lo}..{hi}");
    assert_eq!(Nuisances::default().gain(3, 1.0), 1.0);

    // Validation at the edge.
    let bad = SynthConfig {
        nuisances: Nuisances {
            vignetting: 1.5,
            ..Nuisances::default()
        },
        ..small(0, 1)
    };
    assert!(render_sequence(&bad, &temp_dir("nuis-bad")).is_err());
    for dir in [a, b] {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// A rolling-shutter rendering is the global one when the pose does not change, and each row
/// is the row of the global rendering from that row's pose when it does.
#[test]
fn dataset_synth_rolling_shutter_renders_each_row_from_its_pose() {
    let config = small(2, 1);
    let camera = config.camera().expect("camera");
    let scene = Scene::generate(config.seed);
    let pose = config.poses()[0];
    let still = render_rolling(&scene, &camera, &|_| pose, 1);
    assert_eq!(still.0, render_frame_with(&scene, &camera, &pose, 1).0);
    let turn = |y: u32| {
        pose * SE3::exp(&nalgebra::Vector6::new(
            0.0,
            0.0,
            0.0,
            0.0,
            0.002 * f64::from(y),
            0.0,
        ))
    };
    let rolling = render_rolling(&scene, &camera, &turn, 1).0;
    let last = camera.height - 1;
    let row = |img: &::image::RgbImage, y: u32| -> Vec<u8> {
        (0..img.width())
            .flat_map(|x| img.get_pixel(x, y).0)
            .collect()
    };
    for y in [0, camera.height / 2, last] {
        let global = render_frame_with(&scene, &camera, &turn(y), 1).0;
        assert_eq!(row(&rolling, y), row(&global, y), "row {y}");
    }
    assert_ne!(row(&rolling, last), row(&still.0, last));
}
