//! The semi-dense structure adaptive filter (§III-C, eqs. 4–9): a bilateral filter of the
//! keyframe's semi-dense inverse depth whose weights also ask the prior (CNN depth consistency
//! w_c) and the depth variance (uncertainty w_u), a re-estimated local variance (eq. 8), the γ
//! threshold that removes noisy pixels, and the rescaling of the variance to the original
//! mean (eq. 9) so that densification weighs the filtered map like the raw one.
//!
//! Split in two so that the expensive, per-pixel part runs on the GPU:
//! - [`adaptive_filter_cpu`] (CPU reference) or [`GpuAdaptiveFilter::run`] (the WGSL kernel
//!   `adaptive_filter.wgsl`) compute D' and V' (eqs. 7–8) at every valid pixel: [`FilterRaw`];
//! - [`finish_filter`] applies γ, eq. 9 and a variance floor (global means, cheap on the CPU).
//!
//! [`filter_semidense`] chains both.
//!
//! Definitions shared by the CPU reference and the kernel (they agree to float rounding):
//! - a pixel is *valid* when D and V are finite and > 0 (and its intensity is finite: it has to
//!   be weighed photometrically); inputs are sanitised once ([`Prepared`]: D = V = 0 where
//!   invalid) so that the kernel tests only `D > 0` (WGSL may assume floats are finite);
//! - window (2r+1)², neighbours outside the image skipped, only valid neighbours (the centre
//!   included) contribute; `w = exp(−(e_s + e_d + e_c + e_u))` with the exponents of eqs. 4–6,
//!   i.e. the product w_s·w_d·w_c·w_u computed with one exp; e_c = 0 (w_c = 1) without a prior
//!   or where P(x) or P(n) is not > 0;
//! - D'(x) = Σ w·D(n) / W' (eq. 7), V'(x) = (|N| / n_valid) · Σ w_v·(D'(x) − D(n))² / W_v
//!   (eq. 8) with |N| = (2r+1)² (also at the border, as the paper counts "the total number of
//!   pixels within the window") and n_valid the valid pixels of the window inside the image;
//! - the variance weights w_v are w_s·w_d·w_u, i.e. w without w_c, and W_v = Σ w_v (our
//!   reading; [`FilterParams::consistency_in_variance`] gives the literal one, w_v = w). Why:
//!   w_c compares the ratio D(x)/D(n) with the prior's. At a gross outlier x every neighbour's
//!   ratio disagrees, so with w_v = w all neighbours weigh ≈ 0, only the centre's own
//!   (D'(x) − D(x))² ≈ 0 is left, and V' ≈ 0: the outlier survives γ as the most trusted pixel.
//!   On the test plane below, 74 of 279 spurious pixels survive that way (mean error of the
//!   kept map 0.025 against 0.044 raw) against 10 of 279 with w_v = w_s·w_d·w_u (0.0022).
//!   The paper says the filter exists "to remove the semi-dense depth pixels that have large
//!   local variance compared to their corresponding CNN depth"; w_c still decides how much
//!   each neighbour pulls D' (eq. 7);
//! - output only at valid centre pixels (w_c needs D(x)), and only when n_valid ≥ 2 and
//!   W' ≥ 1e-30. Our reading of eq. 8 for n_valid = 1: an isolated semi-dense pixel has no local
//!   variance to estimate; it is exactly the spurious kind the filter exists to remove, so it
//!   is dropped rather than given V' = 0 (which would make it the most trusted pixel).

use super::FilterParams;
use crate::image::ImageF32;
use crate::{Error, Result};

/// Largest half-window accepted (15×15); the cost grows with (2r+1)². Same bound as
/// [`super::DenseConfig::validate`].
pub const MAX_RADIUS: usize = 7;

/// Below this weight sum W' the filtered value is not trusted (the centre's own w_u has
/// underflowed, so nothing in the window vouches for the pixel).
pub const MIN_WEIGHT_SUM: f32 = 1e-30;

/// After eq. 9, each kept variance is at least this fraction of the mean: a V' that came out
/// 0 (all contributing depths equal) must not get infinite weight in densification.
pub const VARIANCE_FLOOR_FRACTION: f64 = 1e-3;

