//! How far a densified pixel is from the semi-dense depth that supports it, and the variance
//! that distance adds.
//!
//! Eq. (16)'s `V_opt` carries only the keyframe's pose uncertainty, so it is nearly flat
//! across the image; but the densified depth is interpolated from the filtered semi-dense
//! pixels by the prior's gradients, and its error grows with the distance to them. An
//! interpolation's error behaves like a random walk away from its anchors: its variance grows
//! about linearly with the distance (docs/tuning.md, "Support variance").

use crate::image::ImageF32;

/// Chamfer distance (in pixels, steps 1 and √2) from every pixel to the nearest pixel with a
/// positive value in `support`; `f32::INFINITY` everywhere when `support` has none. Two passes
/// (forward and backward raster), within 8 % of the Euclidean distance.
pub fn distance_to_support(support: &ImageF32) -> Vec<f32> {
    let (w, h) = (support.width, support.height);
    let mut d: Vec<f32> = support
        .data
        .iter()
        .map(|&v| if v > 0.0 { 0.0 } else { f32::INFINITY })
        .collect();
    let diag = std::f32::consts::SQRT_2;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let mut best = d[i];
            if x > 0 {
                best = best.min(d[i - 1] + 1.0);
            }
            if y > 0 {
                best = best.min(d[i - w] + 1.0);
                if x > 0 {
                    best = best.min(d[i - w - 1] + diag);
                }
                if x + 1 < w {
                    best = best.min(d[i - w + 1] + diag);
                }
            }
            d[i] = best;
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let i = y * w + x;
            let mut best = d[i];
            if x + 1 < w {
                best = best.min(d[i + 1] + 1.0);
            }
            if y + 1 < h {
                best = best.min(d[i + w] + 1.0);
                if x + 1 < w {
                    best = best.min(d[i + w + 1] + diag);
                }
                if x > 0 {
                    best = best.min(d[i + w - 1] + diag);
                }
            }
            d[i] = best;
        }
    }
    d
}

/// Adds `growth · d · ρ²` to the inverse-depth variance of every densified pixel, `d` its
/// distance to the nearest filtered semi-dense pixel (`filtered > 0`) and ρ its inverse depth:
/// a relative variance `(σ_ρ/ρ)²` that grows by `growth` per pixel. Semi-dense pixels
/// (`d = 0`) keep theirs. Without any semi-dense pixel the distance is the image diagonal.
pub fn grow_with_distance(
    variance: &mut ImageF32,
    idepth: &ImageF32,
    filtered: &ImageF32,
    growth: f32,
) {
    if growth <= 0.0 {
        return;
    }
    let cap = (variance.width as f32).hypot(variance.height as f32);
    let dist = distance_to_support(filtered);
    for ((v, &rho), &d) in variance.data.iter_mut().zip(&idepth.data).zip(&dist) {
        if rho > 0.0 && d > 0.0 {
            *v += growth * d.min(cap) * rho * rho;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chamfer_distance_is_close_to_euclidean() {
        let mut support = ImageF32::filled(40, 30, 0.0);
        *support.at_mut(5, 7) = 1.0;
        *support.at_mut(33, 20) = 2.0;
        let d = distance_to_support(&support);
        for y in 0..30usize {
            for x in 0..40usize {
                let e = |px: f32, py: f32| (x as f32 - px).hypot(y as f32 - py);
                let exact = e(5.0, 7.0).min(e(33.0, 20.0));
                let got = d[y * 40 + x];
                assert!(got >= exact - 1e-4, "({x}, {y}): {got} < {exact}");
                assert!(got <= exact * 1.09 + 1e-4, "({x}, {y}): {got} vs {exact}");
            }
        }
        assert_eq!(d[7 * 40 + 5], 0.0);
        let none = distance_to_support(&ImageF32::filled(4, 3, 0.0));
        assert!(none.iter().all(|v| v.is_infinite()));
    }

    #[test]
    fn variance_grows_with_distance_only_off_support() {
        let (w, h) = (16, 8);
        let mut filtered = ImageF32::filled(w, h, 0.0);
        *filtered.at_mut(0, 0) = 0.5;
        let idepth = ImageF32::filled(w, h, 0.5);
        let mut variance = ImageF32::filled(w, h, 1e-4);
        grow_with_distance(&mut variance, &idepth, &filtered, 0.001);
        assert_eq!(variance.at(0, 0), 1e-4);
        // (4, 0): 4 px away, + 0.001 · 4 · 0.25.
        assert!((variance.at(4, 0) - (1e-4 + 1e-3)).abs() < 1e-7);
        assert!(variance.at(15, 7) > variance.at(8, 4));
        // Off: unchanged.
        let mut same = ImageF32::filled(w, h, 1e-4);
        grow_with_distance(&mut same, &idepth, &filtered, 0.0);
        assert!(same.data.iter().all(|&v| v == 1e-4));
        // No support at all: capped at the diagonal, finite.
        let mut capped = ImageF32::filled(w, h, 1e-4);
        grow_with_distance(&mut capped, &idepth, &ImageF32::filled(w, h, 0.0), 0.001);
        assert!(capped.data.iter().all(|v| v.is_finite() && *v > 1e-4));
    }
}
