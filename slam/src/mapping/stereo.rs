//! Epipolar line stereo between the keyframe and one tracked frame (Engel et al., ICCV 2013
//! §2.1; LSD-SLAM `DepthMap::makeAndCheckEPL` and `DepthMap::doLineStereo`).
//!
//! For a keyframe pixel `u` the search walks the frame's epipolar segment between the
//! projections of the inverse-depth bounds, in unit steps, comparing 5 equidistant samples
//! (SSD). The minimum is refined to sub-pixel precision, converted to an inverse depth, and
//! given the variance of eq. (4)–(6): `σ²_ρ = α²·(σ²_disc + σ²_geo + σ²_photo)` with `α` the
//! derivative of inverse depth by disparity.

use nalgebra::{Matrix3, Vector2, Vector3};

use super::MappingConfig;
use crate::geometry::{PinholeCamera, SE3};
use crate::image::ImageF32;

/// Guards divisions of squared gradients (LSD `DIVISION_EPS`).
const DIVISION_EPS: f32 = 1e-10;

/// Pinhole intrinsics in `f32` with the inverse's coefficients (`x_n = fxi·u + cxi`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Intrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub fxi: f32,
    pub fyi: f32,
    pub cxi: f32,
    pub cyi: f32,
}

impl Intrinsics {
    pub fn new(camera: &PinholeCamera) -> Self {
        let (fx, fy, cx, cy) = (camera.fx, camera.fy, camera.cx, camera.cy);
        Self {
            fx: fx as f32,
            fy: fy as f32,
            cx: cx as f32,
            cy: cy as f32,
            fxi: (1.0 / fx) as f32,
            fyi: (1.0 / fy) as f32,
            cxi: (-cx / fx) as f32,
            cyi: (-cy / fy) as f32,
        }
    }

    /// `K` as a matrix.
    pub fn k(&self) -> Matrix3<f32> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// `K⁻¹·(u, v, 1)`: the ray of a pixel at depth 1.
    #[inline]
    pub fn ray(&self, u: f32, v: f32) -> Vector3<f32> {
        Vector3::new(self.fxi * u + self.cxi, self.fyi * v + self.cyi, 1.0)
    }
}

/// Bilinear interpolation without the domain check: callers guarantee
/// `0 ≤ x ≤ w − 1`, `0 ≤ y ≤ h − 1` (the search keeps `sample_point_to_border` away).
#[inline]
pub(crate) fn interp(img: &ImageF32, x: f32, y: f32) -> f32 {
    let w = img.width;
    let x0 = (x.max(0.0) as usize).min(w.saturating_sub(2));
    let y0 = (y.max(0.0) as usize).min(img.height.saturating_sub(2));
    let (dx, dy) = (x - x0 as f32, y - y0 as f32);
    let i = y0 * w + x0;
    let (Some(t), Some(b)) = (img.data.get(i..i + 2), img.data.get(i + w..i + w + 2)) else {
        return 0.0;
    };
    let top = t[0] + dx * (t[1] - t[0]);
    let bottom = b[0] + dx * (b[1] - b[0]);
    top + dy * (bottom - top)
}

/// Why a search produced no inverse depth (LSD's negative return codes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum StereoFailure {
    /// The segment or the samples leave the image, or the prior lies behind a camera
    /// (LSD −1): no information, try again with another frame.
    OutOfBounds,
    /// The minimum is ambiguous or the inverse depth negative (LSD −2): evidence against the
    /// hypothesis.
    Ambiguous,
    /// The best SSD is too large (LSD −3): the point is not visible (occlusion, reflection).
    NotFound,
    /// NaN/∞ in the geometry (LSD −4).
    Arithmetic,
}

/// A successful match.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct StereoMatch {
    /// Inverse depth in the keyframe.
    pub idepth: f32,
    /// Its variance (ICCV 2013 eq. 4).
    pub var: f32,
    /// Length of the searched segment before cropping, pixels (decides frame skipping).
    pub epl_length: f32,
    /// SSD at the minimum.
    pub error: f32,
}

