//! End to end: the real `relfusion synth` binary writes a sequence that the TUM reader loads
//! and whose depth, poses and intrinsics agree with each other.

use std::path::Path;
use std::process::Command;

use nalgebra::Vector2;
use relfusion_slam::dataset::TumSequence;
use relfusion_tests::{bin_path, temp_dir};

/// Runs `relfusion synth` and returns its one JSON line.
fn synth(out: &Path, extra: &[&str]) -> serde_json::Value {
    let output = Command::new(bin_path("relfusion"))
        .arg("synth")
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .expect("run relfusion");
    assert!(
        output.status.success(),
        "relfusion synth failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let stdout = String::from_utf8(output.stdout).expect("utf-8 stdout");
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 1, "one summary line, got {stdout:?}");
    serde_json::from_str(lines[0]).expect("summary is JSON")
}

#[test]
fn synth_cli_writes_a_consistent_tum_sequence() {
    let out = temp_dir("orbit");
    let args = [
        "--frames", "10", "--seed", "7", "--width", "320", "--height", "240",
    ];
    let summary = synth(&out, &args);
    assert_eq!(summary["frames"], 10);
    assert_eq!(summary["motion"], "orbit");
    let path = summary["path_length_m"].as_f64().expect("path_length_m");
    assert!(path > 0.02 && path < 0.5, "10 frames of orbit: {path} m");

    let seq = TumSequence::open(&out, None).expect("output loads as a TUM sequence");
    assert_eq!(seq.len(), 10);
    assert_eq!((seq.camera.width, seq.camera.height), (320, 240));
    assert_eq!(
        seq.camera.fx, 262.5,
        "f = 525 at 640 px, scaled with the width"
    );
    assert!(
        seq.frames
            .iter()
            .all(|f| f.depth.is_some() && f.world_from_camera.is_some())
    );
    let gt = seq.groundtruth();
    let measured: f64 = gt
        .windows(2)
        .map(|w| (w[1].1.translation - w[0].1.translation).norm())
        .sum();
    assert!(
        (measured - path).abs() < 1e-6,
        "summary {path} vs groundtruth.txt {measured}"
    );

    // Depth of frame 0 warped into frame 9 matches frame 9's depth where both see a surface.
    let (d0, d9) = (
        seq.load_depth(0).expect("depth 0").expect("has depth"),
        seq.load_depth(9).expect("depth 9").expect("has depth"),
    );
    assert!(
        d0.data.iter().all(|&d| d > 0.0),
        "the room is closed: depth everywhere"
    );
    let (p0, p9) = (
        seq.frames[0].world_from_camera.expect("pose"),
        seq.frames[9].world_from_camera.expect("pose"),
    );
    let nine_from_zero = p9.inverse() * p0;
    let mut rel = Vec::new();
    for y in (0..d0.height).step_by(4) {
        for x in (0..d0.width).step_by(4) {
            let p = nine_from_zero.act(
                &seq.camera
                    .unproject(&Vector2::new(x as f64, y as f64), f64::from(d0.at(x, y))),
            );
            let uv = seq.camera.project(&p);
            let (u, v) = (uv.x.round(), uv.y.round());
            if p.z > 0.0 && u >= 0.0 && v >= 0.0 && u < 320.0 && v < 240.0 {
                let d = f64::from(d9.at(u as usize, v as usize));
                rel.push((p.z - d).abs() / d);
            }
        }
    }
    assert!(rel.len() > 2000, "{} warped pixels", rel.len());
    rel.sort_by(f64::total_cmp);
    // Nearest-pixel lookup: the error is the depth change over half a pixel, well under 1 %.
    assert!(
        rel[rel.len() / 2] < 0.01,
        "median relative depth difference {}",
        rel[rel.len() / 2]
    );
    let gray = seq.load_gray(5).expect("gray");
    let mean = gray.data.iter().map(|&g| f64::from(g)).sum::<f64>() / gray.data.len() as f64;
    assert!(mean > 30.0 && mean < 220.0, "mean grey {mean}");

    // Same arguments, same bytes.
    let again = temp_dir("orbit-again");
    synth(&again, &args);
    for name in [
        "rgb.txt",
        "groundtruth.txt",
        "rgb/0.100000.png",
        "depth/0.300000.png",
    ] {
        let a = std::fs::read(out.join(name)).expect("first run file");
        let b = std::fs::read(again.join(name)).expect("second run file");
        assert!(a == b, "{name} differs between identical runs");
    }
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&again);
}

#[test]
fn synth_cli_rejects_bad_arguments() {
    let out = temp_dir("bad");
    let status = Command::new(bin_path("relfusion"))
        .args(["synth", "--motion", "spin", "--out"])
        .arg(&out)
        .output()
        .expect("run relfusion");
    assert!(!status.status.success(), "unknown motion must fail");
    assert!(String::from_utf8_lossy(&status.stderr).contains("spin"));
    let status = Command::new(bin_path("relfusion"))
        .args(["synth", "--frames", "0", "--out"])
        .arg(&out)
        .output()
        .expect("run relfusion");
    assert!(!status.status.success(), "zero frames must fail");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn run_refuses_the_sensor_depth_baseline_on_a_sequence_without_depth() {
    let seq = temp_dir("no-depth");
    synth(
        &seq,
        &[
            "--frames", "3", "--seed", "1", "--width", "160", "--height", "120",
        ],
    );
    std::fs::remove_file(seq.join("depth.txt")).expect("remove depth.txt");
    let config = seq.join("gt.toml");
    std::fs::write(&config, "[dense.two_view]\nground_truth_depth = true\n").expect("config");
    let out = seq.join("out");
    let output = Command::new(bin_path("relfusion"))
        .arg("run")
        .arg(&seq)
        .arg("--out")
        .arg(&out)
        .arg("--config")
        .arg(&config)
        .args(["--deterministic", "--quiet"])
        .output()
        .expect("run relfusion");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "must fail without depth images");
    assert!(
        stderr.contains("ground_truth_depth") && stderr.contains("depth.txt"),
        "unclear error: {stderr}"
    );
    let _ = std::fs::remove_dir_all(&seq);
}
