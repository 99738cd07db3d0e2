//! Densification of the semi-dense structure (§III-D, eqs. 10–13): the per-pixel inverse depth
//! `D` that minimises
//!
//! ```text
//! E = E_CNN_grad (eq. 11) + λ·E_semi-dense (eq. 13) [+ term 3, DeepFusion's CNN depth]
//! ```
//!
//! by Adam from the aligned prior, as the paper does with PyTorch autograd — here with the
//! gradient written out analytically (checked against numeric differences of [`energy`] in the
//! tests) so that the GPU kernel can compute it pixel by pixel (`densify_adam.wgsl`,
//! [`super::gpu_densify`]).
//!
//! # One energy for every variant
//! A [`DensifyProblem`] holds per-pixel weight maps, so the kernel never knows which variant it
//! solves: [`DensifyProblem::with_prior`] builds the paper's energy and every Table II row (the
//! term switches of [`EnergyTerms`](super::EnergyTerms) zero weights or scales), and
//! [`DensifyProblem::without_prior`] builds the no-model variant (image-edge-aware smoothness in
//! place of the prior's gradients). In terms of `L = ln D` and forward differences
//! (zero at the last column / row):
//!
//! ```text
//! ex(n) = L(x+1,y) − L(x,y) − tx(n),   ey(n) = L(x,y+1) − L(x,y) − ty(n)
//! E = grad_scale · Σ_n [wx·ex² + wy·ey²]
//!   + semi_scale · Σ_{semi>0} ρ((D − semi)² / semi_var)
//!   + grad_scale · Σ_n cnn_weight · (D − cnn)²
//! ```
//!
//! # Reading of eq. (13)
//! The paper applies the generalised Charbonnier ρ(u) = (u² + ε²)^α to the *squared*
//! variance-normalised residual `u = (D − D'_semi)² / V'_semi`, as printed. We follow the print:
//! with α = 0.45 this behaves like `|r|^1.8 / V^0.9` for large residuals (close to the
//! least-squares term the paper extends, yet robust), and the ε = 0.001 floor keeps it smooth
//! at zero. With `terms.charbonnier` off, ρ(u) = u (plain variance-weighted least squares).
//!
//! # Adam
//! PyTorch's `torch.optim.Adam` (no weight decay, no amsgrad), `t` counted from 1:
//! `m = β1 m + (1−β1) g`, `v = β2 v + (1−β2) g²`,
//! `D −= lr · (m / (1−β1^t)) / (sqrt(v / (1−β2^t)) + ε_adam)`, evaluated in PyTorch's own
//! order (`step_size = lr / (1−β1^t)`, `denom = sqrt(v) / sqrt(1−β2^t) + ε_adam`,
//! `D −= step_size · m / denom`, see [`adam_step_constants`]), then `D = max(D, min_idepth)`
//! so that `ln D` exists (the projection PyTorch's users add with `clamp_`). Every pixel's
//! gradient is taken at the previous iterate before any pixel moves (a Jacobi sweep, as
//! autograd does), which is what lets the GPU update every pixel independently.

use super::config::DensifyParams;
use crate::image::ImageF32;
use crate::{Error, Result};

/// The densification energy of one keyframe as per-pixel maps (see the module docs). All maps
/// are row-major `width × height`.
#[derive(Clone, Debug, PartialEq)]
pub struct DensifyProblem {
    pub width: usize,
    pub height: usize,
    /// Initial inverse depth: the aligned prior `D'_CNN` (no model: the filled semi-dense map).
    pub init: Vec<f32>,
    /// Weight of the horizontal (`wx`) and vertical (`wy`) forward-difference terms at each
    /// pixel; 0 where the difference does not exist (last column / row) or the term is off.
    pub wx: Vec<f32>,
    pub wy: Vec<f32>,
    /// Target log-gradients (forward differences of `ln D'_CNN`; 0 without a model).
    pub tx: Vec<f32>,
    pub ty: Vec<f32>,
    /// `D'_semi`, 0 where there is none; every pixel with `semi > 0` has `semi_var > 0`.
    pub semi: Vec<f32>,
    /// `V'_semi` (ignored where `semi` is 0).
    pub semi_var: Vec<f32>,
    /// Term 3's target `D'_CNN` and its weight `μ·D'_CNN²` (0 when the term is off).
    pub cnn: Vec<f32>,
    pub cnn_weight: Vec<f32>,
    /// `λ / |Ω_i|` (0 when the semi-dense term is off or `Ω_i` is empty).
    pub semi_scale: f32,
    /// `1 / |Ω|` (eq. 11's normalisation; also term 3's).
    pub grad_scale: f32,
}

