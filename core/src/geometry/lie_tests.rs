//! One property suite for the group axioms and Jacobians of [`SO3`], [`SE3`] and [`Sim3`]
//! (as Sophus writes them once, generically). Each group's own file keeps only what is
//! particular to it (projection onto SO(3), the Sim(3) W matrix, series branches, ...).
//!
//! `N` is the tangent dimension, `M` the size of the group's matrix (3 for SO(3), 4 for the
//! homogeneous SE(3) and Sim(3)).

use super::testing::*;
use super::{SE3, SO3, Sim3};
use nalgebra::{SMatrix, SVector, Vector3};
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;

/// What the suite needs of a group, each a one-line delegation to the group's own method.
trait LieGroup<const N: usize, const M: usize>: Copy + std::fmt::Debug {
    fn identity() -> Self;
    fn compose(&self, other: &Self) -> Self;
    fn inverse(&self) -> Self;
    fn exp(xi: &SVector<f64, N>) -> Self;
    fn log(&self) -> SVector<f64, N>;
    fn matrix(&self) -> SMatrix<f64, M, M>;
    fn adjoint(&self) -> SMatrix<f64, N, N>;
    fn hat(xi: &SVector<f64, N>) -> SMatrix<f64, M, M>;
    fn vee(m: &SMatrix<f64, M, M>) -> SVector<f64, N>;
    /// The Lie bracket as a matrix: `ad(x)·y = [x, y]`.
    fn ad(xi: &SVector<f64, N>) -> SMatrix<f64, N, N>;
    fn right_jacobian(xi: &SVector<f64, N>) -> SMatrix<f64, N, N>;
    fn right_jacobian_inverse(xi: &SVector<f64, N>) -> SMatrix<f64, N, N>;
    fn act(&self, p: &Vector3<f64>) -> Vector3<f64>;
    fn act_jacobian(&self, p: &Vector3<f64>) -> SMatrix<f64, 3, N>;
    /// The point `matrix()` maps `p` to (directly, or in homogeneous coordinates).
    fn act_by_matrix(m: &SMatrix<f64, M, M>, p: &Vector3<f64>) -> Vector3<f64>;
    /// The rotation angle of a tangent (where `log` is discontinuous at π).
    fn rotation_angle(xi: &SVector<f64, N>) -> f64;
}

macro_rules! delegate_lie_group {
    ($group:ty, $n:literal, $m:literal, ad = $ad:expr, act_by_matrix = $abm:expr, angle = $angle:expr) => {
        impl LieGroup<$n, $m> for $group {
            fn identity() -> Self {
                <$group>::identity()
            }
            fn compose(&self, other: &Self) -> Self {
                *self * *other
            }
            fn inverse(&self) -> Self {
                <$group>::inverse(self)
            }
            fn exp(xi: &SVector<f64, $n>) -> Self {
                <$group>::exp(xi)
            }
            fn log(&self) -> SVector<f64, $n> {
                <$group>::log(self)
            }
            fn matrix(&self) -> SMatrix<f64, $m, $m> {
                <$group>::matrix(self)
            }
            fn adjoint(&self) -> SMatrix<f64, $n, $n> {
                <$group>::adjoint(self)
            }
            fn hat(xi: &SVector<f64, $n>) -> SMatrix<f64, $m, $m> {
                <$group>::hat(xi)
            }
            fn vee(m: &SMatrix<f64, $m, $m>) -> SVector<f64, $n> {
                <$group>::vee(m)
            }
            fn ad(xi: &SVector<f64, $n>) -> SMatrix<f64, $n, $n> {
                $ad(xi)
            }
            fn right_jacobian(xi: &SVector<f64, $n>) -> SMatrix<f64, $n, $n> {
                <$group>::right_jacobian(xi)
            }
            fn right_jacobian_inverse(xi: &SVector<f64, $n>) -> SMatrix<f64, $n, $n> {
                <$group>::right_jacobian_inverse(xi)
            }
            fn act(&self, p: &Vector3<f64>) -> Vector3<f64> {
                <$group>::act(self, p)
            }
            fn act_jacobian(&self, p: &Vector3<f64>) -> SMatrix<f64, 3, $n> {
                <$group>::act_jacobian(self, p)
            }
            fn act_by_matrix(m: &SMatrix<f64, $m, $m>, p: &Vector3<f64>) -> Vector3<f64> {
                $abm(m, p)
            }
            fn rotation_angle(xi: &SVector<f64, $n>) -> f64 {
                $angle(xi)
            }
        }
    };
}

