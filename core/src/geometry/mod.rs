//! Lie groups and the camera model.
//!
//! # Conventions (used by every module of the crate)
//! - **Groups**: [`SO3`] (unit quaternion), [`SE3`] (`p ↦ R·p + t`), [`Sim3`] (`p ↦ s·R·p + t`).
//!   Poses are named by their frames: `world_from_camera: SE3` maps camera coordinates to world
//!   coordinates (the TUM ground-truth convention); `a * b` composes (`(a*b).act(p) =
//!   a.act(&b.act(p))`).
//! - **Tangent order**: SO(3) φ; SE(3) ξ = (ρ, φ) — translation part first, then rotation;
//!   Sim(3) ξ = (ρ, φ, σ) with scale `s = exp(σ)`. ρ is *not* the translation itself but
//!   `t = V(φ)·ρ` (SE(3)) or `t = W(φ, σ)·ρ` (Sim(3)).
//! - **Perturbations are on the right**: increments are applied as `T ← T·exp(δ)`, so every
//!   Jacobian here is with respect to a right perturbation δ at δ = 0:
//!   `act_jacobian(p) = d(T·exp(δ)·p)/dδ`, `right_jacobian(ξ)` with
//!   `exp(ξ + δ) ≈ exp(ξ)·exp(J_r(ξ)·δ)`, and `right_jacobian_inverse(ξ)` with
//!   `log(exp(ξ)·exp(δ)) ≈ ξ + J_r⁻¹(ξ)·δ`.
//! - **Adjoint**: `T·exp(ξ)·T⁻¹ = exp(Ad_T·ξ)`, i.e. `T·exp(δ) = exp(Ad_T·δ)·T` converts a right
//!   perturbation into a left one.
//! - `log` returns rotation angles in [0, π]; all small-angle branches are continuous (tested).
//!
//! # Camera
//! [`PinholeCamera`] with optional OpenCV radial-tangential [`Distortion`]; `project`/`unproject`
//! are the *ideal* pinhole model — images are undistorted once on input with [`UndistortMap`],
//! after which the pipeline never sees distortion (as LSD-SLAM does).

mod camera;
mod information;
mod se3;
mod sim3;
mod so3;
mod undistort;

#[cfg(test)]
mod lie_tests;

pub use camera::{Distortion, PinholeCamera};
pub use information::Information7;
pub use se3::SE3;
pub use sim3::{Matrix3x7, Matrix7, Sim3, Vector7, sim3_w_matrix};
pub use so3::{SMALL_ANGLE, SO3};
pub use undistort::UndistortMap;

/// Random inputs and numeric differentiation shared by the group tests (and, with the feature
/// `testing`, by other crates' tests).
#[cfg(any(test, feature = "testing"))]
pub mod testing {
    use super::{SE3, SO3, Sim3, Vector7};
    use nalgebra::{SMatrix, SVector, Vector3, Vector6};
    use proptest::prelude::*;
    use std::f64::consts::PI;

    /// A unit axis.
    pub fn arb_axis() -> impl Strategy<Value = Vector3<f64>> {
        (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)
            .prop_map(|(x, y, z)| Vector3::new(x, y, z))
            .prop_filter("non-degenerate axis", |v| v.norm() > 0.1)
            .prop_map(|v| v.normalize())
    }

    /// Rotation angles: general, tiny (1e-9..1e-4), around both series thresholds, near π.
    pub fn arb_angle() -> impl Strategy<Value = f64> {
        prop_oneof![
            4 => 0.0..PI,
            2 => 1e-9..1e-4f64,
            1 => Just(0.0),
            1 => (super::SMALL_ANGLE - 1e-9)..(super::SMALL_ANGLE + 1e-9),
            1 => (1.0 - 1e-9)..(1.0 + 1e-9),
            2 => (PI - 1e-6)..PI,
        ]
    }

    /// Angles away from π (for Jacobians of `log`, which jumps at π).
    pub fn arb_angle_no_pi() -> impl Strategy<Value = f64> {
        prop_oneof![
            4 => 0.0..(PI - 0.05),
            2 => 1e-9..1e-4f64,
            1 => Just(0.0),
            1 => (super::SMALL_ANGLE - 1e-9)..(super::SMALL_ANGLE + 1e-9),
            1 => (1.0 - 1e-9)..(1.0 + 1e-9),
        ]
    }

    pub fn arb_rotation_vector() -> impl Strategy<Value = Vector3<f64>> {
        (arb_axis(), arb_angle()).prop_map(|(a, t)| a * t)
    }