impl DensifyProblem {
    /// The paper's energy (eqs. 10–13) on an aligned prior: `wx = wy = D'_CNN²` (eq. 11
    /// divides by the prior's "variance" `(1/D'_CNN)²`), `tx`, `ty` the forward differences of
    /// `ln D'_CNN`. The switches of `params.terms` select the Table II row: `cnn_grad` off
    /// zeroes `wx`, `wy`; `semi_dense` off zeroes `semi_scale`; `cnn_depth` on sets
    /// `cnn_weight = params.cnn_depth_weight · D'_CNN²`.
    ///
    /// Prior values below `params.min_idepth` (an eq. (3) shift can push far pixels below zero)
    /// are raised to it: an inverse depth must be positive for `ln` to exist. Semi-dense pixels
    /// count (`Ω_i`) only where both `D'_semi` and `V'_semi` are finite and positive.
    pub fn with_prior(
        prior_aligned: &ImageF32,
        semidense: &ImageF32,
        semi_var: &ImageF32,
        params: &DensifyParams,
    ) -> Result<Self> {
        check_inputs(
            prior_aligned,
            &[("semi-dense", semidense), ("variance", semi_var)],
        )?;
        if prior_aligned.data.iter().any(|v| !v.is_finite()) {
            return Err(Error::Prior(
                "the aligned prior has non-finite values".into(),
            ));
        }
        let (w, h) = (prior_aligned.width, prior_aligned.height);
        let prior: Vec<f32> = prior_aligned
            .data
            .iter()
            .map(|&v| v.max(params.min_idepth))
            .collect();
        let log_prior: Vec<f32> = prior.iter().map(|v| v.ln()).collect();
        let terms = &params.terms;
        let n = w * h;
        let (mut wx, mut wy) = (vec![0.0; n], vec![0.0; n]);
        let (mut tx, mut ty) = (vec![0.0; n], vec![0.0; n]);
        if terms.cnn_grad {
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    let weight = prior[i] * prior[i];
                    if x + 1 < w {
                        wx[i] = weight;
                        tx[i] = log_prior[i + 1] - log_prior[i];
                    }
                    if y + 1 < h {
                        wy[i] = weight;
                        ty[i] = log_prior[i + w] - log_prior[i];
                    }
                }
            }
        }
        let cnn_weight = if terms.cnn_depth {
            prior
                .iter()
                .map(|p| params.cnn_depth_weight * p * p)
                .collect()
        } else {
            vec![0.0; n]
        };
        let (semi, var, count) = valid_semidense(semidense, semi_var);
        Ok(Self {
            width: w,
            height: h,
            init: prior.clone(),
            wx,
            wy,
            tx,
            ty,
            semi,
            semi_var: var,
            cnn: prior,
            cnn_weight,
            semi_scale: semi_scale(params, count),
            grad_scale: 1.0 / n as f32,
        })
    }

    /// The no-model variant (a user without a depth model): the smoothness weights follow the
    /// image edges, `wx = exp(−|I(x+1,y) − I(x,y)|/edge_sigma)` (`wy` likewise), the target
    /// log-gradients are 0 (piecewise-constant log depth between edges), term 3 is off (there
    /// is no CNN depth), and the start is the semi-dense map with its holes filled by push-pull
    /// interpolation. `terms.cnn_grad` switches the smoothness term (it stands in for the
    /// prior's gradients), `terms.semi_dense` the data term.
    ///
    /// Fails when the semi-dense map has no valid pixel: there is nothing to densify.
    pub fn without_prior(
        intensity: &ImageF32,
        semidense: &ImageF32,
        semi_var: &ImageF32,
        params: &DensifyParams,
    ) -> Result<Self> {
        check_inputs(
            intensity,
            &[("semi-dense", semidense), ("variance", semi_var)],
        )?;
        let (w, h) = (intensity.width, intensity.height);
        let n = w * h;
        let (semi, var, count) = valid_semidense(semidense, semi_var);
        if count == 0 {
            return Err(Error::Shape(
                "the semi-dense map has no valid pixel: nothing to densify without a prior".into(),
            ));
        }
        let valid: Vec<bool> = semi.iter().map(|&s| s > 0.0).collect();
        let init = push_pull_fill(&semi, &valid, w, h);
        let (mut wx, mut wy) = (vec![0.0; n], vec![0.0; n]);
        if params.terms.cnn_grad {
            let edge = |a: f32, b: f32| {
                let weight = (-(a - b).abs() / params.edge_sigma).exp();
                // A NaN intensity must not poison the energy: no smoothing across it.
                if weight.is_finite() { weight } else { 0.0 }
            };
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    if x + 1 < w {
                        wx[i] = edge(intensity.data[i + 1], intensity.data[i]);
                    }
                    if y + 1 < h {
                        wy[i] = edge(intensity.data[i + w], intensity.data[i]);
                    }
                }
            }
        }
        Ok(Self {
            width: w,
            height: h,
            init,
            wx,
            wy,
            tx: vec![0.0; n],
            ty: vec![0.0; n],
            semi,
            semi_var: var,
            cnn: vec![0.0; n],
            cnn_weight: vec![0.0; n],
            semi_scale: semi_scale(params, count),
            grad_scale: 1.0 / n as f32,
        })
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True for a 0-pixel problem (never built by the constructors).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Checks what the solvers index by: every map has `width × height` values, the size is
    /// not empty, and every semi-dense pixel has a positive finite variance (the kernel
    /// divides by it).
    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        if n == 0 {
            return Err(Error::Shape("empty densification problem".into()));
        }
        for (name, map) in [
            ("init", &self.init),
            ("wx", &self.wx),
            ("wy", &self.wy),
            ("tx", &self.tx),
            ("ty", &self.ty),
            ("semi", &self.semi),
            ("semi_var", &self.semi_var),
            ("cnn", &self.cnn),
            ("cnn_weight", &self.cnn_weight),
        ] {
            if map.len() != n {
                return Err(Error::Shape(format!(
                    "densify: {name} has {} values for {}x{}",
                    map.len(),
                    self.width,
                    self.height
                )));
            }
        }
        if let Some(i) = (0..n).find(|&i| {
            self.semi[i] > 0.0 && !(self.semi_var[i].is_finite() && self.semi_var[i] > 0.0)
        }) {
            return Err(Error::Shape(format!(
                "densify: semi-dense pixel {i} has variance {}",
                self.semi_var[i]
            )));
        }
        Ok(())
    }

    /// The starting point of Adam: `max(init, min_idepth)`.
    pub fn start(&self, params: &DensifyParams) -> Vec<f32> {
        self.init.iter().map(|v| v.max(params.min_idepth)).collect()
    }
}