fn homogeneous(m: &SMatrix<f64, 4, 4>, p: &Vector3<f64>) -> Vector3<f64> {
    (m * p.push(1.0)).xyz()
}

fn rotation_part<const N: usize>(xi: &SVector<f64, N>) -> f64 {
    xi.fixed_rows::<3>(3).norm()
}

delegate_lie_group!(
    SO3,
    3,
    3,
    ad = SO3::hat,
    act_by_matrix = |m: &SMatrix<f64, 3, 3>, p| m * p,
    angle = |xi: &Vector3<f64>| xi.norm()
);
delegate_lie_group!(
    SE3,
    6,
    4,
    ad = SE3::ad,
    act_by_matrix = homogeneous,
    angle = rotation_part::<6>
);
delegate_lie_group!(
    Sim3,
    7,
    4,
    ad = Sim3::ad,
    act_by_matrix = homogeneous,
    angle = rotation_part::<7>
);

fn close<const R: usize, const C: usize>(
    a: &SMatrix<f64, R, C>,
    b: &SMatrix<f64, R, C>,
    tol: f64,
) -> bool {
    (a - b).abs().max() <= tol * (1.0 + b.abs().max())
}

/// exp of a square matrix by scaling and squaring of its power series: a reference
/// independent of every closed form.
fn expm<const M: usize>(m: &SMatrix<f64, M, M>) -> SMatrix<f64, M, M> {
    let scaled = m / 256.0;
    let mut sum = SMatrix::<f64, M, M>::identity();
    let mut term = SMatrix::<f64, M, M>::identity();
    for k in 1..30 {
        term = term * scaled / k as f64;
        sum += term;
    }
    for _ in 0..8 {
        sum = sum * sum;
    }
    sum
}

type Check = Result<(), TestCaseError>;

fn identity_and_inverse<const N: usize, const M: usize, G: LieGroup<N, M>>(a: G) -> Check {
    let (i, eye) = (G::identity(), SMatrix::<f64, M, M>::identity());
    prop_assert!(close(&a.compose(&i).matrix(), &a.matrix(), 1e-14));
    prop_assert!(close(&i.compose(&a).matrix(), &a.matrix(), 1e-14));
    prop_assert!(close(&a.compose(&a.inverse()).matrix(), &eye, 1e-13));
    prop_assert!(close(&a.inverse().compose(&a).matrix(), &eye, 1e-13));
    Ok(())
}

fn composition<const N: usize, const M: usize, G: LieGroup<N, M>>(a: G, b: G, c: G) -> Check {
    let (left, right) = (a.compose(&b).compose(&c), a.compose(&b.compose(&c)));
    prop_assert!(close(&left.matrix(), &right.matrix(), 1e-13));
    prop_assert!(close(
        &a.compose(&b).matrix(),
        &(a.matrix() * b.matrix()),
        1e-13
    ));
    Ok(())
}

fn exp_log<const N: usize, const M: usize, G: LieGroup<N, M>>(xi: SVector<f64, N>) -> Check {
    let t = G::exp(&xi);
    prop_assert!(close(&t.matrix(), &expm(&G::hat(&xi)), 1e-11));
    let back = t.log();
    // Near a rotation of π, ξ and its mirror are the same element: compare as elements, and
    // as vectors away from π.
    prop_assert!(close(&G::exp(&back).matrix(), &t.matrix(), 1e-12));
    if G::rotation_angle(&xi) < std::f64::consts::PI - 1e-6 {
        prop_assert!(
            (back - xi).norm() <= 1e-11 * (1.0 + xi.norm()),
            "{xi} -> {back}"
        );
    }
    Ok(())
}

fn log_exp<const N: usize, const M: usize, G: LieGroup<N, M>>(a: G) -> Check {
    prop_assert!(close(&G::exp(&a.log()).matrix(), &a.matrix(), 1e-12));
    prop_assert!(G::rotation_angle(&a.log()) <= std::f64::consts::PI + 1e-12);
    Ok(())
}

fn action<const N: usize, const M: usize, G: LieGroup<N, M>>(a: G, p: Vector3<f64>) -> Check {
    let q = a.act(&p);
    prop_assert!((q - G::act_by_matrix(&a.matrix(), &p)).norm() <= 1e-12 * (1.0 + q.norm()));
    prop_assert!((a.inverse().act(&q) - p).norm() <= 1e-11 * (1.0 + p.norm() + q.norm()));
    Ok(())
}

