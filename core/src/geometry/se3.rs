//! SE(3): rigid-body motions `p ↦ R·p + t`.
//!
//! Tangent ξ = (ρ, φ) ∈ ℝ⁶, translation part first; perturbations on the right, `T·exp(δ)`.
//! exp/log use the V matrix (= SO(3) left Jacobian); the 6×6 Jacobians follow Barfoot,
//! *State Estimation for Robotics* §7.1.5 (eqs. 7.85–7.86, reordered for the right Jacobian
//! via J_r(ξ) = J_l(−ξ)).

use super::so3::{SERIES_ANGLE, SO3, alternating_series, coef_b, coef_c, factorial};
use nalgebra::{Matrix3, Matrix3x6, Matrix4, Matrix6, UnitQuaternion, Vector3, Vector6};
use serde::{Deserialize, Serialize};
use std::ops::Mul;

/// A rigid-body transform. Name values by their frames: `world_from_camera` maps camera
/// coordinates to world coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SE3 {
    pub rotation: SO3,
    pub translation: Vector3<f64>,
}

impl Default for SE3 {
    fn default() -> Self {
        Self::identity()
    }
}

/// (θ² + 2cos θ − 2)/(2θ⁴) = (½ − B(θ))/θ² = Σ_m (−θ²)^m/(2m+4)!, second coefficient of
/// Barfoot's Q (eq. 7.86).
fn coef_q2(theta: f64) -> f64 {
    if theta < SERIES_ANGLE {
        alternating_series(theta, |m| 1.0 / factorial(2 * m + 4))
    } else {
        (0.5 - coef_b(theta)) / (theta * theta)
    }
}

/// (2θ − 3 sin θ + θ cos θ)/(2θ⁵) = Σ_m (−θ²)^m·(m+1)/(2m+5)!, third coefficient of Barfoot's
/// Q (eq. 7.86).
fn coef_q3(theta: f64) -> f64 {
    if theta < SERIES_ANGLE {
        alternating_series(theta, |m| f64::from(m + 1) / factorial(2 * m + 5))
    } else {
        (2.0 * theta - 3.0 * theta.sin() + theta * theta.cos()) / (2.0 * theta.powi(5))
    }
}

/// Barfoot's Q(ρ, φ), the off-diagonal block of the SE(3) left Jacobian (eq. 7.86).
fn q_left(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let p = SO3::hat(phi);
    let r = SO3::hat(rho);
    let prp = p * r * p;
    0.5 * r
        + coef_c(theta) * (p * r + r * p + prp)
        + coef_q2(theta) * (p * p * r + r * p * p - 3.0 * prp)
        + coef_q3(theta) * (prp * p + p * prp)
}

/// Splits a 6-vector into (ρ, φ).
fn split(xi: &Vector6<f64>) -> (Vector3<f64>, Vector3<f64>) {
    (
        xi.fixed_rows::<3>(0).into_owned(),
        xi.fixed_rows::<3>(3).into_owned(),
    )
}

