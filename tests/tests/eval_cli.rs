//! `relfusion eval` end to end: the real binary on the evo fixtures (tests/fixtures/evo), its
//! JSON compared with evo's figures in expected.json, and the depth metric on constructed maps.
//!
//! Needs the `relfusion` binary built beside this test (`cargo build -p relfusion-client`).

use std::path::{Path, PathBuf};
use std::process::Command;

use relfusion_slam::image::ImageF32;
use relfusion_tests::{bin_path, data_dir, relfusion_json, temp_dir};
use serde_json::Value;

/// The brief's tolerance against evo (measured differences are ~1e-15).
const TOL: f64 = 1e-6;

fn fixture_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/evo"))
}

fn expected() -> Value {
    let text = std::fs::read_to_string(fixture_dir().join("expected.json")).expect("expected.json");
    serde_json::from_str(&text).expect("expected.json parses")
}

/// Runs `relfusion eval ARGS`, asserts success, parses its JSON report.
fn relfusion_eval(args: &[&str]) -> Value {
    relfusion_json(&[&["eval"], args].concat())
}

fn num(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("`{key}` missing or not a number in {v}"))
}

fn close(what: &str, ours: f64, evo: f64) {
    assert!(
        (ours - evo).abs() <= TOL,
        "{what}: relfusion {ours:.12} vs evo {evo:.12}"
    );
}

/// Ground-truth path of a fixture, or `None` when it lives in the absent data folder.
fn gt_path(name: &str, entry: &Value) -> Option<PathBuf> {
    match entry["gt"]["data"].as_str() {
        Some(rel) => {
            let p = data_dir().join(rel);
            if p.is_file() {
                Some(p)
            } else {
                eprintln!(
                    "skipping fixture `{name}`: {} not found (set RELFUSION_DATA)",
                    p.display()
                );
                None
            }
        }
        None => Some(fixture_dir().join(entry["gt"]["fixture"].as_str().expect("gt.fixture"))),
    }
}

#[test]
fn eval_cli_traj_matches_evo() {
    let all = expected();
    let max_dt = num(&all, "t_max_diff").to_string();
    let mut checked = 0;
    for (name, entry) in all["fixtures"].as_object().expect("fixtures") {
        let Some(gt) = gt_path(name, entry) else {
            continue;
        };
        let est = fixture_dir().join(entry["est"].as_str().expect("est"));
        let res = &entry["results"];
        // (mode, evo APE result, evo RPE translation result): a rigid alignment cannot change
        // the RPE, so se3 and none both compare with the unaligned evo_rpe.
        for (align, ape, rpe) in [
            ("sim3", "ape_sim3", "rpe_trans_d1_sim3"),
            ("se3", "ape_se3", "rpe_trans_d1"),
            ("none", "ape_none", "rpe_trans_d1"),
        ] {
            let out = relfusion_eval(&[
                "traj",
                "--gt",
                gt.to_str().expect("utf-8 path"),
                "--est",
                est.to_str().expect("utf-8 path"),
                "--align",
                align,
                "--max-dt",
                &max_dt,
            ]);
            let what = |k: &str| format!("{name} --align {align} {k}");
            assert_eq!(out["align"], align);
            assert_eq!(
                out["matched"].as_u64(),
                res[ape]["count"].as_u64(),
                "{}",
                what("matched")
            );
            for (key, stat) in [
                ("ate_rmse_m", "rmse"),
                ("ate_mean_m", "mean"),
                ("ate_median_m", "median"),
                ("ate_std_m", "std"),
                ("ate_min_m", "min"),
                ("ate_max_m", "max"),
            ] {
                close(&what(key), num(&out, key), num(&res[ape], stat));
            }
            let evo_scale = if align == "none" {
                1.0
            } else {
                num(&res[ape], "scale")
            };
            close(&what("scale"), num(&out, "scale"), evo_scale);
            assert_eq!(out["rpe_pairs"].as_u64(), res[rpe]["count"].as_u64());
            close(
                &what("rpe_trans_rmse_m"),
                num(&out, "rpe_trans_rmse_m"),
                num(&res[rpe], "rmse"),
            );
            close(
                &what("rpe_rot_rmse_deg"),
                num(&out, "rpe_rot_rmse_deg"),
                num(&res["rpe_rot_deg_d1"], "rmse"),
            );
            checked += 1;
        }
    }
    assert!(
        checked >= 3,
        "the synthetic fixture at least must have been checked"
    );
}

