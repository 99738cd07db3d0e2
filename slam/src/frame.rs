//! A camera frame as the SLAM layer sees it: undistorted grayscale pyramid with gradients.

use crate::spill::{Reader, Writer};
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
#[derive(Debug, PartialEq)]
pub struct Frame {
    /// Sequence number given by the pipeline (0, 1, 2, ... in arrival order).
    pub id: u64,
    /// The caller's id of the frame (`pipeline::FrameInput::frame_id`, a client's), echoed in
    /// the events about it and about the keyframe made from it; `id` when none was given.
    pub input_id: u64,
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
            input_id: id,
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

    /// Bytes of the pyramid (images and gradients over every level) and colour image.
    pub fn heap_bytes(&self) -> usize {
        let pyramid: usize = self
            .pyramid
            .levels
            .iter()
            .map(|l| 4 * 4 * l.width() * l.height())
            .sum();
        pyramid + self.rgb.as_ref().map_or(0, |rgb| rgb.as_raw().len())
    }

    /// The compact form of this frame (see [`CompactFrame`]).
    pub fn compact(&self) -> CompactFrame {
        CompactFrame::of(self)
    }
}

/// What a keyframe keeps of its frame once it leaves the working set (issue 37): the image
/// the pyramid was built from, not the pyramid. An undistorted colour frame keeps only its
/// colour image (3 B per pixel, shared with whoever else holds it), whose grey conversion is
/// the pyramid's base; a frame without colour (or whose base is not its colour's grey) keeps
/// the grey base (4 B per pixel). [`CompactFrame::rebuild`] gives back a frame bit-identical
/// to the original, so rebuilding on demand never changes a result. The pyramid with its
/// gradients costs 21 B per pixel.
#[derive(Clone, Debug)]
pub struct CompactFrame {
    pub id: u64,
    pub input_id: u64,
    pub timestamp: f64,
    /// Undistorted pinhole camera of level 0.
    pub camera: PinholeCamera,
    /// The colour image, when the frame had one.
    pub rgb: Option<Arc<::image::RgbImage>>,
    /// The pyramid's base when it cannot be recomputed from `rgb`.
    gray: Option<Arc<ImageF32>>,
    pub sensor_depth: Option<Arc<ImageF32>>,
}

impl CompactFrame {
    /// The compact form of `frame` (converts its colour image once to check that the grey
    /// base can be recomputed from it).
    pub fn of(frame: &Frame) -> Self {
        let base = &frame.level(0).image;
        let from_rgb = frame
            .rgb
            .as_deref()
            .is_some_and(|rgb| ImageF32::from_rgb8(rgb) == *base);
        Self {
            id: frame.id,
            input_id: frame.input_id,
            timestamp: frame.timestamp,
            camera: frame.camera,
            rgb: frame.rgb.clone(),
            gray: (!from_rgb).then(|| Arc::new(base.clone())),
            sensor_depth: frame.sensor_depth.clone(),
        }
    }

    /// The full frame again, pyramid and gradients recomputed: equal to the frame this was
    /// made from.
    pub fn rebuild(&self) -> Result<Frame> {
        let converted;
        let gray = match (&self.gray, &self.rgb) {
            (Some(gray), _) => gray.as_ref(),
            (None, Some(rgb)) => {
                converted = ImageF32::from_rgb8(rgb);
                &converted
            }
            (None, None) => {
                return Err(Error::Shape(
                    "a compact frame without an image cannot be rebuilt".into(),
                ));
            }
        };
        let mut frame = Frame::new(self.id, self.timestamp, self.camera, gray, self.rgb.clone())?;
        frame.sensor_depth = self.sensor_depth.clone();
        frame.input_id = self.input_id;
        Ok(frame)
    }

    /// The grey base, when it is kept (a frame without colour, or whose base is not its
    /// colour's grey).
    pub fn gray(&self) -> Option<&ImageF32> {
        self.gray.as_deref()
    }

    /// Bytes this form holds (images counted in full even when shared).
    pub fn heap_bytes(&self) -> usize {
        let rgb = self.rgb.as_ref().map_or(0, |rgb| rgb.as_raw().len());
        let gray = self.gray.as_ref().map_or(0, |g| g.data.len() * 4);
        let depth = self.sensor_depth.as_ref().map_or(0, |d| d.data.len() * 4);
        rgb + gray + depth
    }
}

