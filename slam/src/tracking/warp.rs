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
    fn sample(&self, u: f32, v: f32) -> [f32; 4] {
        let (x0, y0) = (u as usize, v as usize);
        let (fx, fy) = (u - x0 as f32, v - y0 as f32);
        let i = y0 * self.width + x0;
        let (p00, p10) = (self.data[i], self.data[i + 1]);
        let (p01, p11) = (self.data[i + self.width], self.data[i + self.width + 1]);
        // All four lanes (the last is padding) so that the compiler can use one vector op.
        let mut out = [0.0f32; 4];
        for k in 0..4 {
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
    /// Photometric residual `c1 − c2`, `c1 = a·I_ref + b`, `c2 = I_frame(π(T·p))`.
    pub residual: Vec<f32>,
    /// Frame intensity `c2` at the warped pixel.
    pub frame_intensity: Vec<f32>,
    /// Depth of the point in the keyframe (`1/d`).
    pub ref_depth: Vec<f32>,
    /// Variance of the keyframe inverse depth `d`.
    pub idepth_var: Vec<f32>,
    /// Combined weight `w_huber / σ_r²`.
    pub weight: Vec<f32>,
    /// Points that passed LSD's good-residual test.
    pub good: usize,
    /// Warped points that failed it.
    pub bad: usize,
    /// `Σ min(1, z_ref / z_frame)` over warped points (LSD-SLAM `pointUsage` numerator: a
    /// point seen from farther away covers fewer pixels and counts less).
    pub usage: f64,
    /// Mean of `w_huber · r² / σ_r²` over the warped points: the cost LM decreases.
    pub cost: f64,
    /// Affine brightness `(a, b)` fitted to this evaluation's intensity pairs, if defined.
    pub affine_estimate: Option<(f32, f32)>,
}

impl WarpBuffers {
    fn columns(&mut self) -> [&mut Vec<f32>; 10] {
        [
            &mut self.px,
            &mut self.py,
            &mut self.pz,
            &mut self.gx,
            &mut self.gy,
            &mut self.residual,
            &mut self.frame_intensity,
            &mut self.ref_depth,
            &mut self.idepth_var,
            &mut self.weight,
        ]
    }

    /// Number of warped points.
    pub fn len(&self) -> usize {
        self.residual.len()
    }

    /// Whether no point landed in the image.
    pub fn is_empty(&self) -> bool {
        self.residual.is_empty()
    }

    /// Pearson correlation of the reference intensities `c1 = r + c2` and the frame
    /// intensities `c2` over the warped points; 0 when undefined. Near 1 when the frame shows
    /// the keyframe's edges where the pose puts them, near 0 for an unrelated image. Plain,
    /// not Huber-weighted: robust weights favour the pairs that already agree and would
    /// inflate it for unrelated images.
    pub fn correlation(&self) -> f32 {
        let n = self.len();
        if n < 2 {
            return 0.0;
        }
        let (mut m1, mut m2, mut m11, mut m22, mut m12) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for (&r, &c2) in self.residual.iter().zip(&self.frame_intensity) {
            let (c1, c2) = (f64::from(r + c2), f64::from(c2));
            m1 += c1;
            m2 += c2;
            m11 += c1 * c1;
            m22 += c2 * c2;
            m12 += c1 * c2;
        }
        let nf = n as f64;
        let cov = m12 - m1 * m2 / nf;
        let v1 = m11 - m1 * m1 / nf;
        let v2 = m22 - m2 * m2 / nf;
        let rho = cov / (v1 * v2).sqrt();
        if rho.is_finite() { rho as f32 } else { 0.0 }
    }
}

/// Warps every reference point with `params`, samples the frame, and fills `out` with the
/// residuals, their weights and the statistics (LSD-SLAM `calcResidualAndBuffers` followed by
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
    step: usize,
    out: &mut WarpBuffers,
) {
    warp_points(reference, frame, params, step, out);
    weigh(params, config, out);
}