impl SE3 {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: SO3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// `p ↦ rotation·p + translation`.
    pub fn new(rotation: SO3, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// From a unit quaternion and a translation (the TUM trajectory file layout).
    pub fn from_quaternion_translation(q: UnitQuaternion<f64>, t: Vector3<f64>) -> Self {
        Self::new(SO3::from_quaternion(q), t)
    }

    /// From a homogeneous 4×4 matrix; the rotation block is re-orthonormalised
    /// ([`SO3::from_matrix`]) and the bottom row ignored.
    pub fn from_matrix(m: &Matrix4<f64>) -> Self {
        let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
        Self::new(
            SO3::from_matrix(&r),
            m.fixed_view::<3, 1>(0, 3).into_owned(),
        )
    }

    /// The homogeneous 4×4 matrix.
    pub fn matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&self.rotation.matrix());
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.translation);
        m
    }

    /// Exponential map: (ρ, φ) → (exp(φ), V(φ)·ρ).
    pub fn exp(xi: &Vector6<f64>) -> Self {
        let (rho, phi) = split(xi);
        Self::new(SO3::exp(&phi), SO3::left_jacobian(&phi) * rho)
    }

    /// Logarithm: (R, t) → (V⁻¹(φ)·t, φ) with φ = log R, |φ| ≤ π.
    pub fn log(&self) -> Vector6<f64> {
        let phi = self.rotation.log();
        let rho = SO3::left_jacobian_inverse(&phi) * self.translation;
        let mut xi = Vector6::zeros();
        xi.fixed_rows_mut::<3>(0).copy_from(&rho);
        xi.fixed_rows_mut::<3>(3).copy_from(&phi);
        xi
    }

    /// The inverse transform (Rᵀ, −Rᵀt).
    pub fn inverse(&self) -> Self {
        let r = self.rotation.inverse();
        Self::new(r, -r.act(&self.translation))
    }

    /// Transforms a point: R·p + t.
    pub fn act(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation.act(p) + self.translation
    }

    /// Adjoint in (ρ, φ) order, `T·exp(ξ)·T⁻¹ = exp(Ad_T·ξ)`: `[[R, t^R], [0, R]]`.
    pub fn adjoint(&self) -> Matrix6<f64> {
        let r = self.rotation.matrix();
        let mut a = Matrix6::zeros();
        a.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        a.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(SO3::hat(&self.translation) * r));
        a.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
        a
    }

    /// ξ^ = [[φ^, ρ], [0, 0]].
    pub fn hat(xi: &Vector6<f64>) -> Matrix4<f64> {
        let (rho, phi) = split(xi);
        let mut m = Matrix4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&SO3::hat(&phi));
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&rho);
        m
    }

    /// Inverse of [`SE3::hat`].
    pub fn vee(m: &Matrix4<f64>) -> Vector6<f64> {
        let phi = SO3::vee(&m.fixed_view::<3, 3>(0, 0).into_owned());
        let mut xi = Vector6::zeros();
        xi.fixed_rows_mut::<3>(0)
            .copy_from(&m.fixed_view::<3, 1>(0, 3));
        xi.fixed_rows_mut::<3>(3).copy_from(&phi);
        xi
    }

    /// Lie bracket matrix ad(ξ) = `[[φ^, ρ^], [0, φ^]]`, with `[ξ₁^, ξ₂^]^∨ = ad(ξ₁)·ξ₂`.
    pub fn ad(xi: &Vector6<f64>) -> Matrix6<f64> {
        let (rho, phi) = split(xi);
        let p = SO3::hat(&phi);
        let mut a = Matrix6::zeros();
        a.fixed_view_mut::<3, 3>(0, 0).copy_from(&p);
        a.fixed_view_mut::<3, 3>(0, 3).copy_from(&SO3::hat(&rho));
        a.fixed_view_mut::<3, 3>(3, 3).copy_from(&p);
        a
    }

    /// Right Jacobian: `exp(ξ + δ) ≈ exp(ξ)·exp(J_r(ξ)·δ)`;
    /// `J_r(ξ) = [[J_r(φ), Q(−ρ, −φ)], [0, J_r(φ)]]`.
    pub fn right_jacobian(xi: &Vector6<f64>) -> Matrix6<f64> {
        let (rho, phi) = split(xi);
        let j = SO3::right_jacobian(&phi);
        let mut m = Matrix6::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&j);
        m.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&q_left(&-rho, &-phi));
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(&j);
        m
    }

    /// Inverse right Jacobian, `log(exp(ξ)·exp(δ)) ≈ ξ + J_r⁻¹(ξ)·δ`:
    /// `[[J⁻¹, −J⁻¹·Q·J⁻¹], [0, J⁻¹]]` (finite for θ < 2π).
    pub fn right_jacobian_inverse(xi: &Vector6<f64>) -> Matrix6<f64> {
        let (rho, phi) = split(xi);
        let ji = SO3::right_jacobian_inverse(&phi);
        let q = q_left(&-rho, &-phi);
        let mut m = Matrix6::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&ji);
        m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-ji * q * ji));
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(&ji);
        m
    }

    /// `d(T·exp(δ)·p)/dδ` at δ = 0: `[R, −R·p^]` (the photometric-tracking Jacobian's
    /// geometric part).
    pub fn act_jacobian(&self, p: &Vector3<f64>) -> Matrix3x6<f64> {
        let r = self.rotation.matrix();
        let mut j = Matrix3x6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        j.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(-r * SO3::hat(p)));
        j
    }

    /// `d(T·p)/dp` = R.
    pub fn act_jacobian_wrt_point(&self) -> Matrix3<f64> {
        self.rotation.matrix()
    }
}

impl Mul for SE3 {
    type Output = SE3;
    fn mul(self, rhs: SE3) -> SE3 {
        SE3::new(self.rotation * rhs.rotation, self.act(&rhs.translation))
    }
}

