//! Spatial regularisation and hole filling of the inverse-depth map (Engel et al., ICCV 2013
//! §2.3; LSD-SLAM `DepthMap::regularizeDepthMap` and `regularizeDepthMapFillHoles`).

use super::MappingConfig;
use super::bands::map_row_bands;
use super::hypothesis::{Estimate, Pixel, unzero};
use crate::image::ImageF32;

/// Neighbourhood radius of both passes (5×5).
const RADIUS: usize = 2;

/// The raw values the passes read, as planes (structure of arrays) so that a row of
/// centres can be processed lane-parallel against each of the 25 neighbour offsets
/// (auto-vectorised). "No hypothesis" is `var = +∞`, `idepth = 0`, `validity = 0`: it then
/// agrees with everything, weighs 0 and adds no validity, which keeps the loops branch-free.
struct Planes {
    idepth: Vec<f32>,
    var: Vec<f32>,
    validity: Vec<f32>,
}

impl Planes {
    fn new(pixels: &[Pixel]) -> Self {
        let n = pixels.len();
        let mut p = Planes {
            idepth: vec![0.0; n],
            var: vec![f32::INFINITY; n],
            validity: vec![0.0; n],
        };
        for (i, e) in pixels
            .iter()
            .enumerate()
            .filter_map(|(i, px)| Some((i, px.estimate?)))
        {
            p.idepth[i] = e.idepth;
            p.var[i] = e.var;
            p.validity[i] = e.validity as f32;
        }
        p
    }
}

/// Per-row accumulators of the smoothing pass, one lane per centre pixel.
#[derive(Default)]
struct RowSums {
    sum: Vec<f32>,
    sum_ivar: Vec<f32>,
    val_sum: Vec<f32>,
    occluding: Vec<f32>,
    not_occluding: Vec<f32>,
}

impl RowSums {
    fn reset(&mut self, n: usize) {
        for v in [
            &mut self.sum,
            &mut self.sum_ivar,
            &mut self.val_sum,
            &mut self.occluding,
            &mut self.not_occluding,
        ] {
            v.clear();
            v.resize(n, 0.0);
        }
    }
}

/// Smoothing pass. For every hypothesis, the neighbours (5×5, itself included) that agree
/// within the 1σ test `fac·Δ² ≤ σ²ᵢ + σ²ⱼ` are averaged with weights
/// `1/(σ²ⱼ + d²·reg_dist_var)` (closer, more certain neighbours count more); the result
/// becomes the smoothed estimate. A hypothesis whose agreeing neighbours' validity sums to
/// less than `val_sum_min_for_keep` is an unsupported outlier: it is removed and its pixel's
/// blacklist counter decremented. With `remove_occlusions` (after propagation), a hypothesis
/// outvoted by closer (larger inverse depth) disagreeing neighbours is removed as occluded.
/// Reads a snapshot, so the result does not depend on the visiting order.
pub(crate) fn smooth(
    pixels: &mut [Pixel],
    width: usize,
    height: usize,
    cfg: &MappingConfig,
    remove_occlusions: bool,
    threads: usize,
) {
    let src = Planes::new(pixels);
    let src = &src;
    let fac = cfg.diff_fac_smoothing;
    let keep = cfg.val_sum_min_for_keep as f32;
    // Centres x ∈ [RADIUS, width − RADIUS): `n` lanes starting at column RADIUS.
    let n = width - 2 * RADIUS;
    map_row_bands(pixels, width, threads, |y0, band| {
        let mut acc = RowSums::default();
        for (r, row) in band.chunks_mut(width).enumerate() {
            let y = y0 + r;
            if y < RADIUS || y + RADIUS >= height {
                continue;
            }
            let c0 = y * width + RADIUS;
            if src.var[c0..c0 + n].iter().all(|v| *v == f32::INFINITY) {
                continue;
            }
            acc.reset(n);
            let c_id = &src.idepth[c0..c0 + n];
            let c_var = &src.var[c0..c0 + n];
            for dy in 0..=2 * RADIUS {
                for dx in 0..=2 * RADIUS {
                    let d2 = (dx.abs_diff(RADIUS).pow(2) + dy.abs_diff(RADIUS).pow(2)) as f32;
                    let dist_var = d2 * cfg.reg_dist_var;
                    let base = (y + dy - RADIUS) * width + dx;
                    let n_id = &src.idepth[base..base + n];
                    let n_var = &src.var[base..base + n];
                    let n_val = &src.validity[base..base + n];
                    // Equal-length slices let the compiler drop bounds checks and vectorise.
                    let (c_id, c_var) = (&c_id[..n], &c_var[..n]);
                    let occluding = &mut acc.occluding[..n];
                    let not_occluding = &mut acc.not_occluding[..n];
                    let val_sum = &mut acc.val_sum[..n];
                    let sum = &mut acc.sum[..n];
                    let sum_ivar = &mut acc.sum_ivar[..n];
                    for i in 0..n {
                        let diff = n_id[i] - c_id[i];
                        let agree = fac * diff * diff <= n_var[i] + c_var[i];
                        let a = if agree { 1.0f32 } else { 0.0 };
                        let closer = if n_id[i] > c_id[i] { 1.0f32 } else { 0.0 };
                        let valid = if n_var[i] < f32::INFINITY {
                            1.0f32
                        } else {
                            0.0
                        };
                        occluding[i] += (1.0 - a) * closer;
                        not_occluding[i] += a * valid;
                        val_sum[i] += a * n_val[i];
                        let ivar = a / (n_var[i] + dist_var);
                        sum[i] += n_id[i] * ivar;
                        sum_ivar[i] += ivar;
                    }
                }
            }
            for (i, dest) in row[RADIUS..RADIUS + n].iter_mut().enumerate() {
                if dest.estimate.is_none() {
                    continue;
                }
                if acc.val_sum[i] < keep {
                    dest.estimate = None;
                    dest.blacklist -= 1;
                    continue;
                }
                if remove_occlusions && acc.occluding[i] > acc.not_occluding[i] {
                    dest.estimate = None;
                    continue;
                }
                if let Some(e) = dest.estimate.as_mut() {
                    e.idepth_smoothed = unzero(acc.sum[i] / acc.sum_ivar[i]);
                    e.var_smoothed = 1.0 / acc.sum_ivar[i];
                }
            }
        }
    });
}