/// Pass 1: warp, project, keep the points inside the image (compacted), sample the frame.
/// Only every `step`-th reference point is used (1 = all; see
/// [`TrackingConfig::level0_point_step`]).
pub(crate) fn warp_points(
    reference: &ReferenceLevel,
    frame: &InterleavedLevel,
    params: &WarpParams,
    step: usize,
    out: &mut WarpBuffers,
) {
    let n = reference.len();
    let step = step.max(1);
    let used = n.div_ceil(step);
    for v in out.columns() {
        v.resize(used, 0.0); // no allocation once the buffers have grown
    }
    let [r0, r1, r2, r3, r4, r5, r6, r7, r8] = params.r;
    let [tx, ty, tz] = params.t;
    let (umax, vmax) = (frame.width as f32 - 2.0, frame.height as f32 - 2.0);
    let (a, b) = (params.affine_a, params.affine_b);
    let (xs, ys, zs) = (&reference.x[..n], &reference.y[..n], &reference.z[..n]);
    let (intensity, idepth_var) = (&reference.intensity[..n], &reference.idepth_var[..n]);
    let (o_px, o_py, o_pz) = (
        &mut out.px[..used],
        &mut out.py[..used],
        &mut out.pz[..used],
    );
    let (o_gx, o_gy) = (&mut out.gx[..used], &mut out.gy[..used]);
    let (o_res, o_c2) = (&mut out.residual[..used], &mut out.frame_intensity[..used]);
    let (o_z, o_var) = (&mut out.ref_depth[..used], &mut out.idepth_var[..used]);
    let mut idx = 0usize;
    for i in (0..n).step_by(step) {
        let (x, y, z) = (xs[i], ys[i], zs[i]);
        let px = r0 * x + r1 * y + r2 * z + tx;
        let py = r3 * x + r4 * y + r5 * z + ty;
        let pz = r6 * x + r7 * y + r8 * z + tz;
        // (A NaN depth gives NaN pixel coordinates, rejected below.)
        if pz <= MIN_WARPED_DEPTH {
            continue;
        }
        let iz = 1.0 / pz;
        let u = params.fx * px * iz + params.cx;
        let v = params.fy * py * iz + params.cy;
        // Negated test so that NaN coordinates are rejected too.
        if !(u > 1.0 && v > 1.0 && u < umax && v < vmax) {
            continue;
        }
        let [c2, gx, gy, _] = frame.sample(u, v);
        o_px[idx] = px;
        o_py[idx] = py;
        o_pz[idx] = pz;
        o_gx[idx] = params.fx * gx;
        o_gy[idx] = params.fy * gy;
        o_res[idx] = a * intensity[i] + b - c2;
        o_c2[idx] = c2;
        o_z[idx] = z;
        o_var[idx] = idepth_var[i];
        idx += 1;
    }
    for v in out.columns() {
        v.truncate(idx);
    }
}

/// Lanes processed together by [`weigh`] (two SSE or one AVX register per quantity), so that
/// the sums vectorise without reassociating floating-point additions.
const LANES: usize = 8;

/// Chunks of [`LANES`] points summed in `f32` before being flushed into `f64` (256 points:
/// 255²·256 ≈ 1.7e7 keeps `f32` sums accurate, and nothing is lost over 10⁵ points).
const CHUNKS_PER_FLUSH: usize = 32;

/// Per-lane partial sums of [`weigh`].
#[derive(Clone, Copy, Debug, Default)]
struct LaneSums {
    cost: [f32; LANES],
    good: [f32; LANES],
    usage: [f32; LANES],
    // Huber-weighted moments of (c1, c2) for the affine brightness fit.
    sxx: [f32; LANES],
    syy: [f32; LANES],
    sx: [f32; LANES],
    sy: [f32; LANES],
    sw: [f32; LANES],
}

