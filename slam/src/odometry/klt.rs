//! Corner tracks for the initialiser's two-view check ([`super::two_view`]): Shi–Tomasi
//! corners of the first frame, followed frame to frame by pyramidal Lucas–Kanade with a
//! forward–backward check (Shi & Tomasi 1994; Bouguet's pyramidal form; the check of Kalal et
//! al. 2010).
//!
//! Why corners and not the photometric points: a point on an edge slides along it between
//! frames, and its track then lies off the epipolar line; a corner's does not.

use nalgebra::{Matrix2, Vector2};

use crate::image::ImageF32;
use crate::image::pyramid::{Pyramid, PyramidLevel};

/// Half the side of a tracked patch (15×15 pixels at every level).
const HALF_WINDOW: i32 = 7;
/// Coarsest level tracked (×4 at 640×480): with the patch's reach this follows motions of
/// about 30 pixels a frame, more than a hand-held camera makes at 30 Hz, while a coarser
/// level's patch would cover most of its image.
const TOP_LEVEL: usize = 2;
/// Half the side of the window over which a corner's structure tensor is summed (7×7).
const HALF_CORNER: i32 = 3;
/// Lucas–Kanade iterations per level at most; a step below [`CONVERGED`] pixels ends them.
const ITERATIONS: usize = 20;
const CONVERGED: f64 = 0.01;
/// A track is kept when tracking it back lands within this many level-0 pixels of where it
/// came from (a track that drifted, was occluded or slid along an edge does not come back).
const FORWARD_BACKWARD: f64 = 0.5;
/// A corner's smaller structure-tensor eigenvalue must be at least this share of the image's
/// largest (OpenCV's `qualityLevel` in `goodFeaturesToTrack`): flat or edge-only cells give
/// none.
const QUALITY: f32 = 0.005;
/// Smallest mean eigenvalue per patch pixel a patch needs to be tracked at a level (squared
/// intensity gradient, intensities in 0..255): below it the step is noise.
const MIN_EIGEN: f64 = 1e-2;

/// The smaller eigenvalue of `[[a, b], [b, c]]`.
fn min_eigenvalue(a: f64, b: f64, c: f64) -> f64 {
    0.5 * (a + c - ((a - c).powi(2) + 4.0 * b * b).sqrt())
}

/// Shi–Tomasi corners of `level`: in each `cell`×`cell` block of the image the pixel with the
/// largest smaller eigenvalue of its structure tensor, when that is at least [`QUALITY`] of the
/// image's largest. A grid spreads them over the image, which the two-view geometry needs.
pub fn corners(level: &PyramidLevel, cell: usize) -> Vec<Vector2<f64>> {
    let (w, h) = (level.width(), level.height());
    let border = (HALF_WINDOW + 1) as usize;
    if cell == 0 || w <= 2 * border || h <= 2 * border {
        return Vec::new();
    }
    let r = HALF_CORNER as isize;
    let tensor = |x: usize, y: usize| {
        let (mut a, mut b, mut c) = (0.0f64, 0.0f64, 0.0f64);
        for dy in -r..=r {
            for dx in -r..=r {
                let (px, py) = ((x as isize + dx) as usize, (y as isize + dy) as usize);
                let (gx, gy) = (
                    f64::from(level.gx.at(px, py)),
                    f64::from(level.gy.at(px, py)),
                );
                a += gx * gx;
                b += gx * gy;
                c += gy * gy;
            }
        }
        min_eigenvalue(a, b, c) as f32
    };
    let mut best: Vec<(f32, usize, usize)> = Vec::new();
    for cy in (border..h - border).step_by(cell) {
        for cx in (border..w - border).step_by(cell) {
            let mut top = (0.0f32, cx, cy);
            for y in cy..(cy + cell).min(h - border) {
                for x in cx..(cx + cell).min(w - border) {
                    let v = tensor(x, y);
                    if v > top.0 {
                        top = (v, x, y);
                    }
                }
            }
            best.push(top);
        }
    }
    let largest = best.iter().map(|b| b.0).fold(0.0f32, f32::max);
    best.into_iter()
        .filter(|b| b.0 > 0.0 && b.0 >= QUALITY * largest)
        .map(|(_, x, y)| Vector2::new(x as f64, y as f64))
        .collect()
}

