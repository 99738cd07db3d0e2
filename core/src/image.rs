//! Grayscale float images, the pixel type every tracking and dense kernel works on.
//!
//! Intensities stay in [0, 255] (not [0, 1]) because LSD-SLAM's photometric thresholds and the
//! paper's σs = 76.5 (adaptive filter) are expressed in 8-bit units.

use crate::{Error, Result};

/// A row-major single-channel `f32` image.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageF32 {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl ImageF32 {
    /// A `width × height` image filled with `value`.
    pub fn filled(width: usize, height: usize, value: f32) -> Self {
        Self {
            width,
            height,
            data: vec![value; width * height],
        }
    }

    /// Wraps `data`; fails unless it holds exactly `width × height` pixels.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Result<Self> {
        if data.len() != width * height {
            return Err(Error::Shape(format!(
                "{} values for a {width}x{height} image",
                data.len()
            )));
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Fails unless `data` holds exactly `width × height` pixels (the fields are public, so a
    /// hand-built image can be inconsistent; kernels check before indexing).
    pub fn check_size(&self) -> Result<()> {
        if self.data.len() != self.width * self.height {
            return Err(Error::Shape(format!(
                "image claims {}x{} but holds {} values",
                self.width,
                self.height,
                self.data.len()
            )));
        }
        Ok(())
    }

    /// Pixel at column `x`, row `y` (panics when out of bounds, like slice indexing).
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Mutable pixel at column `x`, row `y`.
    #[inline]
    pub fn at_mut(&mut self, x: usize, y: usize) -> &mut f32 {
        &mut self.data[y * self.width + x]
    }

    /// Bilinear interpolation at a sub-pixel position; `None` outside `[0, w-1] × [0, h-1]`.
    #[inline]
    pub fn bilinear(&self, x: f32, y: f32) -> Option<f32> {
        self.bilinear_at(x, y).map(|at| self.sample(&at))
    }

    /// Where [`ImageF32::bilinear`] reads at `(x, y)`, to apply to several images of this size
    /// (an image and its gradients) with one bounds check; `None` outside `[0, w-1] × [0, h-1]`.
    #[inline]
    pub fn bilinear_at(&self, x: f32, y: f32) -> Option<BilinearAt> {
        if !(x >= 0.0 && y >= 0.0 && x <= (self.width - 1) as f32 && y <= (self.height - 1) as f32)
        {
            return None;
        }
        // x, y ≥ 0 here, so truncation is the floor (and no call into libm's `floorf`).
        let x0 = (x as usize).min(self.width.saturating_sub(2));
        let y0 = (y as usize).min(self.height.saturating_sub(2));
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        Some(BilinearAt {
            top: (y0 * self.width + x0, y0 * self.width + x1),
            bottom: (y1 * self.width + x0, y1 * self.width + x1),
            fx: x - x0 as f32,
            fy: y - y0 as f32,
        })
    }

    /// The bilinear interpolation at `at`, which must come from an image of this size (from
    /// another, it reads other pixels, or panics past the end like slice indexing).
    #[inline]
    pub fn sample(&self, at: &BilinearAt) -> f32 {
        let (d, fx, fy) = (&self.data, at.fx, at.fy);
        let top = d[at.top.0] * (1.0 - fx) + d[at.top.1] * fx;
        let bottom = d[at.bottom.0] * (1.0 - fx) + d[at.bottom.1] * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// Luma (ITU-R BT.601 weights, as OpenCV's `cvtColor` uses) of an 8-bit RGB image.
    pub fn from_rgb8(rgb: &::image::RgbImage) -> Self {
        let (w, h) = rgb.dimensions();
        let data = rgb
            .pixels()
            .map(|p| 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]))
            .collect();
        Self {
            width: w as usize,
            height: h as usize,
            data,
        }
    }
}

/// The four pixels and weights of one bilinear lookup ([`ImageF32::bilinear_at`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BilinearAt {
    /// Indices of the upper and lower pixel pairs (left, right).
    top: (usize, usize),
    bottom: (usize, usize),
    fx: f32,
    fy: f32,
}