impl LaneSums {
    fn fields_mut(&mut self) -> [&mut [f32; LANES]; 8] {
        [
            &mut self.cost,
            &mut self.good,
            &mut self.usage,
            &mut self.sxx,
            &mut self.syy,
            &mut self.sx,
            &mut self.sy,
            &mut self.sw,
        ]
    }

    fn flush(&mut self, total: &mut [f64; 8]) {
        for (t, lanes) in total.iter_mut().zip(self.fields_mut()) {
            *t += lanes.iter().map(|&v| f64::from(v)).sum::<f64>();
            *lanes = [0.0; LANES];
        }
    }
}

/// Constants of the per-point weight computation.
#[derive(Clone, Copy, Debug)]
struct WeighParams {
    t: [f32; 3],
    noise2: f32,
    var_weight: f32,
    huber: f32,
    max_diff_c: f32,
    /// `max_diff_grad_mult` divided by the squared focal lengths (the stored gradients are
    /// focal-scaled; the good-point test uses per-pixel gradients).
    max_diff_gx: f32,
    max_diff_gy: f32,
}

/// Weights, cost, good flags, usage and affine-fit moments of [`LANES`] warped points, written
/// lane-wise (one short loop per operation) so that LLVM turns each loop into vector
/// instructions. Inputs: `[px, py, pz, gx, gy, r, c2, z_ref, var]`.
#[inline(always)]
fn weigh_lanes(k: &WeighParams, sums: &mut LaneSums, v: [&[f32; LANES]; 9], w: &mut [f32; LANES]) {
    let [px, py, pz, gx, gy, r, c2, z, var] = v;
    let mut sigma2 = [0.0f32; LANES];
    for l in 0..LANES {
        let (g0, g1) = normalized_projection_idepth_derivative(px[l], py[l], pz[l], z[l], k.t);
        let drdd = gx[l] * g0 + gy[l] * g1;
        sigma2[l] = k.noise2 + k.var_weight * var[l] * drdd * drdd;
    }
    for l in 0..LANES {
        // Huber on r/σ: w_h = min(1, huber·σ/|r|) (r = 0 gives +∞ → 1).
        let w_h = (k.huber * sigma2[l].sqrt() / r[l].abs()).min(1.0);
        w[l] = w_h / sigma2[l];
        sums.cost[l] += w[l] * r[l] * r[l];
    }
    for l in 0..LANES {
        let threshold =
            k.max_diff_c + k.max_diff_gx * gx[l] * gx[l] + k.max_diff_gy * gy[l] * gy[l];
        sums.good[l] += if r[l] * r[l] < threshold { 1.0 } else { 0.0 };
        sums.usage[l] += (z[l] / pz[l]).min(1.0);
    }
    for l in 0..LANES {
        let c1 = r[l] + c2[l];
        let wa = AFFINE_HUBER / r[l].abs().max(AFFINE_HUBER);
        sums.sxx[l] += wa * c1 * c1;
        sums.syy[l] += wa * c2[l] * c2[l];
        sums.sx[l] += wa * c1;
        sums.sy[l] += wa * c2[l];
        sums.sw[l] += wa;
    }
}

