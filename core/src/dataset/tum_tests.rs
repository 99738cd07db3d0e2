//! Tests of the TUM reader on the two real sequences in shared/data and on malformed folders.

use super::*;
use nalgebra::Vector3;
use std::path::PathBuf;

/// `$RELFUSION_DATA`, defaulting to the shared data folder next to the workspace.
fn data_dir() -> PathBuf {
    std::env::var_os("RELFUSION_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data")))
}

fn sequence(name: &str) -> Option<PathBuf> {
    let dir = data_dir().join("sequences").join(name);
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!("skipping: {} not found (set RELFUSION_DATA)", dir.display());
        None
    }
}

/// A fresh empty temporary folder, unique per test.
fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("relfusion-tum-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("rgb")).expect("create temp dir");
    dir
}

fn write(path: PathBuf, text: &str) {
    std::fs::write(path, text).expect("write test file");
}

fn valid_fraction(depth: &ImageF32) -> f64 {
    depth.data.iter().filter(|&&d| d > 0.0).count() as f64 / depth.data.len() as f64
}

#[test]
fn dataset_tum_fr1_rpy_loads_with_preset_intrinsics() {
    let Some(dir) = sequence("tum_fr1_rpy_f0000-0249") else {
        return;
    };
    let seq = TumSequence::open(&dir, None).expect("open fr1/rpy");
    assert_eq!(seq.len(), 250);
    assert!(
        seq.frames.iter().all(|f| f.depth.is_some()),
        "every rgb frame has a depth partner"
    );
    assert!(
        seq.frames.iter().all(|f| f.world_from_camera.is_some()),
        "ground truth covers all"
    );
    let cam = &seq.camera;
    assert_eq!(
        (cam.fx, cam.fy, cam.cx, cam.cy),
        (517.3, 516.5, 318.6, 255.3)
    );
    assert_eq!((cam.width, cam.height), (640, 480));
    let d = cam
        .distortion
        .as_ref()
        .expect("fr1 distortion from the preset");
    assert_eq!(
        (d.k1, d.k2, d.p1, d.p2, d.k3),
        (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    );
    assert_eq!(seq.groundtruth().len(), 1030);
    let poses = seq.groundtruth_poses();
    assert!(
        poses
            .iter()
            .zip(seq.groundtruth())
            .all(|(p, (t, pose))| p.timestamp == t && p.world_from_camera == pose)
            && poses.len() == 1030
    );
    // Timestamps increase, associated depth is within the associate.py window.
    for w in seq.frames.windows(2) {
        assert!(w[1].timestamp > w[0].timestamp);
    }

    let rgb = seq.load_rgb(0).expect("rgb 0");
    assert_eq!(rgb.dimensions(), (640, 480));
    let gray = seq.load_gray(0).expect("gray 0");
    let mean = gray.data.iter().map(|&v| f64::from(v)).sum::<f64>() / gray.data.len() as f64;
    assert!(mean > 20.0 && mean < 235.0, "mean grey {mean}");
    let depth = seq
        .load_depth(0)
        .expect("depth 0")
        .expect("frame 0 has depth");
    let valid = valid_fraction(&depth);
    assert!(
        (0.6..0.8).contains(&valid),
        "fr1 valid depth fraction {valid} (README: ~71 %)"
    );
    let max = depth.data.iter().cloned().fold(0.0f32, f32::max);
    assert!(max > 0.5 && max < 10.0, "max depth {max} m");

    // Interpolated ground truth sits between the bracketing 100 Hz poses.
    let gt = seq.groundtruth();
    let f = &seq.frames[10];
    let pose = f.world_from_camera.expect("pose");
    let k = gt.partition_point(|(t, _)| *t < f.timestamp);
    let (a, b) = (&gt[k - 1].1, &gt[k].1);
    let span = (a.translation - b.translation).norm();
    assert!((pose.translation - a.translation).norm() <= span + 1e-9);
    assert!((pose.translation - b.translation).norm() <= span + 1e-9);
}

#[test]
fn dataset_tum_7scenes_loads_with_calibration_and_jpeg() {
    let Some(dir) = sequence("7scenes_redkitchen_f0000-0299") else {
        return;
    };
    let seq = TumSequence::open(&dir, None).expect("open 7-Scenes");
    assert_eq!(seq.len(), 300);
    assert!(seq.frames.iter().all(|f| f.depth.is_some()));
    let cam = &seq.camera;
    assert_eq!(
        (cam.fx, cam.fy, cam.cx, cam.cy),
        (585.0, 585.0, 320.0, 240.0)
    );
    assert!(cam.distortion.is_none());
    let gt = seq.groundtruth();
    assert_eq!(gt.len(), 300);
    // Stamps coincide, so each frame's pose is exactly the file's pose of that frame.
    for (f, (t, p)) in seq.frames.iter().zip(&gt) {
        assert!((f.timestamp - t).abs() < 1e-9);
        let pose = f.world_from_camera.expect("pose for every frame");
        assert!((pose.translation - p.translation).norm() < 1e-12);
    }
    assert_eq!(seq.load_rgb(5).expect("jpeg rgb").dimensions(), (640, 480));
    let depth = seq
        .load_depth(0)
        .expect("depth 0")
        .expect("frame 0 has depth");
    let valid = valid_fraction(&depth);
    assert!(
        (0.82..0.97).contains(&valid),
        "7-Scenes valid depth fraction {valid} (~90 %)"
    );
    assert!(seq.load_rgb(300).is_err(), "out-of-range frame is an error");
}

#[test]
fn dataset_tum_preset_names() {
    assert_eq!(
        preset("rgbd_dataset_freiburg2_xyz").map(|c| c.fx),
        Some(520.9)
    );
    let fr3 = preset("FR3_office").expect("fr3");
    assert_eq!(
        (fr3.fx, fr3.fy, fr3.cx, fr3.cy),
        (535.4, 539.2, 320.1, 247.6)
    );
    assert!(fr3.distortion.is_none());
    assert!(preset("kitchen").is_none());
}

#[test]
fn dataset_tum_association_is_greedy_one_to_one() {
    // 0.010 and 0.012 both want depth 0.011; the closer one wins, the other gets nothing
    // within 0.02 s except 0.03 (0.018 away), which it takes.
    let rgb = [0.010, 0.012, 0.100];
    let depth = [0.011, 0.030, 0.5];
    let m = associate(&rgb, &depth, MAX_ASSOCIATION_DT);
    assert_eq!(m, vec![Some(0), Some(1), None]);
}

#[test]
fn dataset_tum_association_stays_linear_on_repeated_stamps() {
    // 20 000 identical stamps on both sides: associate.py would weigh 4·10⁸ pairs; each
    // stamp considers a bounded number of neighbours instead.
    let n = 20_000;
    let stamps = vec![0.0; n];
    let t = std::time::Instant::now();
    let m = associate(&stamps, &stamps, MAX_ASSOCIATION_DT);
    let matched = m.iter().flatten().count();
    assert!(matched <= ASSOCIATION_NEIGHBOURS, "{matched} pairs");
    assert!(t.elapsed().as_secs() < 5, "{:?}", t.elapsed());
    // A 30 Hz pair of streams, interleaved: every frame still finds its partner.
    let rgb: Vec<f64> = (0..300).map(|i| f64::from(i) / 30.0).collect();
    let depth: Vec<f64> = rgb.iter().map(|t| t + 0.004).collect();
    let m = associate(&rgb, &depth, MAX_ASSOCIATION_DT);
    assert!(m.iter().enumerate().all(|(i, p)| *p == Some(i)));
}

#[test]
fn dataset_tum_limits_bound_lists_and_files() {
    let dir = temp_dir("limits");
    let png = {
        let img = ::image::RgbImage::from_pixel(8, 6, ::image::Rgb([9, 9, 9]));
        let mut bytes = Vec::new();
        img.write_to(
            &mut std::io::Cursor::new(&mut bytes),
            ::image::ImageFormat::Png,
        )
        .expect("png");
        bytes
    };
    std::fs::write(dir.join("rgb/a.png"), &png).expect("write");
    write(dir.join("calibration.txt"), "5 5 4 3\n");
    let list: String = (0..10).map(|i| format!("{i}.0 rgb/a.png\n")).collect();
    write(dir.join("rgb.txt"), &list);
    let limits = SequenceLimits {
        max_frames: 9,
        max_text_bytes: 1 << 20,
        max_image_bytes: 1 << 20,
    };
    let err = TumSequence::open_bounded(&dir, None, limits).expect_err("10 entries > 9");
    assert!(err.to_string().contains("more than 9 entries"), "{err}");
    let ten = SequenceLimits {
        max_frames: 10,
        ..limits
    };
    let seq = TumSequence::open_bounded(&dir, None, ten).expect("10 entries");
    assert_eq!(seq.load_rgb(3).expect("read").width(), 8);
    // A valid image padded past the image limit: refused from its size, before reading.
    let mut padded = png.clone();
    padded.resize(4096, 0);
    std::fs::write(dir.join("rgb/a.png"), &padded).expect("write");
    let small = SequenceLimits {
        max_image_bytes: 2048,
        ..ten
    };
    let seq = TumSequence::open_bounded(&dir, None, small).expect("open");
    let err = seq.load_rgb(0).expect_err("image over the limit");
    let text = err.to_string();
    assert!(
        text.contains("rgb/a.png holds 4096 bytes, more than the 2048 allowed for an image"),
        "{text}"
    );
    assert!(!text.contains(&*dir.to_string_lossy()), "{text}");
    // A list file over the text limit is refused before it is read.
    let tiny = SequenceLimits {
        max_text_bytes: 32,
        ..ten
    };
    let err = TumSequence::open_bounded(&dir, None, tiny).expect_err("rgb.txt too large");
    assert!(err.to_string().contains("allowed for a text file"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn dataset_tum_groundtruth_interpolation() {
    let a = SE3::identity();
    let b = SE3::new(
        SO3::exp(&Vector3::new(0.0, 0.0, 0.2)),
        Vector3::new(1.0, 0.0, 0.0),
    );
    let poses = vec![(1.00, a), (1.01, b)];
    let mid = interpolate_pose(&poses, 1.0025, MAX_ASSOCIATION_DT).expect("bracketed");
    assert!((mid.translation.x - 0.25).abs() < 1e-9);
    assert!((mid.rotation.log().z - 0.05).abs() < 1e-9);
    assert!(
        interpolate_pose(&poses, 1.05, MAX_ASSOCIATION_DT).is_none(),
        "after the end"
    );
    let gap = vec![(1.00, a), (1.10, b)];
    assert!(
        interpolate_pose(&gap, 1.05, MAX_ASSOCIATION_DT).is_none(),
        "gap too large"
    );
    let exact = interpolate_pose(&gap, 1.10, MAX_ASSOCIATION_DT).expect("same stamp");
    assert!((exact.translation.x - 1.0).abs() < 1e-12);
}

#[test]
fn dataset_tum_malformed_inputs_are_errors() {
    // Missing rgb.txt.
    let dir = temp_dir("no-rgb-txt");
    let err = TumSequence::open(&dir, preset("fr1")).expect_err("no rgb.txt");
    assert!(matches!(err, Error::Dataset(_)), "{err}");

    // Bad line.
    write(
        dir.join("rgb.txt"),
        "# header\n0.0 rgb/a.png\nnot-a-number rgb/b.png\n",
    );
    let err = TumSequence::open(&dir, preset("fr1")).expect_err("bad line");
    assert!(
        err.to_string().contains(":3:"),
        "error names the line: {err}"
    );

    // Listed file missing.
    write(dir.join("rgb.txt"), "0.0 rgb/a.png\n");
    let err = TumSequence::open(&dir, preset("fr1")).expect_err("missing image");
    assert!(err.to_string().contains("a.png"), "{err}");

    // Present but corrupt image: opening works, loading reports an image error.
    write(dir.join("rgb/a.png"), "definitely not a png");
    let seq = TumSequence::open(&dir, preset("fr1")).expect("open with lazy images");
    assert!(matches!(seq.load_rgb(0), Err(Error::Image { .. })));

    // No intrinsics from anywhere.
    let err = TumSequence::open(&dir, None).expect_err("no intrinsics");
    assert!(err.to_string().contains("calibration.txt"), "{err}");

    // Wrong image size for the camera.
    ::image::RgbImage::new(32, 24)
        .save(dir.join("rgb/a.png"))
        .expect("save png");
    let seq = TumSequence::open(&dir, preset("fr1")).expect("open");
    let err = seq.load_rgb(0).expect_err("size mismatch");
    assert!(err.to_string().contains("32x24"), "{err}");

    // calibration.txt takes the size from the images; a bad one is an error.
    write(
        dir.join("calibration.txt"),
        "# fx fy cx cy\n100 100 15.5 11.5\n",
    );
    let seq = TumSequence::open(&dir, None).expect("open with calibration");
    assert_eq!(
        (seq.camera.width, seq.camera.height, seq.camera.fx),
        (32, 24, 100.0)
    );
    assert!(seq.load_rgb(0).is_ok());
    assert_eq!(seq.load_depth(0).expect("no depth is fine"), None);
    write(dir.join("calibration.txt"), "100 100 15.5\n");
    assert!(TumSequence::open(&dir, None).is_err(), "three numbers");

    // Malformed ground truth.
    write(dir.join("calibration.txt"), "100 100 15.5 11.5\n");
    write(dir.join("groundtruth.txt"), "0.0 1 2 3 0 0 0\n");
    assert!(TumSequence::open(&dir, None).is_err(), "seven numbers");
    write(dir.join("groundtruth.txt"), "0.0 1 2 3 0 0 0 0\n");
    assert!(TumSequence::open(&dir, None).is_err(), "zero quaternion");

    // An 8-bit depth image is rejected with a clear message.
    write(dir.join("groundtruth.txt"), "0.0 1 2 3 0 0 0 1\n");
    std::fs::create_dir_all(dir.join("depth")).expect("mkdir");
    ::image::GrayImage::new(32, 24)
        .save(dir.join("depth/a.png"))
        .expect("save png");
    write(dir.join("depth.txt"), "0.001 depth/a.png\n");
    let seq = TumSequence::open(&dir, None).expect("open");
    assert!(seq.frames[0].world_from_camera.is_some());
    let err = seq.load_depth(0).expect_err("8-bit depth");
    assert!(err.to_string().contains("16-bit"), "{err}");

    let _ = std::fs::remove_dir_all(&dir);
}
