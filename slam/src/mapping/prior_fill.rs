//! Filling the holes of a new keyframe's propagated depth from the depth prior.
//!
//! Under pure rotation few stereo observations succeed, so the semi-dense map of each new
//! keyframe (propagated from the last, ICCV 2013 §2.2) is sparser than the one before and
//! tracking eventually runs out of points (LSD-SLAM's `MIN_GOODPERALL_PIXEL` test fails on a
//! correct pose). The relative depth prior of DeepRelativeFusion (Loo et al., IROS 2021, §III)
//! has a value at every pixel: aligned to the propagated semi-dense depth with eq. (3)
//! (`scale_shift::fit_scale_shift`, `D' = a·D_CNN + b`), it fills the holes with hypotheses
//! of large variance that stereo confirms or replaces, exactly as LSD-SLAM's hole filling does
//! from neighbours (`regularizeDepthMapFillHoles`) but reaching textured pixels far from any
//! estimate. This is the information the dense layer later provides for the whole map.
//!
//! A prior whose depth order contradicts the map (PyDNet++ inverts it on about one frame in
//! six) carries no shape that eq. (3) could use. Its holes are then filled at the map's median
//! inverse depth: a hypothesis of the right depth level and no shape, which stereo corrects as
//! it corrects a random initialisation. Writing the inverted prior instead planted a wrong
//! shape (docs/tuning.md, "Prior hole filling").

use super::DepthFilter;
use super::hypothesis::Estimate;
use crate::image::ImageF32;
use crate::scale_shift::{ScaleShift, fit_scale_shift};
use crate::{Error, Result};

/// How [`DepthFilter::fill_from_prior`] writes the prior (the pipeline's `prior_fill_*`
/// settings, documented there).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PriorFillParams {
    /// Variance of a filled hypothesis (the keyframe's scale).
    pub var: f32,
    /// Validity counter of a filled hypothesis.
    pub validity: i32,
    /// Fewest existing estimates the alignment needs.
    pub min_fit_pixels: usize,
    /// Nothing is filled when the existing estimates already cover more than this share of
    /// the usable pixels: stereo is doing its job and the prior would only add its errors.
    pub max_coverage: f32,
}

/// What [`DepthFilter::fill_from_prior`] did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PriorFill {
    /// The eq. (3) fit of the prior onto the existing estimates; `a = 0` and `b` = their
    /// median inverse depth when the fit failed (see [`DepthFilter::fill_from_prior`]).
    pub fit: ScaleShift,
    /// Hypotheses created.
    pub filled: usize,
    /// Share of the usable pixels that held an estimate before.
    pub coverage: f32,
}