/// The geometry of one keyframe/frame pair, prepared once per observed frame (LSD
/// `Frame::prepareForStereoWith`).
#[derive(Debug)]
pub(crate) struct StereoPair<'a> {
    pub kf_image: &'a ImageF32,
    pub kf_gx: &'a ImageF32,
    pub kf_gy: &'a ImageF32,
    pub frame_image: &'a ImageF32,
    pub k: Intrinsics,
    /// `K·R` of `frame_from_keyframe`.
    k_r: Matrix3<f32>,
    /// `K·t` of `frame_from_keyframe`.
    k_t: Vector3<f32>,
    /// Rotation of `frame_from_keyframe`.
    r: Matrix3<f32>,
    /// Translation of `frame_from_keyframe`.
    t: Vector3<f32>,
    /// The frame's optical centre in keyframe coordinates (`keyframe_from_frame.translation`).
    centre: Vector3<f32>,
    /// σ_l of eq. (5): `epipolar_line_noise·(1 + tracking residual)`.
    line_noise: f32,
    width: f32,
    height: f32,
}

impl<'a> StereoPair<'a> {
    pub fn new(
        kf_image: &'a ImageF32,
        kf_gx: &'a ImageF32,
        kf_gy: &'a ImageF32,
        frame_image: &'a ImageF32,
        k: Intrinsics,
        keyframe_from_frame: &SE3,
        line_noise: f32,
    ) -> Self {
        let frame_from_keyframe = keyframe_from_frame.inverse();
        let r: Matrix3<f32> = frame_from_keyframe.rotation.matrix().cast();
        let t: Vector3<f32> = frame_from_keyframe.translation.cast();
        let kk = k.k();
        Self {
            kf_image,
            kf_gx,
            kf_gy,
            frame_image,
            k,
            k_r: kk * r,
            k_t: kk * t,
            r,
            t,
            centre: keyframe_from_frame.translation.cast(),
            line_noise,
            width: kf_image.width as f32,
            height: kf_image.height as f32,
        }
    }

    /// The unit epipolar direction at keyframe pixel (x, y), pointing away from the epipole,
    /// or `None` when stereo is hopeless there (LSD `makeAndCheckEPL`): the line is too short
    /// (tiny baseline — the pixel lies on the epipole), the gradient along it too weak, or the
    /// gradient almost orthogonal to it (ICCV 2013 §2.1.2, eq. 5 would explode).
    pub fn epipolar_direction(
        &self,
        x: usize,
        y: usize,
        cfg: &MappingConfig,
    ) -> Option<Vector2<f32>> {
        let c = &self.centre;
        let k = &self.k;
        // Direction from the epipole K·c to the pixel, scaled by c_z (no division, so it also
        // works when the frame centre lies in the keyframe's image plane).
        let epx = -k.fx * c.x + c.z * (x as f32 - k.cx);
        let epy = -k.fy * c.y + c.z * (y as f32 - k.cy);
        let len2 = epx * epx + epy * epy;
        if !len2.is_finite() || len2 < cfg.min_epl_length_squared {
            return None;
        }
        // Full central differences, as LSD's thresholds are expressed in them.
        let w = self.kf_image.width;
        let d = &self.kf_image.data;
        let i = y * w + x;
        let gx = d[i + 1] - d[i - 1];
        let gy = d[i + w] - d[i - w];
        let along = gx * epx + gy * epy;
        let grad2_along = along * along / len2;
        if grad2_along < cfg.min_epl_grad_squared {
            return None;
        }
        if grad2_along / (gx * gx + gy * gy) < cfg.min_epl_angle_squared {
            return None;
        }
        let s = cfg.gradient_sample_dist / len2.sqrt();
        Some(Vector2::new(epx * s, epy * s))
    }

