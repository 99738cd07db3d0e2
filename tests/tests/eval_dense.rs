//! `relfusion eval depth --dataset --run` and `relfusion eval ablation` end to end: the real
//! binary on a run folder built by hand from a rendered synthetic sequence, whose every stage
//! map is the ground truth with a known distortion, so that each stage's score is known.
//!
//! The construction (map = ground truth shrunk by `SIGMA`, each keyframe in its own gauge with
//! scale `s_kf`): the true inverse depth of keyframe k in its gauge is `SIGMA·s_kf / d_gt`.
//! - `depth` (densified): exact → 100 %; it scores 0 % unless both the trajectory scale and
//!   the keyframe scale are applied.
//! - `prior`: `3 / d_gt + 0.7` (an affine function of the true inverse depth) → the per-frame
//!   ground-truth fit is exact → 100 %.
//! - `prior_aligned`: 1.2 × the true inverse depth → every depth 17 % short → 0 %.
//! - `semidense`: values on every 5th pixel, exact on even columns, twice the truth on odd ones
//!   → the share of even columns among its pixels.
//! - `filtered`: the same pixels, all exact → 100 %.

use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::Arc;

use nalgebra::Vector3;
use relfusion_slam::dataset::trajectory::{StampedPose, write_tum_trajectory};
use relfusion_slam::dataset::tum::TumSequence;
use relfusion_slam::dense::store::write_dense_keyframes;
use relfusion_slam::dense::{DenseKeyframe, DenseMode, DenseStages, DenseTimings, ScaleShift};
use relfusion_slam::geometry::{SE3, SO3, Sim3};
use relfusion_slam::image::ImageF32;
use relfusion_tests::{relfusion, synth_sequence, temp_dir};
use serde_json::Value;

/// Map units per metre are 1/SIGMA: the trajectory alignment must find scale SIGMA.
const SIGMA: f64 = 2.5;
/// Frames of the synthetic sequence and the keyframes taken from it.
const FRAMES: usize = 24;
const KEYFRAME_FRAMES: [usize; 4] = [0, 7, 15, 23];

/// What the construction implies, counted from the ground truth itself.
#[derive(Default)]
struct Expected {
    /// Pixels with a valid ground truth, over the keyframes with a prior / over all scored.
    valid_prior: usize,
    valid_all: usize,
    /// Semi-dense pixels with a valid ground truth, and the exact ones among them.
    semi: usize,
    semi_exact: usize,
    /// Mean over keyframes of the per-keyframe semi-dense percentage.
    semi_percents: Vec<f64>,
}

struct Fixture {
    dataset: PathBuf,
    run: PathBuf,
    expected: Expected,
}

fn map(gt: &ImageF32, f: impl Fn(usize, usize, f32) -> f32) -> ImageF32 {
    let mut out = ImageF32::filled(gt.width, gt.height, 0.0);
    for y in 0..gt.height {
        for x in 0..gt.width {
            *out.at_mut(x, y) = f(x, y, gt.at(x, y));
        }
    }
    out
}