#[test]
fn eval_cli_traj_rpe_delta_matches_evo() {
    let all = expected();
    let entry = &all["fixtures"]["synthetic"];
    let fx = fixture_dir();
    let out = relfusion_eval(&[
        "traj",
        "--gt",
        fx.join("synthetic_gt.txt").to_str().expect("utf-8"),
        "--est",
        fx.join("synthetic_est.txt").to_str().expect("utf-8"),
        "--align",
        "none",
        "--rpe-delta",
        "5",
    ]);
    // The default --max-dt must be the 0.02 s the fixtures were made with.
    assert_eq!(num(&out, "max_dt_s"), num(&all, "t_max_diff"));
    assert_eq!(out["rpe_delta"], 5);
    assert_eq!(
        out["rpe_pairs"].as_u64(),
        entry["results"]["rpe_trans_d5"]["count"].as_u64()
    );
    close(
        "rpe d5",
        num(&out, "rpe_trans_rmse_m"),
        num(&entry["results"]["rpe_trans_d5"], "rmse"),
    );
    // The per-axis rotation gain of the ground truth against itself is 1 on every turning axis.
    let gt = fx.join("synthetic_gt.txt");
    let gt = gt.to_str().expect("utf-8");
    let same = relfusion_eval(&["traj", "--gt", gt, "--est", gt]);
    assert_eq!(same["rotation_gain_delta"], 10);
    let gains = same["rotation_gain_xyz"].as_array().expect("three gains");
    assert_eq!(gains.len(), 3);
    assert!(gains.iter().any(|g| g.is_number()), "{same}");
    for g in gains.iter().filter_map(|g| g.as_f64()) {
        assert!((g - 1.0).abs() < 1e-9, "{same}");
    }
    // Against itself every window keeps the global scale: no drift, no window error.
    let windowed = relfusion_eval(&["traj", "--gt", gt, "--est", gt, "--scale-window", "20"]);
    assert_eq!(windowed["scale_window"], 20);
    let windows = windowed["scale_windows"].as_array().expect("windows");
    assert!(windows.len() >= 2, "{windowed}");
    assert!(
        (num(&windowed, "scale_drift") - 1.0).abs() < 1e-6,
        "{windowed}"
    );
    assert!(num(&windowed, "window_ate_rmse_max_m") < 1e-6, "{windowed}");
}

#[test]
fn eval_cli_traj_reports_bad_lines() {
    let dir = temp_dir("eval-bad-traj");
    let bad = dir.join("bad.txt");
    std::fs::write(&bad, "# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n").expect("write");
    let gt = fixture_dir().join("synthetic_gt.txt");
    let out = Command::new(bin_path("relfusion"))
        .args(["eval", "traj", "--gt"])
        .arg(&gt)
        .arg("--est")
        .arg(&bad)
        .output()
        .expect("run relfusion");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("bad.txt:3"),
        "error must name file and line: {stderr}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Writes an estimate for `gt` (metres) in units of 1/`scale`, with four pixel classes by
/// (x + 2y) mod 4: exact, +15 % (wrong), missing (wrong), −5 % (correct). Returns the expected
/// (valid_gt, evaluated, correct).
fn write_estimate(gt: &ImageF32, scale: f32, path: &Path) -> (u64, u64, u64) {
    let mut est = ImageF32::filled(gt.width, gt.height, 0.0);
    let (mut valid, mut evaluated, mut correct) = (0, 0, 0);
    for y in 0..gt.height {
        for x in 0..gt.width {
            let g = gt.at(x, y);
            let class = (x + 2 * y) % 4;
            *est.at_mut(x, y) = match class {
                0 => g / scale,
                1 => 1.15 * g / scale,
                2 => 0.0,
                _ => 0.95 * g / scale,
            };
            if g > 0.0 {
                valid += 1;
                evaluated += u64::from(class != 2);
                correct += u64::from(class == 0 || class == 3);
            }
        }
    }
    relfusion_slam::npy::write_f32(path, &est).expect("write estimate");
    (valid, evaluated, correct)
}

fn check_depth(gt: &Path, est: &Path, scale: f32, want: (u64, u64, u64)) {
    let out = relfusion_eval(&[
        "depth",
        "--gt-depth",
        gt.to_str().expect("utf-8"),
        "--est",
        est.to_str().expect("utf-8"),
        "--scale",
        &scale.to_string(),
    ]);
    let (valid, evaluated, correct) = want;
    assert!(
        valid > 0 && correct < valid,
        "the construction must leave wrong pixels"
    );
    assert_eq!(out["valid_gt"].as_u64(), Some(valid), "{out}");
    assert_eq!(out["evaluated"].as_u64(), Some(evaluated), "{out}");
    assert_eq!(out["correct"].as_u64(), Some(correct), "{out}");
    close(
        "percent_correct",
        num(&out, "percent_correct"),
        100.0 * correct as f64 / valid as f64,
    );
}

#[test]
fn eval_cli_depth_on_constructed_maps() {
    let dir = temp_dir("eval-depth");
    // Ground truth with an invalid band (0) and a ramp of depths.
    let mut gt = ImageF32::filled(64, 48, 0.0);
    for y in 0..48 {
        for x in 0..64 {
            *gt.at_mut(x, y) = if y < 5 {
                0.0
            } else {
                0.5 + 0.05 * (x + y) as f32
            };
        }
    }
    let gt_path = dir.join("gt.npy");
    relfusion_slam::npy::write_f32(&gt_path, &gt).expect("write gt");
    let est_path = dir.join("est.npy");
    let want = write_estimate(&gt, 3.5, &est_path);
    check_depth(&gt_path, &est_path, 3.5, want);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn eval_cli_depth_on_a_real_tum_png() {
    let seq = data_dir().join("sequences/tum_fr1_rpy_f0000-0249");
    let Some(png) = std::fs::read_to_string(seq.join("depth.txt"))
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| !l.starts_with('#'))
                .and_then(|l| l.split_whitespace().nth(1))
                .map(|p| seq.join(p))
        })
    else {
        eprintln!("skipping: {} not found (set RELFUSION_DATA)", seq.display());
        return;
    };
    let gt = relfusion_slam::eval::read_depth_map(&png, 5000.0).expect("read TUM depth PNG");
    let dir = temp_dir("eval-depth-png");
    let est_path = dir.join("est.npy");
    let want = write_estimate(&gt, 0.25, &est_path);
    assert!(
        want.0 < (gt.width * gt.height) as u64,
        "real depth has holes"
    );
    check_depth(&png, &est_path, 0.25, want);
    std::fs::remove_dir_all(&dir).ok();
}
