//! Parameters of the dense layer (`[dense]` in the pipeline config), with the paper's values
//! (Loo et al., IROS 2021, §IV "Implementation") as defaults.
//!
//! Every term of the densification energy can be switched off so that the paper's ablation
//! (Table II) can be run on the same keyframes (`relfusion eval ablation`).

use serde::{Deserialize, Serialize};

pub use crate::scale_shift::AlignParams;

use crate::{Error, Result};

/// Where the dense kernels run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DenseCompute {
    /// The WGSL kernels through wgpu (a real GPU, or lavapipe on a CPU-only machine); falls
    /// back to the CPU reference, with a warning, when no adapter can be opened.
    #[default]
    Gpu,
    /// The CPU reference implementations (the ground truth the GPU kernels are tested against).
    Cpu,
}

/// The semi-dense structure adaptive filter (§III-C, eqs. 4–9; §IV values).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FilterParams {
    /// Apply the filter ("(f)" in Table II). Default true.
    pub enabled: bool,
    /// Half window: 2 gives the paper's 5×5 window.
    pub radius: usize,
    /// Photometric similarity σs (intensity units 0..255). Paper: 76.5.
    pub sigma_s: f32,
    /// Geometric closeness σd (pixels). Paper: 2.
    pub sigma_d: f32,
    /// CNN depth consistency σc (ratio difference). Paper: 0.3.
    pub sigma_c: f32,
    /// Depth-uncertainty weight σu. Paper: 2.
    pub sigma_u: f32,
    /// Keep a filtered pixel only when its re-estimated variance (eq. 8) is below γ. Paper:
    /// 0.0025.
    pub gamma: f32,
    /// Also weigh eq. 8's squared deviations by w_c (the literal reading of eq. 8, where the
    /// deviations carry the full weight of eq. 7). Default false: w_c shapes D' (eq. 7) only,
    /// and V' weighs the deviations by w_s·w_d·w_u. With it, a gross outlier that every
    /// neighbour's ratio disagrees with (w_c ≈ 0 for all of them) keeps only its own weight,
    /// gets V' ≈ 0 and survives γ as the most trusted pixel of the map, the opposite of the
    /// filter's purpose (§III-C; measured in `dense::filter`'s plane test).
    pub consistency_in_variance: bool,
}

impl Default for FilterParams {
    fn default() -> Self {
        Self {
            enabled: true,
            radius: 2,
            sigma_s: 76.5,
            sigma_d: 2.0,
            sigma_c: 0.3,
            sigma_u: 2.0,
            gamma: 0.0025,
            consistency_in_variance: false,
        }
    }
}

/// Which terms of the densification energy are on (Table II's rows).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EnergyTerms {
    /// Term 2, CNN depth-gradient consistency E_CNN_grad (eq. 11). Default true.
    pub cnn_grad: bool,
    /// Term 1, semi-dense depth consistency E_semi-dense (eq. 13). Default true.
    pub semi_dense: bool,
    /// "(c)": the generalised Charbonnier penalty ρ on the semi-dense term. Default true.
    pub charbonnier: bool,
    /// Term 3, DeepFusion's CNN depth consistency `(1/|Ω|) Σ D'_CNN² (D − D'_CNN)²` (the CNN
    /// depth as its own uncertainty, as the paper's footnote describes). Default false: the
    /// paper's method leaves it out (Table II, last rows).
    pub cnn_depth: bool,
}

impl Default for EnergyTerms {
    fn default() -> Self {
        Self {
            cnn_grad: true,
            semi_dense: true,
            charbonnier: true,
            cnn_depth: false,
        }
    }
}