/// Builds `run/keyframes.txt` and `run/keyframes/` for the keyframes of `KEYFRAME_FRAMES`
/// (the second one densified without a model), plus one keyframe with no dataset frame.
fn build_run(tag: &str) -> Fixture {
    let dataset = synth_sequence(tag, FRAMES, 3);
    let seq = TumSequence::open(&dataset, None).expect("open synthetic sequence");
    let camera = seq.camera;
    let run = temp_dir(tag);
    // A map frame unrelated to the ground truth's: rotated, shifted, shrunk by SIGMA.
    let map_from_gt = Sim3::new(
        SO3::exp(&Vector3::new(0.3, -0.2, 0.5)),
        Vector3::new(0.4, -1.0, 2.0),
        1.0 / SIGMA,
    );
    let mut expected = Expected::default();
    let mut keyframes = Vec::new();
    let mut trajectory = Vec::new();
    for (k, &i) in KEYFRAME_FRAMES.iter().enumerate() {
        let frame = &seq.frames[i];
        let gt = seq.load_depth(i).expect("depth").expect("synthetic depth");
        let world_from_camera = frame.world_from_camera.expect("synthetic pose");
        // The keyframe's pose in the map: rigid part moved by map_from_gt, its own scale s_kf.
        let in_map = map_from_gt * Sim3::from_se3(&world_from_camera, 1.0);
        let s_kf = 0.8 + 0.15 * k as f64;
        let world_from_keyframe = Sim3::new(in_map.rotation, in_map.translation, s_kf);
        trajectory.push(StampedPose {
            timestamp: frame.timestamp,
            world_from_camera: SE3::new(in_map.rotation, in_map.translation),
        });
        let g = (SIGMA * s_kf) as f32;
        let truth = |d: f32| if d > 0.0 { g / d } else { 0.0 };
        let with_prior = k != 1;
        let semi_pixel = |x: usize, y: usize| (x + 2 * y).is_multiple_of(5);
        let semidense = map(&gt, |x, y, d| {
            if !semi_pixel(x, y) {
                0.0
            } else if x % 2 == 0 {
                truth(d)
            } else {
                2.0 * truth(d)
            }
        });
        let filtered = map(&gt, |x, y, d| if semi_pixel(x, y) { truth(d) } else { 0.0 });
        let stages = DenseStages {
            intensity: seq.load_gray(i).expect("grey"),
            prior: with_prior
                .then(|| map(&gt, |_, _, d| if d > 0.0 { 3.0 / d + 0.7 } else { 0.7 })),
            prior_aligned: with_prior.then(|| map(&gt, |_, _, d| 1.2 * truth(d))),
            semidense,
            semidense_var: map(&gt, |x, y, _| if semi_pixel(x, y) { 1e-3 } else { 0.0 }),
            filtered,
            filtered_var: map(&gt, |x, y, _| if semi_pixel(x, y) { 1e-3 } else { 0.0 }),
        };
        let valid = gt.data.iter().filter(|&&d| d > 0.0).count();
        let (mut semi, mut exact) = (0, 0);
        for y in 0..gt.height {
            for x in 0..gt.width {
                if semi_pixel(x, y) && gt.at(x, y) > 0.0 {
                    semi += 1;
                    exact += usize::from(x % 2 == 0);
                }
            }
        }
        expected.valid_all += valid;
        if with_prior {
            expected.valid_prior += valid;
        }
        expected.semi += semi;
        expected.semi_exact += exact;
        expected
            .semi_percents
            .push(100.0 * exact as f64 / semi as f64);
        keyframes.push((
            DenseKeyframe {
                keyframe_id: k,
                timestamp: frame.timestamp,
                camera,
                world_from_keyframe,
                idepth: Arc::new(map(&gt, |_, _, d| truth(d))),
                variance: Arc::new(ImageF32::filled(gt.width, gt.height, 1e-3)),
                mode: if with_prior {
                    DenseMode::Prior
                } else {
                    DenseMode::NoModel
                },
                align: with_prior.then_some(ScaleShift {
                    a: 1.0,
                    b: 0.0,
                    used: semi,
                }),
                align_error: (!with_prior).then(|| "no depth model loaded".to_string()),
                consistent_pixels: 0,
                timings: DenseTimings::default(),
                stages: Some(Arc::new(stages)),
            },
            world_from_keyframe,
        ));
    }
    // A keyframe no dataset frame matches (its maps are never read for scoring).
    let mut stray = keyframes[0].clone();
    stray.0.keyframe_id = 99;
    stray.0.timestamp = 500.0;
    keyframes.push(stray);

    write_tum_trajectory(&run.join("keyframes.txt"), &trajectory).expect("keyframes.txt");
    write_dense_keyframes(&run.join("keyframes"), &keyframes).expect("store");
    Fixture {
        dataset,
        run,
        expected,
    }
}