impl DepthFilter {
    /// Fills every usable pixel without hypothesis (enough gradient, as for stereo: the map
    /// stays semi-dense; not blacklisted; inside the 1-pixel border) with the prior inverse
    /// depth aligned to the existing smoothed estimates by eq. (3), with the variance and
    /// validity of `params`. Existing hypotheses are left untouched: measured depth wins.
    /// When the affine fit fails (depth order inverted, `a ≤ 0`, or singular: the prior has no
    /// shape the map agrees with) the holes get the median of the existing estimates.
    ///
    /// Returns `Ok(None)` (and changes nothing) when the estimates cover more than
    /// `params.max_coverage` of the usable pixels, when fewer than `params.min_fit_pixels`
    /// estimates support the fit, or when no fit exists: a prior that cannot be related to
    /// the map must not be written into it. Aligned values that are not positive are skipped.
    pub fn fill_from_prior(
        &mut self,
        prior_inv: &ImageF32,
        params: &PriorFillParams,
    ) -> Result<Option<PriorFill>> {
        let PriorFillParams {
            var,
            validity,
            min_fit_pixels,
            max_coverage,
        } = *params;
        let (w, h) = (self.width(), self.height());
        if (prior_inv.width, prior_inv.height) != (w, h) {
            return Err(Error::Shape(format!(
                "prior is {}x{}, keyframe {w}x{h}",
                prior_inv.width, prior_inv.height
            )));
        }
        if !(var.is_finite() && var > 0.0) {
            return Err(Error::Config(format!(
                "fill_from_prior: variance must be positive, got {var}"
            )));
        }
        let coverage = self.coverage();
        if coverage > max_coverage {
            return Ok(None);
        }
        // Target of eq. (3): the smoothed (published) estimates; 0 = no value.
        let target_data = self
            .pixels
            .iter()
            .map(|p| match p.estimate {
                Some(e) if e.idepth_smoothed.is_finite() && e.idepth_smoothed > 0.0 => {
                    e.idepth_smoothed
                }
                _ => 0.0,
            })
            .collect();
        let target = ImageF32::from_vec(w, h, target_data)?;
        let fit = match fit_scale_shift(prior_inv, &target, None) {
            Ok(fit) => fit,
            // The affine fit inverts the depth order or is singular (a nearly fronto-parallel
            // map gives the prior's noise the upper hand). The least-squares fit constrained
            // to a ≥ 0 then has a = 0: the depth level only (its robust form, the median).
            Err(_) => match median_level(&target) {
                Some(fit) => fit,
                None => return Ok(None),
            },
        };
        if fit.used < min_fit_pixels.max(1) {
            return Ok(None);
        }
        let cfg = &self.config;
        let mut filled = 0;
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let i = y * w + x;
                let px = &mut self.pixels[i];
                if px.estimate.is_some()
                    || px.blacklist < cfg.min_blacklist
                    || self.max_grad.data[i] < cfg.min_use_grad
                {
                    continue;
                }
                let p = prior_inv.data[i];
                if !p.is_finite() {
                    continue;
                }
                let d = fit.apply(p);
                if d.is_finite() && d > 0.0 {
                    px.set(Estimate::new(d, var, validity));
                    filled += 1;
                }
            }
        }
        Ok(Some(PriorFill {
            fit,
            filled,
            coverage,
        }))
    }

    /// Share of the usable pixels (enough gradient, not blacklisted, inside the 1-pixel
    /// border) that hold a hypothesis; 1 when no pixel is usable.
    pub fn coverage(&self) -> f32 {
        let (w, h) = (self.width(), self.height());
        let cfg = &self.config;
        let (mut usable, mut covered) = (0usize, 0usize);
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let i = y * w + x;
                let px = &self.pixels[i];
                if px.estimate.is_some() {
                    usable += 1;
                    covered += 1;
                } else if px.blacklist >= cfg.min_blacklist
                    && self.max_grad.data[i] >= cfg.min_use_grad
                {
                    usable += 1;
                }
            }
        }
        if usable == 0 {
            1.0
        } else {
            covered as f32 / usable as f32
        }
    }
}

