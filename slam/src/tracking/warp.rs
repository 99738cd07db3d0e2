//! The inner loops of direct SE(3) alignment: warp the reference points into the new frame,
//! compute variance-normalised, Huber-weighted photometric residuals (LSD-SLAM ECCV 2014 §3.3,
//! eqs. (12)–(14)), and accumulate the 6×6 normal equations.
//!
//! Everything here is `f32` on struct-of-arrays buffers that are allocated once per tracker and
//! reused, so one Levenberg–Marquardt iteration touches no allocator.

use nalgebra::{Matrix6, Vector3, Vector6};

use super::config::TrackingConfig;
use super::reference::ReferenceLevel;
use crate::geometry::{PinholeCamera, SE3};
use crate::image::pyramid::PyramidLevel;

/// Points closer than this (in the frame, keyframe scale) are not projected: the projection
/// is undefined at z = 0 and flips behind the camera.
const MIN_WARPED_DEPTH: f32 = 1e-6;

/// Huber width (8-bit units) of the robust weights of the affine brightness fit (LSD-SLAM's
/// constant 5 in `calcResidualAndBuffers`).
const AFFINE_HUBER: f32 = 5.0;

/// One frame level with intensity and gradients interleaved per pixel (`[I, ∂I/∂x, ∂I/∂y, 0]`),
/// so that a bilinear lookup touches four 16-byte cells instead of twelve scattered floats.
#[derive(Clone, Debug, Default)]
pub(crate) struct InterleavedLevel {
    pub width: usize,
    pub height: usize,
    pub data: Vec<[f32; 4]>,
}

impl InterleavedLevel {
    /// Refills from a pyramid level, reusing the allocation.
    pub fn fill(&mut self, level: &PyramidLevel) {
        self.width = level.width();
        self.height = level.height();
        self.data.clear();
        self.data.extend(
            level
                .image
                .data
                .iter()
                .zip(&level.gx.data)
                .zip(&level.gy.data)
                .map(|((&i, &gx), &gy)| [i, gx, gy, 0.0]),
        );
    }

    /// Bilinear interpolation of `[I, gx, gy]` at `(u, v)`; the caller guarantees
    /// `0 ≤ u < width − 1` and `0 ≤ v < height − 1`.
    #[inline(always)]
    fn sample(&self, u: f32, v: f32) -> [f32; 3] {
        let (x0, y0) = (u as usize, v as usize);
        let (fx, fy) = (u - x0 as f32, v - y0 as f32);
        let i = y0 * self.width + x0;
        let (p00, p10) = (self.data[i], self.data[i + 1]);
        let (p01, p11) = (self.data[i + self.width], self.data[i + self.width + 1]);
        let mut out = [0.0f32; 3];
        for k in 0..3 {
            let top = p00[k] + fx * (p10[k] - p00[k]);
            let bottom = p01[k] + fx * (p11[k] - p01[k]);
            out[k] = top + fy * (bottom - top);
        }
        out
    }
}

/// The pose and intrinsics of one evaluation in `f32`, plus the affine brightness model.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WarpParams {
    /// Rotation of `frame_from_keyframe`, row-major.
    pub r: [f32; 9],
    /// Translation of `frame_from_keyframe`.
    pub t: [f32; 3],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Affine brightness: the reference intensity predicts `a·I_ref + b` in the frame.
    pub affine_a: f32,
    pub affine_b: f32,
}

impl WarpParams {
    pub fn new(frame_from_keyframe: &SE3, camera: &PinholeCamera, affine: (f32, f32)) -> Self {
        let m = frame_from_keyframe.rotation.matrix();
        let t = frame_from_keyframe.translation;
        Self {
            r: [
                m[(0, 0)] as f32,
                m[(0, 1)] as f32,
                m[(0, 2)] as f32,
                m[(1, 0)] as f32,
                m[(1, 1)] as f32,
                m[(1, 2)] as f32,
                m[(2, 0)] as f32,
                m[(2, 1)] as f32,
                m[(2, 2)] as f32,
            ],
            t: [t.x as f32, t.y as f32, t.z as f32],
            fx: camera.fx as f32,
            fy: camera.fy as f32,
            cx: camera.cx as f32,
            cy: camera.cy as f32,
            affine_a: affine.0,
            affine_b: affine.1,
        }
    }
}