fn algebra<const N: usize, const M: usize, G: LieGroup<N, M>>(
    x: SVector<f64, N>,
    y: SVector<f64, N>,
) -> Check {
    prop_assert!((G::vee(&G::hat(&x)) - x).norm() <= 1e-15 * (1.0 + x.norm()));
    let (hx, hy) = (G::hat(&x), G::hat(&y));
    let bracket = G::vee(&(hx * hy - hy * hx));
    prop_assert!((G::ad(&x) * y - bracket).norm() <= 1e-12 * (1.0 + bracket.norm()));
    Ok(())
}

fn adjoint<const N: usize, const M: usize, G: LieGroup<N, M>>(a: G, xi: SVector<f64, N>) -> Check {
    let lhs = a.compose(&G::exp(&xi)).compose(&a.inverse());
    let rhs = G::exp(&(a.adjoint() * xi));
    prop_assert!(close(&lhs.matrix(), &rhs.matrix(), 1e-10));
    Ok(())
}

fn right_jacobians<const N: usize, const M: usize, G: LieGroup<N, M>>(
    xi: SVector<f64, N>,
) -> Check {
    let t = G::exp(&xi);
    let f = |d: &SVector<f64, N>| t.inverse().compose(&G::exp(&(xi + d))).log();
    let (ana, num) = (G::right_jacobian(&xi), numeric_jacobian::<N, N>(&f));
    prop_assert!(close(&ana, &num, 1e-6), "{ana} vs {num}");
    let g = |d: &SVector<f64, N>| t.compose(&G::exp(d)).log();
    let inv = G::right_jacobian_inverse(&xi);
    prop_assert!(close(&inv, &numeric_jacobian::<N, N>(&g), 1e-6));
    prop_assert!(close(
        &(inv * ana),
        &SMatrix::<f64, N, N>::identity(),
        1e-10
    ));
    Ok(())
}

fn act_jacobian<const N: usize, const M: usize, G: LieGroup<N, M>>(a: G, p: Vector3<f64>) -> Check {
    let f = |d: &SVector<f64, N>| a.compose(&G::exp(d)).act(&p);
    prop_assert!(close(
        &a.act_jacobian(&p),
        &numeric_jacobian::<N, 3>(&f),
        1e-6
    ));
    Ok(())
}

/// The whole suite for one group, as property tests in a module named for it.
macro_rules! lie_group_suite {
    ($name:ident, $g:ty, $n:literal, $m:literal, $elem:expr, $tangent:expr, $tangent_no_pi:expr) => {
        mod $name {
            use super::*;
            type G = $g;
            proptest! {
                #![proptest_config(ProptestConfig::with_cases(256))]
                #[test]
                fn identity_and_inverse(a in $elem) { super::identity_and_inverse::<$n, $m, G>(a)?; }
                #[test]
                fn composition(a in $elem, b in $elem, c in $elem) { super::composition::<$n, $m, G>(a, b, c)?; }
                #[test]
                fn exp_log(xi in $tangent) { super::exp_log::<$n, $m, G>(xi)?; }
                #[test]
                fn log_exp(a in $elem) { super::log_exp::<$n, $m, G>(a)?; }
                #[test]
                fn action(a in $elem, p in arb_point()) { super::action::<$n, $m, G>(a, p)?; }
                #[test]
                fn algebra(x in $tangent, y in $tangent) { super::algebra::<$n, $m, G>(x, y)?; }
                #[test]
                fn adjoint(a in $elem, xi in $tangent) { super::adjoint::<$n, $m, G>(a, xi)?; }
                #[test]
                fn right_jacobians(xi in $tangent_no_pi) { super::right_jacobians::<$n, $m, G>(xi)?; }
                #[test]
                fn act_jacobian(a in $elem, p in arb_point()) { super::act_jacobian::<$n, $m, G>(a, p)?; }
            }
        }
    };
}

lie_group_suite!(
    so3,
    SO3,
    3,
    3,
    arb_so3(),
    arb_rotation_vector(),
    arb_rotation_vector_no_pi()
);
lie_group_suite!(
    se3,
    SE3,
    6,
    4,
    arb_se3(),
    arb_se3_tangent(),
    arb_se3_tangent_no_pi()
);
lie_group_suite!(
    sim3,
    Sim3,
    7,
    4,
    arb_sim3(),
    arb_sim3_tangent(),
    arb_sim3_tangent_no_pi()
);