/// The constant "fit" `target ≈ 0·prior + median(target)` over the pixels with an estimate:
/// the depth level of the map without a shape.
fn median_level(target_inv: &ImageF32) -> Option<ScaleShift> {
    let mut values: Vec<f32> = target_inv
        .data
        .iter()
        .copied()
        .filter(|t| t.is_finite() && *t > 0.0)
        .collect();
    if values.is_empty() {
        return None;
    }
    let mid = values.len() / 2;
    let (_, median, _) = values.select_nth_unstable_by(mid, f32::total_cmp);
    Some(ScaleShift {
        a: 0.0,
        b: f64::from(*median),
        used: values.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mapping::MappingConfig;
    use crate::mapping::test_scene::{median, orbit_320, relative_errors};

    const PARAMS: PriorFillParams = PriorFillParams {
        var: 0.1,
        validity: 5,
        min_fit_pixels: 1000,
        max_coverage: 0.5,
    };

    /// A filter on synthetic frame 0 holding the exact inverse depth only in the columns
    /// `x < keep_cols` (a propagated map with a large hole), and the exact inverse depth.
    fn holey_filter(keep_cols: usize) -> (DepthFilter, ImageF32) {
        let s = orbit_320();
        let gt = s.idepth(0);
        let mut f =
            DepthFilter::new(s.frames[0].clone(), MappingConfig::default()).expect("filter");
        let mut partial = gt.clone();
        for y in 0..gt.height {
            for x in keep_cols..gt.width {
                partial.data[y * gt.width + x] = 0.0;
            }
        }
        f.init_from_depth(&partial, 1e-4).expect("init");
        (f, gt)
    }

    /// The prior as a network would give it: an affine distortion `(ρ − b)/a` of the truth.
    fn distorted(gt: &ImageF32, a: f32, b: f32) -> ImageF32 {
        let data = gt.data.iter().map(|&d| (d - b) / a).collect();
        ImageF32::from_vec(gt.width, gt.height, data).expect("same size")
    }

    #[test]
    fn mapping_prior_fill_recovers_scale_and_shift_and_fills_holes() {
        let (mut f, gt) = holey_filter(100);
        let before = f.depth_map();
        let coverage = f.coverage();
        assert!(
            coverage < 0.5,
            "hole too small for the test: coverage {coverage}"
        );
        let fill = f
            .fill_from_prior(&distorted(&gt, 4.0, 0.1), &PARAMS)
            .expect("fill")
            .expect("sparse map is filled");
        assert!((fill.fit.a - 4.0).abs() < 1e-3, "scale {}", fill.fit.a);
        assert!((fill.fit.b - 0.1).abs() < 1e-3, "shift {}", fill.fit.b);
        assert_eq!(fill.coverage, coverage);
        let after = f.depth_map();
        assert_eq!(
            after.num_estimates(),
            before.num_estimates() + fill.filled,
            "every filled pixel is published"
        );
        assert!(
            f.coverage() > 0.99,
            "textured holes remain: {}",
            f.coverage()
        );
        // Existing (measured) estimates are untouched; filled ones carry the prior variance.
        let mut new_pixels = 0;
        for (b, a) in before.pixels.iter().zip(&after.pixels) {
            match (b.estimate(), a.estimate()) {
                (Some(old), Some(new)) => assert_eq!(old, new),
                (None, Some((_, var))) => {
                    assert_eq!(var, PARAMS.var);
                    new_pixels += 1;
                }
                (Some(_), None) => panic!("fill removed an estimate"),
                (None, None) => {}
            }
        }
        assert_eq!(new_pixels, fill.filled);
        let errs = relative_errors(&after, &gt);
        assert!(median(errs) < 1e-3, "filled depth is not the aligned prior");
    }

    #[test]
    fn mapping_prior_fill_leaves_well_covered_maps_alone() {
        let (mut f, gt) = holey_filter(300);
        assert!(f.coverage() > PARAMS.max_coverage);
        let before = f.depth_map();
        let fill = f
            .fill_from_prior(&distorted(&gt, 4.0, 0.1), &PARAMS)
            .expect("fill");
        assert!(fill.is_none());
        assert_eq!(f.depth_map(), before);
        // Too few estimates to trust a fit: nothing either.
        let (mut f, gt) = holey_filter(100);
        let strict = PriorFillParams {
            min_fit_pixels: 1_000_000,
            ..PARAMS
        };
        assert!(f.fill_from_prior(&gt, &strict).expect("fill").is_none());
        let small = crate::image::ImageF32::filled(10, 10, 1.0);
        assert!(f.fill_from_prior(&small, &PARAMS).is_err());
    }

    #[test]
    fn mapping_prior_fill_uses_the_median_level_when_the_order_is_inverted() {
        let (mut f, gt) = holey_filter(100);
        let before = f.depth_map();
        let mut existing: Vec<f32> = before
            .pixels
            .iter()
            .filter_map(|p| p.estimate().map(|(d, _)| d))
            .collect();
        let mid = existing.len() / 2;
        let level = *existing.select_nth_unstable_by(mid, f32::total_cmp).1;
        // Depth order inverted: the affine fit has a < 0, so no shape is taken from it.
        let inverted_data = gt.data.iter().map(|&d| 2.0 - d * 0.5).collect();
        let inverted = ImageF32::from_vec(gt.width, gt.height, inverted_data).expect("size");
        let fill = f
            .fill_from_prior(&inverted, &PARAMS)
            .expect("fill")
            .expect("median fill");
        assert_eq!(fill.fit.a, 0.0);
        assert!(fill.filled > 0);
        let after = f.depth_map();
        let mut filled = 0;
        for (b, a) in before.pixels.iter().zip(&after.pixels) {
            if let (None, Some((d, var))) = (b.estimate(), a.estimate()) {
                assert!((d - level).abs() < 1e-6, "filled {d}, median level {level}");
                assert_eq!(var, PARAMS.var);
                filled += 1;
            }
        }
        assert_eq!(filled, fill.filled);
    }
}
