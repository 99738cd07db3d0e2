//! Two-view consistency and pose-uncertainty propagation (DeepRelativeFusion, Loo et al.
//! IROS 2021, §III-E "Pose-graph refinement", eqs. 14–16), CPU reference; the warp also runs
//! as a kernel ([`super::gpu_warp`]).
//!
//! # What it computes, per new keyframe `i`
//! 1. **Eq. 14**: the previous keyframe's filtered semi-dense map `D'_{i−1,semi}` and its
//!    densified map `D_{i−1,opt}` (its semi-dense pixels excluded, "to retain the semi-dense
//!    structure") are forward-warped into keyframe `i` with `S_{i−1→i}`
//!    ([`warp_inverse_depth_cpu`]).
//! 2. **Eq. 15**: a pixel of `D'_{i,semi}` (or, off the semi-dense pixels, of `D_{i,opt}`) is
//!    kept when it differs from the warped value by less than τe; the rest becomes 0.
//! 3. **Eq. 16**: the dense depth's variance is the keyframe pose's uncertainty propagated
//!    into each pixel's inverse depth, `V_opt = J_d Σ_ξ J_dᵀ` ([`pose_variance`]); semi-dense
//!    pixels keep the filter's variance `V'_semi`.
//!
//! # How the result refines the pose graph
//! The orchestration (`dense::layer`) passes
//! `to_depth_map(&result.idepth, &result.variance, kf_w, kf_h)` to
//! [`crate::graph::Backend::update_keyframe_depth`]. The back end swaps the keyframe's depth
//! map, rebuilds its per-level depth pyramid and reference points
//! ([`crate::graph::points::KeyframeLevels`]) and, at its next `process`, re-runs the reciprocal
//! Sim(3) test against every neighbour from the current relative pose; accepted pairs replace
//! the old edges and the graph is re-optimised. The Sim(3) alignment uses every pixel with an
//! estimate as a reference point (photometric residual plus depth residual, each weighted by the
//! inverse of its propagated variance), and reads the other keyframe's map at the warped
//! positions for the depth residual — so the dense, two-view consistent pixels add depth
//! constraints where the semi-dense map had none, and the per-pixel variances decide how much
//! each counts. The working-resolution map is upsampled 2× by nearest neighbour; the back end's
//! level-1 pyramid (where its alignment stops by default) then recovers the working map exactly
//! (tested below).
//!
//! # Gauge and threshold
//! All inverse depths are in the current keyframe's gauge (LSD-SLAM normalises each keyframe's
//! mean inverse depth to 1): `cur_from_prev` carries the scale between the two keyframes, so
//! the warped map is directly comparable. τe = 0.001 (§IV) is therefore 0.1 % of the mean
//! inverse depth: a relative depth error of τe·z (z in units of the mean depth), 0.1 % at the
//! mean depth, 100× stricter than the 10 % of the "correct depth" metric. It also bounds the
//! relative scale error of `cur_from_prev`: on the synthetic plane of the tests a 0.1 % scale
//! error already rejects a quarter of the pixels, 0.2 % all of them, and Gaussian noise of
//! 0.01 (1 % of the mean) on the current maps leaves ~8 % of the pixels consistent. The
//! nearest-pixel forward warp alone errs by up to half a
//! pixel times the inverse-depth gradient, which reaches τe on a surface whose inverse depth
//! changes by 0.002 per working pixel (at the mean depth, a plane inclined ~30° to the image
//! plane at 320×240, fx ≈ 260; nearer surfaces reach it at smaller inclinations): only
//! near-fronto-parallel, accurately reconstructed regions pass.

use nalgebra::{Matrix4, Vector2, Vector4};

use super::config::TwoViewParams;
use crate::geometry::{Matrix7, PinholeCamera, Sim3, Vector7};
use crate::image::ImageF32;
use crate::mapping::{DepthMap, InverseDepth};
use crate::{Error, Result};