    /// Inverse depth (in the keyframe) of keyframe ray `ray` when it is seen at frame pixel
    /// `m`, triangulated along the dominant search axis, and `α = ∂ρ/∂s`, its derivative by
    /// the position `s` along the search direction `inc` (pixels per step; LSD
    /// `doLineStereo`, ICCV 2013 eq. 4).
    ///
    /// With `p = ray/ρ` and the frame point `R·p + t`, the normalised x coordinate satisfies
    /// `x·(r₂·ray + t_z·ρ) = r₀·ray + t_x·ρ`, hence `ρ = (r₀·ray − x·r₂·ray)/(x·t_z − t_x)`.
    pub fn idepth_from_match(
        &self,
        ray: &Vector3<f32>,
        m: Vector2<f32>,
        inc: Vector2<f32>,
    ) -> (f32, f32) {
        let (r, t, k) = (&self.r, &self.t, &self.k);
        let dot2 = r.row(2).transpose().dot(ray);
        if inc.x * inc.x > inc.y * inc.y {
            let xn = k.fxi * m.x + k.cxi;
            let den = xn * t.z - t.x;
            let dot0 = r.row(0).transpose().dot(ray);
            let idepth = (dot0 - xn * dot2) / den;
            // ∂ρ/∂x_n = (r₂·ray·t_x − r₀·ray·t_z)/den², ∂x_n/∂s = inc_x·fxi.
            let alpha = inc.x * k.fxi * (dot2 * t.x - dot0 * t.z) / (den * den);
            (idepth, alpha)
        } else {
            let yn = k.fyi * m.y + k.cyi;
            let den = yn * t.z - t.y;
            let dot1 = r.row(1).transpose().dot(ray);
            let idepth = (dot1 - yn * dot2) / den;
            let alpha = inc.y * k.fyi * (dot2 * t.y - dot1 * t.z) / (den * den);
            (idepth, alpha)
        }
    }

    /// Searches keyframe pixel (u, v) along the frame's epipolar line between inverse depths
    /// `min_idepth` and `max_idepth`; `prior_idepth` sets the scale change between the images.
    /// `epl` is [`Self::epipolar_direction`] of the pixel.
    #[allow(clippy::too_many_arguments)]
    pub fn search(
        &self,
        u: f32,
        v: f32,
        epl: Vector2<f32>,
        min_idepth: f32,
        prior_idepth: f32,
        max_idepth: f32,
        cfg: &MappingConfig,
    ) -> Result<StereoMatch, StereoFailure> {
        let ray = self.k.ray(u, v);
        let (rescale, reference) = self.reference_samples(u, v, epl, &ray, prior_idepth)?;
        let Segment {
            far,
            close,
            inc,
            epl_length,
        } = self.segment(&ray, min_idepth, max_idepth, cfg)?;
        let best = self.scan(far, close, inc, &reference, cfg)?;
        let mut best_pos = far + inc * best.index as f32;
        let mut best_err = best.err;
        let mut subpixel = false;
        if cfg.use_subpixel_stereo
            && let Some((shift, err)) = best.subpixel()
        {
            best_pos += inc * shift;
            best_err = err;
            subpixel = true;
        }

        // Squared intensity gradient along the line, in the frame's pixel units.
        let sample_dist = cfg.gradient_sample_dist * rescale;
        let grad_along = reference
            .windows(2)
            .map(|p| (p[1] - p[0]) * (p[1] - p[0]))
            .sum::<f32>()
            / (sample_dist * sample_dist);
        // LSD's allowance: strongly textured patches may match with a larger SSD.
        if best_err > cfg.max_error_stereo + grad_along.sqrt() * 20.0 {
            return Err(StereoFailure::NotFound);
        }

        let (idepth, alpha) = self.idepth_from_match(&ray, best_pos, inc);
        if !(idepth.is_finite() && alpha.is_finite()) {
            return Err(StereoFailure::Arithmetic);
        }
        if idepth < 0.0 && !cfg.allow_negative_idepths {
            return Err(StereoFailure::Ambiguous);
        }

        // eq. (6): photometric disparity error σ²_I/g_p² (with LSD's constants: 4 squared
        // differences in `grad_along`, noise counted in both images).
        let photo = 4.0 * cfg.camera_pixel_noise2 / (grad_along + DIVISION_EPS);
        // eq. (5): geometric disparity error σ_l²/⟨g, l⟩² for the normalised gradient g and
        // epipolar direction l in the keyframe.
        let geo = self.geometric_disparity_var(u, v, epl);
        // Discretisation: a quarter/half step depending on the sub-pixel refinement.
        let disc = if subpixel { 0.05 } else { 0.5 } * sample_dist * sample_dist;
        let var = alpha * alpha * (disc + geo + photo);
        Ok(StereoMatch {
            idepth,
            var,
            epl_length,
            error: best_err,
        })
    }

