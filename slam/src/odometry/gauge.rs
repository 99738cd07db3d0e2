//! The gauge of a monocular window: the 7 directions (a rigid motion and a scale of the whole
//! world) along which no photometric residual changes.
//!
//! Why: nothing in the images fixes them, so the solver must neither move along them (the
//! step is projected out of them, DSO's `SOLVER_ORTHOGONALIZE_X_LATER`) nor gain information
//! about them (first-estimate Jacobians; the tests check both).

use nalgebra::{DMatrix, DVector, Vector6};

use super::residual::{FRAME_PARAMS, FrameState};

/// Number of gauge directions of a monocular window: 6 (SE(3)) + 1 (scale).
pub const GAUGE_DIMENSION: usize = 7;

/// The gauge directions of the window's keyframe parameters at `states`, one column each
/// (`8·n × 7`): columns 0-5 move the world by `exp(ξ)` on the left (`ξ` a unit tangent in
/// (v, ω) order), column 6 scales it by `1 + s`. The points' inverse depths move too (a scale
/// divides them), but they are eliminated before the frames' step is taken, so their part is
/// not needed here.
pub fn basis(states: &[FrameState]) -> DMatrix<f64> {
    let mut n = DMatrix::<f64>::zeros(states.len() * FRAME_PARAMS, GAUGE_DIMENSION);
    for (k, state) in states.iter().enumerate() {
        let pose = &state.world_from_camera;
        // exp(ξ)·T = T·exp(Ad_{T⁻¹} ξ).
        let ad = pose.inverse().adjoint();
        for j in 0..6 {
            let mut xi = Vector6::zeros();
            xi[j] = 1.0;
            let delta = ad * xi;
            n.view_mut((k * FRAME_PARAMS, j), (6, 1)).copy_from(&delta);
        }
        // (R, t) → (R, (1 + s)·t) = T·exp((s·Rᵀt, 0)).
        let v = pose.rotation.inverse().act(&pose.translation);
        n.view_mut((k * FRAME_PARAMS, 6), (3, 1)).copy_from(&v);
    }
    n
}

/// Removes from `step` (the keyframes' parameters, `8·n`) its component in the span of
/// `basis`: a least-squares projection, so that the solver never moves the gauge.
pub fn project_out(basis: &DMatrix<f64>, step: &mut DVector<f64>) {
    let gram = basis.transpose() * basis;
    // A window whose keyframes all sit at the origin has no scale direction; the
    // pseudo-inverse leaves that column out instead of failing.
    let Ok(inverse) = gram.pseudo_inverse(1e-12) else {
        return;
    };
    let coefficients = inverse * (basis.transpose() * &*step);
    *step -= basis * coefficients;
}