/// Where `image` is read at `(x, y)`, clamped to its border (a patch that overhangs the
/// image repeats its edge, as OpenCV's tracker does); `None` when the centre itself is out.
fn clamped(image: &ImageF32, x: f64, y: f64) -> Option<relfusion_core::image::BilinearAt> {
    let (w, h) = ((image.width - 1) as f64, (image.height - 1) as f64);
    image.bilinear_at(x.clamp(0.0, w) as f32, y.clamp(0.0, h) as f32)
}

fn inside(image: &ImageF32, at: &Vector2<f64>) -> bool {
    at.x >= 0.0
        && at.y >= 0.0
        && at.x <= (image.width - 1) as f64
        && at.y <= (image.height - 1) as f64
}

/// The patch of `image` around `at` ([`HALF_WINDOW`]), with its mean and standard deviation
/// removed (a change of exposure between frames moves neither); `None` when it leaves the
/// image.
fn patch(image: &ImageF32, at: &Vector2<f64>) -> Option<Vec<f64>> {
    if !inside(image, at) {
        return None;
    }
    let mut values = Vec::with_capacity(((2 * HALF_WINDOW + 1) * (2 * HALF_WINDOW + 1)) as usize);
    for dy in -HALF_WINDOW..=HALF_WINDOW {
        for dx in -HALF_WINDOW..=HALF_WINDOW {
            let sample = clamped(image, at.x + f64::from(dx), at.y + f64::from(dy))?;
            values.push(f64::from(image.sample(&sample)));
        }
    }
    normalise(&mut values);
    Some(values)
}

/// Removes the mean of `values` and divides by their standard deviation (not when that is
/// about 0); returns the standard deviation.
fn normalise(values: &mut [f64]) -> f64 {
    let n = values.len().max(1) as f64;
    let mean = values.iter().sum::<f64>() / n;
    let sd = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    let scale = if sd > 1e-9 { 1.0 / sd } else { 1.0 };
    for v in values.iter_mut() {
        *v = (*v - mean) * scale;
    }
    sd
}

/// Lucas–Kanade at one level: where the patch of `from` at `at` lies in `to`, starting at
/// `guess` (inverse compositional: the template's gradients, summed once).
fn track_level(
    from: &PyramidLevel,
    to: &PyramidLevel,
    at: &Vector2<f64>,
    guess: Vector2<f64>,
) -> Option<Vector2<f64>> {
    if !inside(&from.image, at) {
        return None;
    }
    let mut template = Vec::new();
    let mut gradients = Vec::new();
    for dy in -HALF_WINDOW..=HALF_WINDOW {
        for dx in -HALF_WINDOW..=HALF_WINDOW {
            let sample = clamped(&from.image, at.x + f64::from(dx), at.y + f64::from(dy))?;
            template.push(f64::from(from.image.sample(&sample)));
            gradients.push(Vector2::new(
                f64::from(from.gx.sample(&sample)),
                f64::from(from.gy.sample(&sample)),
            ));
        }
    }
    // The gradients in the normalised template's units.
    let n = template.len() as f64;
    let sd = normalise(&mut template);
    if sd <= 1e-9 {
        return None;
    }
    let mut hessian = Matrix2::zeros();
    for g in gradients.iter_mut() {
        *g /= sd;
        hessian += *g * g.transpose();
    }
    if min_eigenvalue(hessian[(0, 0)], hessian[(0, 1)], hessian[(1, 1)]) / n < MIN_EIGEN / sd / sd {
        return None;
    }
    let inverse = hessian.try_inverse()?;
    let mut position = guess;
    for _ in 0..ITERATIONS {
        let current = patch(&to.image, &position)?;
        let mut b = Vector2::zeros();
        for ((c, t), g) in current.iter().zip(&template).zip(&gradients) {
            b += g * (c - t);
        }
        let step = inverse * b;
        position -= step;
        if step.norm() < CONVERGED {
            break;
        }
    }
    position.iter().all(|v| v.is_finite()).then_some(position)
}