/// A warped point must lie at least this far in front of the target camera (in the keyframe
/// gauge, where the mean depth is 1): nearer points would project to absurd inverse depths.
pub const MIN_WARP_DEPTH: f32 = 1e-3;

/// The f32 constants of one warp, shared by the CPU twin and the GPU uniform so that both start
/// from bit-identical inputs: `[sR | t]` of `dst_from_src`, intrinsics, reciprocal focal
/// lengths (back-projection multiplies, it does not divide).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct WarpMatrix {
    pub rows: [[f32; 4]; 3],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub fx_inv: f32,
    pub fy_inv: f32,
    pub min_depth: f32,
}

impl WarpMatrix {
    pub fn new(camera: &PinholeCamera, dst_from_src: &Sim3) -> Self {
        let m = dst_from_src.matrix();
        let row = |r: usize| {
            [
                m[(r, 0)] as f32,
                m[(r, 1)] as f32,
                m[(r, 2)] as f32,
                m[(r, 3)] as f32,
            ]
        };
        Self {
            rows: [row(0), row(1), row(2)],
            fx: camera.fx as f32,
            fy: camera.fy as f32,
            cx: camera.cx as f32,
            cy: camera.cy as f32,
            fx_inv: (1.0 / camera.fx) as f32,
            fy_inv: (1.0 / camera.fy) as f32,
            min_depth: MIN_WARP_DEPTH,
        }
    }

    /// Warps source pixel `(x, y)` with inverse depth `d`: the target pixel index and the
    /// warped inverse depth, or `None` (invalid `d`, too near / behind the camera, outside).
    /// The f32 operations and their order are those of `two_view_warp.wgsl`.
    #[inline]
    fn warp_pixel(
        &self,
        x: usize,
        y: usize,
        d: f32,
        width: usize,
        height: usize,
    ) -> Option<(usize, f32)> {
        if !(d > 0.0 && d <= f32::MAX) {
            return None;
        }
        let xn = (x as f32 - self.cx) * self.fx_inv;
        let yn = (y as f32 - self.cy) * self.fy_inv;
        let [r0, r1, r2] = self.rows;
        let qx = ((r0[0] * xn + r0[1] * yn) + r0[2]) + r0[3] * d;
        let qy = ((r1[0] * xn + r1[1] * yn) + r1[2]) + r1[3] * d;
        let qz = ((r2[0] * xn + r2[1] * yn) + r2[2]) + r2[3] * d;
        // z' = qz/d > min_depth without dividing (d > 0); a NaN fails too.
        if qz.is_nan() || qz <= self.min_depth * d {
            return None;
        }
        let inv = 1.0 / qz;
        let u = self.fx * (qx * inv) + self.cx;
        let v = self.fy * (qy * inv) + self.cy;
        // Nearest pixel, halves rounded up (as the kernel's floor(u + 0.5)).
        let (ur, vr) = ((u + 0.5).floor(), (v + 0.5).floor());
        if !(ur >= 0.0 && vr >= 0.0 && ur <= (width - 1) as f32 && vr <= (height - 1) as f32) {
            return None;
        }
        let warped = d * inv;
        if !(warped > 0.0 && warped <= f32::MAX) {
            return None;
        }
        Some((vr as usize * width + ur as usize, warped))
    }
}

/// Fails unless `src` (and `exclude`) have the camera's size.
pub(crate) fn check_warp_inputs(
    src: &ImageF32,
    exclude: Option<&ImageF32>,
    camera: &PinholeCamera,
) -> Result<()> {
    src.check_size()?;
    let size = (camera.width as usize, camera.height as usize);
    if (src.width, src.height) != size {
        return Err(Error::Shape(format!(
            "two-view warp: map {}x{}, camera {}x{}",
            src.width, src.height, size.0, size.1
        )));
    }
    if let Some(ex) = exclude {
        ex.check_size()?;
        if (ex.width, ex.height) != size {
            return Err(Error::Shape(format!(
                "two-view warp: exclusion mask {}x{}, map {}x{}",
                ex.width, ex.height, size.0, size.1
            )));
        }
    }
    Ok(())
}