/// What the filter reads, all at the working resolution and of one size.
#[derive(Clone, Copy, Debug)]
pub struct FilterInputs<'a> {
    /// Keyframe intensity, 0..255 (σs is in those units).
    pub intensity: &'a ImageF32,
    /// Raw semi-dense inverse depth D, 0 = none.
    pub semidense: &'a ImageF32,
    /// Its variance V (> 0 where D > 0).
    pub variance: &'a ImageF32,
    /// The aligned prior D'_CNN (eq. 2); `None` (no model) makes w_c = 1.
    pub prior: Option<&'a ImageF32>,
}

/// Eqs. 7–8 before thresholding: D' and V' at valid centre pixels, 0 elsewhere.
#[derive(Clone, Debug, PartialEq)]
pub struct FilterRaw {
    pub idepth: ImageF32,
    pub variance: ImageF32,
}

/// The inputs checked and sanitised once, for the CPU reference and the GPU upload alike:
/// invalid pixels have D = V = 0, a prior value that is not finite and > 0 is 0.
#[derive(Debug)]
pub(crate) struct Prepared<'a> {
    pub width: usize,
    pub height: usize,
    pub intensity: &'a [f32],
    pub idepth: Vec<f32>,
    pub variance: Vec<f32>,
    pub prior: Option<Vec<f32>>,
}

/// Whether a semi-dense pixel takes part in the filter (see the module docs).
fn is_valid(intensity: f32, idepth: f32, variance: f32) -> bool {
    intensity.is_finite()
        && idepth.is_finite()
        && idepth > 0.0
        && variance.is_finite()
        && variance > 0.0
}

/// Rejects parameters the filter cannot use (a hand-built [`FilterParams`] bypasses
/// [`super::DenseConfig::validate`]).
pub(crate) fn check_params(params: &FilterParams) -> Result<()> {
    let bad = |what: &str| Err(Error::Config(format!("dense.filter.{what}")));
    if params.radius > MAX_RADIUS {
        return bad(&format!("radius must be ≤ {MAX_RADIUS}"));
    }
    for (name, v) in [
        ("sigma_s", params.sigma_s),
        ("sigma_d", params.sigma_d),
        ("sigma_c", params.sigma_c),
        ("gamma", params.gamma),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return bad(&format!("{name} must be > 0"));
        }
    }
    if !(params.sigma_u.is_finite() && params.sigma_u >= 0.0) {
        return bad("sigma_u must be ≥ 0");
    }
    Ok(())
}

impl<'a> Prepared<'a> {
    /// Checks that every map has the intensity's size and sanitises them.
    pub(crate) fn new(inputs: &FilterInputs<'a>) -> Result<Self> {
        let FilterInputs {
            intensity,
            semidense,
            variance,
            prior,
        } = *inputs;
        intensity.check_size()?;
        let (width, height) = (intensity.width, intensity.height);
        let named = [
            ("semi-dense map", Some(semidense)),
            ("variance", Some(variance)),
        ];
        for (name, image) in named.into_iter().chain([("prior", prior)]) {
            let Some(image) = image else { continue };
            image.check_size()?;
            if (image.width, image.height) != (width, height) {
                return Err(Error::Shape(format!(
                    "adaptive filter: {name} is {}x{}, the intensity {width}x{height}",
                    image.width, image.height
                )));
            }
        }
        let n = width * height;
        let (mut d, mut v) = (vec![0.0f32; n], vec![0.0f32; n]);
        for i in 0..n {
            let (di, vi) = (semidense.data[i], variance.data[i]);
            if is_valid(intensity.data[i], di, vi) {
                d[i] = di;
                v[i] = vi;
            }
        }
        let prior = prior.map(|p| {
            p.data
                .iter()
                .map(|&x| if x.is_finite() && x > 0.0 { x } else { 0.0 })
                .collect()
        });
        Ok(Self {
            width,
            height,
            intensity: &intensity.data,
            idepth: d,
            variance: v,
            prior,
        })
    }
}

/// Exponent coefficients 1/(2σ²) of w_s, w_d, w_c, computed as the kernel does.
#[derive(Clone, Copy, Debug)]
struct Coefficients {
    ks: f32,
    kd: f32,
    kc: f32,
    sigma_u: f32,
    consistency_in_variance: bool,
}

