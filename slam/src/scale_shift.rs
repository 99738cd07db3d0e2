//! Scale and shift correction of the relative depth prior, the paper's eqs. (2)–(3).
//!
//! The prior `D_CNN` is a relative inverse-depth map: correct up to an unknown scale and shift
//! (MiDaS's scale- and shift-invariant loss). Eq. (2) corrects it as `D'_CNN = a·D_CNN + b`
//! with `a > 0`, and eq. (3) finds `h = (a, b)ᵀ` in closed form from the 2×2 normal equations
//! `(Σ dₙ dₙᵀ) h = Σ dₙ d′ₙ`, `dₙ = (pₙ, 1)ᵀ`, over the pixels where a target inverse depth is
//! known (the semi-dense map in the pipeline; ground truth in evaluation).
//!
//! Below both the mapping (prior hole filling) and the dense layer, which use it.
//!
//! Note on eq. (3) as printed: its symbols name `dₙ` the semi-dense value and `d′ₙ` the CNN
//! value, which would regress the prediction on the target. The intended fit (and the one in
//! MiDaS's `compute_scale_and_shift`, which the paper cites) maps the *prior* onto the
//! *target*; that is what is implemented here.

use serde::{Deserialize, Serialize};

use crate::image::ImageF32;
use crate::{Error, Result};

/// Fewest usable pixels accepted for a fit. Two determine a line exactly; a handful more keeps
/// a fit from a few noisy semi-dense pixels from passing as a correction of a whole keyframe.
pub const MIN_ALIGN_PIXELS: usize = 8;

/// Robust eq. (3) alignment of the prior to the semi-dense inverse depth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlignParams {
    /// Fewest semi-dense pixels (at the working resolution) a fit needs. Default 200: the
    /// semi-dense map of a converged keyframe has thousands; a few hundred cannot pin down
    /// scale and shift of the whole prior.
    pub min_pixels: usize,
    /// Re-fits after dropping outliers (residual > `outlier_k` × 1.4826 × MAD). Default 3.
    pub outlier_rounds: usize,
    /// Outlier threshold in robust standard deviations. Default 3.
    pub outlier_k: f64,
}

impl Default for AlignParams {
    fn default() -> Self {
        Self {
            min_pixels: 200,
            outlier_rounds: 3,
            outlier_k: 3.0,
        }
    }
}

/// The result of eq. (3): `target ≈ a · prior + b`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ScaleShift {
    /// Scale `a` (> 0 from [`fit_scale_shift`]).
    pub a: f64,
    /// Shift `b`.
    pub b: f64,
    /// Number of pixels the fit used.
    pub used: usize,
}

impl ScaleShift {
    /// Applies eq. (2) to one prior inverse depth.
    #[inline]
    pub fn apply(&self, prior_inv: f32) -> f32 {
        (self.a * f64::from(prior_inv) + self.b) as f32
    }

    /// Applies eq. (2) to a whole prior map: `D'_CNN = a·D_CNN + b`.
    pub fn apply_image(&self, prior_inv: &ImageF32) -> ImageF32 {
        let data = prior_inv.data.iter().map(|&p| self.apply(p)).collect();
        ImageF32 {
            width: prior_inv.width,
            height: prior_inv.height,
            data,
        }
    }
}

/// Eq. (3) with the paper's constraint `a > 0`: fits `target_inv ≈ a·prior_inv + b` over the
/// pixels where `mask` (if given) is true, the target is a positive finite inverse depth (0
/// means "no value") and the prior is finite.
///
/// Fails on a size mismatch, fewer than [`MIN_ALIGN_PIXELS`] usable pixels, a prior that is
/// (numerically) constant over them (singular normal equations), or `a ≤ 0` (the prior's
/// ordering contradicts the target; a negative scale would flip near and far).
pub fn fit_scale_shift(
    prior_inv: &ImageF32,
    target_inv: &ImageF32,
    mask: Option<&[bool]>,
) -> Result<ScaleShift> {
    let fit = fit_scale_shift_unconstrained(prior_inv, target_inv, mask)?;
    if fit.a.is_nan() || fit.a <= 0.0 {
        return Err(Error::Prior(format!(
            "scale/shift fit gave scale a = {:.4e} <= 0 over {} pixels: the prior's depth \
             ordering contradicts the target",
            fit.a, fit.used
        )));
    }
    Ok(fit)
}

