//! Closed-form least-squares similarity alignment of two point sets.
//!
//! S. Umeyama, "Least-squares estimation of transformation parameters between two point
//! patterns", IEEE PAMI 13(4), 1991. Given pairs (xᵢ, yᵢ), finds s, R, t minimising
//! Σ‖yᵢ − (s·R·xᵢ + t)‖². Equation numbers below are the paper's; the code follows evo's
//! `geometry.umeyama_alignment` step by step so that alignments agree with evo's to rounding.

use nalgebra::{Matrix3, Vector3};

use crate::geometry::{SO3, Sim3};
use crate::{Error, Result};

/// The similarity `dst ≈ s·R·src + t` (as a [`Sim3`], whose `act` is exactly that map).
/// With `with_scale = false` the scale is fixed to 1 and the result is a rigid motion.
///
/// Fails when the lengths differ, there are no points, or the cross-covariance has rank < 2
/// (all points collinear, or fewer than three distinct points): then the rotation about the
/// line is undetermined.
pub fn umeyama(src: &[Vector3<f64>], dst: &[Vector3<f64>], with_scale: bool) -> Result<Sim3> {
    if src.len() != dst.len() {
        return Err(Error::Shape(format!(
            "umeyama: {} source points but {} destination points",
            src.len(),
            dst.len()
        )));
    }
    if src.is_empty() {
        return Err(Error::Eval("umeyama: no points to align".into()));
    }
    let n = src.len() as f64;
    // Means, eqs. (34) and (35).
    let mean_x = src.iter().sum::<Vector3<f64>>() / n;
    let mean_y = dst.iter().sum::<Vector3<f64>>() / n;
    // Variance of the source, eq. (36), and cross-covariance Σxy, eq. (38).
    let sigma_x = src.iter().map(|x| (x - mean_x).norm_squared()).sum::<f64>() / n;
    let cov = src
        .iter()
        .zip(dst)
        .map(|(x, y)| (y - mean_y) * (x - mean_x).transpose())
        .sum::<Matrix3<f64>>()
        / n;

    let svd = cov.svd(true, true);
    let (u, v_t) = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => (u, v_t),
        _ => return Err(Error::Eval("umeyama: SVD of the covariance failed".into())),
    };
    let d = svd.singular_values;
    if d.iter().filter(|&&x| x > f64::EPSILON).count() < 2 {
        return Err(Error::Eval(
            "umeyama: degenerate covariance (points collinear or coincident), alignment is \
             not possible"
                .into(),
        ));
    }
    // S, eq. (43): flip the axis of the smallest singular value when U·Vᵀ would be a reflection,
    // so that R is a proper rotation (det R = +1).
    let mut s = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s[d.imin()] = -1.0;
    }
    // Rotation, eq. (40).
    let r = u * Matrix3::from_diagonal(&s) * v_t;
    // Scale and translation, eqs. (42) and (41).
    let scale = if with_scale {
        if sigma_x <= 0.0 {
            return Err(Error::Eval(
                "umeyama: source points have zero variance".into(),
            ));
        }
        d.component_mul(&s).sum() / sigma_x
    } else {
        1.0
    };
    let translation = mean_y - scale * (r * mean_x);
    Ok(Sim3 {
        rotation: SO3::from_matrix(&r),
        translation,
        scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_points(rng: &mut ChaCha8Rng, n: usize) -> Vec<Vector3<f64>> {
        (0..n)
            .map(|_| {
                Vector3::new(
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(0.0..3.0),
                )
            })
            .collect()
    }

    #[test]
    fn eval_umeyama_recovers_an_exact_similarity() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for trial in 0..20 {
            let truth = Sim3 {
                rotation: SO3::exp(&Vector3::new(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                )),
                translation: Vector3::new(rng.random_range(-5.0..5.0), 1.0, -2.0),
                scale: rng.random_range(0.05..20.0),
            };
            let src = random_points(&mut rng, 3 + trial);
            let dst: Vec<_> = src.iter().map(|p| truth.act(p)).collect();
            let est = umeyama(&src, &dst, true).expect("alignment");
            assert!(
                (est.scale - truth.scale).abs() < 1e-9 * truth.scale,
                "{est:?} vs {truth:?}"
            );
            assert!((est.rotation.inverse() * truth.rotation).log().norm() < 1e-9);
            assert!((est.translation - truth.translation).norm() < 1e-8);
            // Without scale the rotation is still the least-squares one (same for exact data).
            let rigid = umeyama(&src, &dst, false).expect("rigid alignment");
            assert_eq!(rigid.scale, 1.0);
            assert!((rigid.rotation.inverse() * truth.rotation).log().norm() < 1e-9);
        }
    }

    #[test]
    fn eval_umeyama_never_returns_a_reflection() {
        // dst is a mirror image of src: the best *rotation* is not U·Vᵀ (det −1).
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let src = random_points(&mut rng, 30);
        let dst: Vec<_> = src.iter().map(|p| Vector3::new(-p.x, p.y, p.z)).collect();
        let est = umeyama(&src, &dst, true).expect("alignment");
        let r = est.rotation.matrix();
        assert!(
            (r.determinant() - 1.0).abs() < 1e-12,
            "det {}",
            r.determinant()
        );
        assert!(
            est.scale > 0.0 && est.scale < 1.0,
            "a mirror fits worse than 1: {}",
            est.scale
        );
        // The reflection fix must give a residual no larger than any other tried rotation.
        let cost = |t: &Sim3| {
            src.iter()
                .zip(&dst)
                .map(|(x, y)| (y - t.act(x)).norm_squared())
                .sum::<f64>()
        };
        let best = cost(&est);
        for k in 0..50 {
            let other = Sim3 {
                rotation: est.rotation
                    * SO3::exp(&(Vector3::new(0.3, -0.2, 0.5) * (f64::from(k) / 25.0 - 1.0))),
                ..est
            };
            assert!(cost(&other) >= best - 1e-9);
        }
    }

    #[test]
    fn eval_umeyama_rejects_degenerate_input() {
        let line: Vec<_> = (0..10)
            .map(|i| Vector3::new(f64::from(i), 2.0 * f64::from(i), 0.0))
            .collect();
        assert!(umeyama(&line, &line, true).is_err());
        assert!(umeyama(&[], &[], true).is_err());
        assert!(umeyama(&line[..3], &line[..2], false).is_err());
    }
}