impl Mul<&SE3> for &SE3 {
    type Output = SE3;
    fn mul(self, rhs: &SE3) -> SE3 {
        *self * *rhs
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::sim3::integrate_unit_interval;
    use crate::geometry::testing::*;
    use proptest::prelude::*;

    fn close<const R: usize, const C: usize>(
        a: &nalgebra::SMatrix<f64, R, C>,
        b: &nalgebra::SMatrix<f64, R, C>,
        tol: f64,
    ) -> bool {
        (a - b).abs().max() <= tol * (1.0 + b.abs().max())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        #[test]
        fn from_matrix_recovers(a in arb_se3()) {
            prop_assert!(close(&SE3::from_matrix(&a.matrix()).matrix(), &a.matrix(), 1e-13));
        }

        #[test]
        fn right_jacobian_matches_integral(xi in arb_se3_tangent()) {
            // J_r(ξ) = ∫₀¹ Ad(exp(−uξ)) du, independently of Barfoot's closed form.
            let reference = integrate_unit_interval(|u| SE3::exp(&(-u * xi)).adjoint(), xi.norm());
            prop_assert!(close(&SE3::right_jacobian(&xi), &reference, 1e-11));
        }

        #[test]
        fn point_jacobian_matches_numeric(a in arb_se3(), p in arb_point()) {
            let g = |q: &Vector3<f64>| a.act(&(p + q));
            prop_assert!(close(&a.act_jacobian_wrt_point(), &numeric_jacobian::<3, 3>(&g), 1e-6));
        }
    }

    #[test]
    fn small_angle_branches_continuous() {
        for f in [coef_q2 as fn(f64) -> f64, coef_q3] {
            let (lo, hi) = (
                f(SERIES_ANGLE * (1.0 - 1e-12)),
                f(SERIES_ANGLE * (1.0 + 1e-12)),
            );
            assert!((lo - hi).abs() < 1e-12 * lo.abs(), "{lo} vs {hi}");
        }
        // The series reproduce the closed forms where both are accurate.
        for theta in [0.3, 0.6, 0.95] {
            let q2 = (theta * theta + 2.0 * f64::cos(theta) - 2.0) / (2.0 * theta.powi(4));
            let q3 =
                (2.0 * theta - 3.0 * theta.sin() + theta * theta.cos()) / (2.0 * theta.powi(5));
            assert!((coef_q2(theta) - q2).abs() < 1e-11 * q2);
            assert!((coef_q3(theta) - q3).abs() < 1e-9 * q3);
        }
        let axis = Vector3::new(0.6, -0.3, 0.74).normalize();
        let rho = Vector3::new(1.5, -2.0, 0.7);
        let at = |theta: f64| {
            let mut xi = Vector6::zeros();
            xi.fixed_rows_mut::<3>(0).copy_from(&rho);
            xi.fixed_rows_mut::<3>(3).copy_from(&(axis * theta));
            xi
        };
        for threshold in [SERIES_ANGLE, crate::geometry::SMALL_ANGLE] {
            let (lo, hi) = (at(threshold * (1.0 - 1e-10)), at(threshold * (1.0 + 1e-10)));
            let (jl, jh) = (SE3::right_jacobian(&lo), SE3::right_jacobian(&hi));
            assert!(close(&jl, &jh, 1e-9));
            assert!(close(
                &SE3::right_jacobian_inverse(&lo),
                &SE3::right_jacobian_inverse(&hi),
                1e-9
            ));
            assert!(close(
                &SE3::exp(&lo).matrix(),
                &SE3::exp(&hi).matrix(),
                1e-9
            ));
            assert!((SE3::exp(&lo).log() - lo).norm() < 1e-12);
            assert!((SE3::exp(&hi).log() - hi).norm() < 1e-12);
        }
    }

    #[test]
    fn log_near_pi_keeps_translation() {
        let phi = Vector3::new(0.0, 1.0, 0.0) * (std::f64::consts::PI - 1e-7);
        let mut xi = Vector6::zeros();
        xi.fixed_rows_mut::<3>(0)
            .copy_from(&Vector3::new(0.3, 0.2, -1.0));
        xi.fixed_rows_mut::<3>(3).copy_from(&phi);
        assert!((SE3::exp(&xi).log() - xi).norm() < 1e-9);
    }
}
