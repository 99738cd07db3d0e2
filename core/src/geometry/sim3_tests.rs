//! Property tests of [`Sim3`] (kept apart so that sim3.rs stays readable).

use super::*;
use crate::geometry::testing::*;
use proptest::prelude::*;

fn close<const R: usize, const C: usize>(
    a: &SMatrix<f64, R, C>,
    b: &SMatrix<f64, R, C>,
    tol: f64,
) -> bool {
    (a - b).abs().max() <= tol * (1.0 + b.abs().max())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn w_matrix_matches_integral(phi in arb_rotation_vector(), sigma in arb_sigma()) {
        // W = ∫₀¹ e^{uσ} exp(u·φ^) du, by quadrature: independent of the series/closed forms.
        let reference = integrate_unit_interval(
            |u| (u * sigma).exp() * SO3::exp(&(u * phi)).matrix(),
            sigma.abs() + phi.norm(),
        );
        prop_assert!(close(&sim3_w_matrix(&phi, sigma), &reference, 1e-13));
    }

    #[test]
    fn from_matrix_and_se3_round_trips(a in arb_sim3(), p in arb_point()) {
        prop_assert!(close(&Sim3::from_matrix(&a.matrix()).matrix(), &a.matrix(), 1e-13));
        let (rigid, s) = a.to_se3_and_scale();
        prop_assert!((rigid.act(&(s * p)) - a.act(&p)).norm() <= 1e-12 * (1.0 + a.act(&p).norm()));
        prop_assert_eq!(Sim3::from_se3(&rigid, s), a);
        // An SE(3) with scale 1 acts identically as a Sim(3).
        let one = Sim3::from_se3(&rigid, 1.0);
        prop_assert!((one.act(&p) - rigid.act(&p)).norm() <= 1e-12 * (1.0 + p.norm()));
    }

    #[test]
    fn point_jacobian_matches_numeric(a in arb_sim3(), p in arb_point()) {
        let g = |q: &Vector3<f64>| a.act(&(p + q));
        prop_assert!(close(&a.act_jacobian_wrt_point(), &numeric_jacobian::<3, 3>(&g), 1e-6));
    }
}

#[test]
fn right_jacobian_near_zero() {
    let xi = join(
        &Vector3::new(0.3, -0.2, 0.1),
        &Vector3::new(1.0, 2.0, -1.0),
        1.0,
    ) * 1e-6;
    let expected = Matrix7::identity() - 0.5 * Sim3::ad(&xi);
    assert!(close(&Sim3::right_jacobian(&xi), &expected, 1e-12));
    assert!(close(
        &Sim3::right_jacobian(&Vector7::zeros()),
        &Matrix7::identity(),
        1e-15
    ));
}

proptest! {
    #[test]
    fn right_jacobian_matches_series(xi in arb_sim3_tangent()) {
        // J_r(ξ) = Σ (−ad ξ)ⁿ/(n+1)!, summed to 80 terms.
        let ad = -Sim3::ad(&xi);
        let (mut sum, mut term) = (Matrix7::identity(), Matrix7::identity());
        for n in 1..80 {
            term = term * ad / (n + 1) as f64;
            sum += term;
        }
        prop_assert!(close(&Sim3::right_jacobian(&xi), &sum, 1e-10));
    }
}

#[test]
fn moments_match_quadrature() {
    for sigma in [
        -9.0, -4.0, -3.999, -1.0, -1e-9, 0.0, 1e-12, 0.7, 3.999, 4.0, 6.5,
    ] {
        let m = exp_moments(sigma);
        for (n, mn) in m.iter().enumerate() {
            let q = integrate_unit_interval(
                |u| SMatrix::<f64, 1, 1>::new(u.powi(n as i32) * (u * sigma).exp()),
                sigma,
            )[(0, 0)];
            assert!(
                (mn - q).abs() <= 1e-13 * q.abs(),
                "σ = {sigma}, n = {n}: {mn} vs {q}"
            );
        }
    }
}

#[test]
fn w_coefficients_continuous_across_branches() {
    let agree = |x: (f64, f64, f64), y: (f64, f64, f64), what: &str| {
        for (u, v) in [(x.0, y.0), (x.1, y.1), (x.2, y.2)] {
            assert!(
                (u - v).abs() <= 1e-11 * (1.0 + v.abs()),
                "{what}: {x:?} vs {y:?}"
            );
        }
    };
    let below = SMALL_ANGLE * (1.0 - 1e-12);
    let above = SMALL_ANGLE * (1.0 + 1e-12);
    for sigma in [0.0, 1e-12, -1e-7, 0.5, -0.5, 3.9, -4.2, 6.0, -6.0] {
        agree(
            w_coefficients(sigma, below),
            w_coefficients(sigma, above),
            "θ threshold",
        );
    }
    for theta in [0.0, 1e-9, 0.05, 0.5, 2.0, 3.1] {
        for edge in [SIGMA_SERIES, -SIGMA_SERIES] {
            agree(
                w_coefficients(edge * (1.0 - 1e-12), theta),
                w_coefficients(edge * (1.0 + 1e-12), theta),
                "σ threshold",
            );
        }
        // σ → 0 from both sides is continuous with σ = 0 (the SE(3) V matrix).
        agree(
            w_coefficients(1e-13, theta),
            w_coefficients(0.0, theta),
            "σ → 0⁺",
        );
        agree(
            w_coefficients(-1e-13, theta),
            w_coefficients(0.0, theta),
            "σ → 0⁻",
        );
    }
    // σ = 0 reduces to the SO(3) left Jacobian; θ = σ = 0 to the identity.
    let phi = Vector3::new(0.2, -0.4, 1.1);
    assert!(close(
        &sim3_w_matrix(&phi, 0.0),
        &SO3::left_jacobian(&phi),
        1e-14
    ));
    assert!(close(
        &sim3_w_matrix(&Vector3::zeros(), 0.0),
        &Matrix3::identity(),
        1e-16
    ));
    // θ = 0 with σ ≠ 0 reduces to (e^σ − 1)/σ·I.
    let s = 0.8_f64;
    let expected = Matrix3::identity() * (s.exp() - 1.0) / s;
    assert!(close(
        &sim3_w_matrix(&Vector3::zeros(), s),
        &expected,
        1e-15
    ));
}

#[test]
fn log_exp_with_scale_and_rotation_together() {
    // Both small (the doubly-degenerate corner) and both large.
    for (theta, sigma) in [
        (1e-9, 1e-9),
        (1e-5, -1e-7),
        (0.0, 1e-12),
        (3.0, 2.5),
        (std::f64::consts::PI - 1e-5, -3.0),
    ] {
        let phi = Vector3::new(0.48, 0.6, -0.64) * theta;
        let xi = join(&Vector3::new(1.0, -2.0, 0.5), &phi, sigma);
        let back = Sim3::exp(&xi).log();
        assert!(
            (back - xi).norm() < 1e-12 * (1.0 + xi.norm()),
            "θ={theta}, σ={sigma}: {back}"
        );
    }
}