/// Densification by minimising E = E_CNN_grad + λ·E_semi-dense (§III-D, eqs. 10–13) with
/// Adam (§IV values).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DensifyParams {
    /// Adam iterations. Paper: 30.
    pub iterations: usize,
    /// Adam learning rate. Paper: 0.05.
    pub learning_rate: f32,
    /// Adam β1 (PyTorch default 0.9; the paper uses PyTorch's Adam).
    pub beta1: f32,
    /// Adam β2 (PyTorch default 0.999).
    pub beta2: f32,
    /// Adam ε (PyTorch default 1e-8).
    pub adam_epsilon: f32,
    /// Weight λ of the semi-dense term. Paper: 0.003.
    pub lambda: f32,
    /// Generalised Charbonnier exponent α, ρ(u) = (u² + ε²)^α. Paper: 0.45.
    pub alpha: f32,
    /// Generalised Charbonnier ε. Paper: 0.001.
    pub epsilon: f32,
    /// Weight of term 3 when `terms.cnn_depth` is on. The paper gives none; λ's value, so that
    /// it weighs like the semi-dense term.
    pub cnn_depth_weight: f32,
    /// Inverse depths are kept ≥ this (ln D must exist). Default 1e-3 (1000× the mean in the
    /// keyframe gauge).
    pub min_idepth: f32,
    /// Without a model: edge scale σ_edge (intensity units) of the image-edge-aware smoothness
    /// weights `exp(−|ΔI| / σ_edge)` that stand in for the prior's gradients. Default 10.
    pub edge_sigma: f32,
    /// The terms in force.
    pub terms: EnergyTerms,
}

impl Default for DensifyParams {
    fn default() -> Self {
        Self {
            iterations: 30,
            learning_rate: 0.05,
            beta1: 0.9,
            beta2: 0.999,
            adam_epsilon: 1e-8,
            lambda: 0.003,
            alpha: 0.45,
            epsilon: 0.001,
            cnn_depth_weight: 0.003,
            min_idepth: 1e-3,
            edge_sigma: 10.0,
            terms: EnergyTerms::default(),
        }
    }
}

/// Two-view consistency and pose-graph refinement (§III-E, eqs. 14–16).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TwoViewParams {
    /// Run the check and hand the consistent depth to the back end. Default true.
    pub enabled: bool,
    /// Consistency threshold τe on inverse depth (keyframe gauge). Paper: 0.001.
    pub tau_e: f32,
    /// Fewest consistent pixels (working resolution) for the consistent depth to replace the
    /// keyframe's semi-dense map in the back end; below it the keyframe keeps its semi-dense
    /// constraints. Default 500 (a converged semi-dense keyframe has a few thousand pixels at
    /// 320×240).
    pub min_pixels: usize,
    /// The paper's Table III baseline "*" (pose-graph refinement with ground-truth depth): the
    /// back end gets the keyframe's sensor depth (`Frame::sensor_depth`, RGB-D datasets only)
    /// instead of the two-view consistent estimate, brought to the keyframe's gauge by the
    /// median ratio to its semi-dense map ([`super::two_view::sensor_depth_map`]). It bounds
    /// what better dense depth can give the trajectory. Default false; keyframes without a
    /// sensor depth keep the normal refinement.
    pub ground_truth_depth: bool,
}

impl Default for TwoViewParams {
    fn default() -> Self {
        Self {
            enabled: true,
            tau_e: 0.001,
            min_pixels: 500,
            ground_truth_depth: false,
        }
    }
}

/// The `[dense]` section of the pipeline config. Its user settings are listed in
/// [`crate::pipeline::user_config`]; the rest is expert level: the filter's, the energy's and the
/// consistency test's parameters (the paper's §IV values), and the paper's ablations
/// (`densify.terms`, Table II; `two_view.ground_truth_depth`, the Table III baseline).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DenseConfig {
    /// Run the dense layer on every finished keyframe. Default true.
    pub enabled: bool,
    /// Working resolution of prior, filter and densification. Paper: 320×240.
    pub width: usize,
    pub height: usize,
    /// GPU kernels or their CPU references.
    pub compute: DenseCompute,
    /// Keyframes waiting for the dense worker; when full, a new keyframe is not densified (and
    /// counted) rather than slowing tracking down. Default 8.
    pub queue: usize,
    /// Keep every stage's maps (prior, aligned prior, raw/filtered semi-dense) in the
    /// [`super::DenseKeyframe`] for evaluation and `relfusion eval ablation`. Default false
    /// (the service keeps only the result); `relfusion run` turns it on.
    pub keep_stages: bool,
    /// Relative variance `(σ_ρ/ρ)²` a densified pixel gains per pixel (working resolution) of
    /// distance to the nearest filtered semi-dense pixel, in the published
    /// [`super::DenseKeyframe::variance`] that the fusion weighs by (`dense::support`). Eq.
    /// (16)'s variance is flat across the image while the densified error grows away from the
    /// semi-dense depth. Default 0.001, fitted to that growth on the synthetic orbit; 0
    /// publishes the paper's variance (docs/tuning.md, "Support variance").
    pub support_variance: f32,
    pub align: AlignParams,
    pub filter: FilterParams,
    pub densify: DensifyParams,
    pub two_view: TwoViewParams,
}

