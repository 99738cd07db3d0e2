//! `relfusion prior`: runs a depth-prior ONNX model over a TUM-layout RGB-D sequence and reports
//! how good the prior is on its own, as one JSON object on stdout.
//!
//! Per frame (shared data README §1.4): predict the relative inverse depth `p`, fit eq. (3)
//! `1/gt ≈ a·p + b` over the pixels with ground truth deeper than 0.1 m (plain least squares,
//! so frames whose prediction is inverted are scored, not skipped), convert back to depth
//! `d = 1/(a·p + b)` and take the paper's percentage of correct depth (relative error < 10 %,
//! over the valid ground-truth pixels). The figure is the mean over frames. A metric model is
//! also scored as it is, its metres against the sensor's with nothing fitted, and its per-frame
//! scale error is reported (`metric_scale`: percentiles over frames of the median ratio of the
//! sensor's depth to the model's), which bounds what anchoring a map's scale to it can reach.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use relfusion_client::latency::percentile;
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dense::{
    DepthPrior, ModelConfig, OnnxDepthPrior, aligned_depth, fit_scale_shift_unconstrained,
    inverse_depth_target,
};
use relfusion_slam::eval::{DEFAULT_DEPTH_THRESHOLD, percent_correct_depth};
use relfusion_slam::metric_scale;
use serde_json::json;

/// Ground truth closer than this (metres) is ignored, as in the shared data README §1.4.
const MIN_GT_DEPTH: f32 = 0.1;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// ONNX depth model (MiDaS-style relative inverse depth, or a depth network with a config).
    #[arg(long)]
    pub model: PathBuf,
    /// TOML/JSON model description, needed for models relfusion does not recognise.
    #[arg(long)]
    pub model_config: Option<PathBuf>,
    /// Sequence folder in TUM layout (rgb.txt, depth.txt / associations.txt, ...).
    pub dataset: PathBuf,
    /// Evaluate only the first N frames (default: all).
    #[arg(long)]
    pub frames: Option<usize>,
}

/// 10th, 50th and 90th percentiles of `values` (nearest rank), and the 90th over the 10th.
fn quantiles(values: &mut [f64]) -> Option<serde_json::Value> {
    values.sort_by(f64::total_cmp);
    let (p10, p50, p90) = (
        percentile(values, 0.1)?,
        percentile(values, 0.5)?,
        percentile(values, 0.9)?,
    );
    Some(json!({ "p10": p10, "p50": p50, "p90": p90, "p90_over_p10": p90 / p10 }))
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = args
        .model_config
        .as_deref()
        .map(ModelConfig::from_file)
        .transpose()
        .context("reading --model-config")?;
    let mut prior = OnnxDepthPrior::load(&args.model, config)
        .with_context(|| format!("loading {}", args.model.display()))?;
    let seq = TumSequence::open(&args.dataset, None)
        .with_context(|| format!("opening {}", args.dataset.display()))?;
    let n = args.frames.unwrap_or(seq.len()).min(seq.len());
    anyhow::ensure!(n > 0, "no frames to evaluate in {}", args.dataset.display());

    let metric = prior.describe().metric;
    let (mut percents, mut millis, mut inverted, mut skipped) = (Vec::new(), Vec::new(), 0, 0);
    let (mut unaligned, mut scales) = (Vec::new(), Vec::new());
    for i in 0..n {
        let Some(gt) = seq.load_depth(i)? else {
            skipped += 1;
            continue;
        };
        let rgb = seq.load_rgb(i)?;
        let t0 = Instant::now();
        let inv = prior.predict(&rgb)?.into_image();
        millis.push(t0.elapsed().as_secs_f64() * 1e3);
        let (target, mask) = inverse_depth_target(&gt, MIN_GT_DEPTH);
        let fit = match fit_scale_shift_unconstrained(&inv, &target, Some(&mask)) {
            Ok(fit) => fit,
            Err(e) => {
                tracing::warn!(frame = i, "skipped: {e}");
                skipped += 1;
                continue;
            }
        };
        if fit.a <= 0.0 {
            inverted += 1;
        }
        let acc = percent_correct_depth(
            &aligned_depth(&inv, &fit),
            &gt,
            1.0,
            DEFAULT_DEPTH_THRESHOLD,
        )?;
        percents.push(acc.percent);
        if metric {
            let mut depth = inv.clone();
            for v in &mut depth.data {
                *v = if *v > 0.0 { 1.0 / *v } else { 0.0 };
            }
            let raw = percent_correct_depth(&depth, &gt, 1.0, DEFAULT_DEPTH_THRESHOLD)?;
            unaligned.push(raw.percent);
            // The median of ρ_model / ρ_sensor = d_sensor / d_model over the pixels with both.
            scales.extend(metric_scale::observe(&inv, &target).map(|o| o.scale()));
        }
    }
    anyhow::ensure!(
        !percents.is_empty(),
        "no frame had usable ground-truth depth"
    );

    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let config = prior.describe();
    let out = json!({
        "model": config.name,
        "recognised_by": prior.recognition(),
        "model_sha256": prior.sha256(),
        "input": format!("{}x{}", config.input_width, config.input_height),
        "output": config.output,
        "output_kind": config.output_kind,
        "metric": config.metric,
        "dataset": args.dataset,
        "frames": percents.len(),
        "frames_skipped": skipped,
        "frames_inverted": inverted,
        "threshold": DEFAULT_DEPTH_THRESHOLD,
        "percent_correct_depth_mean": mean(&percents),
        "percent_correct_depth_median": median(&mut percents.clone()),
        // A metric model's metres taken as they are, with no scale or shift fitted.
        "percent_correct_depth_unaligned_mean": metric.then(|| mean(&unaligned)),
        // A metric model's per-frame scale error (sensor metres over the model's): how far
        // anchoring a map's scale to it can hold (issue 39).
        "metric_scale": metric.then(|| quantiles(&mut scales)).flatten(),
        "ms_per_frame_mean": mean(&millis),
        "ms_per_frame_median": median(&mut millis),
    });
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}
