//! Sim(3): similarity transforms `p ↦ s·R·p + t`, the keyframe-to-keyframe constraints of a
//! monocular pose graph (LSD-SLAM §3.3; DeepRelativeFusion §III builds on the same graph).
//!
//! Tangent ξ = (ρ, φ, σ) ∈ ℝ⁷ with scale `s = exp(σ)`; perturbations on the right, `T·exp(δ)`.
//! The exponential is the proper Sim(3) one: `t = W(φ, σ)·ρ` with
//! `W = ∫₀¹ e^{uσ} exp(u·φ^) du = a·I + b·Φ + c·Φ²` (the scale-coupled V matrix; Strasdat,
//! *Local Accuracy and Global Consistency for Efficient Visual SLAM*, PhD thesis 2012, §7.1.3;
//! Sophus `Sim3::exp`). Its coefficients are evaluated so that they stay accurate when σ → 0,
//! θ → 0, or both, see [`w_coefficients`].

use super::se3::SE3;
use super::so3::{SMALL_ANGLE, SO3};
use nalgebra::{Matrix3, Matrix4, SMatrix, SVector, Vector3};
use serde::{Deserialize, Serialize};
use std::ops::Mul;
use std::sync::OnceLock;

/// A 7-vector (Sim(3) tangent, order ρ, φ, σ).
pub type Vector7 = SVector<f64, 7>;
/// A 7×7 matrix (Sim(3) adjoints and Jacobians).
pub type Matrix7 = SMatrix<f64, 7, 7>;
/// A 3×7 matrix (derivative of a transformed point with respect to a Sim(3) tangent).
pub type Matrix3x7 = SMatrix<f64, 3, 7>;

/// A similarity transform `p ↦ scale·rotation·p + translation` (scale > 0).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sim3 {
    pub rotation: SO3,
    pub translation: Vector3<f64>,
    pub scale: f64,
}

impl Default for Sim3 {
    fn default() -> Self {
        Self::identity()
    }
}

/// Number of moments `M_n(σ) = ∫₀¹ uⁿ e^{uσ} du` (n = 0..=10) used by the small-θ series.
const MOMENTS: usize = 11;

/// Below this |σ| the moments are summed as a power series in σ; above, by the (then stable)
/// upward recursion `M_n = (e^σ − n·M_{n−1})/σ`, whose error amplification ∏ n/|σ| stays ≲ 4.
const SIGMA_SERIES: f64 = 4.0;

/// `M_n(σ) = ∫₀¹ uⁿ e^{uσ} du` for n = 0..=10. `M_0 = (e^σ − 1)/σ`, and `M_n` are the
/// derivatives `dⁿ M_0/dσⁿ`, i.e. the θ-Taylor coefficients of W.
pub(crate) fn exp_moments(sigma: f64) -> [f64; MOMENTS] {
    let mut m = [0.0; MOMENTS];
    if sigma.abs() < SIGMA_SERIES {
        // Σ_k σᵏ / (k!·(n + k + 1)); at |σ| < 4 the largest term is ~10, so at most one digit
        // is lost to cancellation for negative σ.
        for (n, out) in m.iter_mut().enumerate() {
            let mut term = 1.0;
            let mut sum = 1.0 / (n + 1) as f64;
            for k in 1..100 {
                term *= sigma / k as f64;
                let add = term / (n + k + 1) as f64;
                sum += add;
                if add.abs() <= 1e-18 * sum.abs() {
                    break;
                }
            }
            *out = sum;
        }
    } else {
        let e = sigma.exp();
        m[0] = sigma.exp_m1() / sigma;
        for n in 1..MOMENTS {
            m[n] = (e - n as f64 * m[n - 1]) / sigma;
        }
    }
    m
}