/// The warped points of one evaluation (struct of arrays, only points that landed in the image)
/// and its statistics.
#[derive(Clone, Debug, Default)]
pub(crate) struct WarpBuffers {
    /// Warped point in frame coordinates.
    pub px: Vec<f32>,
    pub py: Vec<f32>,
    pub pz: Vec<f32>,
    /// Frame gradient at the warped pixel times the focal length (`fx·∂I/∂u`, `fy·∂I/∂v`).
    pub gx: Vec<f32>,
    pub gy: Vec<f32>,
    /// Photometric residual `a·I_ref + b − I_frame(π(T·p))`.
    pub residual: Vec<f32>,
    /// Combined weight `w_huber / σ_r²`.
    pub weight: Vec<f32>,
    /// Points that passed LSD's good-residual test.
    pub good: usize,
    /// Warped points that failed it.
    pub bad: usize,
    /// `Σ min(1, z_ref / z_frame)` over warped points (LSD-SLAM `pointUsage` numerator: a
    /// point seen from farther away covers fewer pixels and counts less).
    pub usage: f64,
    /// Weighted mean of `w_huber · r² / σ_r²`: the cost LM decreases.
    pub cost: f64,
    /// Affine brightness `(a, b)` fitted to this evaluation's intensity pairs, if defined.
    pub affine_estimate: Option<(f32, f32)>,
}

impl WarpBuffers {
    fn clear(&mut self) {
        for v in [
            &mut self.px,
            &mut self.py,
            &mut self.pz,
            &mut self.gx,
            &mut self.gy,
            &mut self.residual,
            &mut self.weight,
        ] {
            v.clear();
        }
        self.good = 0;
        self.bad = 0;
        self.usage = 0.0;
        self.cost = 0.0;
        self.affine_estimate = None;
    }

    /// Number of warped points.
    pub fn len(&self) -> usize {
        self.residual.len()
    }

    /// Whether no point landed in the image.
    pub fn is_empty(&self) -> bool {
        self.residual.is_empty()
    }
}