/// Sizes of the inputs against the reference map.
fn check_inputs(reference: &ImageF32, others: &[(&str, &ImageF32)]) -> Result<()> {
    reference.check_size()?;
    if reference.data.is_empty() {
        return Err(Error::Shape("densify: empty input".into()));
    }
    for (name, image) in others {
        image.check_size()?;
        if (image.width, image.height) != (reference.width, reference.height) {
            return Err(Error::Shape(format!(
                "densify: the {name} map is {}x{}, expected {}x{}",
                image.width, image.height, reference.width, reference.height
            )));
        }
    }
    Ok(())
}

/// The semi-dense pixels `Ω_i` that the data term may use (positive finite depth and
/// variance): `(semi, variance, |Ω_i|)` with 0 elsewhere.
fn valid_semidense(semidense: &ImageF32, semi_var: &ImageF32) -> (Vec<f32>, Vec<f32>, usize) {
    let mut count = 0;
    let (semi, var) = semidense
        .data
        .iter()
        .zip(&semi_var.data)
        .map(|(&d, &v)| {
            if d.is_finite() && d > 0.0 && v.is_finite() && v > 0.0 {
                count += 1;
                (d, v)
            } else {
                (0.0, 0.0)
            }
        })
        .unzip();
    (semi, var, count)
}