impl Coefficients {
    fn new(params: &FilterParams) -> Self {
        let k = |s: f32| 1.0 / (2.0 * s * s);
        Self {
            ks: k(params.sigma_s),
            kd: k(params.sigma_d),
            kc: k(params.sigma_c),
            sigma_u: params.sigma_u,
            consistency_in_variance: params.consistency_in_variance,
        }
    }
}

/// Eqs. 7–8 on the CPU: the reference the WGSL kernel is tested against (same f32 operations
/// in the same order). Output only at valid centre pixels (see the module docs).
pub fn adaptive_filter_cpu(inputs: &FilterInputs, params: &FilterParams) -> Result<FilterRaw> {
    check_params(params)?;
    let prepared = Prepared::new(inputs)?;
    Ok(filter_prepared(&prepared, params))
}

fn filter_prepared(p: &Prepared, params: &FilterParams) -> FilterRaw {
    let (w, h) = (p.width, p.height);
    let k = Coefficients::new(params);
    let r = params.radius;
    let side = (2 * r + 1) as f32;
    let (d, v) = (&p.idepth, &p.variance);
    let mut out_d = vec![0.0f32; w * h];
    let mut out_v = vec![0.0f32; w * h];
    // Variance weight and depth of each contributing neighbour of the current pixel, from
    // pass 1 for pass 2 (the kernel keeps them in private arrays alike).
    let mut window: Vec<(f32, f32)> = Vec::with_capacity((2 * params.radius + 1).pow(2));
    for cy in 0..h {
        for cx in 0..w {
            let i = cy * w + cx;
            let dc = d[i];
            // Sanitised: D is never NaN, and D > 0 implies V > 0 and a finite intensity.
            if dc <= 0.0 {
                continue;
            }
            let ic = p.intensity[i];
            let pc = p.prior.as_ref().map_or(0.0, |prior| prior[i]);
            window.clear();
            let (mut wsum, mut wdsum) = (0.0f32, 0.0f32);
            for y in cy.saturating_sub(r)..=(cy + r).min(h - 1) {
                for x in cx.saturating_sub(r)..=(cx + r).min(w - 1) {
                    let n = y * w + x;
                    let dn = d[n];
                    if dn <= 0.0 {
                        continue;
                    }
                    let di = ic - p.intensity[n];
                    let (ox, oy) = (x as i32 - cx as i32, y as i32 - cy as i32);
                    let r2 = (ox * ox + oy * oy) as f32;
                    let c = match &p.prior {
                        Some(prior) if pc > 0.0 && prior[n] > 0.0 => dc / dn - pc / prior[n],
                        _ => 0.0,
                    };
                    let dn2 = dn * dn;
                    // e_s + e_d + e_u, and e_c: the kernel's order.
                    let e_v = k.ks * di * di + k.kd * r2 + k.sigma_u * v[n] / (dn2 * dn2);
                    let e_c = k.kc * c * c;
                    let wn = (-(e_v + e_c)).exp();
                    wsum += wn;
                    wdsum += wn * dn;
                    // w_v = w in the literal reading; e_v + 0 = e_v exactly.
                    let e_cv = if k.consistency_in_variance { e_c } else { 0.0 };
                    let wv = (-(e_v + e_cv)).exp();
                    window.push((wv, dn));
                }
            }
            // NaN (σu = 0 with an underflowing D⁴) counts as too small.
            if window.len() < 2 || wsum.is_nan() || wsum < MIN_WEIGHT_SUM {
                continue;
            }
            let d_filtered = wdsum / wsum;
            // W_v ≥ W' ≥ MIN_WEIGHT_SUM (w_c ≤ 1), so the division is safe.
            let (mut acc, mut wvsum) = (0.0f32, 0.0f32);
            for &(wv, dn) in &window {
                let dev = d_filtered - dn;
                acc += wv * dev * dev;
                wvsum += wv;
            }
            let scale = side * side / window.len() as f32;
            out_d[i] = d_filtered;
            out_v[i] = scale * (acc / wvsum);
        }
    }
    FilterRaw {
        idepth: ImageF32 {
            width: w,
            height: h,
            data: out_d,
        },
        variance: ImageF32 {
            width: w,
            height: h,
            data: out_v,
        },
    }
}

