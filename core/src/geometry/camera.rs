//! Pinhole camera with the OpenCV radial-tangential ("plumb bob") distortion model.
//!
//! Pixel convention: pixel centres sit at integer coordinates, (0, 0) is the centre of the
//! top-left pixel, x to the right, y down; `(u, v) = (fx·X/Z + cx, fy·Y/Z + cy)`.
//!
//! Distortion acts on normalised image coordinates x = (X/Z, Y/Z) as in OpenCV
//! (`cv::projectPoints`) and the TUM RGB-D calibration page:
//! `x_d = x·(1 + k1 r² + k2 r⁴ + k3 r⁶) + [2p1xy + p2(r² + 2x²), p1(r² + 2y²) + 2p2xy]`.

use crate::{Error, Result};
use nalgebra::{Matrix2, Matrix2x3, Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// OpenCV radial-tangential distortion coefficients (k1, k2, p1, p2, k3 order as in OpenCV's
/// `distCoeffs` and TUM's calibration table).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Distortion {
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub k3: f64,
}

impl Distortion {
    /// Coefficients in OpenCV order.
    pub fn new(k1: f64, k2: f64, p1: f64, p2: f64, k3: f64) -> Self {
        Self { k1, k2, p1, p2, k3 }
    }

    /// Whether all coefficients are finite.
    pub fn is_finite(&self) -> bool {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
            .iter()
            .all(|v| v.is_finite())
    }

    /// Applies the model to normalised coordinates (undistorted → distorted).
    pub fn distort(&self, x: &Vector2<f64>) -> Vector2<f64> {
        let (u, v) = (x.x, x.y);
        let r2 = u * u + v * v;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        Vector2::new(
            u * radial + 2.0 * self.p1 * u * v + self.p2 * (r2 + 2.0 * u * u),
            v * radial + self.p1 * (r2 + 2.0 * v * v) + 2.0 * self.p2 * u * v,
        )
    }

    /// ∂distort(x)/∂x (used by the Newton inversion).
    pub fn distort_jacobian(&self, x: &Vector2<f64>) -> Matrix2<f64> {
        let (u, v) = (x.x, x.y);
        let r2 = u * u + v * v;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let d_radial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2); // d radial / d r²
        let cross = 2.0 * u * v * d_radial + 2.0 * self.p1 * u + 2.0 * self.p2 * v;
        Matrix2::new(
            radial + 2.0 * u * u * d_radial + 2.0 * self.p1 * v + 6.0 * self.p2 * u,
            cross,
            cross,
            radial + 2.0 * v * v * d_radial + 6.0 * self.p1 * v + 2.0 * self.p2 * u,
        )
    }

    /// Inverts [`Distortion::distort`] by damped Newton iterations started at `xd` (at most 30;
    /// stops when the residual is below 1e-14). Converges for TUM fr1's strong k3 everywhere
    /// inside the image, where the radial map is monotonic.
    pub fn undistort(&self, xd: &Vector2<f64>) -> Vector2<f64> {
        let mut x = *xd;
        let mut residual = self.distort(&x) - xd;
        for _ in 0..30 {
            if residual.norm() < 1e-14 {
                break;
            }
            let Some(inv) = self.distort_jacobian(&x).try_inverse() else {
                break;
            };
            let step = inv * residual;
            // Backtrack if a full step does not reduce the residual (far outside the image).
            let mut t = 1.0;
            let mut improved = false;
            for _ in 0..8 {
                let candidate = x - t * step;
                let r = self.distort(&candidate) - xd;
                if r.norm() < residual.norm() {
                    x = candidate;
                    residual = r;
                    improved = true;
                    break;
                }
                t *= 0.5;
            }
            if !improved {
                break;
            }
        }
        x
    }
}

/// Raw serde form, validated into a [`PinholeCamera`] (so a config file cannot yield an
/// invalid camera).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: u32,
    height: u32,
    #[serde(default)]
    distortion: Option<Distortion>,
}