    /// The keyframe's 5 samples around (u, v) along `epl`, spread by the depth ratio between
    /// the images at `prior_idepth` so that they correspond to unit steps in the frame; that
    /// ratio and the samples.
    fn reference_samples(
        &self,
        u: f32,
        v: f32,
        epl: Vector2<f32>,
        ray: &Vector3<f32>,
        prior_idepth: f32,
    ) -> Result<(f32, [f32; 5]), StereoFailure> {
        let (w, h) = (self.width, self.height);
        let p_inf = self.k_r * ray;
        let p_real = p_inf / prior_idepth + self.k_t;
        // Depth in the frame over depth in the keyframe: the keyframe samples are spread by it
        // so that they correspond to unit steps in the frame.
        let rescale = p_real.z * prior_idepth;
        let reach = 2.0 * rescale;
        let (first, last) = (
            (u - reach * epl.x, v - reach * epl.y),
            (u + reach * epl.x, v + reach * epl.y),
        );
        let inside = |p: (f32, f32)| p.0 > 0.0 && p.0 < w - 2.0 && p.1 > 0.0 && p.1 < h - 2.0;
        if !(inside(first) && inside(last)) {
            return Err(StereoFailure::OutOfBounds);
        }
        // A large scale change breaks the constant-spacing sample model.
        if !(rescale > 0.7 && rescale < 1.4) {
            return Err(StereoFailure::OutOfBounds);
        }
        let kf = self.kf_image;
        let reference: [f32; 5] = std::array::from_fn(|i| {
            let s = (i as f32 - 2.0) * rescale;
            interp(kf, u + s * epl.x, v + s * epl.y)
        });
        Ok((rescale, reference))
    }

    /// The segment of the frame's epipolar line between the inverse depths, far → close,
    /// cropped, padded and clipped to the image as LSD-SLAM does, with its step.
    fn segment(
        &self,
        ray: &Vector3<f32>,
        min_idepth: f32,
        mut max_idepth: f32,
        cfg: &MappingConfig,
    ) -> Result<Segment, StereoFailure> {
        let (w, h) = (self.width, self.height);
        let p_inf = self.k_r * ray;
        // Segment endpoints in the frame: far (min_idepth) → close (max_idepth).
        let mut p_close = p_inf + self.k_t * max_idepth;
        if p_close.z < 0.001 {
            // The close end lies behind the frame: stop where it enters.
            max_idepth = (0.001 - p_inf.z) / self.k_t.z;
            p_close = p_inf + self.k_t * max_idepth;
        }
        let p_far = p_inf + self.k_t * min_idepth;
        if p_far.z < 0.001 || max_idepth < min_idepth {
            return Err(StereoFailure::OutOfBounds);
        }
        let mut close = Vector2::new(p_close.x / p_close.z, p_close.y / p_close.z);
        let mut far = Vector2::new(p_far.x / p_far.z, p_far.y / p_far.z);
        if !(far.x + close.x).is_finite() || !(far.y + close.y).is_finite() {
            return Err(StereoFailure::Arithmetic);
        }
        let delta = close - far;
        let epl_length = delta.norm();
        if !epl_length.is_finite() || epl_length <= 0.0 {
            return Err(StereoFailure::Arithmetic);
        }
        if epl_length > cfg.max_epl_length_crop {
            close = far + delta * (cfg.max_epl_length_crop / epl_length);
        }
        let inc = delta * (cfg.gradient_sample_dist / epl_length);
        // One extra step on each side, and pad short segments to the minimal length.
        far -= inc;
        close += inc;
        if epl_length < cfg.min_epl_length_crop {
            let pad = (cfg.min_epl_length_crop - epl_length) / 2.0;
            far -= inc * pad;
            close += inc * pad;
        }
        let b = cfg.sample_point_to_border;
        let outside = |p: &Vector2<f32>| p.x <= b || p.x >= w - b || p.y <= b || p.y >= h - b;
        if outside(&far) {
            return Err(StereoFailure::OutOfBounds);
        }
        if outside(&close) {
            // Clip the close end to the border along the line; keep it only if ≥ 8 px remain.
            if close.x <= b {
                close += inc * ((b - close.x) / inc.x);
            } else if close.x >= w - b {
                close += inc * ((w - b - close.x) / inc.x);
            }
            if close.y <= b {
                close += inc * ((b - close.y) / inc.y);
            } else if close.y >= h - b {
                close += inc * ((h - b - close.y) / inc.y);
            }
            let remaining = (close - far).norm();
            if outside(&close) || remaining.is_nan() || remaining < 8.0 {
                return Err(StereoFailure::OutOfBounds);
            }
        }
        Ok(Segment {
            far,
            close,
            inc,
            epl_length,
        })
    }