/// Hole filling. A pixel without hypothesis but with enough gradient, whose 5×5
/// neighbourhood's validity sums to more than `val_sum_min_for_create` (more than
/// `val_sum_min_for_unblacklist` when blacklisted), gets the inverse-variance-weighted mean of
/// its neighbours with the large initial variance and validity 0: it must earn support from
/// stereo before the next regularisation keeps it for long. Interpolating inside well-observed
/// regions lets stereo find those pixels within a narrow search range.
pub(crate) fn fill_holes(
    pixels: &mut [Pixel],
    max_grad: &ImageF32,
    width: usize,
    height: usize,
    cfg: &MappingConfig,
    threads: usize,
) {
    let src = Planes::new(pixels);
    let src = &src;
    let integral = validity_integral(&src.validity, width, height);
    let iw = width + 1;
    // Validity summed over [x0, x1) × [y0, y1).
    let rect = |x0: usize, y0: usize, x1: usize, y1: usize| -> i64 {
        integral[y1 * iw + x1] - integral[y0 * iw + x1] - integral[y1 * iw + x0]
            + integral[y0 * iw + x0]
    };
    map_row_bands(pixels, width, threads, |y0, band| {
        for (r, row) in band.chunks_mut(width).enumerate() {
            let y = y0 + r;
            if y < RADIUS + 1 || y + RADIUS >= height {
                continue;
            }
            for (x, dest) in row
                .iter_mut()
                .enumerate()
                .take(width - RADIUS)
                .skip(RADIUS + 1)
            {
                let i = y * width + x;
                // Pixels filled earlier in this pass are not in `src`: no cascade.
                if src.var[i].is_finite() || max_grad.data[i] < cfg.min_use_grad {
                    continue;
                }
                let val = rect(x - RADIUS, y - RADIUS, x + RADIUS + 1, y + RADIUS + 1);
                let allowed = dest.blacklist >= cfg.min_blacklist
                    && val > i64::from(cfg.val_sum_min_for_create);
                if !(allowed || val > i64::from(cfg.val_sum_min_for_unblacklist)) {
                    continue;
                }
                let (mut sum, mut sum_ivar) = (0.0f32, 0.0f32);
                for dy in 0..5 {
                    let start = (y + dy - RADIUS) * width + x - RADIUS;
                    let ids = &src.idepth[start..start + 5];
                    for (d, v) in ids.iter().zip(&src.var[start..start + 5]) {
                        sum += d / v;
                        sum_ivar += 1.0 / v;
                    }
                }
                if sum_ivar > 0.0 {
                    dest.set(Estimate::new(
                        unzero(sum / sum_ivar),
                        cfg.var_random_init_initial,
                        0,
                    ));
                }
            }
        }
    });
}

/// Summed-area table of the validity counters of valid hypotheses, `(w+1)×(h+1)` with a zero
/// first row and column.
fn validity_integral(validity: &[f32], width: usize, height: usize) -> Vec<i64> {
    let iw = width + 1;
    let mut out = vec![0i64; iw * (height + 1)];
    for y in 0..height {
        let mut row_sum = 0i64;
        for x in 0..width {
            row_sum += validity[y * width + x] as i64;
            out[(y + 1) * iw + x + 1] = out[y * iw + x + 1] + row_sum;
        }
    }
    out
}