/// Where `point` (level-0 pixel of `from`) lies in `to`, coarse to fine; `None` when the patch
/// leaves the image or has no texture at some level.
fn track_point(from: &Pyramid, to: &Pyramid, point: &Vector2<f64>) -> Option<Vector2<f64>> {
    let top = from
        .levels
        .len()
        .min(to.levels.len())
        .saturating_sub(1)
        .min(TOP_LEVEL);
    let mut displacement = Vector2::zeros();
    for level in (0..=top).rev() {
        let scale = f64::from(1u32 << level);
        let at = point / scale;
        let found = track_level(
            &from.levels[level],
            &to.levels[level],
            &at,
            at + displacement,
        )?;
        displacement = found - at;
        if level > 0 {
            displacement *= 2.0;
        }
    }
    Some(point + displacement)
}

/// Where each of `points` (level-0 pixels of `from`) lies in `to`: `None` for a track lost, or
/// one that tracked back lands more than [`FORWARD_BACKWARD`] pixels from where it started.
pub fn track(from: &Pyramid, to: &Pyramid, points: &[Vector2<f64>]) -> Vec<Option<Vector2<f64>>> {
    points
        .iter()
        .map(|p| {
            let forward = track_point(from, to, p)?;
            let back = track_point(to, from, &forward)?;
            ((back - p).norm() <= FORWARD_BACKWARD).then_some(forward)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth random texture shifted by `(sx, sy)` pixels.
    fn texture(w: usize, h: usize, sx: f64, sy: f64) -> ImageF32 {
        let mut img = ImageF32::filled(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let (u, v) = (x as f64 - sx, y as f64 - sy);
                let value = 128.0
                    + 40.0 * (0.21 * u + 0.05 * v).sin() * (0.17 * v - 0.03 * u).cos()
                    + 30.0 * (0.09 * u * 0.7 + 0.13 * v).sin()
                    + 20.0 * ((0.31 * u).sin() * (0.27 * v).sin());
                *img.at_mut(x, y) = value as f32;
            }
        }
        img
    }

    #[test]
    fn corners_spread_over_the_image_and_tracks_follow_a_shift_and_an_exposure_change() {
        let a = Pyramid::build_cpu(&texture(160, 120, 0.0, 0.0), 3).expect("pyramid");
        let mut shifted = texture(160, 120, 3.4, -1.7);
        for v in &mut shifted.data {
            *v = 1.3 * *v + 12.0;
        }
        let b = Pyramid::build_cpu(&shifted, 3).expect("pyramid");
        let points = corners(&a.levels[0], 16);
        assert!(points.len() >= 30, "{} corners", points.len());
        let tracked = track(&a, &b, &points);
        let found: Vec<_> = points
            .iter()
            .zip(&tracked)
            .filter_map(|(p, t)| t.map(|t| (p, t)))
            .collect();
        assert!(
            found.len() * 2 >= points.len(),
            "{} of {} tracked",
            found.len(),
            points.len()
        );
        for (p, t) in found {
            let error = (t - p - Vector2::new(3.4, -1.7)).norm();
            assert!(error < 0.1, "track error {error} px at {p:?}");
        }
    }

    #[test]
    fn a_flat_image_has_no_corners_and_nothing_to_track() {
        let flat = Pyramid::build_cpu(&ImageF32::filled(80, 60, 100.0), 2).expect("pyramid");
        assert!(corners(&flat.levels[0], 8).is_empty());
        let tracked = track(&flat, &flat, &[Vector2::new(40.0, 30.0)]);
        assert_eq!(tracked, vec![None]);
    }
}
