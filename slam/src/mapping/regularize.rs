//! Spatial regularisation and hole filling of the inverse-depth map (Engel et al., ICCV 2013
//! §2.3; LSD-SLAM `DepthMap::regularizeDepthMap` and `regularizeDepthMapFillHoles`).

use super::MappingConfig;
use super::bands::map_row_bands;
use super::hypothesis::{Estimate, Pixel, unzero};
use crate::image::ImageF32;

/// Neighbourhood radius of both passes (5×5).
const RADIUS: usize = 2;

/// The raw values the passes read, as planes (structure of arrays) so that a block of
/// centres can be processed lane-parallel against each of the 25 neighbour offsets
/// (auto-vectorised). "No hypothesis" is `var = +∞`, `idepth = 0`, `validity = 0`: it then
/// agrees with everything, weighs 0 and adds no validity, which keeps the loops branch-free.
///
/// Kept by the filter between frames (with the hole-filling integral image) so that the
/// per-frame passes allocate nothing.
#[derive(Clone, Debug, Default)]
pub(crate) struct Planes {
    idepth: Vec<f32>,
    var: Vec<f32>,
    validity: Vec<f32>,
    /// Summed-area table of `validity` (see [`validity_integral`]).
    integral: Vec<i64>,
}

impl Planes {
    fn new(pixels: &[Pixel]) -> Self {
        let mut p = Planes::default();
        p.load(pixels);
        p
    }

    /// Snapshot of `pixels`, reusing the buffers.
    fn load(&mut self, pixels: &[Pixel]) {
        let n = pixels.len();
        for v in [&mut self.idepth, &mut self.var, &mut self.validity] {
            v.resize(n, 0.0);
        }
        let planes = self
            .idepth
            .iter_mut()
            .zip(self.var.iter_mut())
            .zip(self.validity.iter_mut());
        for (px, ((d, v), val)) in pixels.iter().zip(planes) {
            (*d, *v, *val) = match px.estimate {
                Some(e) => (e.idepth, e.var, e.validity as f32),
                None => (0.0, f32::INFINITY, 0.0),
            };
        }
    }

    /// Records a hypothesis created after the snapshot.
    fn patch(&mut self, i: usize, e: &Estimate) {
        self.idepth[i] = e.idepth;
        self.var[i] = e.var;
        self.validity[i] = e.validity as f32;
    }
}

/// One regularisation step (LSD `updateKeyframe`'s post-processing): [`fill_holes_with`], then
/// [`smooth`] without occlusion removal, sharing one snapshot (patched with the filled
/// pixels, so the result equals running the two passes one after the other).
pub(crate) fn regularize(
    pixels: &mut [Pixel],
    max_grad: &ImageF32,
    width: usize,
    height: usize,
    cfg: &MappingConfig,
    threads: usize,
    scratch: &mut Planes,
) {
    scratch.load(pixels);
    let filled = fill_holes_with(scratch, pixels, max_grad, width, height, cfg, threads);
    for i in filled {
        if let Some(e) = &pixels[i].estimate {
            scratch.patch(i, e);
        }
    }
    smooth_with(scratch, pixels, width, height, cfg, false, threads);
}

/// Lanes (centre pixels) processed together by the smoothing kernel: the five accumulators of
/// a block stay in registers across all 25 neighbour offsets (SSE2: 2 vectors each).
const LANES: usize = 8;

/// Accumulators of one block of [`LANES`] centres.
#[derive(Clone, Copy, Default)]
struct BlockSums {
    sum: [f32; LANES],
    sum_ivar: [f32; LANES],
    val_sum: [f32; LANES],
    occluding: [f32; LANES],
    not_occluding: [f32; LANES],
}

/// The 25 neighbour offsets (row-major, like LSD's loops) with their distance variance
/// `d²·reg_dist_var`.
fn neighbour_offsets(cfg: &MappingConfig) -> [(usize, usize, f32); 25] {
    std::array::from_fn(|k| {
        let (dy, dx) = (k / 5, k % 5);
        let d2 = (dx.abs_diff(RADIUS).pow(2) + dy.abs_diff(RADIUS).pow(2)) as f32;
        (dy, dx, d2 * cfg.reg_dist_var)
    })
}