    pub fn arb_rotation_vector_no_pi() -> impl Strategy<Value = Vector3<f64>> {
        (arb_axis(), arb_angle_no_pi()).prop_map(|(a, t)| a * t)
    }

    pub fn arb_so3() -> impl Strategy<Value = SO3> {
        arb_rotation_vector().prop_map(|p| SO3::exp(&p))
    }

    /// Points (and translations) in a 20 m cube.
    pub fn arb_point() -> impl Strategy<Value = Vector3<f64>> {
        (-10.0..10.0f64, -10.0..10.0f64, -10.0..10.0f64).prop_map(|(x, y, z)| Vector3::new(x, y, z))
    }

    /// Small translation tangents (|ρ| ≲ 5).
    fn arb_rho() -> impl Strategy<Value = Vector3<f64>> {
        (-3.0..3.0f64, -3.0..3.0f64, -3.0..3.0f64).prop_map(|(x, y, z)| Vector3::new(x, y, z))
    }

    /// Log-scales σ: general, tiny (±1e-9..1e-4), zero, around the moment-series threshold,
    /// and large (scale factors up to e⁶).
    pub fn arb_sigma() -> impl Strategy<Value = f64> {
        prop_oneof![
            4 => -2.0..2.0f64,
            2 => 1e-9..1e-4f64,
            2 => -1e-4..-1e-9f64,
            1 => Just(0.0),
            1 => 3.99..4.01f64,
            1 => -4.01..-3.99f64,
            1 => -6.0..6.0f64,
        ]
    }

    fn se3_tangent(rho: Vector3<f64>, phi: Vector3<f64>) -> Vector6<f64> {
        let mut xi = Vector6::zeros();
        xi.fixed_rows_mut::<3>(0).copy_from(&rho);
        xi.fixed_rows_mut::<3>(3).copy_from(&phi);
        xi
    }

    fn sim3_tangent(rho: Vector3<f64>, phi: Vector3<f64>, sigma: f64) -> Vector7 {
        let mut xi = Vector7::zeros();
        xi.fixed_rows_mut::<3>(0).copy_from(&rho);
        xi.fixed_rows_mut::<3>(3).copy_from(&phi);
        xi[6] = sigma;
        xi
    }

    pub fn arb_se3_tangent() -> impl Strategy<Value = Vector6<f64>> {
        (arb_rho(), arb_rotation_vector()).prop_map(|(r, p)| se3_tangent(r, p))
    }

    pub fn arb_se3_tangent_no_pi() -> impl Strategy<Value = Vector6<f64>> {
        (arb_rho(), arb_rotation_vector_no_pi()).prop_map(|(r, p)| se3_tangent(r, p))
    }

    pub fn arb_se3() -> impl Strategy<Value = SE3> {
        (arb_so3(), arb_point()).prop_map(|(r, t)| SE3::new(r, t))
    }

    pub fn arb_sim3_tangent() -> impl Strategy<Value = Vector7> {
        (arb_rho(), arb_rotation_vector(), arb_sigma()).prop_map(|(r, p, s)| sim3_tangent(r, p, s))
    }

    pub fn arb_sim3_tangent_no_pi() -> impl Strategy<Value = Vector7> {
        (arb_rho(), arb_rotation_vector_no_pi(), arb_sigma())
            .prop_map(|(r, p, s)| sim3_tangent(r, p, s))
    }

    /// Sim(3) elements with scales in [e⁻³, e³].
    pub fn arb_sim3() -> impl Strategy<Value = Sim3> {
        (
            arb_so3(),
            arb_point(),
            prop_oneof![-3.0..3.0f64, Just(0.0), -1e-6..1e-6f64],
        )
            .prop_map(|(r, t, s)| Sim3::new(r, t, s.exp()))
    }

    /// Central differences with step 1e-6: column j is (f(x + h·e_j) − f(x − h·e_j)) / 2h
    /// around x = 0 (the functions under test already include their base point).
    pub fn numeric_jacobian<const N: usize, const M: usize>(
        f: &dyn Fn(&SVector<f64, N>) -> SVector<f64, M>,
    ) -> SMatrix<f64, M, N> {
        const H: f64 = 1e-6;
        let mut j = SMatrix::<f64, M, N>::zeros();
        for c in 0..N {
            let mut d = SVector::<f64, N>::zeros();
            d[c] = H;
            j.set_column(c, &((f(&d) - f(&-d)) / (2.0 * H)));
        }
        j
    }
}
