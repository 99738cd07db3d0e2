//! Tests of `filter`.

use super::*;
use crate::dense::gpu_filter::GpuAdaptiveFilter;
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
    let raw_mean_v =
        s.v.data.iter().map(|&x| f64::from(x)).sum::<f64>() / (raw.inliers + raw.outliers) as f64;
    for (prior, device, on_gpu) in [
        (Some(&s.prior), &CpuFilter as &dyn FilterStep, false),
        (None, &CpuFilter, false),
        (Some(&s.prior), &gpu, true),
    ] {
        let what = format!("prior {} gpu {on_gpu}", prior.is_some());
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
    let (fd, fv) = filter_semidense(&inputs, &literal, &CpuFilter).expect("filter runs");
    let f = score(&s, &fd);
    let default = score(
        &s,
        &filter_semidense(&inputs, &FilterParams::default(), &CpuFilter)
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
        &filter_semidense(&inputs, &literal, &gpu).expect("gpu").0,
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
        filter_semidense(&inputs(&intensity, &d, &v, None), &params, &CpuFilter).expect("runs");
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
    let agree = adaptive_filter_cpu(&inputs(&flat, &d, &v, Some(&p_bump)), &params).expect("runs");
    let none = adaptive_filter_cpu(&inputs(&flat, &d, &v, None), &params).expect("runs");
    assert_eq!(centre(&agree), centre(&none));
    assert!(
        (centre(&disagree) - 1.0) < 0.2 * (centre(&agree) - 1.0),
        "{} vs {}",
        centre(&disagree),
        centre(&agree)
    );
}
