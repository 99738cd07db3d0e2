//! `relfusion bench densify` end to end: the real binary on small random `.npy` inputs in a
//! temp folder; its JSON line, both outputs (size, agreement) and a bad-input case.
//!
//! Runs the GPU path for real (lavapipe on machines without a GPU).

use std::path::Path;
use std::process::{Command, Output};

use relfusion_slam::image::ImageF32;
use relfusion_slam::npy;
use relfusion_tests::{bin_path, temp_dir};
use serde_json::Value;

/// Deterministic uniform values in [lo, hi) (SplitMix64: the tests crate has no RNG crate).
fn uniform(n: usize, lo: f32, hi: f32, seed: u64) -> Vec<f32> {
    let mut state = seed;
    (0..n)
        .map(|_| {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            lo + (hi - lo) * ((z >> 40) as f32 / (1u64 << 24) as f32)
        })
        .collect()
}

/// prior.npy (smooth plus noise), semidense.npy (~15% of the pixels near the prior),
/// variance.npy in `dir`, all `width × height`.
fn write_inputs(dir: &Path, width: usize, height: usize) {
    let n = width * height;
    let noise = uniform(n, -0.05, 0.05, 1);
    let prior: Vec<f32> = (0..n)
        .map(|i| 0.5 + (i % width) as f32 / width as f32 + noise[i])
        .collect();
    let keep = uniform(n, 0.0, 1.0, 2);
    let offset = uniform(n, 0.9, 1.1, 3);
    let semi: Vec<f32> = (0..n)
        .map(|i| {
            if keep[i] < 0.15 {
                prior[i] * offset[i]
            } else {
                0.0
            }
        })
        .collect();
    let var = uniform(n, 2e-4, 1e-3, 4);
    for (name, data) in [
        ("prior.npy", prior),
        ("semidense.npy", semi),
        ("variance.npy", var),
    ] {
        let image = ImageF32::from_vec(width, height, data).expect("sizes match");
        npy::write_f32(&dir.join(name), &image).expect("write input");
    }
}

fn bench_densify(dir: &Path, extra: &[&str]) -> Output {
    Command::new(bin_path("relfusion"))
        .args(["bench", "densify", "--inputs"])
        .arg(dir)
        .args(extra)
        .output()
        .expect("run relfusion")
}

fn num(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("`{key}` missing or not a number in {v}"))
}

#[test]
fn bench_densify_runs_both_paths_and_writes_agreeing_outputs() {
    let dir = temp_dir("bench-densify");
    let (width, height) = (41, 23);
    write_inputs(&dir, width, height);
    // A config that changes the iteration count proves the `[dense]` section is read.
    let config = dir.join("dense.toml");
    std::fs::write(&config, "[dense.densify]\niterations = 25\n").expect("write config");
    let out = bench_densify(
        &dir,
        &["--runs", "2", "--config", config.to_str().expect("utf-8")],
    );
    assert!(
        out.status.success(),
        "bench densify failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let lines: Vec<&str> = stdout.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one JSON line, got: {stdout}");
    let report: Value = serde_json::from_str(lines[0]).expect("stdout is JSON");
    assert_eq!(num(&report, "width"), width as f64);
    assert_eq!(num(&report, "height"), height as f64);
    assert_eq!(num(&report, "iterations"), 25.0);
    assert!(
        report["adapter"].as_str().is_some_and(|s| !s.is_empty()),
        "adapter name missing: {report}"
    );
    for key in ["gpu_ms", "cpu_ms"] {
        assert!(num(&report, key) > 0.0, "{key} not positive: {report}");
    }
    let (e0, eg, ec) = (
        num(&report, "energy_init"),
        num(&report, "energy_gpu"),
        num(&report, "energy_cpu"),
    );
    assert!(
        eg < e0 && ec < e0,
        "densification did not lower the energy: {report}"
    );
    assert!((eg - ec).abs() <= 1e-4 * ec, "energies differ: {report}");
    let max_abs_diff = num(&report, "max_abs_diff");

    let gpu = npy::read_f32(&dir.join("dense_gpu.npy")).expect("dense_gpu.npy");
    let cpu = npy::read_f32(&dir.join("dense_cpu.npy")).expect("dense_cpu.npy");
    for map in [&gpu, &cpu] {
        assert_eq!((map.width, map.height), (width, height));
        assert!(map.data.iter().all(|v| v.is_finite() && *v > 0.0));
    }
    let diff = gpu
        .data
        .iter()
        .zip(&cpu.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    // Same f32 arithmetic on both sides; see slam's gpu_densify tests for the bound.
    assert!(diff < 5e-3, "outputs differ by {diff}");
    assert!(
        (f64::from(diff) - max_abs_diff).abs() < 1e-9,
        "reported {max_abs_diff}, files {diff}"
    );
    // The outputs are the densified maps, not copies of the prior.
    let prior = npy::read_f32(&dir.join("prior.npy")).expect("prior");
    assert!(
        gpu.data
            .iter()
            .zip(&prior.data)
            .any(|(a, b)| (a - b).abs() > 1e-3)
    );
}

#[test]
fn bench_densify_names_the_file_on_bad_inputs() {
    let dir = temp_dir("bench-densify-bad");
    write_inputs(&dir, 16, 12);
    let wrong = ImageF32::filled(15, 12, 1e-3);
    npy::write_f32(&dir.join("variance.npy"), &wrong).expect("write");
    let out = bench_densify(&dir, &["--runs", "1"]);
    assert!(!out.status.success(), "mismatched sizes were accepted");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("variance.npy"),
        "message does not name the file: {stderr}"
    );
    assert!(
        !dir.join("dense_gpu.npy").exists(),
        "outputs written despite the error"
    );

    std::fs::remove_file(dir.join("semidense.npy")).expect("remove");
    let out = bench_densify(&dir, &["--runs", "1"]);
    assert!(!out.status.success(), "a missing file was accepted");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("semidense.npy"),
        "message does not name the file: {stderr}"
    );
}
