//! SO(3): 3-D rotations stored as unit quaternions.
//!
//! Tangent vectors φ ∈ ℝ³ are rotation vectors (axis · angle); perturbations are on the right,
//! `R · exp(δ)`. Formulas: Barfoot, *State Estimation for Robotics* (2017) §7.1 (Rodrigues,
//! eq. 7.14; left/right Jacobians, eqs. 7.77a/7.83), and Solà et al., *A micro Lie theory for
//! state estimation in robotics* (2018), appendix B.
//!
//! Every coefficient with a removable singularity at θ = 0 switches to its Taylor series below a
//! threshold — [`SMALL_ANGLE`] for the mildly cancelling ones, `SERIES_ANGLE` (= 1) for those
//! whose closed forms lose ~ε/θ² or worse — chosen so that both branches agree to ~1e-13 at the
//! switch, which the continuity tests check.

use nalgebra::{Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::ops::Mul;

/// Below this rotation angle (radians) the inverse-Jacobian coefficient D(θ) and the Sim(3) W
/// coefficients use fixed-length Taylor series. At 0.1 the closed forms lose at most ~1e-12 to
/// cancellation and the series are truncated at ~1e-16.
pub const SMALL_ANGLE: f64 = 0.1;

/// A rotation of ℝ³, stored as a unit quaternion with non-negative real part (so that two
/// equal rotations compare equal with `==`, except exactly at θ = π).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SO3 {
    q: UnitQuaternion<f64>,
}

impl Default for SO3 {
    fn default() -> Self {
        Self::identity()
    }
}

/// sin θ / θ, accurate for every θ (the closed form has no cancellation; only θ = 0 needs care).
pub(crate) fn sinc(theta: f64) -> f64 {
    if theta.abs() < 1e-4 {
        let t2 = theta * theta;
        1.0 - t2 / 6.0 + t2 * t2 / 120.0
    } else {
        theta.sin() / theta
    }
}

/// B(θ) = (1 − cos θ)/θ², computed as ½·sinc²(θ/2), which has no cancellation.
pub(crate) fn coef_b(theta: f64) -> f64 {
    let s = sinc(0.5 * theta);
    0.5 * s * s
}

/// Below this angle the coefficients whose closed forms cancel badly (C, and SE(3)'s Q
/// coefficients whose relative cancellation error grows like ε/θ⁴) are summed as their full
/// Taylor series until the terms vanish; at θ = 1 the closed forms are exact to ~1e-14 and the
/// series converge in ≤ 10 terms.
pub(crate) const SERIES_ANGLE: f64 = 1.0;

/// Σ_{m≥0} c(m)·(−θ²)^m, summed until a term is below 1e-18 of the sum (at most 24 terms; for
/// θ < [`SERIES_ANGLE`] the terms fall factorially).
pub(crate) fn alternating_series(theta: f64, c: impl Fn(u32) -> f64) -> f64 {
    let x = -theta * theta;
    let (mut sum, mut pow) = (0.0, 1.0);
    for m in 0..24 {
        let term = c(m) * pow;
        sum += term;
        if term.abs() <= 1e-18 * sum.abs() {
            break;
        }
        pow *= x;
    }
    sum
}

/// n! as f64 (exact up to 22!).
pub(crate) fn factorial(n: u32) -> f64 {
    (2..=n).map(f64::from).product()
}

/// C(θ) = (θ − sin θ)/θ³ = Σ_m (−θ²)^m/(2m+3)!.
pub(crate) fn coef_c(theta: f64) -> f64 {
    if theta < SERIES_ANGLE {
        alternating_series(theta, |m| 1.0 / factorial(2 * m + 3))
    } else {
        (theta - theta.sin()) / (theta * theta * theta)
    }
}

/// D(θ) = 1/θ² − (1 + cos θ)/(2θ sin θ) = (1 − (θ/2)·cot(θ/2))/θ², the Φ² coefficient of the
/// inverse Jacobians (Barfoot eq. 7.83). Written with cot(θ/2) it stays finite at θ = π.
pub(crate) fn coef_d(theta: f64) -> f64 {
    if theta < SMALL_ANGLE {
        let t2 = theta * theta;
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30_240.0 + t2 * t2 * t2 / 1_209_600.0
    } else {
        let half = 0.5 * theta;
        (1.0 - half * half.cos() / half.sin()) / (theta * theta)
    }
}

impl SO3 {
    /// The identity rotation.
    pub fn identity() -> Self {
        Self {
            q: UnitQuaternion::identity(),
        }
    }

    /// Wraps a unit quaternion (its sign is normalised so that the real part is ≥ 0).
    pub fn from_quaternion(q: UnitQuaternion<f64>) -> Self {
        if q.w < 0.0 {
            Self {
                q: UnitQuaternion::new_unchecked(-q.into_inner()),
            }
        } else {
            Self { q }
        }
    }

