//! The marginalisation prior: what keyframes and points that left the window knew about the
//! keyframes that stay, as a quadratic in their offsets from their first estimates (DSO,
//! TPAMI 2018, §2.3; `FullSystemMarginalize.cpp`).
//!
//! Why: fixing old keyframes (the previous window of this crate) freezes whatever gauge and
//! scale error they carry; dropping them forgets what they measured. The prior keeps their
//! information, including the relative scale, without freezing anything.

use nalgebra::{DMatrix, DVector};

use super::residual::FRAME_PARAMS;

/// `E(δ) = bᵀδ + ½ δᵀHδ` over the window's keyframes (in window order), `δ` each keyframe's
/// offset from its first estimate ([`super::FrameState::delta_from`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MarginalisationPrior {
    pub h: DMatrix<f64>,
    pub b: DVector<f64>,
}

impl MarginalisationPrior {
    /// Keyframes the prior spans.
    pub fn frames(&self) -> usize {
        self.b.len() / FRAME_PARAMS
    }

    /// Extends the prior by a keyframe it knows nothing about.
    pub fn push_frame(&mut self) {
        let n = self.b.len() + FRAME_PARAMS;
        self.h = std::mem::take(&mut self.h).resize(n, n, 0.0);
        self.b = std::mem::take(&mut self.b).resize_vertically(n, 0.0);
    }

    /// The prior's energy at offsets `delta`.
    pub fn energy(&self, delta: &DVector<f64>) -> f64 {
        self.b.dot(delta) + 0.5 * delta.dot(&(&self.h * delta))
    }

    /// The prior's gradient at offsets `delta`.
    pub fn gradient(&self, delta: &DVector<f64>) -> DVector<f64> {
        &self.b + &self.h * delta
    }

    /// Adds a term `(h, g)` linearised at offsets `delta` (its Hessian and its gradient
    /// there): `b += g − hδ`, `H += h`, so that its gradient at `δ` is `g`.
    pub fn add_linearised(&mut self, h: &DMatrix<f64>, g: &DVector<f64>, delta: &DVector<f64>) {
        self.b += g - h * delta;
        self.h += h;
    }

    /// Eliminates keyframe `k` (Schur complement): the other keyframes keep what it knew
    /// about them, the prior no longer spans it.
    pub fn remove_frame(&mut self, k: usize) {
        let n = self.frames();
        let keep: Vec<usize> = (0..n * FRAME_PARAMS)
            .filter(|i| i / FRAME_PARAMS != k)
            .collect();
        let gone: Vec<usize> = (k * FRAME_PARAMS..(k + 1) * FRAME_PARAMS).collect();
        let pick = |rows: &[usize], cols: &[usize]| {
            DMatrix::from_fn(rows.len(), cols.len(), |r, c| self.h[(rows[r], cols[c])])
        };
        let h_rr = pick(&keep, &keep);
        let h_rk = pick(&keep, &gone);
        let mut h_kk = pick(&gone, &gone);
        let b_r = DVector::from_fn(keep.len(), |r, _| self.b[keep[r]]);
        let b_k = DVector::from_fn(gone.len(), |r, _| self.b[gone[r]]);
        // Symmetric and, with the affine prior in it, positive definite; the pseudo-inverse
        // covers a keyframe nothing was measured against.
        h_kk = 0.5 * (&h_kk + h_kk.transpose());
        let inv = h_kk
            .clone()
            .cholesky()
            .map(|c| c.inverse())
            .or_else(|| h_kk.pseudo_inverse(1e-12).ok())
            .unwrap_or_else(|| DMatrix::zeros(FRAME_PARAMS, FRAME_PARAMS));
        let coupling = &h_rk * inv;
        let h = &h_rr - &coupling * h_rk.transpose();
        self.h = 0.5 * (&h + h.transpose());
        self.b = b_r - coupling * b_k;
    }
}