/// Warps an inverse-depth map into another view (eq. 14's warp): the CPU reference
/// ([`CpuWarp`]) or its GPU twin (`gpu_warp::GpuWarp`); the dense layer picks one.
pub trait InverseDepthWarp {
    fn warp(
        &self,
        src: &ImageF32,
        exclude: Option<&ImageF32>,
        camera: &PinholeCamera,
        dst_from_src: &Sim3,
    ) -> Result<ImageF32>;
}

/// The CPU reference warp ([`warp_inverse_depth_cpu`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuWarp;

impl InverseDepthWarp for CpuWarp {
    fn warp(
        &self,
        src: &ImageF32,
        exclude: Option<&ImageF32>,
        camera: &PinholeCamera,
        dst_from_src: &Sim3,
    ) -> Result<ImageF32> {
        warp_inverse_depth_cpu(src, exclude, camera, dst_from_src)
    }
}

/// Eq. 14: forward-warps `src` (inverse depth, 0 = none; pixels where `exclude` > 0 are
/// skipped) into the other view of the same `camera`. Each valid source pixel is
/// back-projected at depth 1/d, moved by `dst_from_src` and projected; it lands on the nearest
/// pixel (halves rounded up). Where several land on one pixel the nearest surface (largest
/// inverse depth) wins; 0 = nothing landed (or only points behind / within
/// [`MIN_WARP_DEPTH`] of the camera). Non-finite and non-positive source values are skipped.
///
/// This is the CPU twin of `two_view_warp.wgsl` (same f32 operations in the same order).
/// Fails when a map's size differs from the camera's.
pub fn warp_inverse_depth_cpu(
    src: &ImageF32,
    exclude: Option<&ImageF32>,
    camera: &PinholeCamera,
    dst_from_src: &Sim3,
) -> Result<ImageF32> {
    check_warp_inputs(src, exclude, camera)?;
    let (w, h) = (src.width, src.height);
    let m = WarpMatrix::new(camera, dst_from_src);
    let mut out = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if exclude.is_some_and(|ex| ex.data[i] > 0.0) {
                continue;
            }
            if let Some((j, warped)) = m.warp_pixel(x, y, src.data[i], w, h)
                && warped > out.data[j]
            {
                out.data[j] = warped;
            }
        }
    }
    Ok(out)
}

/// `J_d`, the 1×7 derivative of pixel `(x, y)`'s inverse depth `d` under a right perturbation
/// of the keyframe pose, `world_from_keyframe ← world_from_keyframe · exp(δ)`, δ = (ρ, φ, σ)
/// as in [`Sim3`].
///
/// Derivation: the pixel's point `p = (xn, yn, 1)/d` (normalised coordinates `xn = (x−cx)/fx`,
/// `yn = (y−cy)/fy`) is a fixed point of the world; after the perturbation the keyframe sees it
/// at `p' = exp(δ)⁻¹·p ≈ p − (ρ + φ×p + σ·p)`, i.e. `∂p'/∂δ = −[I, −p^, p]`
/// (= −[`Sim3::act_jacobian`] at the identity). With `d' = 1/p'_z`,
/// `∂d'/∂p' = (0, 0, −d²)`, so
///
/// `J_d = d²·(0, 0, 1, p_y, −p_x, 0, p_z) = (0, 0, d², d·yn, −d·xn, 0, d)`.
///
/// A left perturbation of `keyframe_from_world` (`exp(δ)·T_kw`, the same tangent space) gives
/// `−J_d`, hence the same variance. The Σ_ξ it is used with must be the covariance of this
/// perturbation: the inverse of a right-perturbation information such as the pose graph's and
/// the Sim(3) tracker's (e.g. of the keyframe's parent edge, `parent_from_keyframe·exp(δ)`).
pub fn idepth_pose_jacobian(camera: &PinholeCamera, x: f64, y: f64, d: f64) -> Vector7 {
    let n = camera.pixel_to_normalized(&Vector2::new(x, y));
    Vector7::from_column_slice(&[0.0, 0.0, d * d, d * n.y, -d * n.x, 0.0, d])
}