/// The plain least-squares solution of eq. (3), without the `a > 0` constraint. Evaluation
/// protocols that score the raw prior (shared data README §1.4) use this, so that frames
/// whose prediction is inverted are scored rather than skipped.
pub fn fit_scale_shift_unconstrained(
    prior_inv: &ImageF32,
    target_inv: &ImageF32,
    mask: Option<&[bool]>,
) -> Result<ScaleShift> {
    let n_pixels = prior_inv.data.len();
    if (prior_inv.width, prior_inv.height) != (target_inv.width, target_inv.height) {
        return Err(Error::Shape(format!(
            "prior is {}x{}, target {}x{}",
            prior_inv.width, prior_inv.height, target_inv.width, target_inv.height
        )));
    }
    if let Some(m) = mask
        && m.len() != n_pixels
    {
        return Err(Error::Shape(format!(
            "mask has {} values for {n_pixels} pixels",
            m.len()
        )));
    }
    let usable = |i: usize| {
        let t = target_inv.data[i];
        mask.is_none_or(|m| m[i]) && t.is_finite() && t > 0.0 && prior_inv.data[i].is_finite()
    };
    // Normal equations of eq. (3), accumulated in f64 on mean-centred values: the same closed
    // form, without the cancellation of n·Σp² − (Σp)² when the prior has a large offset.
    let (mut n, mut sum_p, mut sum_t) = (0usize, 0.0f64, 0.0f64);
    for i in (0..n_pixels).filter(|&i| usable(i)) {
        n += 1;
        sum_p += f64::from(prior_inv.data[i]);
        sum_t += f64::from(target_inv.data[i]);
    }
    if n < MIN_ALIGN_PIXELS {
        return Err(Error::Prior(format!(
            "scale/shift fit needs at least {MIN_ALIGN_PIXELS} pixels with a target, got {n}"
        )));
    }
    let (mean_p, mean_t) = (sum_p / n as f64, sum_t / n as f64);
    let (mut spp, mut spt) = (0.0f64, 0.0f64);
    for i in (0..n_pixels).filter(|&i| usable(i)) {
        let dp = f64::from(prior_inv.data[i]) - mean_p;
        spp += dp * dp;
        spt += dp * (f64::from(target_inv.data[i]) - mean_t);
    }
    // Singular when the prior's variance vanishes relative to its magnitude (f32 inputs carry
    // ~1e-7 relative precision, so anything below that is noise).
    let scale2 = mean_p * mean_p + spp / n as f64;
    if spp.is_nan() || spp <= 1e-12 * n as f64 * scale2 {
        return Err(Error::Prior(format!(
            "scale/shift fit is singular: the prior is constant over the {n} fitted pixels"
        )));
    }
    let a = spt / spp;
    Ok(ScaleShift {
        a,
        b: mean_t - a * mean_p,
        used: n,
    })
}

/// Eq. (3) made robust for the pipeline, where the target is LSD-SLAM's semi-dense map with
/// its spurious points (the reason for the paper's adaptive filter): fit, drop the pixels whose
/// residual exceeds `params.outlier_k` robust standard deviations (1.4826 × the median absolute
/// residual), re-fit, `params.outlier_rounds` times. Rejected, with the reason, when fewer than
/// `params.min_pixels` pixels have a target or remain, when the prior is constant over them, or
/// when the scale comes out ≤ 0 (the prior's ordering contradicts the map).
pub fn fit_scale_shift_robust(
    prior_inv: &ImageF32,
    target_inv: &ImageF32,
    params: &AlignParams,
) -> Result<ScaleShift> {
    let has_target = |i: usize| {
        let t = target_inv.data[i];
        t.is_finite() && t > 0.0 && prior_inv.data.get(i).is_some_and(|p| p.is_finite())
    };
    let mut mask: Vec<bool> = (0..target_inv.data.len()).map(has_target).collect();
    let count = |m: &[bool]| m.iter().filter(|&&k| k).count();
    let too_few = |n: usize, what: &str| {
        Error::Prior(format!(
            "prior alignment needs at least {} semi-dense pixels, {what} {n}",
            params.min_pixels
        ))
    };
    let n = count(&mask);
    if n < params.min_pixels {
        return Err(too_few(n, "the keyframe has"));
    }
    let mut fit = fit_scale_shift(prior_inv, target_inv, Some(&mask))?;
    for _ in 0..params.outlier_rounds {
        let mut residuals: Vec<f64> = (0..mask.len())
            .filter(|&i| mask[i])
            .map(|i| {
                (f64::from(fit.apply(prior_inv.data[i])) - f64::from(target_inv.data[i])).abs()
            })
            .collect();
        let mid = residuals.len() / 2;
        let (_, median, _) = residuals.select_nth_unstable_by(mid, f64::total_cmp);
        let bound = params.outlier_k * 1.4826 * *median;
        if bound.is_nan() || bound <= 0.0 {
            break;
        }
        let mut changed = false;
        for (i, keep) in mask.iter_mut().enumerate() {
            if *keep
                && (f64::from(fit.apply(prior_inv.data[i])) - f64::from(target_inv.data[i])).abs()
                    > bound
            {
                *keep = false;
                changed = true;
            }
        }
        let n = count(&mask);
        if n < params.min_pixels {
            return Err(too_few(n, "outlier rejection left"));
        }
        fit = fit_scale_shift(prior_inv, target_inv, Some(&mask))?;
        if !changed {
            break;
        }
    }
    Ok(fit)
}

