//! Evaluation: trajectory accuracy (ATE, RPE) and depth accuracy (percentage of correct depth).
//!
//! The trajectory metrics reproduce evo (Grupp, <https://github.com/MichaelGrupp/evo>), the tool
//! most SLAM papers report with, figure for figure: `tests/fixtures/evo/expected.json` holds
//! evo's own outputs on three trajectory pairs and the tests assert equality to 1e-6.
//! - [`associate`]: pairs estimated and ground-truth poses by nearest timestamp (evo's
//!   `associate_trajectories`).
//! - [`umeyama`]: closed-form least-squares Sim(3)/SE(3) alignment (Umeyama, PAMI 1991).
//! - [`ate`]: absolute trajectory error on translations after alignment (`evo_ape`; Sturm et al.
//!   IROS 2012 §VI.B).
//! - [`rpe`]: relative pose error over a fixed frame offset (`evo_rpe`; Sturm et al. §VI.A).
//! - [`rotation_gain`]: per-axis share of the ground truth's rotation recovered (focal length,
//!   or rotation taken for translation).
//! - [`scale_drift`]: Sim(3) scale and ATE of consecutive windows (how much of a monocular ATE
//!   is scale drift).
//! - [`depth`]: the paper's reconstruction accuracy (§V.A, after CNN-SLAM).
//! - [`dense_depth`]: that accuracy per dense-layer stage over a run's stored keyframes.
//! - [`depth_slope`]: whether a map's depth ratios are right, compressed or stretched.
//! - [`ablation`]: Table II, re-densifying the stored keyframes with each energy.
//! - [`localization`]: recall and accuracy of a sequence localised in a saved map.
//! - [`mesh`]: surface accuracy and completeness of a fused mesh against ground-truth depth.

pub mod ablation;
pub mod associate;
pub mod ate;
pub mod dense_depth;
pub mod depth;
pub mod depth_slope;
pub mod fused_mesh;
pub mod localization;
pub mod mesh;
pub mod rotation_gain;
pub mod rpe;
pub mod scale_drift;
pub mod umeyama;

#[cfg(test)]
mod evo_tests;

pub use associate::{DEFAULT_MAX_DT, Matched, associate, associate_poses};
pub use ate::{AlignMode, AteResult, align, ate, ate_matched};
pub use depth::{DEFAULT_DEPTH_THRESHOLD, DepthAccuracy, percent_correct_depth, read_depth_map};
pub use mesh::{MeshScores, PointGrid, ground_truth_points, score_surface, transform_vertices};
pub use rotation_gain::{RotationGain, rotation_gain};
pub use rpe::{RpeResult, rpe, rpe_matched};
pub use scale_drift::{ScaleDrift, ScaleWindow, scale_drift};
pub use umeyama::umeyama;

use serde::Serialize;

use crate::{Error, Result};

/// Summary statistics of a list of errors, defined as evo's `PE.get_all_statistics`:
/// population standard deviation (`np.std`), median averaging the two middle values of an
/// even count (`np.median`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stats {
    /// √(Σe²/n).
    pub rmse: f64,
    pub mean: f64,
    pub median: f64,
    /// Population standard deviation √(Σ(e − mean)²/n).
    pub std: f64,
    pub min: f64,
    pub max: f64,
    /// Sum of squared errors Σe².
    pub sse: f64,
    /// Number of errors.
    pub count: usize,
}

impl Stats {
    /// Statistics of `errors`; fails on an empty list or a non-finite error.
    pub fn from_errors(errors: &[f64]) -> Result<Self> {
        if errors.is_empty() {
            return Err(Error::Eval("no errors to summarise".into()));
        }
        if let Some(bad) = errors.iter().find(|e| !e.is_finite()) {
            return Err(Error::Eval(format!("non-finite error {bad}")));
        }
        let n = errors.len() as f64;
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        let mean = errors.iter().sum::<f64>() / n;
        let var = errors.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / n;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mid = sorted.len() / 2;
        let median = if sorted.len() % 2 == 1 {
            sorted[mid]
        } else {
            0.5 * (sorted[mid - 1] + sorted[mid])
        };
        Ok(Self {
            rmse: (sse / n).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: sorted[0],
            max: sorted[sorted.len() - 1],
            sse,
            count: errors.len(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eval_stats_match_numpy_definitions() {
        // numpy: rmse=√(30/4), mean=2.5, median=2.5 (even count), std=√1.25, sse=30.
        let s = Stats::from_errors(&[4.0, 1.0, 3.0, 2.0]).expect("stats");
        assert_eq!(s.count, 4);
        assert!((s.rmse - 7.5_f64.sqrt()).abs() < 1e-15);
        assert_eq!(
            (s.mean, s.median, s.min, s.max, s.sse),
            (2.5, 2.5, 1.0, 4.0, 30.0)
        );
        assert!((s.std - 1.25_f64.sqrt()).abs() < 1e-15);
        let odd = Stats::from_errors(&[5.0, 1.0, 3.0]).expect("stats");
        assert_eq!(odd.median, 3.0);
    }

    #[test]
    fn eval_stats_reject_empty_and_nan() {
        assert!(Stats::from_errors(&[]).is_err());
        assert!(Stats::from_errors(&[1.0, f64::NAN]).is_err());
    }
}
