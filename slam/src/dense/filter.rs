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
use super::gpu_filter::GpuAdaptiveFilter;
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

/// The whole filter: eqs. 7–8 on the GPU when `gpu` is given, else on the CPU reference, then
/// [`finish_filter`]. With `params.enabled == false` (Table II rows without "(f)") returns the
/// raw semi-dense map and variance unchanged, except that invalid pixels (not finite, ≤ 0) are
/// zeroed in both so that later stages see one convention.
pub fn filter_semidense(
    inputs: &FilterInputs,
    params: &FilterParams,
    gpu: Option<&GpuAdaptiveFilter>,
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
    let raw = match gpu {
        Some(gpu) => gpu.run(inputs, params)?,
        None => adaptive_filter_cpu(inputs, params)?,
    };
    Ok(finish_filter(raw, inputs, params))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn image(width: usize, height: usize, f: impl Fn(usize, usize) -> f32) -> ImageF32 {
        let data = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| f(x, y))
            .collect();
        ImageF32::from_vec(width, height, data).expect("sizes match")
    }

    fn inputs<'a>(
        intensity: &'a ImageF32,
        semidense: &'a ImageF32,
        variance: &'a ImageF32,
        prior: Option<&'a ImageF32>,
    ) -> FilterInputs<'a> {
        FilterInputs {
            intensity,
            semidense,
            variance,
            prior,
        }
    }

    /// Eq. 7–8 by hand for one pixel of a 3×1 image (all valid, no prior).
    #[test]
    fn filter_matches_hand_computation_on_a_tiny_row() {
        let intensity = image(3, 1, |x, _| [10.0, 20.0, 40.0][x]);
        let d = image(3, 1, |x, _| [1.0, 2.0, 4.0][x]);
        let v = image(3, 1, |x, _| [0.01, 0.02, 0.04][x]);
        let params = FilterParams::default();
        let raw = adaptive_filter_cpu(&inputs(&intensity, &d, &v, None), &params).expect("runs");
        // Centre x = 1.
        let w = |di: f64, r2: f64, dn: f64, vn: f64| {
            (-(di * di / (2.0 * 76.5f64.powi(2)) + r2 / 8.0 + 2.0 * vn / dn.powi(4))).exp()
        };
        let ws = [
            w(10.0, 1.0, 1.0, 0.01),
            w(0.0, 0.0, 2.0, 0.02),
            w(-20.0, 1.0, 4.0, 0.04),
        ];
        let ds = [1.0, 2.0, 4.0];
        let wsum: f64 = ws.iter().sum();
        let dp: f64 = ws.iter().zip(&ds).map(|(w, d)| w * d).sum::<f64>() / wsum;
        let vp = 25.0 / 3.0
            * ws.iter()
                .zip(&ds)
                .map(|(w, d)| w * (dp - d).powi(2))
                .sum::<f64>()
            / wsum;
        assert!((f64::from(raw.idepth.data[1]) - dp).abs() < 1e-5 * dp);
        assert!((f64::from(raw.variance.data[1]) - vp).abs() < 1e-5 * vp);
    }

    #[test]
    fn filter_drops_isolated_and_invalid_pixels() {
        let intensity = image(7, 5, |_, _| 100.0);
        // One isolated pixel at (1, 1); a NaN and a zero-variance pixel near (5, 3).
        let d = image(7, 5, |x, y| match (x, y) {
            (1, 1) => 1.0,
            (5, 3) => 1.0,
            (6, 3) => f32::NAN,
            (6, 4) => 1.2,
            _ => 0.0,
        });
        let v = image(7, 5, |x, y| if (x, y) == (6, 4) { 0.0 } else { 1e-3 });
        let raw = adaptive_filter_cpu(&inputs(&intensity, &d, &v, None), &FilterParams::default())
            .expect("runs");
        assert!(
            raw.idepth.data.iter().all(|&x| x == 0.0),
            "{:?}",
            raw.idepth.data
        );
        assert!(raw.variance.data.iter().all(|&x| x == 0.0));
        // With a valid neighbour the pair survives.
        let v = image(7, 5, |_, _| 1e-3);
        let d = image(7, 5, |x, y| {
            if (x, y) == (5, 3) || (x, y) == (6, 4) {
                1.0
            } else {
                0.0
            }
        });
        let raw = adaptive_filter_cpu(&inputs(&intensity, &d, &v, None), &FilterParams::default())
            .expect("runs");
        assert_eq!(raw.idepth.data.iter().filter(|&&x| x > 0.0).count(), 2);
        assert_eq!(raw.idepth.at(5, 3), 1.0);
    }

    #[test]
    fn filter_rejects_mismatched_shapes_and_bad_params() {
        let a = image(8, 8, |_, _| 1.0);
        let b = image(8, 7, |_, _| 1.0);
        let params = FilterParams::default();
        assert!(matches!(
            adaptive_filter_cpu(&inputs(&a, &b, &a, None), &params),
            Err(Error::Shape(_))
        ));
        assert!(matches!(
            adaptive_filter_cpu(&inputs(&a, &a, &a, Some(&b)), &params),
            Err(Error::Shape(_))
        ));
        let bad = FilterParams {
            sigma_c: 0.0,
            ..FilterParams::default()
        };
        assert!(matches!(
            adaptive_filter_cpu(&inputs(&a, &a, &a, None), &bad),
            Err(Error::Config(_))
        ));
    }

    /// A synthetic slanted plane, inverse depth linear in x and y, observed semi-densely with
    /// small noise and 5 % spurious pixels (uniform in [0.2, 3], claiming a small variance).
    struct Plane {
        intensity: ImageF32,
        truth: ImageF32,
        d: ImageF32,
        v: ImageF32,
        prior: ImageF32,
        outlier: Vec<bool>,
    }

    fn plane(seed: u64) -> Plane {
        let (w, h) = (160, 120);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let truth = image(w, h, |x, y| 0.5 + 0.004 * x as f32 + 0.003 * y as f32);
        // A smooth texture (a real keyframe's intensity varies; far from an edge here).
        let intensity = image(w, h, |x, y| {
            128.0 + 40.0 * ((x as f32) * 0.05).sin() * ((y as f32) * 0.07).cos()
        });
        let noise = 0.005f32;
        let mut d = ImageF32::filled(w, h, 0.0);
        let mut v = ImageF32::filled(w, h, 0.0);
        let mut outlier = vec![false; w * h];
        for (i, spurious) in outlier.iter_mut().enumerate() {
            if rng.random::<f32>() < 0.3 {
                if rng.random::<f32>() < 0.05 {
                    d.data[i] = rng.random_range(0.2..3.0);
                    *spurious = true;
                } else {
                    // Sum of uniforms: roughly Gaussian with standard deviation `noise`.
                    let g: f32 = (0..12).map(|_| rng.random::<f32>()).sum::<f32>() - 6.0;
                    d.data[i] = truth.data[i] + noise * g;
                }
                v.data[i] = noise * noise * rng.random_range(0.5..2.0);
            }
        }
        // The aligned prior: the plane up to a few percent of smooth error.
        let prior = image(w, h, |x, y| {
            truth.at(x, y) * (1.0 + 0.03 * ((x + 2 * y) as f32 * 0.02).sin())
        });
        Plane {
            intensity,
            truth,
            d,
            v,
            prior,
            outlier,
        }
    }

    /// How a filtered map `fd` did on the plane: mean absolute error over its kept pixels,
    /// spurious and good pixels kept (of those in the raw map).
    #[derive(Debug)]
    struct Score {
        mae: f64,
        outliers_kept: usize,
        outliers: usize,
        inliers_kept: usize,
        inliers: usize,
    }

    fn score(s: &Plane, fd: &ImageF32) -> Score {
        let (mut sum, mut n) = (0.0f64, 0usize);
        let mut out = Score {
            mae: 0.0,
            outliers_kept: 0,
            outliers: 0,
            inliers_kept: 0,
            inliers: 0,
        };
        for (i, &o) in s.outlier.iter().enumerate() {
            if fd.data[i] > 0.0 {
                sum += f64::from((fd.data[i] - s.truth.data[i]).abs());
                n += 1;
            }
            if s.d.data[i] <= 0.0 {
                continue;
            }
            let kept = usize::from(fd.data[i] > 0.0);
            if o {
                out.outliers += 1;
                out.outliers_kept += kept;
            } else {
                out.inliers += 1;
                out.inliers_kept += kept;
            }
        }
        out.mae = sum / n as f64;
        out
    }

    /// Behaviour on a slanted plane (CPU with and without prior and, through the same entry
    /// point, the GPU): the filtered map is much closer to the plane, the spurious pixels are
    /// gone, most good ones stay, and eq. 9 holds.
    #[test]
    fn filter_cleans_a_noisy_plane_and_keeps_the_mean_variance() {
        let s = plane(11);
        let ctx = crate::gpu::GpuContext::new(&crate::gpu::GpuConfig::default())
            .unwrap_or_else(|e| panic!("no GPU context: {e}"));
        let gpu = GpuAdaptiveFilter::new(std::sync::Arc::new(ctx)).expect("kernel compiles");
        let raw = score(&s, &s.d);
        let raw_mean_v = s.v.data.iter().map(|&x| f64::from(x)).sum::<f64>()
            / (raw.inliers + raw.outliers) as f64;
        for (prior, device) in [
            (Some(&s.prior), None),
            (None, None),
            (Some(&s.prior), Some(&gpu)),
        ] {
            let what = format!("prior {} gpu {}", prior.is_some(), device.is_some());
            let inputs = inputs(&s.intensity, &s.d, &s.v, prior);
            let (fd, fv) =
                filter_semidense(&inputs, &FilterParams::default(), device).expect("filter runs");
            let f = score(&s, &fd);
            eprintln!("{what}: raw {raw:?}\n  filtered {f:?}");
            assert!(f.mae < 0.2 * raw.mae, "{what}: {f:?} vs raw {raw:?}");
            assert!(f.outliers_kept * 10 < f.outliers, "{what}: {f:?}");
            assert!(f.inliers_kept * 10 > f.inliers * 6, "{what}: {f:?}");
            // Eq. 9: the kept variances have the raw map's mean; all above the floor; zero
            // exactly where the depth is.
            let kept: Vec<f64> = fd
                .data
                .iter()
                .zip(&fv.data)
                .filter(|&(&d, _)| d > 0.0)
                .map(|(_, &v)| f64::from(v))
                .collect();
            let mean_v = kept.iter().sum::<f64>() / kept.len() as f64;
            assert!(
                (mean_v - raw_mean_v).abs() < 1e-5 * raw_mean_v,
                "{what}: mean V {mean_v} vs raw {raw_mean_v}"
            );
            assert!(
                kept.iter()
                    .all(|&v| v >= 0.999 * VARIANCE_FLOOR_FRACTION * mean_v)
            );
            assert!(
                fd.data
                    .iter()
                    .zip(&fv.data)
                    .all(|(&d, &v)| (d > 0.0) == (v > 0.0))
            );
        }
    }

    /// Why the variance weights leave w_c out by default: with the literal reading
    /// (`consistency_in_variance`), gross outliers above the plane isolate themselves through
    /// w_c, get V' ≈ 0 and survive, at the variance floor, as the most trusted pixels. The same
    /// holds on the GPU.
    #[test]
    fn filter_literal_variance_weights_keep_gross_outliers() {
        let s = plane(11);
        let literal = FilterParams {
            consistency_in_variance: true,
            ..FilterParams::default()
        };
        let inputs = inputs(&s.intensity, &s.d, &s.v, Some(&s.prior));
        let (fd, fv) = filter_semidense(&inputs, &literal, None).expect("filter runs");
        let f = score(&s, &fd);
        let default = score(
            &s,
            &filter_semidense(&inputs, &FilterParams::default(), None)
                .expect("filter runs")
                .0,
        );
        eprintln!("literal {f:?}\ndefault {default:?}");
        assert!(
            f.outliers_kept > 4 * default.outliers_kept,
            "{f:?} vs {default:?}"
        );
        assert!(f.mae > 5.0 * default.mae, "{f:?} vs {default:?}");
        let mean_v = fv.data.iter().map(|&v| f64::from(v)).sum::<f64>()
            / fd.data.iter().filter(|&&d| d > 0.0).count() as f64;
        let gross_at_floor = (0..fd.data.len())
            .filter(|&i| {
                s.outlier[i]
                    && (fd.data[i] - s.truth.data[i]).abs() > 0.5
                    && f64::from(fv.data[i]) < 0.01 * mean_v
            })
            .count();
        assert!(
            gross_at_floor >= 10,
            "{gross_at_floor} gross outliers near the floor"
        );

        let ctx = crate::gpu::GpuContext::new(&crate::gpu::GpuConfig::default())
            .unwrap_or_else(|e| panic!("no GPU context: {e}"));
        let gpu = GpuAdaptiveFilter::new(std::sync::Arc::new(ctx)).expect("kernel compiles");
        let g = score(
            &s,
            &filter_semidense(&inputs, &literal, Some(&gpu))
                .expect("gpu")
                .0,
        );
        assert_eq!(g.outliers_kept, f.outliers_kept);
    }

    /// The variance floor and the all-zero case of [`finish_filter`], and γ.
    #[test]
    fn finish_filter_thresholds_floors_and_rescales() {
        let intensity = image(4, 1, |_, _| 0.0);
        let d = image(4, 1, |_, _| 1.0);
        let v = image(4, 1, |x, _| [1.0, 2.0, 3.0, 6.0][x]);
        let params = FilterParams::default(); // γ = 0.0025
        let raw = FilterRaw {
            idepth: image(4, 1, |x, _| [1.0, 1.0, 1.0, 0.0][x]),
            variance: image(4, 1, |x, _| [0.0, 0.001, 0.003, 0.0][x]),
        };
        let (fd, fv) = finish_filter(raw, &inputs(&intensity, &d, &v, None), &params);
        // Pixel 2 is above γ, pixel 3 was invalid.
        assert_eq!(fd.data, vec![1.0, 1.0, 0.0, 0.0]);
        // Kept V' = [0, 0.001], mean 0.0005, floor 5e-7: [5e-7, 1e-3] rescaled to mean 3.
        let s = 2.0 * 3.0 / (0.001 + 5e-7);
        assert!((f64::from(fv.data[0]) - 5e-7 * s).abs() < 1e-6);
        assert!((f64::from(fv.data[1]) - 1e-3 * s).abs() < 1e-5);
        assert_eq!(&fv.data[2..], &[0.0, 0.0]);
        // All kept V' exactly 0: each gets the raw mean.
        let raw = FilterRaw {
            idepth: image(4, 1, |_, _| 1.0),
            variance: image(4, 1, |_, _| 0.0),
        };
        let (_, fv) = finish_filter(raw, &inputs(&intensity, &d, &v, None), &params);
        assert_eq!(fv.data, vec![3.0; 4]);
        // Nothing kept: zeros.
        let raw = FilterRaw {
            idepth: image(4, 1, |_, _| 1.0),
            variance: image(4, 1, |_, _| 1.0),
        };
        let (fd, fv) = finish_filter(raw, &inputs(&intensity, &d, &v, None), &params);
        assert!(fd.data.iter().chain(&fv.data).all(|&x| x == 0.0));
    }

    #[test]
    fn filter_disabled_passes_the_raw_map_through() {
        let intensity = image(3, 2, |_, _| 50.0);
        let d = image(3, 2, |x, y| [1.0, f32::NAN, -1.0, 2.0, 0.5, 0.7][y * 3 + x]);
        let v = image(3, 2, |x, _| if x == 2 { f32::INFINITY } else { 0.1 });
        let params = FilterParams {
            enabled: false,
            ..FilterParams::default()
        };
        let (fd, fv) =
            filter_semidense(&inputs(&intensity, &d, &v, None), &params, None).expect("runs");
        assert_eq!(fd.data, vec![1.0, 0.0, 0.0, 2.0, 0.5, 0.0]);
        assert_eq!(fv.data, vec![0.1, 0.0, 0.0, 0.1, 0.1, 0.0]);
    }

    /// The weights do their jobs on a uniform 9×9 patch whose centre (4, 4) has D = 1.
    /// - w_s: across an intensity edge the other side's depth barely moves the centre;
    /// - w_u: a neighbour with a huge variance relative to D⁴ is ignored;
    /// - w_c: a neighbour whose depth ratio disagrees with the prior counts less than one the
    ///   prior agrees with.
    #[test]
    fn filter_weights_respect_edges_uncertainty_and_the_prior() {
        let (w, h) = (9, 9);
        let params = FilterParams::default();
        let centre = |raw: &FilterRaw| raw.idepth.at(4, 4);
        let flat = image(w, h, |_, _| 100.0);
        let v = image(w, h, |_, _| 1e-4);

        // w_s: left of x = 5 is dark with D = 1, right is bright with D = 1.5.
        let d = image(w, h, |x, _| if x < 5 { 1.0 } else { 1.5 });
        let edge = image(w, h, |x, _| if x < 5 { 0.0 } else { 255.0 });
        let across = adaptive_filter_cpu(&inputs(&edge, &d, &v, None), &params).expect("runs");
        let no_edge = adaptive_filter_cpu(&inputs(&flat, &d, &v, None), &params).expect("runs");
        assert!((centre(&across) - 1.0).abs() < 0.01, "{}", centre(&across));
        assert!(centre(&no_edge) - 1.0 > 0.1, "{}", centre(&no_edge));
        // And the edge pixel's re-estimated variance stays small enough to keep it.
        assert!(across.variance.at(4, 4) < params.gamma);
        assert!(no_edge.variance.at(4, 4) > across.variance.at(4, 4) * 10.0);

        // w_u: neighbour (5, 4) at D = 0.5; with V = 1 its w_u = exp(−2·1/0.0625) ≈ 1e-14.
        let d = image(w, h, |x, y| if (x, y) == (5, 4) { 0.5 } else { 1.0 });
        let v_bad = image(w, h, |x, y| if (x, y) == (5, 4) { 1.0 } else { 1e-4 });
        let ignored = adaptive_filter_cpu(&inputs(&flat, &d, &v_bad, None), &params).expect("runs");
        let trusted = adaptive_filter_cpu(&inputs(&flat, &d, &v, None), &params).expect("runs");
        assert!(
            (centre(&ignored) - 1.0).abs() < 1e-6,
            "{}",
            centre(&ignored)
        );
        assert!(1.0 - centre(&trusted) > 0.01, "{}", centre(&trusted));

        // w_c: neighbour (5, 4) at D = 3; a flat prior disagrees (ratio 1/3 vs 1), a prior
        // with the same bump agrees (w_c = 1).
        let d = image(w, h, |x, y| if (x, y) == (5, 4) { 3.0 } else { 1.0 });
        let p_flat = image(w, h, |_, _| 1.0);
        let p_bump = d.clone();
        let disagree =
            adaptive_filter_cpu(&inputs(&flat, &d, &v, Some(&p_flat)), &params).expect("runs");
        let agree =
            adaptive_filter_cpu(&inputs(&flat, &d, &v, Some(&p_bump)), &params).expect("runs");
        let none = adaptive_filter_cpu(&inputs(&flat, &d, &v, None), &params).expect("runs");
        assert_eq!(centre(&agree), centre(&none));
        assert!(
            (centre(&disagree) - 1.0) < 0.2 * (centre(&agree) - 1.0),
            "{} vs {}",
            centre(&disagree),
            centre(&agree)
        );
    }
}