/// Coefficients (a, b, c) of `W(φ, σ) = a·I + b·Φ + c·Φ²`, θ = |φ|:
/// `a = (e^σ − 1)/σ`, `b = Im f(σ + iθ)/θ`, `c = (a − Re f(σ + iθ))/θ²` with
/// `f(z) = (e^z − 1)/z = ∫₀¹ e^{uz} du`.
///
/// For θ < [`SMALL_ANGLE`] the closed forms cancel, so b and c are summed as their Taylor series
/// in θ², whose coefficients are the moments `M_n(σ)` (exact in σ):
/// `b = Σ_k (−θ²)ᵏ M_{2k+1}/(2k+1)!`, `c = Σ_k (−θ²)ᵏ M_{2k+2}/(2k+2)!`, truncated at k = 4
/// (error < 1e-18 relative at θ = 0.1). `a = M_0` is itself a convergent series near σ = 0.
pub(crate) fn w_coefficients(sigma: f64, theta: f64) -> (f64, f64, f64) {
    let m = exp_moments(sigma);
    let a = m[0];
    if theta < SMALL_ANGLE {
        const FACT_ODD: [f64; 5] = [1.0, 6.0, 120.0, 5040.0, 362_880.0];
        const FACT_EVEN: [f64; 5] = [2.0, 24.0, 720.0, 40_320.0, 3_628_800.0];
        let (mut b, mut c, mut pow) = (0.0, 0.0, 1.0);
        for k in 0..5 {
            b += pow * m[2 * k + 1] / FACT_ODD[k];
            c += pow * m[2 * k + 2] / FACT_EVEN[k];
            pow *= -theta * theta;
        }
        (a, b, c)
    } else {
        let s = sigma.exp();
        let (sin, cos) = theta.sin_cos();
        let half_sin = (0.5 * theta).sin();
        // s·cos θ − 1 without cancellation when σ and θ are both small-ish.
        let scos_m1 = sigma.exp_m1() * cos - 2.0 * half_sin * half_sin;
        let denom = sigma * sigma + theta * theta;
        let re = (sigma * scos_m1 + theta * s * sin) / denom;
        let im = (sigma * s * sin - theta * scos_m1) / denom;
        (a, im / theta, (a - re) / (theta * theta))
    }
}

/// The W matrix of the Sim(3) exponential, `t = W·ρ` (coefficients accurate for σ → 0, θ → 0
/// and both; see the module docs).
pub fn sim3_w_matrix(phi: &Vector3<f64>, sigma: f64) -> Matrix3<f64> {
    let (a, b, c) = w_coefficients(sigma, phi.norm());
    let p = SO3::hat(phi);
    a * Matrix3::identity() + b * p + c * p * p
}

/// 16-point Gauss–Legendre nodes and weights on [−1, 1], computed once by Newton's method on
/// the Legendre recurrence.
fn gauss_legendre_16() -> &'static [(f64, f64); 16] {
    static NODES: OnceLock<[(f64, f64); 16]> = OnceLock::new();
    NODES.get_or_init(|| {
        const N: usize = 16;
        let mut out = [(0.0, 0.0); N];
        for (i, slot) in out.iter_mut().enumerate() {
            let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (N as f64 + 0.5)).cos();
            let mut dp = 1.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=N {
                    let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = N as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-16 {
                    break;
                }
            }
            *slot = (x, 2.0 / ((1.0 - x * x) * dp * dp));
        }
        out
    })
}

/// ∫₀¹ f(u) du by composite 16-point Gauss–Legendre. `rate` bounds the exponential growth
/// rate of the integrand's entries (|λ| of e^{λu}); panels of width ≤ 8/rate keep the
/// quadrature error below 1e-25 relative, i.e. the result is exact to rounding.
pub(crate) fn integrate_unit_interval<const R: usize, const C: usize>(
    f: impl Fn(f64) -> SMatrix<f64, R, C>,
    rate: f64,
) -> SMatrix<f64, R, C> {
    let panels = (rate.abs() / 8.0).ceil().clamp(1.0, 256.0) as usize;
    let width = 1.0 / panels as f64;
    let mut sum = SMatrix::<f64, R, C>::zeros();
    for p in 0..panels {
        let mid = (p as f64 + 0.5) * width;
        for &(x, w) in gauss_legendre_16() {
            sum += f(mid + 0.5 * width * x) * (0.5 * width * w);
        }
    }
    sum
}

/// Splits a 7-vector into (ρ, φ, σ).
fn split(xi: &Vector7) -> (Vector3<f64>, Vector3<f64>, f64) {
    (
        xi.fixed_rows::<3>(0).into_owned(),
        xi.fixed_rows::<3>(3).into_owned(),
        xi[6],
    )
}

