//! A camera frame as the SLAM layer sees it: undistorted grayscale pyramid with gradients.

use std::sync::Arc;

use crate::geometry::{PinholeCamera, UndistortMap};
use crate::image::ImageF32;
use crate::image::pyramid::{Pyramid, PyramidLevel};
use crate::{Error, Result};

/// Number of pyramid levels built per frame (LSD-SLAM's `PYRAMID_LEVELS` = 5: 640×480 down to
/// 40×30, coarse enough for the first tracking iterations to converge from far away).
pub const PYRAMID_LEVELS: usize = 5;

/// One input image, undistorted, with its pyramid. Shared read-only (`Arc`) between tracking,
/// mapping, the back end and the dense layer.
#[derive(Debug)]
pub struct Frame {
    /// Sequence number given by the pipeline (0, 1, 2, ... in arrival order).
    pub id: u64,
    /// Capture time in seconds (the dataset's / client's clock).
    pub timestamp: f64,
    /// Undistorted pinhole camera of level 0 (no distortion coefficients).
    pub camera: PinholeCamera,
    /// Intensity pyramid, `levels[0]` at full resolution.
    pub pyramid: Pyramid,
    /// The colour image (undistorted), kept for the dense layer, colouring and the depth prior.
    pub rgb: Option<Arc<::image::RgbImage>>,
    /// Metric depth registered to this (undistorted) image, in metres (0 = none), from an
    /// RGB-D dataset. Only the ground-truth refinement baseline reads it
    /// (`dense.two_view.ground_truth_depth`); the pipeline keeps it only then.
    pub sensor_depth: Option<Arc<ImageF32>>,
}

impl Frame {
    /// Builds the pyramid of an already undistorted grayscale image.
    pub fn new(
        id: u64,
        timestamp: f64,
        camera: PinholeCamera,
        gray: &ImageF32,
        rgb: Option<Arc<::image::RgbImage>>,
    ) -> Result<Self> {
        if camera.distortion.is_some() {
            return Err(Error::InvalidCamera(
                "Frame expects an undistorted camera: undistort the image first".into(),
            ));
        }
        if (gray.width, gray.height) != (camera.width as usize, camera.height as usize) {
            return Err(Error::Shape(format!(
                "image is {}x{}, camera {}x{}",
                gray.width, gray.height, camera.width, camera.height
            )));
        }
        let pyramid = Pyramid::build_cpu(gray, PYRAMID_LEVELS)?;
        Ok(Self {
            id,
            timestamp,
            camera,
            pyramid,
            rgb,
            sensor_depth: None,
        })
    }

    /// A frame from a colour image as `camera` (with its distortion, undone by `undistort`,
    /// which is `None` for an undistorted camera) delivers it; refuses another image size.
    pub fn from_camera_rgb(
        id: u64,
        timestamp: f64,
        camera: &PinholeCamera,
        undistort: Option<&UndistortMap>,
        rgb: ::image::RgbImage,
    ) -> Result<Self> {
        let (w, h) = rgb.dimensions();
        if (w, h) != (camera.width, camera.height) {
            return Err(Error::Shape(format!(
                "frame is {w}x{h} but the camera is {}x{}",
                camera.width, camera.height
            )));
        }
        let rgb = match undistort {
            Some(map) => map.apply_rgb(&rgb)?,
            None => rgb,
        };
        let gray = ImageF32::from_rgb8(&rgb);
        Self::new(
            id,
            timestamp,
            camera.undistorted(),
            &gray,
            Some(Arc::new(rgb)),
        )
    }

    /// Pyramid level `level` (0 = full resolution).
    pub fn level(&self, level: usize) -> &PyramidLevel {
        &self.pyramid.levels[level]
    }

    /// The camera of pyramid level `level`.
    pub fn camera_at(&self, level: usize) -> PinholeCamera {
        self.camera.scaled(level as u32)
    }
}
