//! The dense layer end to end through the real binaries: `relfusion run` on a rendered
//! synthetic sequence (exact ground-truth depth) with the PyDNet++ model from the shared data,
//! then `relfusion eval depth` and `relfusion eval ablation` on its output. Fails when the
//! densification stops improving on the prior, when the adaptive filter stops improving the
//! semi-dense map, or when the outputs of issue 4 go missing. The same without a model
//! (`no_model` mode).

use std::path::Path;

use relfusion_tests::{pydnet_model, relfusion_json, synth_sequence, temp_dir};
use serde_json::Value;

fn run_sequence(seq: &Path, out: &Path, model: Option<&Path>) -> Value {
    // LSD-SLAM's random initialisation: PyDNet++ (trained on Matterport) inverts the depth
    // ordering on much of the rendered room (about half of its keyframes are refused by the
    // a > 0 test of eq. 3), so initialising the first keyframe from it starts this sequence's
    // map badly; the dense layer still uses the prior wherever it aligns.
    let config = out.join("config.toml");
    std::fs::write(&config, "[pipeline]\ninit = \"random\"\n").expect("config");
    let mut args = vec![
        "run".to_string(),
        seq.display().to_string(),
        "--out".into(),
        out.display().to_string(),
        "--deterministic".into(),
        "--quiet".into(),
        "--config".into(),
        config.display().to_string(),
    ];
    if let Some(m) = model {
        args.extend(["--model".into(), m.display().to_string()]);
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    relfusion_json(&args)
}

fn percent(report: &Value, stage: &str) -> f64 {
    report["stages"][stage]["percent_mean"]
        .as_f64()
        .unwrap_or_else(|| panic!("no {stage} in {report}"))
}

#[test]
fn densified_depth_beats_the_prior_and_the_filter_cleans_the_semidense_map() {
    let Some(model) = pydnet_model() else {
        return;
    };
    let seq = synth_sequence("dense", 120, 1);
    let out = temp_dir("dense-prior");
    let summary = run_sequence(&seq, &out, Some(&model));
    assert_eq!(summary["dense_mode"], "prior", "{summary}");
    let keyframes = summary["keyframes"].as_u64().expect("keyframes");
    assert!(keyframes >= 3, "{summary}");
    assert_eq!(summary["keyframes_densified"].as_u64(), Some(keyframes));
    assert!(out.join("dense.ply").metadata().expect("dense.ply").len() > 10_000);
    let index: Value = serde_json::from_slice(
        &std::fs::read(out.join("keyframes/index.json")).expect("index.json"),
    )
    .expect("index");
    assert_eq!(
        index["keyframes"].as_array().map(Vec::len),
        Some(keyframes as usize)
    );
    let stem = index["keyframes"][0]["stem"].as_str().expect("stem");
    let depth = relfusion_slam::npy::read_f32(&out.join(format!("keyframes/{stem}.depth.npy")))
        .expect("depth.npy");
    assert_eq!((depth.width, depth.height), (320, 240));
    assert!(depth.data.iter().filter(|&&d| d > 0.0).count() > 320 * 240 / 2);
    // The published variance grows away from the semi-dense support (`dense.support_variance`
    // per pixel of distance): the relative variance of dense pixels ≥ 8 px from any filtered
    // semi-dense pixel exceeds that of the semi-dense pixels by at least half of 8 κ.
    let map = |name: &str| {
        relfusion_slam::npy::read_f32(&out.join(format!("keyframes/{stem}.{name}.npy")))
            .expect(name)
    };
    let (idepth, variance, filtered) = (map("idepth"), map("variance"), map("filtered"));
    let distance = relfusion_slam::dense::support::distance_to_support(&filtered);
    let median_sigma = |keep: &dyn Fn(f32) -> bool| {
        let mut rel: Vec<f32> = (0..idepth.data.len())
            .filter(|&i| idepth.data[i] > 0.0 && keep(distance[i]))
            .map(|i| variance.data[i].sqrt() / idepth.data[i])
            .collect();
        assert!(rel.len() > 100, "too few pixels");
        let mid = rel.len() / 2;
        *rel.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    let (on, far) = (median_sigma(&|d| d == 0.0), median_sigma(&|d| d >= 8.0));
    let kappa = relfusion_slam::dense::DenseConfig::default().support_variance;
    assert!(
        far * far - on * on > 0.5 * 8.0 * kappa,
        "relative σ {far} at ≥ 8 px vs {on} on semi-dense pixels"
    );

    let (seq_s, out_s) = (seq.display().to_string(), out.display().to_string());
    let report = relfusion_json(&["eval", "depth", "--dataset", &seq_s, "--run", &out_s]);
    let (gt_fit, dense) = (percent(&report, "prior_gt_fit"), percent(&report, "dense"));
    let (raw, filtered) = (
        percent(&report, "semidense_raw"),
        percent(&report, "semidense_filtered"),
    );
    eprintln!(
        "prior fitted to ground truth {gt_fit:.1} %, densified {dense:.1} %, semi-dense raw {raw:.1} %, filtered {filtered:.1} %"
    );
    assert!(dense >= gt_fit + 10.0, "{report}");
    assert!(filtered > raw, "{report}");

    let ablation = relfusion_json(&[
        "eval",
        "ablation",
        "--dataset",
        &seq_s,
        "--run",
        &out_s,
        "--cpu",
    ]);
    let rows = ablation["rows"].as_array().expect("rows");
    assert_eq!(rows.len(), 7, "{ablation}");
    let score = |cost: &str| {
        rows.iter()
            .find(|r| r["cost"] == cost)
            .and_then(|r| r["score"]["percent_mean"].as_f64())
            .unwrap_or_else(|| panic!("no row {cost} in {ablation}"))
    };
    assert!(score("1(f)(c)+2") > score("1"), "{ablation}");
}

#[test]
fn without_a_model_the_dense_layer_still_densifies() {
    let seq = synth_sequence("dense", 120, 1);
    let out = temp_dir("dense-nomodel");
    let summary = run_sequence(&seq, &out, None);
    assert_eq!(summary["dense_mode"], "no_model", "{summary}");
    assert!(
        summary["keyframes_densified"].as_u64().unwrap_or(0) >= 3,
        "{summary}"
    );
    let (seq_s, out_s) = (seq.display().to_string(), out.display().to_string());
    let report = relfusion_json(&["eval", "depth", "--dataset", &seq_s, "--run", &out_s]);
    assert!(report["stages"]["prior_aligned"].is_null(), "{report}");
    let dense = percent(&report, "dense");
    eprintln!("no model: densified {dense:.1} %");
    assert!(dense > 30.0, "{report}");
}