    /// The unit quaternion (real part ≥ 0).
    pub fn quaternion(&self) -> UnitQuaternion<f64> {
        self.q
    }

    /// The closest rotation to `m` in the Frobenius norm (SVD projection `U·diag(1,1,±1)·Vᵀ`), so
    /// slightly non-orthonormal matrices read from files or accumulated in float are repaired.
    /// Non-finite input gives the identity.
    pub fn from_matrix(m: &Matrix3<f64>) -> Self {
        if !m.iter().all(|v| v.is_finite()) {
            return Self::identity();
        }
        let svd = m.try_svd(true, true, f64::EPSILON, 200);
        let r = match svd.and_then(|s| Some((s.u?, s.v_t?))) {
            Some((u, v_t)) => {
                let d = (u * v_t).determinant().signum();
                u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t
            }
            // nalgebra's SVD did not converge: fall back to its iterative polar decomposition.
            None => *Rotation3::from_matrix(m).matrix(),
        };
        Self::from_quaternion(UnitQuaternion::from_rotation_matrix(
            &Rotation3::from_matrix_unchecked(r),
        ))
    }

    /// The 3×3 rotation matrix.
    #[inline]
    pub fn matrix(&self) -> Matrix3<f64> {
        *self.q.to_rotation_matrix().matrix()
    }

    /// Exponential map: rotation vector φ = θ·axis → rotation (quaternion form of Rodrigues'
    /// formula, exact for every θ including θ ≥ π).
    pub fn exp(phi: &Vector3<f64>) -> Self {
        let theta = phi.norm();
        let half = 0.5 * theta;
        // sin(θ/2)/θ = ½·sinc(θ/2)
        let k = 0.5 * sinc(half);
        let q = Quaternion::new(half.cos(), k * phi.x, k * phi.y, k * phi.z);
        Self::from_quaternion(UnitQuaternion::new_normalize(q))
    }

    /// Logarithm: rotation → rotation vector with angle in [0, π].
    ///
    /// Uses θ = 2·atan2(|v|, w) on the quaternion (w, v) with w ≥ 0, which is well conditioned
    /// both near θ = 0 (no division by a vanishing sin) and near θ = π (unlike acos of the
    /// matrix trace).
    pub fn log(&self) -> Vector3<f64> {
        let q = self.q.quaternion();
        let v: Vector3<f64> = q.vector().into_owned();
        let (w, v) = if q.w < 0.0 { (-q.w, -v) } else { (q.w, v) };
        let n = v.norm();
        let scale = if n < 1e-8 {
            // 2·atan(n/w)/n = (2/w)(1 − n²/(3w²) + …); w ≈ 1 here.
            2.0 / w * (1.0 - n * n / (3.0 * w * w))
        } else {
            2.0 * n.atan2(w) / n
        };
        v * scale
    }

    /// The rotation angle θ ∈ [0, π].
    pub fn angle(&self) -> f64 {
        self.log().norm()
    }

    /// The inverse rotation Rᵀ.
    pub fn inverse(&self) -> Self {
        Self::from_quaternion(self.q.inverse())
    }

    /// Rotates a point.
    #[inline]
    pub fn act(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.q.transform_vector(p)
    }

    /// Adjoint: `R·exp(φ)·Rᵀ = exp(Ad_R·φ)` with `Ad_R = R`.
    pub fn adjoint(&self) -> Matrix3<f64> {
        self.matrix()
    }

    /// Skew-symmetric matrix φ^ with φ^·p = φ × p.
    pub fn hat(phi: &Vector3<f64>) -> Matrix3<f64> {
        Matrix3::new(0.0, -phi.z, phi.y, phi.z, 0.0, -phi.x, -phi.y, phi.x, 0.0)
    }

    /// Inverse of [`SO3::hat`] (reads the antisymmetric part).
    pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
        0.5 * Vector3::new(
            m[(2, 1)] - m[(1, 2)],
            m[(0, 2)] - m[(2, 0)],
            m[(1, 0)] - m[(0, 1)],
        )
    }

    /// Left Jacobian J_l(φ) = I + B(θ)·Φ + C(θ)·Φ² (Barfoot eq. 7.77a); also the V matrix of
    /// the SE(3) exponential.
    pub fn left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
        let theta = phi.norm();
        let w = Self::hat(phi);
        Matrix3::identity() + coef_b(theta) * w + coef_c(theta) * w * w
    }

    /// Inverse of the left Jacobian, I − ½Φ + D(θ)·Φ² (finite for θ < 2π).
    pub fn left_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
        let theta = phi.norm();
        let w = Self::hat(phi);
        Matrix3::identity() - 0.5 * w + coef_d(theta) * w * w
    }

    /// Right Jacobian: `exp(φ + δ) ≈ exp(φ)·exp(J_r(φ)·δ)`; J_r(φ) = J_l(−φ).
    pub fn right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
        Self::left_jacobian(&-phi)
    }

    /// Inverse right Jacobian: `log(exp(φ)·exp(δ)) ≈ φ + J_r⁻¹(φ)·δ`.
    pub fn right_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
        Self::left_jacobian_inverse(&-phi)
    }

    /// `d(R·exp(δ)·p)/dδ` at δ = 0, i.e. −R·p^.
    pub fn act_jacobian(&self, p: &Vector3<f64>) -> Matrix3<f64> {
        -self.matrix() * Self::hat(p)
    }
}