fn json_of(out: &Output, what: &str) -> Value {
    assert!(
        out.status.success(),
        "{what} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "{what}: stdout is not one JSON object ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

fn path(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

fn num(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("`{key}` missing or not a number in {v}"))
}

fn count(v: &Value, key: &str) -> usize {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("`{key}` missing or not a count in {v}")) as usize
}

fn assert_close(what: &str, got: f64, want: f64, tol: f64) {
    assert!((got - want).abs() <= tol, "{what}: got {got}, want {want}");
}

#[test]
fn eval_dense_depth_scores_each_stage_as_constructed() {
    let fx = build_run("eval-dense-depth");
    let e = &fx.expected;
    let out = json_of(
        &relfusion(&[
            "eval",
            "depth",
            "--dataset",
            path(&fx.dataset),
            "--run",
            path(&fx.run),
        ]),
        "eval depth --dataset --run",
    );
    eprintln!("{out:#}");
    assert_close(
        "trajectory_scale",
        num(&out, "trajectory_scale"),
        SIGMA,
        1e-6,
    );
    assert!(num(&out, "ate_rmse_m") < 1e-6, "{out}");
    assert_eq!(count(&out, "ate_matched"), KEYFRAME_FRAMES.len());
    assert_eq!(count(&out, "keyframes"), KEYFRAME_FRAMES.len() + 1);
    assert_eq!(count(&out, "keyframes_evaluated"), KEYFRAME_FRAMES.len());
    assert_eq!(count(&out, "keyframes_without_gt"), 1);
    assert_eq!(count(&out, "no_model_keyframes"), 1);
    assert_eq!(count(&out, "prior_gt_fit_failures"), 0);
    assert_close("threshold", num(&out, "threshold"), 0.1, 0.0);

    let stages = &out["stages"];
    let n = KEYFRAME_FRAMES.len();
    // (stage, mean %, pooled %, pixels, keyframes)
    let semi_mean = e.semi_percents.iter().sum::<f64>() / n as f64;
    let semi_pooled = 100.0 * e.semi_exact as f64 / e.semi as f64;
    for (stage, mean, pooled, pixels, keyframes) in [
        ("prior_gt_fit", 100.0, 100.0, e.valid_prior, n - 1),
        ("prior_aligned", 0.0, 0.0, e.valid_prior, n - 1),
        ("semidense_raw", semi_mean, semi_pooled, e.semi, n),
        ("semidense_filtered", 100.0, 100.0, e.semi, n),
        ("dense", 100.0, 100.0, e.valid_all, n),
        ("dense_keyframe_scale", 100.0, 100.0, e.valid_all, n),
    ] {
        let s = &stages[stage];
        assert_close(&format!("{stage} mean"), num(s, "percent_mean"), mean, 1e-9);
        assert_close(
            &format!("{stage} pooled"),
            num(s, "percent_pooled"),
            pooled,
            1e-9,
        );
        assert_eq!(count(s, "pixels"), pixels, "{stage}");
        assert_eq!(count(s, "keyframes"), keyframes, "{stage}");
    }
    // The raw semi-dense stage is neither all right nor all wrong: the mask matters.
    assert!(semi_mean > 30.0 && semi_mean < 70.0, "{semi_mean}");

    // The densified maps agree with the trajectory's scale: every keyframe's ratio is 1.
    let ratios = out["dense_scale_ratios"]
        .as_array()
        .expect("dense_scale_ratios");
    assert_eq!(ratios.len(), n, "{out}");
    for r in ratios {
        assert_close("ratio", num(r, "ratio"), 1.0, 1e-5);
    }

    // Depth-range slopes, one entry per scored keyframe: the semi-dense map is the truth up to
    // a factor 2 unrelated to depth (slope ≈ 1); the prior 3ρ + 0.7 is compressed (slope < 1);
    // the keyframe without a model has no prior.
    let slopes = out["depth_range_slopes"]
        .as_array()
        .expect("depth_range_slopes");
    assert_eq!(slopes.len(), n, "{out}");
    for (k, s) in slopes.iter().enumerate() {
        let semi = num(s, "semidense");
        assert!(
            (semi - 1.0).abs() < 0.05,
            "keyframe {k}: semi-dense slope {semi}"
        );
        if k == 1 {
            assert!(s["prior"].is_null(), "{s}");
        } else {
            let prior = num(s, "prior");
            assert!(
                prior > 0.3 && prior < 0.95,
                "keyframe {k}: prior slope {prior}"
            );
        }
    }

    // A tighter threshold cannot make more pixels right; 25 % accepts the aligned prior
    // (every depth 1/1.2 of the truth, 16.7 % short).
    let loose = json_of(
        &relfusion(&[
            "eval",
            "depth",
            "--dataset",
            path(&fx.dataset),
            "--run",
            path(&fx.run),
            "--threshold",
            "0.25",
        ]),
        "eval depth --threshold 0.25",
    );
    assert_close(
        "prior_aligned at 25 %",
        num(&loose["stages"]["prior_aligned"], "percent_pooled"),
        100.0,
        1e-9,
    );
    std::fs::remove_dir_all(&fx.run).ok();
}

#[test]
fn eval_dense_depth_reports_absent_stages_as_null() {
    // A run densified entirely without a model and stored without stages: only `dense`.
    let dataset = synth_sequence("eval-dense-null", FRAMES, 3);
    let seq = TumSequence::open(&dataset, None).expect("open");
    let run = temp_dir("eval-dense-null");
    let mut keyframes = Vec::new();
    let mut trajectory = Vec::new();
    for (k, &i) in KEYFRAME_FRAMES.iter().enumerate() {
        let frame = &seq.frames[i];
        let pose = frame.world_from_camera.expect("pose");
        let gt = seq.load_depth(i).expect("depth").expect("depth");
        trajectory.push(StampedPose {
            timestamp: frame.timestamp,
            world_from_camera: pose,
        });
        keyframes.push((
            DenseKeyframe {
                keyframe_id: k,
                timestamp: frame.timestamp,
                camera: seq.camera,
                world_from_keyframe: Sim3::from_se3(&pose, 1.0),
                // 20 % too far everywhere: 1/(0.8·d) is 25 % over → 0 %.
                idepth: Arc::new(map(&gt, |_, _, d| if d > 0.0 { 0.8 / d } else { 0.0 })),
                variance: Arc::new(ImageF32::filled(gt.width, gt.height, 1e-3)),
                mode: DenseMode::NoModel,
                align: None,
                align_error: Some("no depth model loaded".into()),
                consistent_pixels: 0,
                timings: DenseTimings::default(),
                stages: None,
            },
            Sim3::from_se3(&pose, 1.0),
        ));
    }
    write_tum_trajectory(&run.join("keyframes.txt"), &trajectory).expect("keyframes.txt");
    write_dense_keyframes(&run.join("keyframes"), &keyframes).expect("store");
    let out = json_of(
        &relfusion(&[
            "eval",
            "depth",
            "--dataset",
            path(&dataset),
            "--run",
            path(&run),
        ]),
        "eval depth on a no-model run",
    );
    let stages = &out["stages"];
    for stage in [
        "prior_gt_fit",
        "prior_aligned",
        "semidense_raw",
        "semidense_filtered",
    ] {
        assert!(stages[stage].is_null(), "{stage} should be null: {out}");
    }
    assert_eq!(num(&stages["dense"], "percent_mean"), 0.0, "{out}");
    // Each keyframe at its own scale is right: its depth is 1.25× the trajectory's unit.
    assert_close(
        "dense_keyframe_scale",
        num(&stages["dense_keyframe_scale"], "percent_mean"),
        100.0,
        1e-9,
    );
    let ratios = out["dense_scale_ratios"]
        .as_array()
        .expect("dense_scale_ratios");
    assert_eq!(ratios.len(), KEYFRAME_FRAMES.len(), "{out}");
    for r in ratios {
        assert_close("ratio", num(r, "ratio"), 0.8, 1e-5);
    }
    assert_eq!(count(&out, "no_model_keyframes"), KEYFRAME_FRAMES.len());
    assert_close("trajectory_scale", num(&out, "trajectory_scale"), 1.0, 1e-9);

    // The ablation needs the stage maps and says so.
    let abl = relfusion(&[
        "eval",
        "ablation",
        "--dataset",
        path(&dataset),
        "--run",
        path(&run),
        "--cpu",
    ]);
    assert!(!abl.status.success(), "ablation without stages must fail");
    let err = String::from_utf8_lossy(&abl.stderr);
    assert!(err.contains("keep_stages"), "unclear error: {err}");
    std::fs::remove_dir_all(&run).ok();
}

#[test]
fn eval_dense_depth_without_keyframes_fails_clearly() {
    let dataset = synth_sequence("eval-dense-missing", FRAMES, 3);
    let run = temp_dir("eval-dense-missing");
    std::fs::write(run.join("keyframes.txt"), "").expect("write");
    let out = relfusion(&[
        "eval",
        "depth",
        "--dataset",
        path(&dataset),
        "--run",
        path(&run),
    ]);
    assert!(!out.status.success(), "a run without keyframes/ must fail");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("keyframes") && err.contains("no densified keyframes"),
        "unclear error: {err}"
    );
    assert!(out.stdout.is_empty(), "no JSON on failure");
    // Half of a mode is a usage error.
    let half = relfusion(&["eval", "depth", "--dataset", path(&dataset)]);
    assert!(!half.status.success());
    std::fs::remove_dir_all(&run).ok();
}

