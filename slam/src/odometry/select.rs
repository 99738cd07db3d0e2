//! Candidate points of a new keyframe, spread over the whole image (DSO's pixel selector,
//! `PixelSelector2.cpp`, TPAMI 2018 §3.2, in our own words).
//!
//! Why: a fixed gradient threshold puts every point on the few strongest edges and none in
//! weakly textured regions, so the window sees the scene's shape through a keyhole. The
//! threshold is therefore adaptive per region (its median gradient plus a margin), each cell
//! of a grid gives its best pixel above it, and a second pass with a lower threshold over
//! larger cells fills what the first left empty.

use nalgebra::Vector2;

use crate::image::pyramid::PyramidLevel;

/// Side of the regions whose median gradient sets the threshold (DSO: 32 pixels).
pub const REGION: usize = 32;
/// Grey levels added to a region's median gradient (`setting_minGradHistAdd` = 7).
pub const THRESHOLD_ADD: f32 = 7.0;
/// Pixels kept away from the border: the residual pattern reaches 2 pixels out, the
/// gradients one more.
pub const MARGIN: usize = 4;

/// Per-region gradient threshold over `width/REGION × height/REGION` regions (rounded up), each the median
/// of its region's gradient magnitude plus [`THRESHOLD_ADD`], smoothed over its 3×3
/// neighbourhood so that neighbouring regions do not jump.
fn thresholds(level: &PyramidLevel) -> Regions {
    let (w, h) = (level.width(), level.height());
    let (rw, rh) = (w.div_ceil(REGION), h.div_ceil(REGION));
    let mut medians = vec![0f32; rw * rh];
    let mut values = Vec::with_capacity(REGION * REGION);
    for ry in 0..rh {
        for rx in 0..rw {
            values.clear();
            for y in ry * REGION..((ry + 1) * REGION).min(h) {
                for x in rx * REGION..((rx + 1) * REGION).min(w) {
                    values.push(level.grad_mag.at(x, y));
                }
            }
            let mid = values.len() / 2;
            values.select_nth_unstable_by(mid, f32::total_cmp);
            medians[ry * rw + rx] = values[mid];
        }
    }
    let mut smoothed = vec![0f32; rw * rh];
    for ry in 0..rh {
        for rx in 0..rw {
            let (mut sum, mut n) = (0f32, 0f32);
            for ny in ry.saturating_sub(1)..=(ry + 1).min(rh - 1) {
                for nx in rx.saturating_sub(1)..=(rx + 1).min(rw - 1) {
                    sum += medians[ny * rw + nx];
                    n += 1.0;
                }
            }
            smoothed[ry * rw + rx] = sum / n + THRESHOLD_ADD;
        }
    }
    Regions {
        columns: rw,
        threshold: smoothed,
    }
}

/// The gradient threshold of each region, row by row.
struct Regions {
    columns: usize,
    threshold: Vec<f32>,
}

/// One pass: the best pixel of each `cell × cell` cell whose gradient is above
/// `factor ×` its region's threshold and which is not already `taken`.
fn pass(
    level: &PyramidLevel,
    regions: &Regions,
    cell: usize,
    factor: f32,
    taken: &mut [bool],
) -> Vec<Vector2<f64>> {
    let (w, h) = (level.width(), level.height());
    let (rw, threshold) = (regions.columns, &regions.threshold);
    let mut out = Vec::new();
    let mut cy = MARGIN;
    while cy + MARGIN < h {
        let mut cx = MARGIN;
        while cx + MARGIN < w {
            let mut best: Option<(f32, usize, usize)> = None;
            let mut occupied = false;
            for y in cy..(cy + cell).min(h - MARGIN) {
                for x in cx..(cx + cell).min(w - MARGIN) {
                    if taken[y * w + x] {
                        occupied = true;
                    }
                    let g = level.grad_mag.at(x, y);
                    let t = factor * threshold[(y / REGION) * rw + x / REGION];
                    if g > t && best.is_none_or(|b| g > b.0) {
                        best = Some((g, x, y));
                    }
                }
            }
            if let (false, Some((_, x, y))) = (occupied, best) {
                taken[y * w + x] = true;
                out.push(Vector2::new(x as f64, y as f64));
            }
            cx += cell;
        }
        cy += cell;
    }
    out
}

/// About `target` well-spread candidate pixels of `level`: cells sized for the target, a
/// second pass at three quarters of the threshold over cells twice as large for weak
/// texture, and the cell size corrected once by the count the first try gave (DSO re-runs
/// its selector the same way).
pub fn select_candidates(level: &PyramidLevel, target: usize) -> Vec<Vector2<f64>> {
    let (w, h) = (level.width(), level.height());
    if target == 0 || w <= 2 * MARGIN || h <= 2 * MARGIN {
        return Vec::new();
    }
    let regions = thresholds(level);
    let run = |cell: usize| {
        let mut taken = vec![false; w * h];
        let mut points = pass(level, &regions, cell, 1.0, &mut taken);
        points.extend(pass(level, &regions, 2 * cell, 0.75, &mut taken));
        points
    };
    let area = ((w - 2 * MARGIN) * (h - 2 * MARGIN)) as f64;
    let mut cell = ((area / target as f64).sqrt().round() as usize).max(1);
    let mut points = run(cell);
    if !points.is_empty() {
        let corrected =
            (cell as f64 * (points.len() as f64 / target as f64).sqrt()).round() as usize;
        let corrected = corrected.max(1);
        if corrected != cell {
            cell = corrected;
            points = run(cell);
        }
    }
    points
}