/// Joins (ρ, φ, σ) into a 7-vector.
fn join(rho: &Vector3<f64>, phi: &Vector3<f64>, sigma: f64) -> Vector7 {
    let mut xi = Vector7::zeros();
    xi.fixed_rows_mut::<3>(0).copy_from(rho);
    xi.fixed_rows_mut::<3>(3).copy_from(phi);
    xi[6] = sigma;
    xi
}

impl Sim3 {
    /// The identity (s = 1).
    pub fn identity() -> Self {
        Self {
            rotation: SO3::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// `p ↦ scale·rotation·p + translation`; `scale` must be > 0 (not checked: it is a
    /// mathematical precondition, as for a unit quaternion).
    pub fn new(rotation: SO3, translation: Vector3<f64>, scale: f64) -> Self {
        Self {
            rotation,
            translation,
            scale,
        }
    }

    /// `p ↦ scale·R·p + t` from the rigid part (R, t) of `pose`.
    pub fn from_se3(pose: &SE3, scale: f64) -> Self {
        Self::new(pose.rotation, pose.translation, scale)
    }

    /// Splits into the rigid part (R, t) and the scale: `self.act(p) = se3.act(scale·p)`.
    pub fn to_se3_and_scale(&self) -> (SE3, f64) {
        (SE3::new(self.rotation, self.translation), self.scale)
    }

    /// From a 4×4 matrix `[[sR, t], [0, 1]]`: s = ∛det(sR), R re-orthonormalised.
    pub fn from_matrix(m: &Matrix4<f64>) -> Self {
        let a: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
        let s = a.determinant().cbrt();
        Self::new(
            SO3::from_matrix(&(a / s)),
            m.fixed_view::<3, 1>(0, 3).into_owned(),
            s,
        )
    }

    /// The 4×4 matrix `[[sR, t], [0, 1]]`.
    pub fn matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(self.scale * self.rotation.matrix()));
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.translation);
        m
    }

    /// Exponential map: (ρ, φ, σ) → (exp(φ), W(φ, σ)·ρ, e^σ).
    pub fn exp(xi: &Vector7) -> Self {
        let (rho, phi, sigma) = split(xi);
        Self::new(
            SO3::exp(&phi),
            sim3_w_matrix(&phi, sigma) * rho,
            sigma.exp(),
        )
    }

    /// Logarithm: (R, t, s) → (W⁻¹·t, log R, ln s) with |φ| ≤ π. W is invertible for
    /// θ ≤ π (its eigenvalues are a > 0 and f(σ ± iθ) ≠ 0), so the result is always finite for
    /// a finite transform with s > 0.
    pub fn log(&self) -> Vector7 {
        let phi = self.rotation.log();
        let sigma = self.scale.ln();
        let w = sim3_w_matrix(&phi, sigma);
        let rho = w
            .lu()
            .solve(&self.translation)
            .unwrap_or_else(|| Vector3::repeat(f64::NAN));
        join(&rho, &phi, sigma)
    }

    /// The inverse `(Rᵀ, −Rᵀt/s, 1/s)`.
    pub fn inverse(&self) -> Self {
        let r = self.rotation.inverse();
        Self::new(r, -r.act(&self.translation) / self.scale, 1.0 / self.scale)
    }

    /// Transforms a point: s·R·p + t.
    #[inline]
    pub fn act(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.scale * self.rotation.act(p) + self.translation
    }

    /// Adjoint in (ρ, φ, σ) order, `T·exp(ξ)·T⁻¹ = exp(Ad_T·ξ)`:
    /// `[[sR, t^R, −t], [0, R, 0], [0, 0, 1]]`.
    pub fn adjoint(&self) -> Matrix7 {
        let r = self.rotation.matrix();
        let mut a = Matrix7::zeros();
        a.fixed_view_mut::<3, 3>(0, 0).copy_from(&(self.scale * r));
        a.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(SO3::hat(&self.translation) * r));
        a.fixed_view_mut::<3, 1>(0, 6).copy_from(&-self.translation);
        a.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
        a[(6, 6)] = 1.0;
        a
    }

    /// ξ^ = [[φ^ + σI, ρ], [0, 0]].
    pub fn hat(xi: &Vector7) -> Matrix4<f64> {
        let (rho, phi, sigma) = split(xi);
        let mut m = Matrix4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(SO3::hat(&phi) + sigma * Matrix3::identity()));
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&rho);
        m
    }

    /// Inverse of [`Sim3::hat`] (σ = trace/3 of the 3×3 block, φ from its antisymmetric part).
    pub fn vee(m: &Matrix4<f64>) -> Vector7 {
        let a: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
        join(
            &m.fixed_view::<3, 1>(0, 3).into_owned(),
            &SO3::vee(&a),
            a.trace() / 3.0,
        )
    }

    /// Lie bracket matrix `ad(ξ) = [[φ^ + σI, ρ^, −ρ], [0, φ^, 0], [0, 0, 0]]`, with
    /// `[ξ₁^, ξ₂^]^∨ = ad(ξ₁)·ξ₂`.
    pub fn ad(xi: &Vector7) -> Matrix7 {
        let (rho, phi, sigma) = split(xi);
        let p = SO3::hat(&phi);
        let mut a = Matrix7::zeros();
        a.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(p + sigma * Matrix3::identity()));
        a.fixed_view_mut::<3, 3>(0, 3).copy_from(&SO3::hat(&rho));
        a.fixed_view_mut::<3, 1>(0, 6).copy_from(&-rho);
        a.fixed_view_mut::<3, 3>(3, 3).copy_from(&p);
        a
    }

    /// Right Jacobian, `exp(ξ + δ) ≈ exp(ξ)·exp(J_r(ξ)·δ)`.
    ///
    /// Sim(3) has no compact closed form, so this evaluates the exact identity
    /// `J_r(ξ) = Σ (−ad ξ)ⁿ/(n+1)! = ∫₀¹ Ad(exp(−uξ)) du` by Gauss–Legendre quadrature
    /// (16-point composite Gauss–Legendre), exact to rounding for any ξ (the integrand is a sum of
    /// exponentials with rates ≤ |σ| + 2θ). Near ξ = 0 it tends to `I − ½ad(ξ)`.
    pub fn right_jacobian(xi: &Vector7) -> Matrix7 {
        let (_, phi, sigma) = split(xi);
        let rate = sigma.abs() + 2.0 * phi.norm() + 1.0;
        integrate_unit_interval(|u| Sim3::exp(&(-u * xi)).adjoint(), rate)
    }

    /// Inverse right Jacobian, `log(exp(ξ)·exp(δ)) ≈ ξ + J_r⁻¹(ξ)·δ` (the pose-graph residual
    /// Jacobian). Invertible whenever θ < 2π, which [`Sim3::log`] guarantees; NaN otherwise.
    pub fn right_jacobian_inverse(xi: &Vector7) -> Matrix7 {
        Self::right_jacobian(xi)
            .try_inverse()
            .unwrap_or_else(|| Matrix7::repeat(f64::NAN))
    }

    /// `d(T·exp(δ)·p)/dδ` at δ = 0: `[sR, −sR·p^, sR·p]`.
    #[inline]
    pub fn act_jacobian(&self, p: &Vector3<f64>) -> Matrix3x7 {
        Self::act_jacobian_with(&self.act_jacobian_wrt_point(), p)
    }

    /// [`Sim3::act_jacobian`] from `sR` ([`Sim3::act_jacobian_wrt_point`]) computed once for
    /// many points: the rotation matrix of a quaternion costs more than the rest of it.
    #[inline]
    pub fn act_jacobian_with(sr: &Matrix3<f64>, p: &Vector3<f64>) -> Matrix3x7 {
        let mut j = Matrix3x7::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(sr);
        j.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(-sr * SO3::hat(p)));
        j.fixed_view_mut::<3, 1>(0, 6).copy_from(&(sr * p));
        j
    }

    /// `d(T·p)/dp` = s·R.
    #[inline]
    pub fn act_jacobian_wrt_point(&self) -> Matrix3<f64> {
        self.scale * self.rotation.matrix()
    }
}

impl Mul for Sim3 {
    type Output = Sim3;
    fn mul(self, rhs: Sim3) -> Sim3 {
        Sim3::new(
            self.rotation * rhs.rotation,
            self.act(&rhs.translation),
            self.scale * rhs.scale,
        )
    }
}

impl Mul<&Sim3> for &Sim3 {
    type Output = Sim3;
    fn mul(self, rhs: &Sim3) -> Sim3 {
        *self * *rhs
    }
}

#[cfg(test)]
#[path = "sim3_tests.rs"]
mod tests;