impl TryFrom<RawCamera> for PinholeCamera {
    type Error = Error;
    fn try_from(r: RawCamera) -> Result<Self> {
        let cam = PinholeCamera::new(r.fx, r.fy, r.cx, r.cy, r.width, r.height)?;
        match r.distortion {
            Some(d) => cam.with_distortion(d),
            None => Ok(cam),
        }
    }
}

/// A pinhole camera: intrinsics in pixels, image size, optional lens distortion.
///
/// `project`/`unproject` are the ideal pinhole model; distortion is removed from images once
/// with [`super::UndistortMap`] (or per point with [`PinholeCamera::undistort_pixel`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawCamera")]
pub struct PinholeCamera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    pub distortion: Option<Distortion>,
}

impl PinholeCamera {
    /// Validated constructor: fx, fy finite and > 0; cx, cy finite; width, height > 0.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32) -> Result<Self> {
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(Error::InvalidCamera(format!(
                    "{name} must be finite and > 0, got {v}"
                )))
            }
        };
        positive("fx", fx)?;
        positive("fy", fy)?;
        for (name, v) in [("cx", cx), ("cy", cy)] {
            if !v.is_finite() {
                return Err(Error::InvalidCamera(format!(
                    "{name} must be finite, got {v}"
                )));
            }
        }
        if width == 0 || height == 0 {
            return Err(Error::InvalidCamera(format!(
                "image size must be non-zero, got {width}x{height}"
            )));
        }
        Ok(Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            distortion: None,
        })
    }

    /// The same camera with lens distortion (all coefficients must be finite).
    pub fn with_distortion(self, distortion: Distortion) -> Result<Self> {
        if !distortion.is_finite() {
            return Err(Error::InvalidCamera(format!(
                "distortion coefficients must be finite, got {distortion:?}"
            )));
        }
        Ok(Self {
            distortion: Some(distortion),
            ..self
        })
    }

    /// TUM RGB-D freiburg1 colour camera, 640×480 (calibration from the dataset's web page).
    pub fn tum_freiburg1() -> Self {
        Self {
            fx: 517.3,
            fy: 516.5,
            cx: 318.6,
            cy: 255.3,
            width: 640,
            height: 480,
            distortion: Some(Distortion::new(0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
        }
    }

    /// TUM RGB-D freiburg2 colour camera, 640×480.
    pub fn tum_freiburg2() -> Self {
        Self {
            fx: 520.9,
            fy: 521.0,
            cx: 325.1,
            cy: 249.7,
            width: 640,
            height: 480,
            distortion: Some(Distortion::new(0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
        }
    }

    /// TUM RGB-D freiburg3 colour camera, 640×480 (images are already undistorted).
    pub fn tum_freiburg3() -> Self {
        Self {
            fx: 535.4,
            fy: 539.2,
            cx: 320.1,
            cy: 247.6,
            width: 640,
            height: 480,
            distortion: None,
        }
    }

    /// The same intrinsics and size without distortion.
    pub fn undistorted(&self) -> Self {
        Self {
            distortion: None,
            ..*self
        }
    }

    /// Ideal pinhole projection of a camera-frame point (no distortion; z must be > 0 for a
    /// meaningful result — callers check depth).
    #[inline]
    pub fn project(&self, p: &Vector3<f64>) -> Vector2<f64> {
        Vector2::new(self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy)
    }

    /// ∂project(p)/∂p = `[[fx/z, 0, −fx·x/z²], [0, fy/z, −fy·y/z²]]`.
    #[inline]
    pub fn project_jacobian(&self, p: &Vector3<f64>) -> Matrix2x3<f64> {
        let iz = 1.0 / p.z;
        Matrix2x3::new(
            self.fx * iz,
            0.0,
            -self.fx * p.x * iz * iz,
            0.0,
            self.fy * iz,
            -self.fy * p.y * iz * iz,
        )
    }

    /// The camera-frame point at `depth` (its z coordinate) behind pixel `uv`.
    pub fn unproject(&self, uv: &Vector2<f64>, depth: f64) -> Vector3<f64> {
        Vector3::new(
            (uv.x - self.cx) / self.fx * depth,
            (uv.y - self.cy) / self.fy * depth,
            depth,
        )
    }

    /// K = `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.
    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// K⁻¹.
    pub fn k_inverse(&self) -> Matrix3<f64> {
        Matrix3::new(
            1.0 / self.fx,
            0.0,
            -self.cx / self.fx,
            0.0,
            1.0 / self.fy,
            -self.cy / self.fy,
            0.0,
            0.0,
            1.0,
        )
    }

    /// Applies the lens distortion to normalised coordinates (identity without distortion).
    pub fn distort_normalized(&self, x: &Vector2<f64>) -> Vector2<f64> {
        self.distortion.map_or(*x, |d| d.distort(x))
    }

    /// Removes the lens distortion from normalised coordinates (Newton, see
    /// [`Distortion::undistort`]; identity without distortion).
    pub fn undistort_normalized(&self, xd: &Vector2<f64>) -> Vector2<f64> {
        self.distortion.map_or(*xd, |d| d.undistort(xd))
    }

    /// Pixel of the ideal (undistorted) image → pixel where the lens actually images it.
    pub fn distort_pixel(&self, uv: &Vector2<f64>) -> Vector2<f64> {
        let xd = self.distort_normalized(&self.pixel_to_normalized(uv));
        self.normalized_to_pixel(&xd)
    }

    /// Pixel of the raw (distorted) image → pixel in the ideal (undistorted) image.
    pub fn undistort_pixel(&self, uv: &Vector2<f64>) -> Vector2<f64> {
        let x = self.undistort_normalized(&self.pixel_to_normalized(uv));
        self.normalized_to_pixel(&x)
    }

    /// `((u − cx)/fx, (v − cy)/fy)`.
    pub fn pixel_to_normalized(&self, uv: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy)
    }

    /// `(fx·x + cx, fy·y + cy)`.
    pub fn normalized_to_pixel(&self, x: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new(self.fx * x.x + self.cx, self.fy * x.y + self.cy)
    }

    /// The camera of pyramid level `level` (the image halved `level` times, each output pixel
    /// the average of a 2×2 block).
    ///
    /// With pixel centres at integer coordinates, level-L pixel i covers level-0 pixels
    /// [2ᴸ·i, 2ᴸ·(i+1)), whose centre is 2ᴸ·i + (2ᴸ − 1)/2; hence `f' = f/2ᴸ` and
    /// `c' = (c + 0.5)/2ᴸ − 0.5`. The size is `width >> L` (floor, odd columns dropped, at
    /// least 1). Distortion is unchanged (it lives in normalised coordinates).
    pub fn scaled(&self, level: u32) -> PinholeCamera {
        let f = f64::from(1u32 << level.min(31));
        Self {
            fx: self.fx / f,
            fy: self.fy / f,
            cx: (self.cx + 0.5) / f - 0.5,
            cy: (self.cy + 0.5) / f - 0.5,
            width: self.width.checked_shr(level).unwrap_or(0).max(1),
            height: self.height.checked_shr(level).unwrap_or(0).max(1),
            distortion: self.distortion,
        }
    }

    /// Whether `uv` lies in `[0, width − 1] × [0, height − 1]`, the domain where bilinear
    /// interpolation of the image is defined.
    pub fn is_in_image(&self, uv: &Vector2<f64>) -> bool {
        self.is_in_image_with_border(uv, 0.0)
    }

    /// Whether `uv` lies at least `border` pixels inside `[0, width − 1] × [0, height − 1]`.
    pub fn is_in_image_with_border(&self, uv: &Vector2<f64>, border: f64) -> bool {
        uv.x >= border
            && uv.y >= border
            && uv.x <= f64::from(self.width) - 1.0 - border
            && uv.y <= f64::from(self.height) - 1.0 - border
    }
}

#[cfg(test)]
#[path = "camera_tests.rs"]
mod tests;