impl Default for DenseConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            width: 320,
            height: 240,
            compute: DenseCompute::Gpu,
            queue: 8,
            keep_stages: false,
            support_variance: 0.001,
            align: AlignParams::default(),
            filter: FilterParams::default(),
            densify: DensifyParams::default(),
            two_view: TwoViewParams::default(),
        }
    }
}

impl DenseConfig {
    /// Rejects values no run can use.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str| Err(Error::Config(format!("dense.{what}")));
        if self.width < 8 || self.height < 8 {
            return bad("width and height must be ≥ 8");
        }
        if self.queue == 0 {
            return bad("queue must be ≥ 1");
        }
        if self.two_view.ground_truth_depth && !self.enabled {
            return bad("two_view.ground_truth_depth needs the dense layer (dense.enabled = true)");
        }
        if !(self.support_variance.is_finite() && self.support_variance >= 0.0) {
            return bad("support_variance must be ≥ 0");
        }
        let f = &self.filter;
        if f.radius == 0 || f.radius > 7 {
            return bad("filter.radius must be in 1..=7");
        }
        for (name, v) in [
            ("filter.sigma_s", f.sigma_s),
            ("filter.sigma_d", f.sigma_d),
            ("filter.sigma_c", f.sigma_c),
            ("filter.gamma", f.gamma),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(&format!("{name} must be > 0"));
            }
        }
        if !(f.sigma_u.is_finite() && f.sigma_u >= 0.0) {
            return bad("filter.sigma_u must be ≥ 0");
        }
        let d = &self.densify;
        if d.iterations > 10_000 {
            return bad("densify.iterations must be ≤ 10000");
        }
        for (name, v) in [
            ("densify.learning_rate", d.learning_rate),
            ("densify.adam_epsilon", d.adam_epsilon),
            ("densify.alpha", d.alpha),
            ("densify.epsilon", d.epsilon),
            ("densify.min_idepth", d.min_idepth),
            ("densify.edge_sigma", d.edge_sigma),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(&format!("{name} must be > 0"));
            }
        }
        for (name, v) in [("densify.beta1", d.beta1), ("densify.beta2", d.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return bad(&format!("{name} must be in [0, 1)"));
            }
        }
        for (name, v) in [
            ("densify.lambda", d.lambda),
            ("densify.cnn_depth_weight", d.cnn_depth_weight),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(&format!("{name} must be ≥ 0"));
            }
        }
        if !(self.two_view.tau_e.is_finite() && self.two_view.tau_e > 0.0) {
            return bad("two_view.tau_e must be > 0");
        }
        if self.align.min_pixels < crate::scale_shift::MIN_ALIGN_PIXELS {
            return bad("align.min_pixels is below the fit's minimum");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_papers_and_validate() {
        let c = DenseConfig::default();
        c.validate().expect("defaults validate");
        assert_eq!((c.width, c.height), (320, 240));
        assert_eq!(c.filter.radius * 2 + 1, 5);
        assert_eq!(
            (c.filter.sigma_s, c.filter.sigma_d, c.filter.sigma_c),
            (76.5, 2.0, 0.3)
        );
        assert_eq!((c.filter.sigma_u, c.filter.gamma), (2.0, 0.0025));
        let d = &c.densify;
        assert_eq!((d.iterations, d.learning_rate, d.lambda), (30, 0.05, 0.003));
        assert_eq!((d.alpha, d.epsilon), (0.45, 0.001));
        assert_eq!(c.two_view.tau_e, 0.001);
        let mut bad = c.clone();
        bad.densify.learning_rate = 0.0;
        assert!(bad.validate().is_err());
    }
}