/// Eq. 16: `V_opt(x) = J_d Σ J_dᵀ` at every pixel with a positive finite `idepth` (0
/// elsewhere), `J_d` from [`idepth_pose_jacobian`] and Σ the 7×7 covariance of a right
/// perturbation of the keyframe pose, tangent order (ρ, φ, σ). Computed in f64; the output has
/// `idepth`'s size, and `camera` must be the camera of that resolution (only its intrinsics are
/// read).
pub fn pose_variance(idepth: &ImageF32, camera: &PinholeCamera, covariance: &Matrix7) -> ImageF32 {
    // J_d is zero in ρx, ρy and φz (moving sideways or rolling about the optical axis leaves a
    // point's depth alone), so only the 4×4 block of Σ on (ρz, φx, φy, σ) matters. Σ is used
    // symmetrised: a covariance that went through an inverse may be asymmetric in its last bits.
    const NONZERO: [usize; 4] = [2, 3, 4, 6];
    let block = Matrix4::from_fn(|r, c| {
        0.5 * (covariance[(NONZERO[r], NONZERO[c])] + covariance[(NONZERO[c], NONZERO[r])])
    });
    let (fx_inv, fy_inv) = (1.0 / camera.fx, 1.0 / camera.fy);
    let width = idepth.width.max(1);
    let data = idepth
        .data
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            if !(d > 0.0 && d.is_finite()) {
                return 0.0;
            }
            let d = f64::from(d);
            let xn = ((i % width) as f64 - camera.cx) * fx_inv;
            let yn = ((i / width) as f64 - camera.cy) * fy_inv;
            // The non-zero entries of idepth_pose_jacobian, in NONZERO's order.
            let j = Vector4::new(d * d, d * yn, -d * xn, d);
            j.dot(&(block * j)) as f32
        })
        .collect();
    ImageF32 {
        width: idepth.width,
        height: idepth.height,
        data,
    }
}

/// The maps eqs. 14–16 read, all at the working resolution of `camera` and in the current
/// keyframe's gauge (0 = no value).
#[derive(Clone, Copy, Debug)]
pub struct TwoViewInputs<'a> {
    /// Undistorted pinhole camera at the working resolution (the same for both keyframes).
    pub camera: &'a PinholeCamera,
    /// `D'_{i−1,semi}`, the previous keyframe's filtered semi-dense inverse depth.
    pub prev_semi: &'a ImageF32,
    /// `D_{i−1,opt}`, the previous keyframe's densified inverse depth.
    pub prev_dense: &'a ImageF32,
    /// `D'_{i,semi}` and `V'_{i,semi}` of the current keyframe.
    pub cur_semi: &'a ImageF32,
    pub cur_semi_var: &'a ImageF32,
    /// `D_{i,opt}` of the current keyframe.
    pub cur_dense: &'a ImageF32,
    /// `S_{i−1→i}`: previous-keyframe coordinates → current-keyframe coordinates, scale
    /// included, so that warped inverse depths are in the current keyframe's gauge.
    pub cur_from_prev: Sim3,
    /// Σ_ξ,i, covariance of a right perturbation of the current keyframe's pose, tangent order
    /// (ρ, φ, σ) (see [`idepth_pose_jacobian`]).
    pub pose_covariance: Matrix7,
}