/// `λ / |Ω_i|` for eq. (13), 0 when the term is off or has no pixel.
fn semi_scale(params: &DensifyParams, count: usize) -> f32 {
    if params.terms.semi_dense && count > 0 {
        params.lambda / count as f32
    } else {
        0.0
    }
}

/// Fills the pixels where `valid` is false by push-pull interpolation: average the valid
/// pixels 2×2 into ever coarser levels until a level has no hole (at the latest at 1×1), then
/// fill each finer level's holes by bilinear interpolation of the filled coarser level. Valid
/// pixels keep their values. Needs at least one valid pixel.
fn push_pull_fill(values: &[f32], valid: &[bool], width: usize, height: usize) -> Vec<f32> {
    // Level k: (width, height, values, weight 0/1).
    let mut levels = vec![(
        width,
        height,
        values.to_vec(),
        valid
            .iter()
            .map(|&v| if v { 1.0f32 } else { 0.0 })
            .collect::<Vec<f32>>(),
    )];
    loop {
        let (w, h, vals, weights) = &levels[levels.len() - 1];
        if (*w == 1 && *h == 1) || weights.iter().all(|&m| m > 0.0) {
            break;
        }
        let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
        let mut cv = vec![0.0f32; cw * ch];
        let mut cm = vec![0.0f32; cw * ch];
        for y in 0..*h {
            for x in 0..*w {
                let i = y * w + x;
                if weights[i] > 0.0 {
                    let c = (y / 2) * cw + x / 2;
                    cv[c] += vals[i];
                    cm[c] += 1.0;
                }
            }
        }
        for (v, &m) in cv.iter_mut().zip(&cm) {
            if m > 0.0 {
                *v /= m;
            }
        }
        levels.push((cw, ch, cv, cm));
    }
    // Pull: the coarsest level is hole-free; fill each finer level from the one above.
    for k in (0..levels.len() - 1).rev() {
        let (upper, lower) = levels.split_at_mut(k + 1);
        let (w, h, vals, weights) = &mut upper[k];
        let (cw, ch, coarse, _) = &lower[0];
        for y in 0..*h {
            for x in 0..*w {
                let i = y * *w + x;
                if weights[i] > 0.0 {
                    continue;
                }
                // Pixel centres: fine x ↦ coarse (x + 0.5)/2 − 0.5.
                let sample = |p: usize, size: usize| {
                    let c = ((p as f32 + 0.5) * 0.5 - 0.5).clamp(0.0, (size - 1) as f32);
                    let c0 = c.floor() as usize;
                    (c0, (c0 + 1).min(size - 1), c - c0 as f32)
                };
                let (x0, x1, fx) = sample(x, *cw);
                let (y0, y1, fy) = sample(y, *ch);
                let at = |xx: usize, yy: usize| coarse[yy * *cw + xx];
                let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
                let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
                vals[i] = top * (1.0 - fy) + bottom * fy;
                weights[i] = 1.0;
            }
        }
    }
    levels.swap_remove(0).2
}

/// The generalised Charbonnier penalty ρ(u) = (u² + ε²)^α, or u when off (f64, for energies).
fn rho(u: f64, params: &DensifyParams) -> f64 {
    if params.terms.charbonnier {
        let (alpha, eps) = (f64::from(params.alpha), f64::from(params.epsilon));
        (u * u + eps * eps).powf(alpha)
    } else {
        u
    }
}