/// Accumulates the agreeing-neighbour sums of the [`LANES`] centres starting at plane index
/// `c` (centre row `y`, first centre column `c − y·width`). `LANES` is a constant, so the
/// lane loop unrolls to vector operations and the accumulators never leave registers.
#[inline(always)]
fn block_sums(
    src: &Planes,
    c: usize,
    width: usize,
    fac: f32,
    offsets: &[(usize, usize, f32); 25],
) -> BlockSums {
    let mut acc = BlockSums::default();
    let c_id: &[f32; LANES] = src.idepth[c..c + LANES].try_into().expect("block");
    let c_var: &[f32; LANES] = src.var[c..c + LANES].try_into().expect("block");
    for &(dy, dx, dist_var) in offsets {
        // Neighbour (x + dx − R, y + dy − R) of centre c.
        let base = c + dy * width + dx - RADIUS * width - RADIUS;
        let n_id: &[f32; LANES] = src.idepth[base..base + LANES].try_into().expect("block");
        let n_var: &[f32; LANES] = src.var[base..base + LANES].try_into().expect("block");
        let n_val: &[f32; LANES] = src.validity[base..base + LANES].try_into().expect("block");
        for i in 0..LANES {
            let diff = n_id[i] - c_id[i];
            let agree = fac * diff * diff <= n_var[i] + c_var[i];
            let a = if agree { 1.0f32 } else { 0.0 };
            let closer = if n_id[i] > c_id[i] { 1.0f32 } else { 0.0 };
            let valid = if n_var[i] < f32::INFINITY {
                1.0f32
            } else {
                0.0
            };
            acc.occluding[i] += (1.0 - a) * closer;
            acc.not_occluding[i] += a * valid;
            acc.val_sum[i] += a * n_val[i];
            let ivar = a / (n_var[i] + dist_var);
            acc.sum[i] += n_id[i] * ivar;
            acc.sum_ivar[i] += ivar;
        }
    }
    acc
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
    smooth_with(&src, pixels, width, height, cfg, remove_occlusions, threads);
}

/// [`smooth`] reading the snapshot `src` of `pixels` (built by the caller, so that one
/// snapshot serves hole filling and smoothing).
fn smooth_with(
    src: &Planes,
    pixels: &mut [Pixel],
    width: usize,
    height: usize,
    cfg: &MappingConfig,
    remove_occlusions: bool,
    threads: usize,
) {
    let fac = cfg.diff_fac_smoothing;
    let keep = cfg.val_sum_min_for_keep as f32;
    let offsets = neighbour_offsets(cfg);
    // Centres x ∈ [RADIUS, width − RADIUS), in blocks of LANES; the last block is shifted
    // left to end at width − RADIUS (it overlaps the previous one, which is harmless: each
    // centre's sums do not depend on the block).
    let n = width.saturating_sub(2 * RADIUS);
    if n < LANES {
        return smooth_narrow(src, pixels, width, height, cfg, remove_occlusions);
    }
    map_row_bands(pixels, width, threads, |y0, band| {
        for (r, row) in band.chunks_mut(width).enumerate() {
            let y = y0 + r;
            if y < RADIUS || y + RADIUS >= height {
                continue;
            }
            let mut x0 = RADIUS;
            loop {
                let x = x0.min(width - RADIUS - LANES);
                let c = y * width + x;
                // Only centres with a hypothesis need sums.
                if src.var[c..c + LANES].iter().any(|v| *v != f32::INFINITY) {
                    let acc = block_sums(src, c, width, fac, &offsets);
                    for (i, dest) in row[x..x + LANES].iter_mut().enumerate() {
                        apply(dest, &acc, i, keep, remove_occlusions);
                    }
                }
                if x + LANES >= width - RADIUS {
                    break;
                }
                x0 += LANES;
            }
        }
    });
}

/// Applies the smoothing result of lane `i` to its pixel. Idempotent for a pixel visited
/// twice (overlapping last block): only hypotheses present in the snapshot are touched, and
/// a second removal cannot happen because the first leaves no estimate.
#[inline]
fn apply(dest: &mut Pixel, acc: &BlockSums, i: usize, keep: f32, remove_occlusions: bool) {
    if dest.estimate.is_none() {
        return;
    }
    if acc.val_sum[i] < keep {
        dest.estimate = None;
        dest.blacklist -= 1;
        return;
    }
    if remove_occlusions && acc.occluding[i] > acc.not_occluding[i] {
        dest.estimate = None;
        return;
    }
    if let Some(e) = dest.estimate.as_mut() {
        e.idepth_smoothed = unzero(acc.sum[i] / acc.sum_ivar[i]);
        e.var_smoothed = 1.0 / acc.sum_ivar[i];
    }
}