/// Warps every reference point with `params`, samples the frame, and fills `out` with the
/// residuals, their weights and the statistics (LSD-SLAM `calcResidualAndBuffers` fused with
/// `calcWeightsAndResidual`).
///
/// A point is used when its projection lies strictly inside `(1, w−2) × (1, h−2)`, as in
/// LSD-SLAM (the gradients there are central differences). Its residual variance is
/// `σ_r² = camera_pixel_noise2 + var_weight·(∂r/∂d)²·V_d` (ECCV 2014 eq. (13)), where
/// `∂r/∂d = ∇I · ∂π/∂d` is the sensitivity of the residual to the keyframe inverse depth `d`;
/// the Huber weight acts on `r/σ_r` with threshold `huber_d / 2`.
pub(crate) fn evaluate(
    reference: &ReferenceLevel,
    frame: &InterleavedLevel,
    params: &WarpParams,
    config: &TrackingConfig,
    out: &mut WarpBuffers,
) {
    out.clear();
    let [r0, r1, r2, r3, r4, r5, r6, r7, r8] = params.r;
    let [tx, ty, tz] = params.t;
    let (umax, vmax) = (frame.width as f32 - 2.0, frame.height as f32 - 2.0);
    let huber = 0.5 * config.huber_d;
    let (noise2, var_weight) = (config.camera_pixel_noise2, config.var_weight);
    let (max_diff_c, max_diff_g) = (config.max_diff_constant, config.max_diff_grad_mult);
    let (a, b) = (params.affine_a, params.affine_b);
    let (mut sxx, mut syy, mut sx, mut sy, mut sw) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let mut cost = 0.0f64;
    let n = reference.len();
    let (xs, ys, zs) = (&reference.x[..n], &reference.y[..n], &reference.z[..n]);
    let (intensity, idepth_var) = (&reference.intensity[..n], &reference.idepth_var[..n]);
    for i in 0..n {
        let (x, y, z) = (xs[i], ys[i], zs[i]);
        let px = r0 * x + r1 * y + r2 * z + tx;
        let py = r3 * x + r4 * y + r5 * z + ty;
        let pz = r6 * x + r7 * y + r8 * z + tz;
        if !(pz > MIN_WARPED_DEPTH) {
            continue;
        }
        let iz = 1.0 / pz;
        let u = params.fx * px * iz + params.cx;
        let v = params.fy * py * iz + params.cy;
        // Negated test so that NaN coordinates are rejected too.
        if !(u > 1.0 && v > 1.0 && u < umax && v < vmax) {
            continue;
        }
        let [c2, gxi, gyi] = frame.sample(u, v);
        let c1 = a * intensity[i] + b;
        let r = c1 - c2;

        // Robust statistics for the affine brightness fit of the next evaluation.
        let wa = f64::from(if r.abs() < AFFINE_HUBER {
            1.0
        } else {
            AFFINE_HUBER / r.abs()
        });
        let (c1d, c2d) = (f64::from(c1), f64::from(c2));
        sxx += wa * c1d * c1d;
        syy += wa * c2d * c2d;
        sx += wa * c1d;
        sy += wa * c2d;
        sw += wa;

        if r * r < max_diff_c + max_diff_g * (gxi * gxi + gyi * gyi) {
            out.good += 1;
        } else {
            out.bad += 1;
        }
        out.usage += f64::from((z * iz).min(1.0));

        let gx = params.fx * gxi;
        let gy = params.fy * gyi;
        let (g0, g1) = normalized_projection_idepth_derivative(px, py, pz, z, params.t);
        let drdd = gx * g0 + gy * g1;
        let w_p = 1.0 / (noise2 + var_weight * idepth_var[i] * drdd * drdd);
        let normalised = (r * w_p.sqrt()).abs();
        let w_h = if normalised < huber {
            1.0
        } else {
            huber / normalised
        };
        cost += f64::from(w_h * w_p * r * r);

        out.px.push(px);
        out.py.push(py);
        out.pz.push(pz);
        out.gx.push(gx);
        out.gy.push(gy);
        out.residual.push(r);
        out.weight.push(w_h * w_p);
    }
    let count = out.len();
    out.cost = if count > 0 {
        cost / count as f64
    } else {
        f64::INFINITY
    };
    // LSD-SLAM's fit: a = ratio of (robust) standard deviations, b matches the means.
    let var1 = sxx - sx * sx / sw;
    let var2 = syy - sy * sy / sw;
    let fit_a = (var2 / var1).sqrt();
    let fit_b = (sy - fit_a * sx) / sw;
    if fit_a.is_finite() && fit_b.is_finite() && fit_a > 0.0 {
        // The fit maps c1 = a·I + b (already corrected) to c2, so compose it with (a, b).
        // LSD-SLAM instead *replaces* (a, b) by this fit, which resets a correct estimate to
        // (1, 0) at every other evaluation; composing is the fixed point it intends.
        out.affine_estimate = Some((
            (fit_a * f64::from(a)) as f32,
            (fit_a * f64::from(b) + fit_b) as f32,
        ));
    }
}

/// `∂(x'/z', y'/z')/∂d`: how the normalised projection of a keyframe point moves with its
/// keyframe inverse depth `d = 1/z` (multiplied by the focal-scaled gradient it gives
/// `∂r/∂d` of eq. (13)). With `p' = R·q/d + t`, `∂p'/∂d = −(p' − t)/d`, hence
/// `∂(x'/z')/∂d = (tx·z' − tz·x')/(z'²·d)` (LSD-SLAM's `g0`, `g1`); `z = 1/d`.
#[inline(always)]
pub(crate) fn normalized_projection_idepth_derivative(
    px: f32,
    py: f32,
    pz: f32,
    z: f32,
    t: [f32; 3],
) -> (f32, f32) {
    let iz = 1.0 / pz;
    let s = z * iz * iz;
    ((t[0] * pz - t[2] * px) * s, (t[1] * pz - t[2] * py) * s)
}

