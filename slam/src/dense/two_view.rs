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
use super::gpu_warp::GpuWarp;
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
/// warped onto is not kept (no evidence of consistency). The warps run on the GPU when `gpu` is
/// given, else on the CPU. Fails when a map's size differs from the camera's.
///
/// A kept pixel whose variance is not positive (a semi-dense pixel without a variance, or
/// Σ = 0) stays in `idepth` but [`to_depth_map`] leaves it out: the back end cannot weigh it.
pub fn two_view_consistency(
    inputs: &TwoViewInputs,
    params: &TwoViewParams,
    gpu: Option<&GpuWarp>,
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
    let warp = |src: &ImageF32, exclude: Option<&ImageF32>| match gpu {
        Some(g) => g.warp(src, exclude, camera, pose),
        None => warp_inverse_depth_cpu(src, exclude, camera, pose),
    };
    let warped_semi = warp(inputs.prev_semi, None)?;
    let warped_dense = warp(inputs.prev_dense, Some(inputs.prev_semi))?;
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
/// baseline: about a Kinect-class sensor's at 1–2 m. The weight matters: on 7-Scenes
/// redkitchen (deterministic, sensor depth on the semi-dense pixels only) 2 % gave a
/// trajectory ATE of 0.020 m, 30 % 0.031 m.
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
pub(crate) mod tests {
    use super::*;
    use crate::frame::Frame;
    use crate::geometry::SO3;
    use crate::gpu::{GpuConfig, GpuContext};
    use crate::graph::points::KeyframeLevels;
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use std::sync::Arc;

    fn camera(w: u32, h: u32, f: f64) -> PinholeCamera {
        PinholeCamera::new(
            f,
            f,
            0.5 * (f64::from(w) - 1.0),
            0.5 * (f64::from(h) - 1.0),
            w,
            h,
        )
        .expect("valid camera")
    }

    /// Inverse depth of the plane `n·p = 1` seen by `camera`: `d(x) = n·K⁻¹x̃`.
    fn plane_idepth(camera: &PinholeCamera, n: &Vector3<f64>) -> ImageF32 {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut out = ImageF32::filled(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let q = camera.pixel_to_normalized(&Vector2::new(x as f64, y as f64));
                *out.at_mut(x, y) = (n.x * q.x + n.y * q.y + n.z) as f32;
            }
        }
        out
    }

    /// The plane `n·p = 1` of the source frame in the target frame of `dst_from_src`.
    fn moved_plane(n: &Vector3<f64>, dst_from_src: &Sim3) -> Vector3<f64> {
        let rn = dst_from_src.rotation.act(n);
        rn / (dst_from_src.scale + rn.dot(&dst_from_src.translation))
    }

    /// Inverse depths in [0.3, 3] (the keyframe gauge has mean 1) with `holes` of them 0.
    pub(crate) fn random_idepth(w: usize, h: usize, holes: f64, rng: &mut impl Rng) -> ImageF32 {
        let data = (0..w * h)
            .map(|_| {
                if rng.random_bool(holes) {
                    0.0
                } else {
                    rng.random_range(0.3f32..3.0)
                }
            })
            .collect();
        ImageF32::from_vec(w, h, data).expect("sizes match")
    }

    #[test]
    fn identity_warp_returns_the_input() {
        let cam = camera(97, 33, 80.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let mut src = random_idepth(97, 33, 0.3, &mut rng);
        src.data[0] = f32::NAN;
        src.data[1] = -0.5;
        src.data[2] = f32::INFINITY;
        let out = warp_inverse_depth_cpu(&src, None, &cam, &Sim3::identity()).expect("warp");
        for (i, (&s, &o)) in src.data.iter().zip(&out.data).enumerate() {
            let expected = if s > 0.0 && s.is_finite() { s } else { 0.0 };
            assert_eq!(o, expected, "pixel {i}");
        }
    }

    #[test]
    fn translated_fronto_parallel_plane_has_the_analytic_inverse_depth() {
        let cam = camera(64, 48, 50.0);
        let d0 = 1.25;
        let src = ImageF32::filled(64, 48, d0 as f32);
        // Scale included: the target's gauge is s× the source's.
        let pose = Sim3::new(SO3::identity(), Vector3::new(0.03, -0.02, 0.05), 1.1);
        let out = warp_inverse_depth_cpu(&src, None, &cam, &pose).expect("warp");
        let z_target = pose.scale / d0 + pose.translation.z;
        let expected = (1.0 / z_target) as f32;
        let (mut inside, mut outside) = (0, 0);
        for y in 0..48 {
            for x in 0..64 {
                // Back-project the target pixel onto the plane and find its source pixel.
                let p_dst = cam.unproject(&Vector2::new(f64::from(x), f64::from(y)), z_target);
                let p_src = pose.inverse().act(&p_dst);
                assert!((p_src.z - 1.0 / d0).abs() < 1e-12);
                let uv = cam.project(&p_src);
                let value = out.at(x as usize, y as usize);
                if uv.x > 1.0 && uv.y > 1.0 && uv.x < 62.0 && uv.y < 46.0 {
                    inside += 1;
                    // The image shrinks (magnification 0.95): every such pixel is hit.
                    assert!(
                        (value - expected).abs() <= 2.0 * f32::EPSILON * expected,
                        "({x}, {y}): {value} vs {expected}"
                    );
                } else if uv.x < -1.0 || uv.y < -1.0 || uv.x > 64.0 || uv.y > 48.0 {
                    outside += 1;
                    assert_eq!(value, 0.0, "({x}, {y}) sees no source pixel");
                }
            }
        }
        assert!(
            inside > 2000 && outside > 50,
            "{inside} inside, {outside} outside"
        );
    }

    #[test]
    fn nearest_surface_wins_and_exclusion_and_disocclusion_leave_holes() {
        // A 20×1 scan line: background at depth 1, pixels 10..=12 at depth 0.5. Moving the
        // points by 0.1 along x shifts the background by fx·0.1·d = 1 pixel and the near strip
        // by 2 pixels.
        let cam = camera(20, 1, 10.0);
        let mut src = ImageF32::filled(20, 1, 1.0);
        for x in 10..=12 {
            src.data[x] = 2.0;
        }
        let pose = Sim3::new(SO3::identity(), Vector3::new(0.1, 0.0, 0.0), 1.0);
        let out = warp_inverse_depth_cpu(&src, None, &cam, &pose).expect("warp");
        let mut expected = vec![1.0f32; 20];
        expected[0] = 0.0; // nothing lands left of the first pixel's target
        expected[11] = 0.0; // disoccluded: behind the near strip's old place
        expected[12..=14].fill(2.0); // near strip; 13 and 14 also receive the background
        for (x, (&o, &e)) in out.data.iter().zip(&expected).enumerate() {
            assert!((o - e).abs() < 1e-6, "x = {x}: {o} vs {e}");
        }
        // Excluding near pixel 12: background pixel 13 is the only one left on target 14.
        let mut exclude = ImageF32::filled(20, 1, 0.0);
        exclude.data[12] = 1.0;
        let out = warp_inverse_depth_cpu(&src, Some(&exclude), &cam, &pose).expect("warp");
        assert!((out.data[14] - 1.0).abs() < 1e-6, "{}", out.data[14]);
        assert!((out.data[13] - 2.0).abs() < 1e-6, "{}", out.data[13]);
    }

    #[test]
    fn points_behind_or_at_the_camera_are_dropped() {
        let cam = camera(16, 12, 12.0);
        let src = ImageF32::filled(16, 12, 1.0);
        for tz in [-1.5, -0.9995] {
            let pose = Sim3::new(SO3::identity(), Vector3::new(0.0, 0.0, tz), 1.0);
            let out = warp_inverse_depth_cpu(&src, None, &cam, &pose).expect("warp");
            assert!(out.data.iter().all(|&v| v == 0.0), "tz = {tz}");
        }
        let wrong = ImageF32::filled(15, 12, 1.0);
        assert!(matches!(
            warp_inverse_depth_cpu(&wrong, None, &cam, &Sim3::identity()),
            Err(Error::Shape(_))
        ));
    }

    #[test]
    fn idepth_jacobian_matches_numeric_differences() {
        let cam = PinholeCamera::new(260.0, 255.0, 158.3, 121.7, 320, 240).expect("camera");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..50 {
            let (x, y) = (rng.random_range(0.0..320.0), rng.random_range(0.0..240.0));
            let d = rng.random_range(0.2..4.0);
            // Any keyframe pose: the derivative is taken in the keyframe's tangent space.
            let world_from_kf = Sim3::exp(&Vector7::from_fn(|_, _| rng.random_range(-1.0..1.0)));
            let p_world = world_from_kf.act(&cam.unproject(&Vector2::new(x, y), 1.0 / d));
            let idepth_after = |delta: &Vector7| {
                let moved = world_from_kf * Sim3::exp(delta);
                1.0 / moved.inverse().act(&p_world).z
            };
            const H: f64 = 1e-6;
            let numeric = Vector7::from_fn(|k, _| {
                let mut e = Vector7::zeros();
                e[k] = H;
                (idepth_after(&e) - idepth_after(&-e)) / (2.0 * H)
            });
            let analytic = idepth_pose_jacobian(&cam, x, y, d);
            let err = (numeric - analytic).norm();
            assert!(
                err < 1e-6 * (1.0 + analytic.norm()),
                "pixel ({x}, {y}), d = {d}: analytic {analytic:?} numeric {numeric:?}"
            );
        }
    }

    #[test]
    fn pose_variance_propagates_the_covariance() {
        let cam = PinholeCamera::new(200.0, 190.0, 40.3, 30.1, 80, 60).expect("camera");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let idepth = random_idepth(80, 60, 0.2, &mut rng);
        let a = Matrix7::from_fn(|_, _| rng.random_range(-0.01..0.01));
        let sigma = a * a.transpose() + Matrix7::identity() * 1e-6;
        let var = pose_variance(&idepth, &cam, &sigma);
        for y in 0..60 {
            for x in 0..80 {
                let d = idepth.at(x, y);
                let v = var.at(x, y);
                if d == 0.0 {
                    assert_eq!(v, 0.0);
                    continue;
                }
                let j = idepth_pose_jacobian(&cam, x as f64, y as f64, f64::from(d));
                let expected = j.dot(&(sigma * j));
                assert!(v > 0.0 && (f64::from(v) - expected).abs() <= 1e-6 * expected);
            }
        }
        // Pure scale uncertainty σ_s: the inverse depth's relative standard deviation is σ_s.
        let mut scale_only = Matrix7::zeros();
        scale_only[(6, 6)] = 0.01f64.powi(2);
        let var = pose_variance(&idepth, &cam, &scale_only);
        for (&d, &v) in idepth.data.iter().zip(&var.data) {
            let expected = (0.01 * d) * (0.01 * d);
            assert!(
                (v - expected).abs() <= 1e-5 * expected.max(1e-12),
                "{v} vs {expected}"
            );
        }
    }

    /// Two views of the slanted plane `n·p = 1` (prev) with exact dense maps, and semi-dense
    /// pixels on a grid of lines painted on the plane (the same 3-D lines in both views).
    struct PlaneScene {
        camera: PinholeCamera,
        cur_from_prev: Sim3,
        prev_semi: ImageF32,
        prev_dense: ImageF32,
        cur_semi: ImageF32,
        cur_semi_var: ImageF32,
        cur_dense: ImageF32,
    }

    fn plane_scene() -> PlaneScene {
        let camera = camera(320, 240, 260.0);
        let n_prev = Vector3::new(0.1, -0.05, 1.0);
        let cur_from_prev = Sim3::new(
            SO3::exp(&Vector3::new(0.02, -0.03, 0.01)),
            Vector3::new(0.05, -0.02, 0.03),
            1.05,
        );
        let n_cur = moved_plane(&n_prev, &cur_from_prev);
        let prev_dense = plane_idepth(&camera, &n_prev);
        let cur_dense = plane_idepth(&camera, &n_cur);
        // Lines 1/12 apart, 30 % of the plane.
        let on_line = |p: &Vector3<f64>| {
            (p.x * 12.0).rem_euclid(1.0) < 0.15 || (p.y * 12.0).rem_euclid(1.0) < 0.15
        };
        let semi = |dense: &ImageF32, prev_from_view: &Sim3| {
            let mut out = ImageF32::filled(320, 240, 0.0);
            for y in 0..240 {
                for x in 0..320 {
                    let d = f64::from(dense.at(x, y));
                    let p = camera.unproject(&Vector2::new(x as f64, y as f64), 1.0 / d);
                    if on_line(&prev_from_view.act(&p)) {
                        *out.at_mut(x, y) = dense.at(x, y);
                    }
                }
            }
            out
        };
        let prev_semi = semi(&prev_dense, &Sim3::identity());
        let cur_semi = semi(&cur_dense, &cur_from_prev.inverse());
        let cur_semi_var = ImageF32::from_vec(
            320,
            240,
            cur_semi
                .data
                .iter()
                .map(|&d| if d > 0.0 { 1e-3 } else { 0.0 })
                .collect(),
        )
        .expect("size");
        PlaneScene {
            camera,
            cur_from_prev,
            prev_semi,
            prev_dense,
            cur_semi,
            cur_semi_var,
            cur_dense,
        }
    }

    fn inputs<'a>(
        s: &'a PlaneScene,
        cur_semi: &'a ImageF32,
        cur_dense: &'a ImageF32,
    ) -> TwoViewInputs<'a> {
        let mut pose_covariance = Matrix7::identity() * 1e-6;
        pose_covariance[(6, 6)] = 1e-4;
        TwoViewInputs {
            camera: &s.camera,
            prev_semi: &s.prev_semi,
            prev_dense: &s.prev_dense,
            cur_semi,
            cur_semi_var: &s.cur_semi_var,
            cur_dense,
            cur_from_prev: s.cur_from_prev,
            pose_covariance,
        }
    }

    /// (semi-dense pixels with a warped counterpart, dense ones) of the current keyframe,
    /// restricted to `region`.
    fn overlapping(s: &PlaneScene, region: &dyn Fn(usize) -> bool) -> (usize, usize) {
        let warped_semi =
            warp_inverse_depth_cpu(&s.prev_semi, None, &s.camera, &s.cur_from_prev).expect("warp");
        let warped_dense = warp_inverse_depth_cpu(
            &s.prev_dense,
            Some(&s.prev_semi),
            &s.camera,
            &s.cur_from_prev,
        )
        .expect("warp");
        let (mut semi, mut dense) = (0, 0);
        for i in (0..320 * 240).filter(|&i| region(i)) {
            if s.cur_semi.data[i] > 0.0 {
                semi += usize::from(warped_semi.data[i] > 0.0);
            } else {
                dense += usize::from(warped_dense.data[i] > 0.0);
            }
        }
        (semi, dense)
    }

    fn check_plane_result(s: &PlaneScene, result: &TwoViewResult) {
        let (semi, dense) = overlapping(s, &|_| true);
        let semi_total = s.cur_semi.data.iter().filter(|&&d| d > 0.0).count();
        assert!(
            semi > semi_total / 2 && dense > 320 * 240 / 3,
            "overlap: {semi} of {semi_total} semi-dense, {dense} dense"
        );
        assert!(
            result.consistent_semi as f64 >= 0.95 * semi as f64
                && result.consistent_dense as f64 >= 0.95 * dense as f64,
            "kept {}/{semi} semi-dense and {}/{dense} dense",
            result.consistent_semi,
            result.consistent_dense
        );
        let expected_var = pose_variance(
            &s.cur_dense,
            &s.camera,
            &inputs(s, &s.cur_semi, &s.cur_dense).pose_covariance,
        );
        assert_eq!(result.dense_variance, expected_var);
        for i in 0..320 * 240 {
            let d = result.idepth.data[i];
            if d == 0.0 {
                assert_eq!(result.variance.data[i], 0.0);
            } else if s.cur_semi.data[i] > 0.0 {
                assert_eq!((d, result.variance.data[i]), (s.cur_semi.data[i], 1e-3));
            } else {
                assert_eq!(
                    (d, result.variance.data[i]),
                    (s.cur_dense.data[i], expected_var.data[i])
                );
            }
        }
    }

    #[test]
    fn consistent_plane_is_kept_and_corrupted_depth_is_rejected() {
        let s = plane_scene();
        let params = TwoViewParams::default();
        let result = two_view_consistency(&inputs(&s, &s.cur_semi, &s.cur_dense), &params, None)
            .expect("two-view");
        check_plane_result(&s, &result);

        // 1 % inverse-depth error in a block of the current keyframe (both maps).
        let in_block = |i: usize| (100..180).contains(&(i % 320)) && (60..140).contains(&(i / 320));
        let corrupt = |m: &ImageF32| {
            let mut m = m.clone();
            for (i, v) in m.data.iter_mut().enumerate() {
                if in_block(i) {
                    *v *= 1.01;
                }
            }
            m
        };
        let (bad_semi, bad_dense) = (corrupt(&s.cur_semi), corrupt(&s.cur_dense));
        let result = two_view_consistency(&inputs(&s, &bad_semi, &bad_dense), &params, None)
            .expect("two-view");
        let kept_in_block = (0..320 * 240)
            .filter(|&i| in_block(i) && result.idepth.data[i] > 0.0)
            .count();
        assert_eq!(kept_in_block, 0, "corrupted pixels kept");
        let (semi_out, dense_out) = overlapping(&s, &|i| !in_block(i));
        let kept_out = (0..320 * 240)
            .filter(|&i| !in_block(i) && result.idepth.data[i] > 0.0)
            .count();
        assert!(
            kept_out as f64 >= 0.95 * (semi_out + dense_out) as f64,
            "outside the block: kept {kept_out} of {}",
            semi_out + dense_out
        );
        // The block's pixels did overlap, so the test above could have failed.
        let (semi_in, dense_in) = overlapping(&s, &in_block);
        assert!(semi_in + dense_in > 4000, "{semi_in} + {dense_in}");
    }

    #[test]
    fn consistency_on_the_gpu_matches_the_cpu() {
        let ctx = Arc::new(
            GpuContext::new(&GpuConfig::default())
                .unwrap_or_else(|e| panic!("no GPU context: {e}")),
        );
        let gpu = GpuWarp::new(ctx).expect("kernel compiles");
        let s = plane_scene();
        let params = TwoViewParams::default();
        let inputs = inputs(&s, &s.cur_semi, &s.cur_dense);
        let cpu = two_view_consistency(&inputs, &params, None).expect("cpu");
        let on_gpu = two_view_consistency(&inputs, &params, Some(&gpu)).expect("gpu");
        check_plane_result(&s, &on_gpu);
        let differ = cpu
            .idepth
            .data
            .iter()
            .zip(&on_gpu.idepth.data)
            .filter(|(a, b)| a != b)
            .count();
        assert!(differ <= 320 * 240 / 1000, "{differ} pixels differ");
    }

    #[test]
    fn depth_map_upsampling_round_trips_and_feeds_the_back_end_pyramid() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let idepth = random_idepth(320, 240, 0.4, &mut rng);
        let mut variance = ImageF32::from_vec(
            320,
            240,
            (0..320 * 240)
                .map(|_| rng.random_range(1e-5f32..1e-2))
                .collect(),
        )
        .expect("size");
        // Some kept depths without a usable variance: they must become Unknown.
        for i in (0..320 * 240).step_by(97) {
            variance.data[i] = if i % 2 == 0 { 0.0 } else { f32::NAN };
        }
        let valid = |i: usize| {
            idepth.data[i] > 0.0 && variance.data[i] > 0.0 && variance.data[i].is_finite()
        };

        for (w, h) in [(640, 480), (320, 240)] {
            let map = to_depth_map(&idepth, &variance, w, h).expect("upsample");
            assert_eq!((map.width, map.height, map.pixels.len()), (w, h, w * h));
            let (fx, fy) = (w / 320, h / 240);
            for y in 0..h {
                for x in 0..w {
                    let i = (y / fy) * 320 + x / fx;
                    let expected = if valid(i) {
                        InverseDepth::Estimate {
                            idepth: idepth.data[i],
                            var: variance.data[i],
                        }
                    } else {
                        InverseDepth::Unknown
                    };
                    assert_eq!(map.at(x, y), expected, "{w}x{h} at ({x}, {y})");
                }
            }
            let n_valid = (0..320 * 240).filter(|&i| valid(i)).count();
            assert_eq!(map.num_estimates(), n_valid * fx * fy);
        }

        // The back end's depth pyramid of a 640×480 keyframe: level 1 is the working map again.
        let full_cam = camera(640, 480, 520.0);
        let gray = ImageF32::from_vec(
            640,
            480,
            (0..640 * 480)
                .map(|_| rng.random_range(0.0f32..255.0))
                .collect(),
        )
        .expect("size");
        let frame = Frame::new(0, 0.0, full_cam, &gray, None).expect("frame");
        let map = to_depth_map(&idepth, &variance, 640, 480).expect("upsample");
        let levels = KeyframeLevels::new(&frame, &map).expect("levels");
        let level1 = &levels.levels[1].depth;
        assert_eq!((level1.width, level1.height), (320, 240));
        for i in 0..320 * 240 {
            if valid(i) {
                let (d, v) = (level1.idepth[i], level1.var[i]);
                assert!(
                    (d - idepth.data[i]).abs() <= f32::EPSILON * d
                        && (v - variance.data[i]).abs() <= f32::EPSILON * v,
                    "pixel {i}: ({d}, {v}) vs ({}, {})",
                    idepth.data[i],
                    variance.data[i]
                );
            } else {
                assert!(level1.var[i] <= 0.0, "pixel {i} should hold no estimate");
            }
        }

        assert!(matches!(
            to_depth_map(&idepth, &ImageF32::filled(320, 239, 1.0), 640, 480),
            Err(Error::Shape(_))
        ));
        assert!(matches!(
            to_depth_map(&idepth, &variance, 0, 480),
            Err(Error::Shape(_))
        ));
    }

    #[test]
    fn sensor_depth_takes_the_keyframe_gauge_and_the_sensor_shape() {
        let (w, h) = (32, 24);
        let depth = ImageF32::from_vec(
            w,
            h,
            (0..w * h)
                .map(|i| {
                    if i % 11 == 0 {
                        0.0
                    } else {
                        0.5 + (i % 97) as f32 * 0.03
                    }
                })
                .collect(),
        )
        .expect("depth");
        // Semi-dense estimates on every third pixel: the truth in a gauge 2.5× the metric
        // inverse depth, with a few gross outliers that the median ignores.
        let gauge = 2.5;
        let mut semi = DepthMap::unknown(w, h);
        for (i, p) in semi.pixels.iter_mut().enumerate() {
            let d = depth.data[i];
            if i % 3 == 0 && d > 0.0 {
                let idepth = if i % 30 == 0 { 40.0 } else { gauge / d };
                *p = InverseDepth::Estimate { idepth, var: 0.1 };
            }
        }
        let map = sensor_depth_map(&semi, &depth)
            .expect("same size")
            .expect("enough pixels");
        for (p, &d) in map.pixels.iter().zip(&depth.data) {
            match p.estimate() {
                Some((idepth, var)) => {
                    assert!(
                        (idepth - gauge / d).abs() < 1e-5 * idepth,
                        "{idepth} vs {d}"
                    );
                    let sd = SENSOR_DEPTH_REL_SD * idepth;
                    assert!((var - sd * sd).abs() < 1e-6 * var);
                }
                None => assert!(d < MIN_SENSOR_DEPTH, "pixel with depth {d} left out"),
            }
        }

        // Too little overlap gives no map; a wrong size is an error.
        let mut sparse = DepthMap::unknown(w, h);
        sparse.pixels[1] = InverseDepth::Estimate {
            idepth: 1.0,
            var: 0.1,
        };
        assert!(
            sensor_depth_map(&sparse, &depth)
                .expect("same size")
                .is_none()
        );
        let small = ImageF32::filled(w - 1, h, 1.0);
        assert!(matches!(
            sensor_depth_map(&semi, &small),
            Err(Error::Shape(_))
        ));
    }
}