/// Pass 2 (vectorisable): weights, cost and statistics of the warped points.
pub(crate) fn weigh(params: &WarpParams, config: &TrackingConfig, out: &mut WarpBuffers) {
    let ph = &config.photometric;
    let k = WeighParams {
        t: params.t,
        noise2: ph.camera_pixel_noise2 as f32,
        var_weight: ph.var_weight as f32,
        huber: 0.5 * ph.huber_d as f32,
        max_diff_c: ph.max_diff_constant as f32,
        max_diff_gx: ph.max_diff_grad_mult as f32 / (params.fx * params.fx),
        max_diff_gy: ph.max_diff_grad_mult as f32 / (params.fy * params.fy),
    };
    let m = out.len();
    let mut sums = LaneSums::default();
    let mut total = [0.0f64; 8];
    let (px, px_rest) = out.px.as_chunks::<LANES>();
    let (py, py_rest) = out.py.as_chunks::<LANES>();
    let (pz, pz_rest) = out.pz.as_chunks::<LANES>();
    let (gx, gx_rest) = out.gx.as_chunks::<LANES>();
    let (gy, gy_rest) = out.gy.as_chunks::<LANES>();
    let (res, res_rest) = out.residual.as_chunks::<LANES>();
    let (c2, c2_rest) = out.frame_intensity.as_chunks::<LANES>();
    let (z, z_rest) = out.ref_depth.as_chunks::<LANES>();
    let (var, var_rest) = out.idepth_var.as_chunks::<LANES>();
    let (w, w_rest) = out.weight.as_chunks_mut::<LANES>();
    for c in 0..w.len() {
        weigh_lanes(
            &k,
            &mut sums,
            [
                &px[c], &py[c], &pz[c], &gx[c], &gy[c], &res[c], &c2[c], &z[c], &var[c],
            ],
            &mut w[c],
        );
        if c % CHUNKS_PER_FLUSH == CHUNKS_PER_FLUSH - 1 {
            sums.flush(&mut total);
        }
    }
    // The last partial chunk, padded with zero-weight dummies (r = 0, c2 = 0, pz = z = 1).
    let rest = w_rest.len();
    if rest > 0 {
        let pad = |src: &[f32], fill: f32| {
            let mut a = [fill; LANES];
            a[..rest].copy_from_slice(src);
            a
        };
        let mut wpad = [0.0f32; LANES];
        let mut tail = LaneSums::default();
        weigh_lanes(
            &k,
            &mut tail,
            [
                &pad(px_rest, 0.0),
                &pad(py_rest, 0.0),
                &pad(pz_rest, 1.0),
                &pad(gx_rest, 0.0),
                &pad(gy_rest, 0.0),
                &pad(res_rest, 0.0),
                &pad(c2_rest, 0.0),
                &pad(z_rest, 1.0),
                &pad(var_rest, 0.0),
            ],
            &mut wpad,
        );
        w_rest.copy_from_slice(&wpad[..rest]);
        // Only the real lanes count.
        for field in tail.fields_mut() {
            for v in &mut field[rest..] {
                *v = 0.0;
            }
        }
        tail.flush(&mut total);
    }
    sums.flush(&mut total);
    let [cost, good, usage, sxx, syy, sx, sy, sw] = total;
    out.good = good as usize;
    out.bad = m - out.good;
    out.usage = usage;
    out.cost = if m > 0 {
        cost / m as f64
    } else {
        f64::INFINITY
    };
    out.affine_estimate = None;
    // LSD-SLAM's affine fit c2 ≈ α·c1 + β: α is the ratio of the robust standard deviations,
    // β matches the means.
    let alpha = ((syy - sy * sy / sw) / (sxx - sx * sx / sw)).sqrt();
    let beta = (sy - alpha * sx) / sw;
    if alpha.is_finite() && beta.is_finite() && alpha > 0.0 {
        // The fit maps c1 = a·I + b (already corrected) to c2, so compose it with (a, b).
        // LSD-SLAM instead *replaces* (a, b) by this fit, which resets a correct estimate to
        // (1, 0) at every other evaluation; composing is the fixed point it intends.
        let (a, b) = (f64::from(params.affine_a), f64::from(params.affine_b));
        out.affine_estimate = Some(((alpha * a) as f32, (alpha * b + beta) as f32));
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
/// `δ = H⁻¹·g`, applied as `T ← exp(δ)·T`. Accumulated in `f64` (27 distinct sums) so that
/// tens of thousands of terms lose no precision; lane-wise `f32` variants measured no faster.
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
        for (r, &vr) in v.iter().enumerate() {
            let wv = w * vr;
            for &vc in &v[r..] {
                h[k] += wv * vc;
                k += 1;
            }
            g[r] += wr * vr;
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
