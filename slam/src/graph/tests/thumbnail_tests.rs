//! The appearance descriptor's 8-bit codes: scores agree with the correlation of the cells
//! they code, stored cells come back as the same codes.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::graph::search::{THUMBNAIL_MAX_SHIFT, THUMBNAIL_SIZE, Thumbnail};

/// The best normalised cross-correlation over shifts of the float cells (the reference).
fn reference_score(a: &[f32], b: &[f32]) -> f64 {
    let (tw, th) = (THUMBNAIL_SIZE.0 as isize, THUMBNAIL_SIZE.1 as isize);
    let m = THUMBNAIL_MAX_SHIFT as isize;
    let mut best = f64::NEG_INFINITY;
    for dy in -m..=m {
        for dx in -m..=m {
            let (mut n, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
            for y in dy.max(0)..(th + dy).min(th) {
                for x in dx.max(0)..(tw + dx).min(tw) {
                    let p = f64::from(a[(y * tw + x) as usize]);
                    let q = f64::from(b[((y - dy) * tw + x - dx) as usize]);
                    n += 1.0;
                    sa += p;
                    sb += q;
                    saa += p * p;
                    sbb += q * q;
                    sab += p * q;
                }
            }
            let var = (n * saa - sa * sa) * (n * sbb - sb * sb);
            let r = if var <= 1e-12 {
                0.0
            } else {
                (n * sab - sa * sb) / var.sqrt()
            };
            best = best.max(r);
        }
    }
    best
}

/// A smooth random field of intensities over a scene `2 * THUMBNAIL_SIZE` wide, seen through
/// a window at (ox, oy) cells, with per-view gain, offset and noise.
fn view(scene: &[(f32, f32, f32, f32)], ox: f32, oy: f32, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let (tw, th) = THUMBNAIL_SIZE;
    let (gain, offset) = (
        rng.random_range(0.5..2.0f32),
        rng.random_range(-50.0..50.0f32),
    );
    (0..tw * th)
        .map(|i| {
            let (x, y) = ((i % tw) as f32 + ox, (i / tw) as f32 + oy);
            let v: f32 = scene
                .iter()
                .map(|&(a, fx, fy, p)| a * (fx * x + fy * y + p).sin())
                .sum();
            gain * (100.0 + v) + offset + rng.random_range(-2.0..2.0f32)
        })
        .collect()
}

#[test]
fn coded_scores_match_the_float_correlation() {
    let mut rng = ChaCha8Rng::seed_from_u64(39);
    let mut worst = 0.0f64;
    for _ in 0..60 {
        let scene: Vec<(f32, f32, f32, f32)> = (0..6)
            .map(|_| {
                (
                    rng.random_range(5.0..40.0),
                    rng.random_range(-0.6..0.6),
                    rng.random_range(-0.6..0.6),
                    rng.random_range(0.0..6.3),
                )
            })
            .collect();
        let a = view(&scene, 0.0, 0.0, &mut rng);
        // The same place shifted by up to ±6 cells (beyond the search too), or another place.
        let (ox, oy) = (
            rng.random_range(-6.0..6.0f32).round(),
            rng.random_range(-6.0..6.0f32).round(),
        );
        let b = if rng.random_bool(0.7) {
            view(&scene, ox, oy, &mut rng)
        } else {
            view(&scene, 40.0 + ox, 30.0 + oy, &mut rng)
        };
        let (ta, tb) = (
            Thumbnail::from_values(a.clone()).unwrap(),
            Thumbnail::from_values(b.clone()).unwrap(),
        );
        let (coded, float) = (ta.score(&tb), reference_score(&a, &b));
        assert!((-1.0..=1.0 + 1e-12).contains(&coded), "score {coded}");
        assert_eq!(coded, tb.score(&ta), "symmetric");
        worst = worst.max((coded - float).abs());
    }
    // Rounding to 1/255 of the range moves a correlation by far less than the search's 0.8
    // threshold's margins.
    eprintln!("largest difference from the float correlation: {worst:.2e}");
    assert!(
        worst < 2e-3,
        "largest difference from the float correlation {worst}"
    );
}

#[test]
fn stored_cells_come_back_as_the_same_codes() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let scene = [(20.0, 0.3, 0.1, 1.0), (10.0, -0.2, 0.4, 2.0)];
    let t = Thumbnail::from_values(view(&scene, 0.0, 0.0, &mut rng)).unwrap();
    let again = Thumbnail::from_values(t.values()).unwrap();
    assert_eq!(again, t);
    assert_eq!(again.values(), t.values());
    assert!((t.score(&again) - 1.0).abs() < 1e-12);
}

#[test]
fn a_uniform_descriptor_scores_zero_and_bad_cells_are_refused() {
    let (tw, th) = THUMBNAIL_SIZE;
    let flat = Thumbnail::from_values(vec![7.0; tw * th]).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let other = Thumbnail::from_values(view(&[(20.0, 0.3, 0.1, 1.0)], 0.0, 0.0, &mut rng)).unwrap();
    assert_eq!(flat.score(&other), 0.0);
    assert_eq!(flat.values(), vec![7.0; tw * th]);
    assert!(Thumbnail::from_values(vec![0.0; tw * th - 1]).is_none());
    let mut nan = vec![0.0; tw * th];
    nan[5] = f32::NAN;
    assert!(Thumbnail::from_values(nan).is_none());
}