/// The two-view consistent depth of the current keyframe.
#[derive(Clone, Debug, PartialEq)]
pub struct TwoViewResult {
    /// `D_{i,c}` (eq. 15): consistent semi-dense and dense pixels, 0 elsewhere.
    pub idepth: ImageF32,
    /// `V_{i,c}`: `V'_semi` on the kept semi-dense pixels, `V_opt` on the kept dense ones, 0
    /// where `idepth` is 0.
    pub variance: ImageF32,
    /// `V_{i,opt}` (eq. 16) at every pixel with `D_opt > 0`.
    pub dense_variance: ImageF32,
    /// Kept pixels of each kind.
    pub consistent_semi: usize,
    pub consistent_dense: usize,
}

/// Eqs. 14–16. Semi-dense pixels of the current keyframe (`cur_semi > 0`) are kept where
/// `|D'_semi − warp(prev_semi)| < τe`; the remaining pixels with `D_opt > 0` are kept where
/// `|D_opt − warp(prev_dense without prev's semi-dense pixels)| < τe`. A pixel nothing was
/// warped onto is not kept (no evidence of consistency). `warp` does the warps (CPU or GPU).
/// Fails when a map's size differs from the camera's.
///
/// A kept pixel whose variance is not positive (a semi-dense pixel without a variance, or
/// Σ = 0) stays in `idepth` but [`to_depth_map`] leaves it out: the back end cannot weigh it.
pub fn two_view_consistency(
    inputs: &TwoViewInputs,
    params: &TwoViewParams,
    warp: &dyn InverseDepthWarp,
) -> Result<TwoViewResult> {
    let camera = inputs.camera;
    for map in [
        inputs.prev_semi,
        inputs.prev_dense,
        inputs.cur_semi,
        inputs.cur_semi_var,
        inputs.cur_dense,
    ] {
        check_warp_inputs(map, None, camera)?;
    }
    let pose = &inputs.cur_from_prev;
    let warped_semi = warp.warp(inputs.prev_semi, None, camera, pose)?;
    let warped_dense = warp.warp(inputs.prev_dense, Some(inputs.prev_semi), camera, pose)?;
    let dense_variance = pose_variance(inputs.cur_dense, camera, &inputs.pose_covariance);

    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut idepth = ImageF32::filled(w, h, 0.0);
    let mut variance = ImageF32::filled(w, h, 0.0);
    let (mut consistent_semi, mut consistent_dense) = (0, 0);
    let consistent = |d: f32, warped: f32| warped > 0.0 && (d - warped).abs() < params.tau_e;
    for i in 0..w * h {
        let semi = inputs.cur_semi.data[i];
        if semi > 0.0 && semi.is_finite() {
            if consistent(semi, warped_semi.data[i]) {
                idepth.data[i] = semi;
                variance.data[i] = inputs.cur_semi_var.data[i];
                consistent_semi += 1;
            }
            continue;
        }
        let dense = inputs.cur_dense.data[i];
        if dense > 0.0 && dense.is_finite() && consistent(dense, warped_dense.data[i]) {
            idepth.data[i] = dense;
            variance.data[i] = dense_variance.data[i];
            consistent_dense += 1;
        }
    }
    Ok(TwoViewResult {
        idepth,
        variance,
        dense_variance,
        consistent_semi,
        consistent_dense,
    })
}