/// γ threshold, eq. 9 and the variance floor, after eqs. 7–8 (`raw`).
///
/// Keeps the pixels with V' < γ; floors each kept V' at [`VARIANCE_FLOOR_FRACTION`] × their
/// mean; then rescales them by mean(V over the raw semi-dense map's valid pixels) / mean(kept,
/// floored V') (eq. 9). Flooring before rescaling keeps eq. 9 exact (the rescaled mean *is*
/// the raw mean) while every kept variance stays ≥ ≈ 1e-3 × that mean. When every kept V' is
/// exactly 0 (a perfectly flat map) they all get the raw mean: nothing tells them apart. No
/// kept pixel gives all zeros. Returns (inverse depth, variance), 0 where not kept.
pub fn finish_filter(
    raw: FilterRaw,
    inputs: &FilterInputs,
    params: &FilterParams,
) -> (ImageF32, ImageF32) {
    let FilterRaw {
        idepth: mut d,
        variance: mut v,
    } = raw;
    // Mean of the raw semi-dense variance (eq. 9's V̄), over the pixels the filter saw.
    let (mut sum_v, mut count_v) = (0.0f64, 0usize);
    let intensity = &inputs.intensity.data;
    let raw_d = &inputs.semidense.data;
    let raw_v = &inputs.variance.data;
    for ((&ii, &di), &vi) in intensity.iter().zip(raw_d).zip(raw_v) {
        if is_valid(ii, di, vi) {
            sum_v += f64::from(vi);
            count_v += 1;
        }
    }
    let mut kept = 0usize;
    let mut sum_kept = 0.0f64;
    for (dp, vp) in d.data.iter_mut().zip(v.data.iter_mut()) {
        if *dp > 0.0 && *vp < params.gamma {
            kept += 1;
            sum_kept += f64::from(*vp);
        } else {
            *dp = 0.0;
            *vp = 0.0;
        }
    }
    if kept == 0 || count_v == 0 {
        d.data.fill(0.0);
        v.data.fill(0.0);
        return (d, v);
    }
    let mean_raw = sum_v / count_v as f64;
    let floor = VARIANCE_FLOOR_FRACTION * sum_kept / kept as f64;
    let mut sum_floored = 0.0f64;
    for (dp, vp) in d.data.iter().zip(v.data.iter_mut()) {
        if *dp > 0.0 {
            let floored = f64::from(*vp).max(floor);
            *vp = floored as f32;
            sum_floored += floored;
        }
    }
    for (dp, vp) in d.data.iter().zip(v.data.iter_mut()) {
        if *dp > 0.0 {
            *vp = if sum_floored > 0.0 {
                (f64::from(*vp) * mean_raw * kept as f64 / sum_floored) as f32
            } else {
                mean_raw as f32
            };
        }
    }
    (d, v)
}

/// Eqs. 7–8 over every pixel: the CPU reference ([`CpuFilter`]) or its GPU twin
/// (`gpu_filter::GpuAdaptiveFilter`); the dense layer picks one, this module knows neither.
pub trait FilterStep {
    fn run(&self, inputs: &FilterInputs, params: &FilterParams) -> Result<FilterRaw>;
}

/// The CPU reference of eqs. 7–8 ([`adaptive_filter_cpu`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuFilter;

impl FilterStep for CpuFilter {
    fn run(&self, inputs: &FilterInputs, params: &FilterParams) -> Result<FilterRaw> {
        adaptive_filter_cpu(inputs, params)
    }
}

/// The whole filter: eqs. 7–8 by `step`, then [`finish_filter`]. With
/// `params.enabled == false` (Table II rows without "(f)") returns the raw semi-dense map and
/// variance unchanged, except that invalid pixels (not finite, ≤ 0) are zeroed in both so that
/// later stages see one convention.
pub fn filter_semidense(
    inputs: &FilterInputs,
    params: &FilterParams,
    step: &dyn FilterStep,
) -> Result<(ImageF32, ImageF32)> {
    if !params.enabled {
        let p = Prepared::new(inputs)?;
        let image = |data| ImageF32 {
            width: p.width,
            height: p.height,
            data,
        };
        return Ok((image(p.idepth.clone()), image(p.variance.clone())));
    }
    let raw = step.run(inputs, params)?;
    Ok(finish_filter(raw, inputs, params))
}

#[cfg(test)]
#[path = "filter_tests.rs"]
mod tests;
