//! Whole-image undistortion, done once per input frame so that tracking, mapping and the depth
//! prior all work with the ideal pinhole model (LSD-SLAM undistorts its input the same way).

use super::camera::PinholeCamera;
use crate::image::ImageF32;
use crate::{Error, Result};
use nalgebra::Vector2;

/// A precomputed warp from a distorted camera image to the ideal pinhole image with the same
/// K and size (OpenCV's `initUndistortRectifyMap` with `newCameraMatrix = K`).
///
/// For every output pixel the map stores where that ray lands in the distorted input; output
/// pixels whose source falls outside the input's `[0, w − 1] × [0, h − 1]` are set to 0
/// (black), so consumers treat 0 near the border as "no data", as they do for invalid depth.
#[derive(Clone, Debug)]
pub struct UndistortMap {
    camera: PinholeCamera,
    /// Source coordinate (x, y) in the distorted input for each output pixel, row-major;
    /// `None` when it falls outside the input.
    source: Vec<Option<[f32; 2]>>,
}

impl UndistortMap {
    /// Precomputes the map for `camera` (identity when it has no distortion).
    pub fn new(camera: &PinholeCamera) -> Self {
        let (w, h) = (camera.width, camera.height);
        let mut source = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            for x in 0..w {
                let src = camera.distort_pixel(&Vector2::new(f64::from(x), f64::from(y)));
                source.push(
                    camera
                        .is_in_image(&src)
                        .then_some([src.x as f32, src.y as f32]),
                );
            }
        }
        Self {
            camera: *camera,
            source,
        }
    }

    /// The camera of the output images: same intrinsics and size, no distortion.
    pub fn undistorted_camera(&self) -> PinholeCamera {
        self.camera.undistorted()
    }

    /// Where output pixel (x, y) samples the distorted input; `None` outside the input or the
    /// output.
    pub fn source(&self, x: u32, y: u32) -> Option<Vector2<f32>> {
        if x >= self.camera.width || y >= self.camera.height {
            return None;
        }
        self.source[(y * self.camera.width + x) as usize].map(|[u, v]| Vector2::new(u, v))
    }

    fn check_size(&self, width: usize, height: usize) -> Result<()> {
        if width != self.camera.width as usize || height != self.camera.height as usize {
            return Err(Error::Shape(format!(
                "undistort map is {}x{}, image is {width}x{height}",
                self.camera.width, self.camera.height
            )));
        }
        Ok(())
    }

    /// Undistorts a grayscale image by bilinear interpolation (0 where the source is outside).
    pub fn apply(&self, image: &ImageF32) -> Result<ImageF32> {
        self.check_size(image.width, image.height)?;
        let data = self
            .source
            .iter()
            .map(|s| s.and_then(|[u, v]| image.bilinear(u, v)).unwrap_or(0.0))
            .collect();
        ImageF32::from_vec(image.width, image.height, data)
    }

    /// Undistorts a depth image by taking the nearest source pixel (0 where the source is
    /// outside): depths must not be blended across the edges of surfaces, and a blend with a
    /// missing measurement (0) would invent a depth.
    pub fn apply_nearest(&self, image: &ImageF32) -> Result<ImageF32> {
        self.check_size(image.width, image.height)?;
        let (w, h) = (image.width as f32, image.height as f32);
        let data = self
            .source
            .iter()
            .map(|s| match *s {
                Some([u, v]) => {
                    let (x, y) = ((u + 0.5).floor(), (v + 0.5).floor());
                    if x >= 0.0 && y >= 0.0 && x < w && y < h {
                        image.at(x as usize, y as usize)
                    } else {
                        0.0
                    }
                }
                None => 0.0,
            })
            .collect();
        ImageF32::from_vec(image.width, image.height, data)
    }

    /// Undistorts an 8-bit RGB image by bilinear interpolation per channel (black outside).
    pub fn apply_rgb(&self, image: &::image::RgbImage) -> Result<::image::RgbImage> {
        let (w, h) = image.dimensions();
        self.check_size(w as usize, h as usize)?;
        let mut out = ::image::RgbImage::new(w, h);
        for (i, px) in out.pixels_mut().enumerate() {
            let Some([u, v]) = self.source[i] else {
                continue;
            };
            let x0 = (u.floor() as u32).min(w.saturating_sub(2));
            let y0 = (v.floor() as u32).min(h.saturating_sub(2));
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (fx, fy) = (u - x0 as f32, v - y0 as f32);
            let (a, b) = (image.get_pixel(x0, y0), image.get_pixel(x1, y0));
            let (c, d) = (image.get_pixel(x0, y1), image.get_pixel(x1, y1));
            for ch in 0..3 {
                let top = f32::from(a[ch]) * (1.0 - fx) + f32::from(b[ch]) * fx;
                let bottom = f32::from(c[ch]) * (1.0 - fx) + f32::from(d[ch]) * fx;
                px[ch] = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
            }
        }
        Ok(out)
    }
}