/// The energy E (module docs) at `d` (values below `min_idepth` are evaluated at it), in f64
/// so that numeric differences of it can check the analytic [`gradient`].
pub fn energy(problem: &DensifyProblem, d: &[f32], params: &DensifyParams) -> f64 {
    let d: Vec<f64> = d.iter().map(|&v| f64::from(v)).collect();
    energy_f64(problem, &d, params)
}

/// [`energy`] on an f64 iterate.
fn energy_f64(problem: &DensifyProblem, d: &[f64], params: &DensifyParams) -> f64 {
    let (w, h) = (problem.width, problem.height);
    let min = f64::from(params.min_idepth);
    let d: Vec<f64> = d.iter().map(|&v| v.max(min)).collect();
    let l: Vec<f64> = d.iter().map(|v| v.ln()).collect();
    let f = |v: &[f32], i: usize| f64::from(v[i]);
    let mut grad_sum = 0.0;
    let mut cnn_sum = 0.0;
    let mut semi_sum = 0.0;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x + 1 < w {
                let ex = l[i + 1] - l[i] - f(&problem.tx, i);
                grad_sum += f(&problem.wx, i) * ex * ex;
            }
            if y + 1 < h {
                let ey = l[i + w] - l[i] - f(&problem.ty, i);
                grad_sum += f(&problem.wy, i) * ey * ey;
            }
            let rc = d[i] - f(&problem.cnn, i);
            cnn_sum += f(&problem.cnn_weight, i) * rc * rc;
            if problem.semi[i] > 0.0 {
                let r = d[i] - f(&problem.semi, i);
                semi_sum += rho(r * r / f(&problem.semi_var, i), params);
            }
        }
    }
    let grad_scale = f64::from(problem.grad_scale);
    grad_scale * grad_sum + f64::from(problem.semi_scale) * semi_sum + grad_scale * cnn_sum
}

/// The analytic gradient dE/dD at `d` (values below `min_idepth` are evaluated at it) into
/// `out` (`width × height` values):
///
/// ```text
/// dE/dD(n) = (1/D) · 2·grad_scale·[−wx(n)ex(n) + wx(n−x̂)ex(n−x̂) − wy(n)ey(n) + wy(n−ŷ)ey(n−ŷ)]
///          + semi_scale · ρ'(u) · 2(D − semi)/semi_var          (semi > 0)
///          + 2·grad_scale · cnn_weight · (D − cnn)
/// ```
///
/// with ρ'(u) = 2αu(u² + ε²)^(α−1) (1 without Charbonnier). In f32 with the kernel's order of
/// operations: this is the CPU twin of `densify_adam.wgsl`.
pub fn gradient(problem: &DensifyProblem, d: &[f32], params: &DensifyParams, out: &mut [f32]) {
    let d: Vec<f32> = d.iter().map(|v| v.max(params.min_idepth)).collect();
    let l: Vec<f32> = d.iter().map(|v| v.ln()).collect();
    gradient_with_logs(problem, &d, &l, params, out);
}

/// [`gradient`] given `d ≥ min_idepth` and `l = ln d`.
fn gradient_with_logs(
    p: &DensifyProblem,
    d: &[f32],
    l: &[f32],
    params: &DensifyParams,
    out: &mut [f32],
) {
    let (w, h) = (p.width, p.height);
    let charbonnier = params.terms.charbonnier;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (dc, lc) = (d[i], l[i]);
            let mut dl = 0.0f32;
            if x + 1 < w {
                let ex = l[i + 1] - lc - p.tx[i];
                dl -= p.wx[i] * ex;
            }
            if x > 0 {
                let ex = lc - l[i - 1] - p.tx[i - 1];
                dl += p.wx[i - 1] * ex;
            }
            if y + 1 < h {
                let ey = l[i + w] - lc - p.ty[i];
                dl -= p.wy[i] * ey;
            }
            if y > 0 {
                let ey = lc - l[i - w] - p.ty[i - w];
                dl += p.wy[i - w] * ey;
            }
            let mut g = 2.0 * p.grad_scale * dl / dc;
            let semi = p.semi[i];
            if semi > 0.0 && p.semi_scale > 0.0 {
                let var = p.semi_var[i];
                let r = dc - semi;
                let u = r * r / var;
                let drho = if charbonnier {
                    2.0 * params.alpha
                        * u
                        * (u * u + params.epsilon * params.epsilon).powf(params.alpha - 1.0)
                } else {
                    1.0
                };
                g += p.semi_scale * drho * (2.0 * r / var);
            }
            g += 2.0 * p.grad_scale * p.cnn_weight[i] * (dc - p.cnn[i]);
            out[i] = g;
        }
    }
}