/// Derivative of the frame intensity at the warped point, `∂I(π(exp(δ)·p'))/∂δ`, for a *left*
/// perturbation δ = (ρ, φ) of `frame_from_keyframe` (the residual's Jacobian is its negative).
///
/// `(px, py, pz)` is the warped point `p'` in frame coordinates and `(gx, gy)` the frame
/// gradient already multiplied by the focal lengths. With `∇I·∂π/∂p' = (a, b, c) =
/// (gx/z, gy/z, −(gx·x + gy·y)/z²)` and `∂p'/∂δ = [I | −p'^]` this is
/// `(a, b, c, c·y − b·z, a·z − c·x, b·x − a·y)`; depending only on `p'` makes it the cheap
/// form (LSD-SLAM's `calculateWarpUpdate`). Right-perturbation Jacobians follow with the
/// adjoint: `J_right = J_left · Ad(T)`.
#[inline(always)]
pub(crate) fn intensity_jacobian_left(px: f32, py: f32, pz: f32, gx: f32, gy: f32) -> [f32; 6] {
    let iz = 1.0 / pz;
    let a = gx * iz;
    let b = gy * iz;
    let c = -(gx * px + gy * py) * iz * iz;
    [a, b, c, c * py - b * pz, a * pz - c * px, b * px - a * py]
}

/// The normal equations `H = Σ w·vᵀv`, `g = Σ w·r·v` of the warped points in `buffers`
/// (left perturbation, `v` from [`intensity_jacobian_left`]); the Gauss–Newton step is
/// `δ = H⁻¹·g`, applied as `T ← exp(δ)·T`. Accumulated in `f64` so that tens of thousands
/// of terms lose no precision.
pub(crate) fn normal_equations(buffers: &WarpBuffers) -> (Matrix6<f64>, Vector6<f64>) {
    let mut h = [0.0f64; 21];
    let mut g = [0.0f64; 6];
    let n = buffers.len();
    let (px, py, pz) = (&buffers.px[..n], &buffers.py[..n], &buffers.pz[..n]);
    let (gx, gy) = (&buffers.gx[..n], &buffers.gy[..n]);
    let (res, wt) = (&buffers.residual[..n], &buffers.weight[..n]);
    for i in 0..n {
        let v = intensity_jacobian_left(px[i], py[i], pz[i], gx[i], gy[i]).map(f64::from);
        let w = f64::from(wt[i]);
        let wr = w * f64::from(res[i]);
        let mut k = 0;
        for r in 0..6 {
            let wv = w * v[r];
            for c in r..6 {
                h[k] += wv * v[c];
                k += 1;
            }
            g[r] += wr * v[r];
        }
    }
    let mut hm = Matrix6::zeros();
    let mut k = 0;
    for r in 0..6 {
        for c in r..6 {
            hm[(r, c)] = h[k];
            hm[(c, r)] = h[k];
            k += 1;
        }
    }
    (hm, Vector6::from(g))
}

/// `d(I(π(T·exp(δ)·p)))/dδ` for a right perturbation of `frame_from_keyframe` at keyframe point
/// `p`, given the frame gradient `grad` (per pixel, not yet scaled by the focal lengths) at
/// the warped pixel — the `f64` reference form of what the inner loop computes, used by the
/// pose-uncertainty code and checked against numeric differences in the tests.
pub fn intensity_jacobian_right(
    camera: &PinholeCamera,
    frame_from_keyframe: &SE3,
    point_keyframe: &Vector3<f64>,
    grad: (f64, f64),
) -> Vector6<f64> {
    let p = frame_from_keyframe.act(point_keyframe);
    let left = intensity_jacobian_left(
        p.x as f32,
        p.y as f32,
        p.z as f32,
        (camera.fx * grad.0) as f32,
        (camera.fy * grad.1) as f32,
    );
    let left = Vector6::from(left.map(f64::from));
    (left.transpose() * frame_from_keyframe.adjoint()).transpose()
}

/// Converts an information matrix of a left perturbation `exp(δ_L)·T` into that of the right
/// perturbation `T·exp(δ_R)`: `δ_L = Ad(T)·δ_R`, so `H_R = Ad(T)ᵀ·H_L·Ad(T)`.
pub(crate) fn left_to_right_information(t: &SE3, h_left: &Matrix6<f64>) -> Matrix6<f64> {
    let ad = t.adjoint();
    ad.transpose() * h_left * ad
}
