//! Depth propagation to a new keyframe (Engel et al., ICCV 2013 §2.2, eq. 8; LSD-SLAM
//! `DepthMap::propagateDepth`).

use nalgebra::Vector3;

use super::DepthFilter;
use super::hypothesis::Estimate;
use super::stereo::interp;
use crate::geometry::SE3;

/// Forward-warps every hypothesis of `old` into `new` (which must be empty), whose pose is
/// `new_from_old` relative to the old keyframe.
///
/// Each point is moved with its smoothed inverse depth and lands on the nearest pixel. The
/// prediction assumes a small rotation: the inverse depth changes as `ρ₁ = 1/z₁` and its
/// variance as `σ₁² = (ρ₁/ρ₀)⁴·σ₀² + σ_p²` (eq. 8). A hypothesis is dropped when it leaves
/// the image, lands on a pixel with too little gradient, or changes colour by more than the
/// photometric tolerance (the point was probably occluded or mis-estimated). When two land on
/// the same pixel and disagree beyond the 1σ test, the farther one is occluded and dropped;
/// when they agree they are fused (product of Gaussians) and their validities summed.
pub(crate) fn warp(old: &DepthFilter, new: &mut DepthFilter, new_from_old: &SE3) {
    let cfg = &new.config;
    let (w, h) = (old.width(), old.height());
    let rot = new_from_old.rotation.matrix().cast::<f32>();
    let trans: Vector3<f32> = new_from_old.translation.cast();
    let old_image = &old.keyframe.level(0).image;
    let new_image = &new.keyframe.level(0).image;
    let k = old.k;
    let validity_cap = (cfg.validity_counter_max + cfg.validity_counter_max_variable) as i32;
    for y in 0..h {
        for x in 0..w {
            let Some(src) = old.pixels[y * w + x].estimate else {
                continue;
            };
            if src.idepth_smoothed.is_nan() || src.idepth_smoothed <= 0.0 {
                continue;
            }
            let pn = rot * k.ray(x as f32, y as f32) / src.idepth_smoothed + trans;
            if pn.z.is_nan() || pn.z <= 0.0 {
                continue;
            }
            let new_idepth = 1.0 / pn.z;
            let u = pn.x * new_idepth * k.fx + k.cx;
            let v = pn.y * new_idepth * k.fy + k.cy;
            if !(u > 2.1 && v > 2.1 && u < w as f32 - 3.1 && v < h as f32 - 3.1) {
                continue;
            }
            let ni = (u + 0.5) as usize + (v + 0.5) as usize * w;
            let dest_grad = new.max_grad.data[ni];
            let residual = interp(new_image, u, v) - old_image.data[y * w + x];
            let tolerance = cfg.max_diff_constant + cfg.max_diff_grad_mult * dest_grad * dest_grad;
            if residual * residual > tolerance || dest_grad < cfg.min_use_grad {
                continue;
            }
            let ratio2 = (new_idepth / src.idepth_smoothed).powi(2);
            let new_var = ratio2 * ratio2 * src.var + cfg.propagation_var_inc;
            let target = &mut new.pixels[ni];
            if let Some(t) = target.estimate {
                let diff = t.idepth - new_idepth;
                if cfg.diff_fac_prop_merge * diff * diff > new_var + t.var {
                    if new_idepth < t.idepth {
                        // The incoming point is behind the one already there.
                        continue;
                    }
                    target.estimate = None;
                }
            }
            let estimate = match target.estimate {
                None => Estimate::new(new_idepth, new_var, src.validity),
                Some(t) => {
                    let wt = new_var / (t.var + new_var);
                    let merged = wt * t.idepth + (1.0 - wt) * new_idepth;
                    let validity = (src.validity + t.validity).min(validity_cap);
                    Estimate::new(merged, 1.0 / (1.0 / t.var + 1.0 / new_var), validity)
                }
            };
            target.set(estimate);
        }
    }
}