/// The per-iteration constants of Adam's step `t ≥ 1`, computed once in f32 (the GPU runner
/// uploads exactly these values, so both sides use the same numbers): PyTorch's
/// `step_size = lr / (1 − β1^t)` and `bias_correction2_sqrt = sqrt(1 − β2^t)`.
pub fn adam_step_constants(params: &DensifyParams, t: usize) -> (f32, f32) {
    let t = i32::try_from(t).unwrap_or(i32::MAX);
    let bias1 = 1.0 - params.beta1.powi(t);
    let bias2 = 1.0 - params.beta2.powi(t);
    (params.learning_rate / bias1, bias2.sqrt())
}

/// The CPU reference: `params.iterations` Adam steps from [`DensifyProblem::start`] (module
/// docs), the same arithmetic as the kernel. Returns the densified inverse depth.
pub fn densify_cpu(problem: &DensifyProblem, params: &DensifyParams) -> Result<ImageF32> {
    problem.validate()?;
    let n = problem.len();
    let mut d = problem.start(params);
    let mut l = vec![0.0f32; n];
    let mut g = vec![0.0f32; n];
    let (mut m, mut v) = (vec![0.0f32; n], vec![0.0f32; n]);
    let (b1, b2) = (params.beta1, params.beta2);
    for t in 1..=params.iterations {
        for (li, di) in l.iter_mut().zip(&d) {
            *li = di.ln();
        }
        gradient_with_logs(problem, &d, &l, params, &mut g);
        let (step_size, bias2_sqrt) = adam_step_constants(params, t);
        for i in 0..n {
            m[i] = b1 * m[i] + (1.0 - b1) * g[i];
            v[i] = b2 * v[i] + (1.0 - b2) * g[i] * g[i];
            // torch.optim.Adam: denom = sqrt(v) / bias_correction2_sqrt + ε;
            // param.addcdiv_(m, denom, value = −step_size).
            let denom = v[i].sqrt() / bias2_sqrt + params.adam_epsilon;
            d[i] = (d[i] - step_size * (m[i] / denom)).max(params.min_idepth);
        }
    }
    ImageF32::from_vec(problem.width, problem.height, d).map_err(Into::into)
}

/// A densification solver: the CPU reference ([`CpuDensifier`]) or its GPU twin
/// (`gpu_densify::GpuDensifier`); the dense layer picks one, this module knows neither.
pub trait DensifySolver {
    fn run(&self, problem: &DensifyProblem, params: &DensifyParams) -> Result<ImageF32>;
}

/// The CPU reference solver ([`densify_cpu`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuDensifier;

impl DensifySolver for CpuDensifier {
    fn run(&self, problem: &DensifyProblem, params: &DensifyParams) -> Result<ImageF32> {
        densify_cpu(problem, params)
    }
}

/// Densifies `problem` with `solver`.
pub fn densify(
    problem: &DensifyProblem,
    params: &DensifyParams,
    solver: &dyn DensifySolver,
) -> Result<ImageF32> {
    solver.run(problem, params)
}