impl crate::spill::Spillable for CompactFrame {
    fn encode(&self, out: &mut Writer) {
        out.u64(self.id);
        out.u64(self.input_id);
        out.f64(self.timestamp);
        out.camera(&self.camera);
        match &self.rgb {
            Some(rgb) => {
                out.u8(1);
                out.u64(u64::from(rgb.width()));
                out.u64(u64::from(rgb.height()));
                out.bytes(rgb.as_raw());
            }
            None => out.u8(0),
        }
        out.opt_image(self.gray.as_deref());
        out.opt_image(self.sensor_depth.as_deref());
    }

    fn decode(input: &mut Reader<'_>) -> Result<Self> {
        let id = input.u64()?;
        let input_id = input.u64()?;
        let timestamp = input.f64()?;
        let camera = input.camera()?;
        let dim = |v: u64| u32::try_from(v).map_err(|_| Error::Spill("a size does not fit".into()));
        let rgb = match input.u8()? {
            0 => None,
            _ => {
                let (w, h) = (dim(input.u64()?)?, dim(input.u64()?)?);
                let raw = input.bytes()?.to_vec();
                let rgb = ::image::RgbImage::from_raw(w, h, raw).ok_or_else(|| {
                    Error::Spill("a spilled colour image has the wrong size".into())
                })?;
                Some(Arc::new(rgb))
            }
        };
        let gray = input.opt_image()?.map(Arc::new);
        let sensor_depth = input.opt_image()?.map(Arc::new);
        Ok(Self {
            id,
            input_id,
            timestamp,
            camera,
            rgb,
            gray,
            sensor_depth,
        })
    }

    fn heap_bytes(&self) -> usize {
        CompactFrame::heap_bytes(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> PinholeCamera {
        PinholeCamera::new(60.0, 60.0, 31.5, 23.5, 64, 48).expect("camera")
    }

    fn colour() -> ::image::RgbImage {
        ::image::RgbImage::from_fn(64, 48, |x, y| {
            ::image::Rgb([(x * 4) as u8, (y * 5) as u8, ((x * y) % 251) as u8])
        })
    }

    #[test]
    fn compact_frame_rebuilds_the_same_frame() {
        // From colour: only the colour image is kept.
        let mut frame = Frame::from_camera_rgb(3, 0.1, &camera(), None, colour()).expect("frame");
        frame.sensor_depth = Some(Arc::new(ImageF32::filled(64, 48, 1.5)));
        let compact = frame.compact();
        assert!(compact.gray().is_none());
        assert_eq!(compact.heap_bytes(), 64 * 48 * 3 + 64 * 48 * 4);
        assert_eq!(compact.rebuild().expect("rebuild"), frame);
        assert!(frame.heap_bytes() > 5 * 64 * 48 * 3);

        // Grey only, or a grey base that is not the colour's conversion: the base is kept.
        let mut gray = ImageF32::from_rgb8(&colour());
        let plain = Frame::new(4, 0.2, camera(), &gray, None).expect("frame");
        assert!(plain.compact().gray().is_some());
        assert_eq!(plain.compact().rebuild().expect("rebuild"), plain);
        gray.data[7] += 0.25;
        let odd = Frame::new(5, 0.3, camera(), &gray, Some(Arc::new(colour()))).expect("frame");
        assert!(odd.compact().gray().is_some());
        assert_eq!(odd.compact().rebuild().expect("rebuild"), odd);

        // Spilled and read back (issue 37): every form, and a distorted camera, come back.
        let mut distorted = frame.compact();
        distorted.camera.distortion = Some(crate::geometry::Distortion {
            k1: 0.1,
            k2: -0.02,
            p1: 1e-3,
            p2: -1e-4,
            k3: 0.0,
        });
        for (compact, original) in [(frame.compact(), &frame), (odd.compact(), &odd)] {
            let back = crate::spill::round_trip(&compact).expect("round trip");
            assert_eq!(back.rebuild().expect("rebuild"), *original);
        }
        let back = crate::spill::round_trip(&plain.compact()).expect("round trip");
        assert_eq!(back.rebuild().expect("rebuild"), plain);
        let back = crate::spill::round_trip(&distorted).expect("round trip");
        assert_eq!(back.camera, distorted.camera);
        assert_eq!(back.sensor_depth, distorted.sensor_depth);
    }
}