    /// ICCV 2013 eq. (5): `σ²_λ(ξ,π) = σ_l²·|g|²/⟨g, l⟩²` with the keyframe gradient `g` at
    /// (u, v) and the unit epipolar direction `l` (LSD uses the half-difference gradients;
    /// the ratio does not depend on their scale).
    pub fn geometric_disparity_var(&self, u: f32, v: f32, epl: Vector2<f32>) -> f32 {
        let gx = interp(self.kf_gx, u, v);
        let gy = interp(self.kf_gy, u, v);
        let len = epl.norm().max(DIVISION_EPS);
        let along = (gx * epl.x + gy * epl.y) / len + DIVISION_EPS;
        self.line_noise * self.line_noise * (gx * gx + gy * gy) / (along * along)
    }

    /// Walks the segment far → close and keeps the data needed for the winner tests and the
    /// sub-pixel step.
    fn scan(
        &self,
        far: Vector2<f32>,
        close: Vector2<f32>,
        inc: Vector2<f32>,
        reference: &[f32; 5],
        cfg: &MappingConfig,
    ) -> Result<BestMatch, StereoFailure> {
        let img = self.frame_image;
        let step = inc.norm();
        // Steps i with far + i·inc not past `close` (LSD's loop condition), at least one.
        let steps = (((close - far).norm() / step) + 1e-4).floor() as usize + 1;
        let at = |k: f32| interp(img, far.x + inc.x * k, far.y + inc.y * k);
        // Sliding window of the 5 frame samples around the current position.
        let mut window = [at(-2.0), at(-1.0), at(0.0), at(1.0), 0.0];
        let mut prev_res = [0.0f32; 5];
        let mut prev_err = f32::NAN;
        let mut best = BestMatch::default();
        let mut second_err = f32::INFINITY;
        let mut second_index = usize::MAX;
        let mut best_was_last = false;
        for i in 0..steps {
            window[4] = at(i as f32 + 2.0);
            let res: [f32; 5] = std::array::from_fn(|k| window[k] - reference[k]);
            // Same order as `iter().sum()`: left to right from −0.0, and −0.0 + a = a.
            let err = res[0] * res[0]
                + res[1] * res[1]
                + res[2] * res[2]
                + res[3] * res[3]
                + res[4] * res[4];
            let cross = (i > 0).then(|| {
                prev_res[0] * res[0]
                    + prev_res[1] * res[1]
                    + prev_res[2] * res[2]
                    + prev_res[3] * res[3]
                    + prev_res[4] * res[4]
            });
            if err < best.err {
                second_err = best.err;
                second_index = best.index;
                best = BestMatch {
                    index: i,
                    err,
                    err_pre: (i > 0).then_some(prev_err),
                    cross_pre: cross,
                    err_post: None,
                    cross_post: None,
                };
                best_was_last = true;
            } else {
                if best_was_last {
                    best.err_post = Some(err);
                    best.cross_post = cross;
                    best_was_last = false;
                }
                if err < second_err {
                    second_err = err;
                    second_index = i;
                }
            }
            prev_err = err;
            prev_res = res;
            window = [window[1], window[2], window[3], window[4], 0.0];
        }
        if best.err > 4.0 * cfg.max_error_stereo {
            return Err(StereoFailure::NotFound);
        }
        // A clear winner: the second-best (unless it is the neighbouring step) must be
        // `min_distance_error_stereo` times worse.
        let apart = second_index != usize::MAX && second_index.abs_diff(best.index) > 1;
        if apart && cfg.min_distance_error_stereo * best.err > second_err {
            return Err(StereoFailure::Ambiguous);
        }
        Ok(best)
    }
}