/// Random problems and synthetic scenes shared by these tests and the GPU runner's.
#[cfg(test)]
pub(crate) mod testing {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A problem with every map random (weights, targets, ~25% semi-dense pixels, term 3), so
    /// that every branch of the gradient is exercised.
    pub(crate) fn random_problem(width: usize, height: usize, seed: u64) -> DensifyProblem {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n = width * height;
        let mut map =
            |lo: f32, hi: f32| -> Vec<f32> { (0..n).map(|_| rng.random_range(lo..hi)).collect() };
        let init = map(0.3, 2.0);
        let wx = map(0.1, 3.0);
        let wy = map(0.1, 3.0);
        let tx = map(-0.2, 0.2);
        let ty = map(-0.2, 0.2);
        let semi_raw = map(0.3, 2.0);
        let keep = map(0.0, 1.0);
        let semi_var = map(1e-3, 1e-2);
        let cnn = map(0.3, 2.0);
        let cnn_weight = map(0.0, 0.5);
        let semi: Vec<f32> = semi_raw
            .iter()
            .zip(&keep)
            .map(|(&s, &k)| if k < 0.25 { s } else { 0.0 })
            .collect();
        let count = semi.iter().filter(|&&s| s > 0.0).count().max(1);
        DensifyProblem {
            width,
            height,
            init,
            wx,
            wy,
            tx,
            ty,
            semi,
            semi_var,
            cnn,
            cnn_weight,
            semi_scale: 0.003 / count as f32,
            grad_scale: 1.0 / n as f32,
        }
    }

    /// Uniform noise image in [lo, hi).
    pub(crate) fn noise(width: usize, height: usize, lo: f32, hi: f32, seed: u64) -> ImageF32 {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let data = (0..width * height)
            .map(|_| rng.random_range(lo..hi))
            .collect();
        ImageF32 {
            width,
            height,
            data,
        }
    }

    /// A synthetic keyframe with known truth: a slanted floor-to-wall inverse depth with two
    /// boxes in front (depth edges), the aligned prior = truth × a smooth multiplicative
    /// distortion, then a residual scale/shift error (what eq. (3) leaves), and the semi-dense
    /// map = truth on ~10% of the pixels with a small noise and variance. Returns
    /// `(truth, prior, semidense, variance)`.
    pub(crate) fn synthetic_scene(
        width: usize,
        height: usize,
        seed: u64,
    ) -> (ImageF32, ImageF32, ImageF32, ImageF32) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let (wf, hf) = (width as f32, height as f32);
        let mut truth = ImageF32::filled(width, height, 0.0);
        let mut prior = ImageF32::filled(width, height, 0.0);
        let mut semi = ImageF32::filled(width, height, 0.0);
        let mut var = ImageF32::filled(width, height, 0.0);
        for y in 0..height {
            for x in 0..width {
                let (u, v) = (x as f32 / wf, y as f32 / hf);
                let mut d = 0.4 + 0.5 * v + 0.1 * u;
                if (0.15..0.4).contains(&u) && (0.3..0.7).contains(&v) {
                    d = 1.6;
                }
                if (0.6..0.85).contains(&u) && (0.2..0.5).contains(&v) {
                    d = 1.2 + 0.3 * u;
                }
                *truth.at_mut(x, y) = d;
                let distortion = 1.0 + 0.25 * (3.0 * u).sin() * (2.0 * v + 0.5).cos();
                *prior.at_mut(x, y) = 1.1 * d * distortion - 0.05;
                if rng.random_range(0.0f32..1.0) < 0.1 {
                    let noise: f32 = rng.random_range(-0.01..0.01);
                    *semi.at_mut(x, y) = d * (1.0 + noise);
                    *var.at_mut(x, y) = rng.random_range(2e-4..1e-3);
                }
            }
        }
        (truth, prior, semi, var)
    }

    /// Fraction of pixels within 10% relative error of the truth.
    pub(crate) fn within_10_percent(estimate: &[f32], truth: &[f32]) -> f64 {
        let good = estimate
            .iter()
            .zip(truth)
            .filter(|&(&e, &t)| ((e - t) / t).abs() < 0.1)
            .count();
        good as f64 / truth.len() as f64
    }
}

#[cfg(test)]
#[path = "densify_tests.rs"]
mod tests;