#[test]
fn eval_ablation_rows_on_a_constructed_store() {
    let fx = build_run("eval-dense-ablation");
    let out = json_of(
        &relfusion(&[
            "eval",
            "ablation",
            "--dataset",
            path(&fx.dataset),
            "--run",
            path(&fx.run),
            "--cpu",
        ]),
        "eval ablation",
    );
    eprintln!("{out:#}");
    let n = KEYFRAME_FRAMES.len();
    assert_eq!(out["compute"], "cpu");
    assert_eq!(count(&out, "iterations"), 30);
    assert_eq!(count(&out, "keyframes"), n + 1);
    // The no-model keyframe has no prior; the stray one no ground truth.
    assert_eq!(count(&out, "skipped_no_prior"), 1);
    assert_eq!(count(&out, "skipped_no_gt"), 1);
    assert_eq!(count(&out, "keyframes_evaluated"), n - 1);
    assert_close(
        "trajectory_scale",
        num(&out, "trajectory_scale"),
        SIGMA,
        1e-6,
    );
    // The stored dense maps are exact.
    assert_close(
        "stored_dense",
        num(&out["stored_dense"], "percent_mean"),
        100.0,
        1e-9,
    );
    let rows = out["rows"].as_array().expect("rows");
    let names: Vec<&str> = rows
        .iter()
        .map(|r| r["cost"].as_str().expect("cost"))
        .collect();
    assert_eq!(
        names,
        [
            "1",
            "1(c)",
            "1(f)(c)",
            "1(c)+2",
            "1(f)(c)+2",
            "1(c)+2+3",
            "1(f)(c)+2+3"
        ]
    );
    let score = |name: &str| {
        let row = rows
            .iter()
            .find(|r| r["cost"] == name)
            .unwrap_or_else(|| panic!("row {name}"));
        assert_eq!(count(&row["score"], "keyframes"), n - 1, "{name}");
        assert_eq!(
            count(&row["score"], "pixels"),
            fx.expected.valid_prior,
            "{name}"
        );
        num(&row["score"], "percent_mean")
    };
    // The aligned prior is 20 % off everywhere (0 % correct), but its log-gradients are the
    // truth's and the filtered semi-dense map is exact: the paper's energy must pull the depth
    // towards the truth far more than the semi-dense term alone on the raw map.
    let paper = score("1(f)(c)+2");
    let semi_only = score("1");
    assert!(
        paper > semi_only + 10.0,
        "1(f)(c)+2 {paper:.1} % vs 1 {semi_only:.1} %"
    );
    std::fs::remove_dir_all(&fx.run).ok();
}