/// Ground truth for eq. (3) from a metric depth map: the target inverse depth `1 / depth` and
/// the mask of pixels with `depth > min_depth` (finite). Other pixels get target 0 ("no value").
/// The shared data README §1.4 uses `min_depth` = 0.1 m.
pub fn inverse_depth_target(depth: &ImageF32, min_depth: f32) -> (ImageF32, Vec<bool>) {
    let mask: Vec<bool> = depth
        .data
        .iter()
        .map(|&d| d.is_finite() && d > min_depth)
        .collect();
    let data = depth
        .data
        .iter()
        .zip(&mask)
        .map(|(&d, &m)| if m { 1.0 / d } else { 0.0 })
        .collect();
    (
        ImageF32 {
            width: depth.width,
            height: depth.height,
            data,
        },
        mask,
    )
}

/// Depth from an aligned prior, `d = 1 / (a·p + b)`; 0 ("no depth") where the corrected
/// inverse depth is not positive.
pub fn aligned_depth(prior_inv: &ImageF32, fit: &ScaleShift) -> ImageF32 {
    let data = prior_inv
        .data
        .iter()
        .map(|&p| {
            let inv = fit.a * f64::from(p) + fit.b;
            if inv > 0.0 && inv.is_finite() {
                (1.0 / inv) as f32
            } else {
                0.0
            }
        })
        .collect();
    ImageF32 {
        width: prior_inv.width,
        height: prior_inv.height,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize) -> ImageF32 {
        let data = (0..w * h)
            .map(|i| 0.2 + (i % 17) as f32 * 0.05 + (i / w) as f32 * 0.01)
            .collect();
        ImageF32 {
            width: w,
            height: h,
            data,
        }
    }

    #[test]
    fn dense_align_recovers_scale_and_shift() {
        let prior = ramp(16, 12);
        let (a, b) = (2.5f32, -0.3f32);
        let mut target = prior.clone();
        for t in &mut target.data {
            *t = a * *t + b;
        }
        // Holes (0 = no value) and a masked-out outlier must not disturb the fit.
        target.data[3] = 0.0;
        target.data[5] = f32::NAN;
        target.data[7] = 100.0;
        let mut mask = vec![true; prior.data.len()];
        mask[7] = false;
        let fit = fit_scale_shift(&prior, &target, Some(&mask)).expect("fit");
        assert!(
            (fit.a - 2.5).abs() < 1e-5 && (fit.b + 0.3).abs() < 1e-5,
            "{fit:?}"
        );
        assert_eq!(fit.used, prior.data.len() - 3);
        let corrected = fit.apply_image(&prior);
        assert!((corrected.data[10] - (a * prior.data[10] + b)).abs() < 1e-5);
        // Without the mask the outlier pulls the fit away.
        let loose = fit_scale_shift(&prior, &target, None).expect("fit");
        assert!((loose.a - 2.5).abs() > 1e-3);
    }

    #[test]
    fn robust_align_ignores_spurious_points_and_explains_rejections() {
        let prior = ramp(40, 30);
        let mut target = prior.clone();
        for (i, t) in target.data.iter_mut().enumerate() {
            *t = 1.5 * *t + 0.2 + if i % 97 == 0 { 0.002 } else { -0.001 };
            if i % 10 == 0 {
                *t *= 4.0; // 10 % spurious points
            }
        }
        let params = AlignParams::default();
        let plain = fit_scale_shift(&prior, &target, None).expect("fit");
        let robust = fit_scale_shift_robust(&prior, &target, &params).expect("fit");
        assert!((plain.a - 1.5).abs() > 0.1, "{plain:?}");
        assert!(
            (robust.a - 1.5).abs() < 0.01 && (robust.b - 0.2).abs() < 0.01,
            "{robust:?}"
        );
        assert!(robust.used < 1200 && robust.used > 1000);
        let sparse = ImageF32::filled(40, 30, 0.0);
        let err = fit_scale_shift_robust(&prior, &sparse, &params).expect_err("must fail");
        assert!(err.to_string().contains("at least 200"), "{err}");
        let mut inverted = prior.clone();
        for p in &mut inverted.data {
            *p = 3.0 - *p;
        }
        let err = fit_scale_shift_robust(&inverted, &prior, &params).expect_err("must fail");
        assert!(err.to_string().contains("<= 0"), "{err}");
    }

    #[test]
    fn dense_align_from_metric_depth() {
        let depth = ImageF32::from_vec(4, 1, vec![0.0, 0.05, 2.0, 0.5]).expect("size");
        let (target, mask) = inverse_depth_target(&depth, 0.1);
        assert_eq!(mask, vec![false, false, true, true]);
        assert_eq!(target.data, vec![0.0, 0.0, 0.5, 2.0]);
        let fit = ScaleShift {
            a: 2.0,
            b: -1.0,
            used: 2,
        };
        let prior = ImageF32::from_vec(4, 1, vec![1.0, 0.25, 0.75, 0.5]).expect("size");
        // 1/(2·1 − 1) = 1; 2·0.25 − 1 < 0 → no depth; 1/(1.5 − 1) = 2; 2·0.5 − 1 = 0 → no depth.
        assert_eq!(aligned_depth(&prior, &fit).data, vec![1.0, 0.0, 2.0, 0.0]);
    }

    #[test]
    fn dense_align_handles_large_offsets() {
        // A prior with a big offset (like raw disparity in the thousands) still fits exactly.
        let mut prior = ramp(32, 8);
        for p in &mut prior.data {
            *p += 5000.0;
        }
        let mut target = prior.clone();
        for t in &mut target.data {
            *t = 0.01 * (*t - 5000.0) + 0.5;
        }
        let fit = fit_scale_shift(&prior, &target, None).expect("fit");
        assert!((fit.a - 0.01).abs() < 1e-4, "{fit:?}");
    }

    #[test]
    fn dense_align_rejects_degenerate_fits() {
        let prior = ramp(8, 8);
        let target = prior.clone();
        // Size mismatch.
        assert!(matches!(
            fit_scale_shift(&prior, &ImageF32::filled(4, 4, 1.0), None),
            Err(Error::Shape(_))
        ));
        // Mask of the wrong length.
        assert!(fit_scale_shift(&prior, &target, Some(&[true; 3])).is_err());
        // Too few pixels with a target.
        let mut sparse = ImageF32::filled(8, 8, 0.0);
        sparse.data[..MIN_ALIGN_PIXELS - 1].fill(1.0);
        assert!(fit_scale_shift(&prior, &sparse, None).is_err());
        // Constant prior: singular normal equations.
        let flat = ImageF32::filled(8, 8, 0.7);
        assert!(fit_scale_shift(&flat, &target, None).is_err());
        // Inverted prior: a < 0 is refused, but the unconstrained fit returns it.
        let mut inverted = prior.clone();
        for p in &mut inverted.data {
            *p = 2.0 - *p;
        }
        assert!(fit_scale_shift(&inverted, &target, None).is_err());
        let raw = fit_scale_shift_unconstrained(&inverted, &target, None).expect("fit");
        assert!(
            (raw.a + 1.0).abs() < 1e-5 && (raw.b - 2.0).abs() < 1e-5,
            "{raw:?}"
        );
    }
}