/// The SSD minimum of a scan with its neighbours' errors `E(i±1)` and the cross terms
/// `Σ e_i·e_{i±1}` of the residual vectors, which determine the error between the samples
/// under linear interpolation of the residuals.
#[derive(Clone, Copy, Debug)]
struct BestMatch {
    index: usize,
    err: f32,
    err_pre: Option<f32>,
    cross_pre: Option<f32>,
    err_post: Option<f32>,
    cross_post: Option<f32>,
}

impl Default for BestMatch {
    fn default() -> Self {
        Self {
            index: 0,
            err: f32::INFINITY,
            err_pre: None,
            cross_pre: None,
            err_post: None,
            cross_post: None,
        }
    }
}

impl BestMatch {
    /// Sub-pixel refinement (LSD `doLineStereo`): with residuals interpolated linearly between
    /// neighbouring steps a → b, `E(s) = Σ(a + s(b−a))²` is a parabola whose half-derivative
    /// is `Σ ab − Σ a²` at a and `Σ b² − Σ ab` at b. The minimum is the zero crossing of that
    /// (linear) derivative on whichever side of the best step it changes sign. Returns the
    /// shift in steps and the interpolated error, or `None` when the best step is at an end
    /// or the crossing is not unique.
    fn subpixel(&self) -> Option<(f32, f32)> {
        let (err_pre, cross_pre) = (self.err_pre?, self.cross_pre?);
        let (err_post, cross_post) = (self.err_post?, self.cross_post?);
        let e = self.err;
        // Half-derivatives dE/ds at the previous step, here (from the left), here (from the
        // right, towards the next step), and at the next step.
        let g_pre_pre = -(err_pre - cross_pre);
        let g_pre_here = e - cross_pre;
        let g_post_here = -(e - cross_post);
        let g_post_post = err_post - cross_post;
        let sign_change = |a: f32, b: f32| (a < 0.0) != (b < 0.0);
        if sign_change(g_post_here, g_pre_here) {
            // The derivative jumps at the sample itself: it is the minimum.
            return None;
        }
        let pre = sign_change(g_pre_pre, g_pre_here);
        let post = sign_change(g_post_post, g_post_here);
        match (pre, post) {
            (true, false) => {
                let d = g_pre_here / (g_pre_here - g_pre_pre);
                Some((
                    -d,
                    e - 2.0 * d * g_pre_here - (g_pre_pre - g_pre_here) * d * d,
                ))
            }
            (false, true) => {
                let d = g_post_here / (g_post_here - g_post_post);
                Some((
                    d,
                    e + 2.0 * d * g_post_here + (g_post_post - g_post_here) * d * d,
                ))
            }
            _ => None,
        }
    }
}

#[cfg(test)]
#[path = "stereo_tests.rs"]
mod tests;

/// A stretch of the frame's epipolar line to scan: its ends, one step along it (pixels) and
/// the uncropped length between the interval's inverse depths.
struct Segment {
    far: Vector2<f32>,
    close: Vector2<f32>,
    inc: Vector2<f32>,
    epl_length: f32,
}