/// Scalar fallback of [`smooth_with`] for maps narrower than a block.
fn smooth_narrow(
    src: &Planes,
    pixels: &mut [Pixel],
    width: usize,
    height: usize,
    cfg: &MappingConfig,
    remove_occlusions: bool,
) {
    let fac = cfg.diff_fac_smoothing;
    let keep = cfg.val_sum_min_for_keep as f32;
    let offsets = neighbour_offsets(cfg);
    for y in RADIUS..height.saturating_sub(RADIUS) {
        for x in RADIUS..width.saturating_sub(RADIUS) {
            let c = y * width + x;
            if src.var[c] == f32::INFINITY {
                continue;
            }
            let mut acc = BlockSums::default();
            for &(dy, dx, dist_var) in &offsets {
                let j = c + dy * width + dx - RADIUS * width - RADIUS;
                let diff = src.idepth[j] - src.idepth[c];
                let a = if fac * diff * diff <= src.var[j] + src.var[c] {
                    1.0f32
                } else {
                    0.0
                };
                let closer = if src.idepth[j] > src.idepth[c] {
                    1.0f32
                } else {
                    0.0
                };
                let valid = if src.var[j] < f32::INFINITY {
                    1.0f32
                } else {
                    0.0
                };
                acc.occluding[0] += (1.0 - a) * closer;
                acc.not_occluding[0] += a * valid;
                acc.val_sum[0] += a * src.validity[j];
                let ivar = a / (src.var[j] + dist_var);
                acc.sum[0] += src.idepth[j] * ivar;
                acc.sum_ivar[0] += ivar;
            }
            apply(&mut pixels[c], &acc, 0, keep, remove_occlusions);
        }
    }
}

/// Hole filling. A pixel without hypothesis but with enough gradient, whose 5×5
/// neighbourhood's validity sums to more than `val_sum_min_for_create` (more than
/// `val_sum_min_for_unblacklist` when blacklisted), gets the inverse-variance-weighted mean of
/// its neighbours with the large initial variance and validity 0: it must earn support from
/// stereo before the next regularisation keeps it for long. Interpolating inside well-observed
/// regions lets stereo find those pixels within a narrow search range.
///
/// Reads the snapshot `planes` of `pixels`; returns the filled pixel indices.
fn fill_holes_with(
    planes: &mut Planes,
    pixels: &mut [Pixel],
    max_grad: &ImageF32,
    width: usize,
    height: usize,
    cfg: &MappingConfig,
    threads: usize,
) -> Vec<usize> {
    let mut integral = std::mem::take(&mut planes.integral);
    validity_integral(&planes.validity, width, height, &mut integral);
    let src = &*planes;
    let integral_ref = &integral;
    let iw = width + 1;
    // Validity summed over [x0, x1) × [y0, y1).
    let rect = |x0: usize, y0: usize, x1: usize, y1: usize| -> i64 {
        let integral = integral_ref;
        integral[y1 * iw + x1] - integral[y0 * iw + x1] - integral[y1 * iw + x0]
            + integral[y0 * iw + x0]
    };
    let parts = map_row_bands(pixels, width, threads, |y0, band| {
        let mut filled = Vec::new();
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
                    filled.push(i);
                }
            }
        }
        filled
    });
    planes.integral = integral;
    parts.into_iter().flatten().collect()
}

/// Summed-area table of the validity counters of valid hypotheses, `(w+1)×(h+1)` with a zero
/// first row and column.
fn validity_integral(validity: &[f32], width: usize, height: usize, out: &mut Vec<i64>) {
    let iw = width + 1;
    out.clear();
    out.resize(iw * (height + 1), 0);
    for y in 0..height {
        let mut row_sum = 0i64;
        for x in 0..width {
            row_sum += validity[y * width + x] as i64;
            out[(y + 1) * iw + x + 1] = out[y * iw + x + 1] + row_sum;
        }
    }
}
