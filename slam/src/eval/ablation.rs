//! The paper's ablation of the densification energy (Table II), reproduced the paper's way:
//! the keyframes of one run are saved once (`OUT/keyframes/`, with every stage map), then
//! densification is re-run on them with each cost, and each result is scored exactly like the
//! `dense` stage of [`super::dense_depth`] (trajectory Sim(3) scale × keyframe scale, every
//! pixel with a valid ground truth).
//!
//! Rows, named as in Table II: "1" the semi-dense depth consistency (eq. 13), "(c)" with the
//! generalised Charbonnier penalty, "(f)" on the adaptively filtered semi-dense map (eqs. 4–9)
//! instead of the raw one, "2" the CNN depth-gradient consistency (eq. 11), "3" DeepFusion's
//! CNN depth consistency. `1(f)(c)+2` is the paper's method.

use std::path::Path;

use serde::Serialize;

use super::dense_depth::{DenseRun, StageScore, StageTally, score_depth};
use crate::dense::config::{DensifyParams, EnergyTerms};
use crate::dense::densify::{CpuDensifier, DensifyProblem, densify};
use crate::dense::gpu_densify::GpuDensifier;
use crate::{Error, Result};

/// One row of Table II: which semi-dense map feeds term 1, and which terms are on.
#[derive(Clone, Debug, PartialEq)]
pub struct AblationRow {
    /// The row's name in the paper ("1(f)(c)+2", ...).
    pub name: &'static str,
    /// "(f)": term 1 uses the filtered semi-dense map and its variance.
    pub filtered: bool,
    pub terms: EnergyTerms,
}

/// The rows of Table II, in the paper's order.
pub fn table_ii_rows() -> Vec<AblationRow> {
    let row = |name, filtered, charbonnier, cnn_grad, cnn_depth| AblationRow {
        name,
        filtered,
        terms: EnergyTerms {
            semi_dense: true,
            charbonnier,
            cnn_grad,
            cnn_depth,
        },
    };
    vec![
        row("1", false, false, false, false),
        row("1(c)", false, true, false, false),
        row("1(f)(c)", true, true, false, false),
        row("1(c)+2", false, true, true, false),
        row("1(f)(c)+2", true, true, true, false),
        row("1(c)+2+3", false, true, true, true),
        row("1(f)(c)+2+3", true, true, true, true),
    ]
}

/// One scored row of the report.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AblationRowScore {
    /// Table II's name of the cost.
    pub cost: String,
    pub filtered: bool,
    pub terms: EnergyTerms,
    /// Its accuracy (None when no keyframe could be scored).
    pub score: Option<StageScore>,
}

/// The JSON `relfusion eval ablation` prints.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AblationReport {
    pub threshold: f64,
    /// "gpu" or "cpu": where densification ran.
    pub compute: String,
    pub iterations: usize,
    pub trajectory_scale: f64,
    pub keyframes: usize,
    /// Keyframes densified and scored for every row.
    pub keyframes_evaluated: usize,
    /// Keyframes left out: no aligned prior (densified without a model), or no ground truth.
    pub skipped_no_prior: usize,
    pub skipped_no_gt: usize,
    /// The run's own dense maps on the same keyframes: equal to row `1(f)(c)+2` when the run
    /// used the same parameters (a check that the re-run reproduces the pipeline).
    pub stored_dense: Option<StageScore>,
    pub rows: Vec<AblationRowScore>,
}