/// Upsamples a working-resolution `(idepth, variance)` pair to the keyframe's full resolution
/// `width × height` as the [`DepthMap`] [`crate::graph::Backend::update_keyframe_depth`] takes:
/// nearest neighbour, full-resolution pixel `X` taking working pixel `⌊(X + ½)·w/W⌋` (for a
/// 2× ratio, the 2×2 block of pixel `x` is `2x, 2x+1`, the inverse of the pyramid's 2×2
/// average). A pixel is [`InverseDepth::Estimate`] where `idepth > 0` and `variance > 0`, both
/// finite, and [`InverseDepth::Unknown`] elsewhere.
pub fn to_depth_map(
    idepth: &ImageF32,
    variance: &ImageF32,
    width: usize,
    height: usize,
) -> Result<DepthMap> {
    idepth.check_size()?;
    variance.check_size()?;
    if (idepth.width, idepth.height) != (variance.width, variance.height) {
        return Err(Error::Shape(format!(
            "inverse depth {}x{}, variance {}x{}",
            idepth.width, idepth.height, variance.width, variance.height
        )));
    }
    if idepth.width == 0 || idepth.height == 0 || width == 0 || height == 0 {
        return Err(Error::Shape(format!(
            "cannot upsample {}x{} to {width}x{height}",
            idepth.width, idepth.height
        )));
    }
    let (w, h) = (idepth.width, idepth.height);
    let source =
        |full: usize, n_full: usize, n: usize| ((2 * full + 1) * n / (2 * n_full)).min(n - 1);
    let columns: Vec<usize> = (0..width).map(|x| source(x, width, w)).collect();
    let mut map = DepthMap::unknown(width, height);
    for y in 0..height {
        let row = source(y, height, h) * w;
        for (x, &col) in columns.iter().enumerate() {
            let (d, v) = (idepth.data[row + col], variance.data[row + col]);
            if d > 0.0 && d.is_finite() && v > 0.0 && v.is_finite() {
                map.pixels[y * width + x] = InverseDepth::Estimate { idepth: d, var: v };
            }
        }
    }
    Ok(map)
}

/// Relative standard deviation given to sensor inverse depths in the ground-truth refinement
/// baseline: about a Kinect-class sensor's at 1–2 m (the weight matters: docs/tuning.md,
/// "Ground-truth refinement").
pub const SENSOR_DEPTH_REL_SD: f32 = 0.02;

/// Sensor depths nearer than this (metres) are not used (below a structured-light sensor's
/// range, and 0 means none).
pub const MIN_SENSOR_DEPTH: f32 = 0.1;

/// Fewest pixels with both a semi-dense estimate and a sensor depth for the gauge ratio.
pub const MIN_GAUGE_PIXELS: usize = 100;

/// The sensor depth `depth` (metres, same size as `semidense`) as an inverse-depth map in the
/// keyframe's gauge, for the ground-truth refinement baseline
/// ([`super::config::TwoViewParams::ground_truth_depth`]): `ρ = k / d` at every pixel with a
/// measurement, `k` the median of `ρ_semi · d` over the pixels that have both (so the map keeps
/// the keyframe's scale and only its shape comes from the sensor), variance
/// `(SENSOR_DEPTH_REL_SD · ρ)²`. `None` when fewer than [`MIN_GAUGE_PIXELS`] pixels have both.
pub fn sensor_depth_map(semidense: &DepthMap, depth: &ImageF32) -> Result<Option<DepthMap>> {
    if (depth.width, depth.height) != (semidense.width, semidense.height)
        || depth.data.len() != semidense.pixels.len()
    {
        return Err(Error::Shape(format!(
            "sensor depth {}x{}, keyframe map {}x{}",
            depth.width, depth.height, semidense.width, semidense.height
        )));
    }
    let usable = |d: f32| d.is_finite() && d >= MIN_SENSOR_DEPTH;
    let mut ratios: Vec<f32> = semidense
        .pixels
        .iter()
        .zip(&depth.data)
        .filter_map(|(p, &d)| Some(p.estimate()?.0 * d).filter(|_| usable(d)))
        .collect();
    if ratios.len() < MIN_GAUGE_PIXELS {
        return Ok(None);
    }
    let mid = ratios.len() / 2;
    let k = *ratios.select_nth_unstable_by(mid, f32::total_cmp).1;
    let mut map = DepthMap::unknown(semidense.width, semidense.height);
    for (p, &d) in map.pixels.iter_mut().zip(&depth.data) {
        if usable(d) {
            let idepth = k / d;
            let sd = SENSOR_DEPTH_REL_SD * idepth;
            *p = InverseDepth::Estimate {
                idepth,
                var: sd * sd,
            };
        }
    }
    Ok(Some(map))
}

#[cfg(test)]
#[path = "two_view_tests.rs"]
pub(crate) mod tests;