impl Mul for SO3 {
    type Output = SO3;
    /// Composition. The product is re-normalised: quaternion products do not keep unit norm,
    /// and poses compounded in a loop (a motion model fed back into itself every frame) would
    /// otherwise grow a 1e-16 norm error geometrically until the rotation blows up.
    fn mul(self, rhs: SO3) -> SO3 {
        SO3::from_quaternion(UnitQuaternion::new_normalize((self.q * rhs.q).into_inner()))
    }
}

impl Mul<&SO3> for &SO3 {
    type Output = SO3;
    fn mul(self, rhs: &SO3) -> SO3 {
        *self * *rhs
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::testing::*;
    use proptest::prelude::*;

    fn close3(a: &Matrix3<f64>, b: &Matrix3<f64>, tol: f64) -> bool {
        (a - b).abs().max() <= tol * (1.0 + b.abs().max())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        #[test]
        fn from_matrix_recovers(a in arb_so3()) {
            let b = SO3::from_matrix(&a.matrix());
            prop_assert!(close3(&b.matrix(), &a.matrix(), 1e-13));
            // A perturbed (non-orthonormal) matrix is projected back onto SO(3).
            let noisy = a.matrix() + Matrix3::from_element(1e-6);
            let c = SO3::from_matrix(&noisy).matrix();
            prop_assert!(close3(&(c.transpose() * c), &Matrix3::identity(), 1e-13));
            prop_assert!(c.determinant() > 0.0);
        }

        #[test]
        fn hat_is_cross_product(phi in arb_point(), p in arb_point()) {
            prop_assert!((SO3::hat(&phi) * p - phi.cross(&p)).norm() <= 1e-12 * (1.0 + phi.norm() * p.norm()));
        }
    }

    #[test]
    fn log_accurate_near_pi() {
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
        for eps in [0.0, 1e-12, 1e-9, 1e-6, 1e-3] {
            let theta = std::f64::consts::PI - eps;
            let phi = axis * theta;
            let back = SO3::exp(&phi).log();
            assert!((back - phi).norm() < 1e-12, "θ = π − {eps}: {back:?}");
        }
    }

    #[test]
    fn log_accurate_near_zero() {
        let axis = Vector3::new(-0.2, 0.9, 0.1).normalize();
        for theta in [0.0, 1e-200, 1e-12, 1e-9, 1e-8, 1e-6, 1e-4] {
            let phi = axis * theta;
            let back = SO3::exp(&phi).log();
            assert!((back - phi).norm() <= 1e-14 * theta, "θ = {theta}");
        }
    }

    #[test]
    fn coefficients_continuous_at_threshold() {
        for f in [coef_c as fn(f64) -> f64, coef_d, coef_b, sinc] {
            for t in [SERIES_ANGLE, SMALL_ANGLE, 1e-4, 1e-8] {
                let (lo, hi) = (f(t * (1.0 - 1e-12)), f(t * (1.0 + 1e-12)));
                assert!((lo - hi).abs() < 1e-12, "at {t}: {lo} vs {hi}");
            }
        }
        // The quaternion log switches branch at |v| = 1e-8.
        let axis = Vector3::new(1.0, 2.0, -2.0).normalize();
        let a = SO3::exp(&(axis * 2e-8 * (1.0 - 1e-9))).log();
        let b = SO3::exp(&(axis * 2e-8 * (1.0 + 1e-9))).log();
        assert!((a - b).norm() < 1e-9 * 2e-8 * 3.0);
        // Jacobians across the series threshold.
        let j1 = SO3::right_jacobian_inverse(&(axis * SMALL_ANGLE * (1.0 - 1e-12)));
        let j2 = SO3::right_jacobian_inverse(&(axis * SMALL_ANGLE * (1.0 + 1e-12)));
        assert!(close3(&j1, &j2, 1e-9));
    }

    #[test]
    fn inverse_jacobian_finite_at_pi() {
        let phi = Vector3::new(0.0, 0.0, std::f64::consts::PI);
        let j = SO3::right_jacobian_inverse(&phi);
        assert!(j.iter().all(|v| v.is_finite()));
        assert!(close3(
            &(j * SO3::right_jacobian(&phi)),
            &Matrix3::identity(),
            1e-12
        ));
    }
}