/// Re-densifies every stored keyframe of `run` with each row of `rows` (`params` gives
/// everything but the terms) and scores the results against `dataset`'s depth. `gpu` runs the
/// kernel; `None` the CPU reference.
///
/// Fails when the store was written without the stage maps (they are the inputs).
pub fn run_ablation(
    dataset: &Path,
    run: &Path,
    rows: &[AblationRow],
    params: &DensifyParams,
    gpu: Option<&GpuDensifier>,
    threshold: f64,
) -> Result<AblationReport> {
    if !(threshold.is_finite() && threshold > 0.0) {
        return Err(Error::Eval(format!(
            "threshold must be finite and > 0, got {threshold}"
        )));
    }
    let run = DenseRun::open(dataset, run)?;
    if let Some(kf) = run.store.keyframes.iter().find(|k| !k.has_stages()) {
        return Err(Error::Eval(format!(
            "{}: keyframe {} (t = {}) was stored without its stage maps (semi-dense, \
             filtered, intensity); the ablation re-densifies from them: re-run `relfusion run` \
             with dense.keep_stages = true",
            run.store.dir.display(),
            kf.id,
            kf.stem
        )));
    }
    let s = run.trajectory_scale();
    let mut tallies = vec![StageTally::default(); rows.len()];
    let mut stored = StageTally::default();
    let (mut evaluated, mut no_prior, mut no_gt) = (0, 0, 0);
    for kf in &run.store.keyframes {
        let store = &run.store;
        let Some(prior_aligned) = store.read_map(kf, "prior_aligned")? else {
            no_prior += 1;
            continue;
        };
        let Some(gt) = run.ground_truth_depth(kf)? else {
            no_gt += 1;
            continue;
        };
        let map = |name: &str| {
            store
                .read_map(kf, name)?
                .ok_or_else(|| Error::Eval(format!("keyframe {}: map `{name}` is missing", kf.id)))
        };
        let (raw, raw_var) = (map("semidense")?, map("semidense_var")?);
        let (filt, filt_var) = (map("filtered")?, map("filtered_var")?);
        evaluated += 1;
        for (row, tally) in rows.iter().zip(&mut tallies) {
            let p = DensifyParams {
                terms: row.terms.clone(),
                ..params.clone()
            };
            let (semi, var) = if row.filtered {
                (&filt, &filt_var)
            } else {
                (&raw, &raw_var)
            };
            let problem = DensifyProblem::with_prior(&prior_aligned, semi, var, &p)?;
            let idepth = match gpu {
                Some(gpu) => densify(&problem, &p, gpu)?,
                None => densify(&problem, &p, &CpuDensifier)?,
            };
            let est = run.map_depth(kf, &idepth);
            if let Some(acc) = score_depth(&est, &gt, s, threshold, None)? {
                tally.add(&acc);
            }
        }
        if let Some(dense) = store.read_map(kf, "depth")?
            && let Some(acc) = score_depth(&dense, &gt, s, threshold, None)?
        {
            stored.add(&acc);
        }
    }
    Ok(AblationReport {
        threshold,
        compute: if gpu.is_some() { "gpu" } else { "cpu" }.to_string(),
        iterations: params.iterations,
        trajectory_scale: s,
        keyframes: run.store.keyframes.len(),
        keyframes_evaluated: evaluated,
        skipped_no_prior: no_prior,
        skipped_no_gt: no_gt,
        stored_dense: stored.score(),
        rows: rows
            .iter()
            .zip(&tallies)
            .map(|(row, t)| AblationRowScore {
                cost: row.name.to_string(),
                filtered: row.filtered,
                terms: row.terms.clone(),
                score: t.score(),
            })
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eval_ablation_rows_are_table_ii() {
        let rows = table_ii_rows();
        let names: Vec<_> = rows.iter().map(|r| r.name).collect();
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
        for r in &rows {
            // The name spells the switches.
            assert!(r.terms.semi_dense);
            assert_eq!(r.filtered, r.name.contains("(f)"), "{}", r.name);
            assert_eq!(r.terms.charbonnier, r.name.contains("(c)"), "{}", r.name);
            assert_eq!(r.terms.cnn_grad, r.name.contains("+2"), "{}", r.name);
            assert_eq!(r.terms.cnn_depth, r.name.contains("+3"), "{}", r.name);
        }
        // The paper's method is the default energy on the filtered map.
        let paper = rows.iter().find(|r| r.name == "1(f)(c)+2").expect("row");
        assert!(paper.filtered);
        assert_eq!(paper.terms, EnergyTerms::default());
    }
}
