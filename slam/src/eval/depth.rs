//! Depth accuracy: the paper's reconstruction metric (§V.A). The scale/shift fit of eq. (3) lives in
//! [`crate::scale_shift`].
//!
//! **Percentage of correct depth** (CNN-SLAM, Tateno et al. CVPR 2017, §5; DeepRelativeFusion
//! §V.A): the share of pixels whose depth has a relative error below 10 %. The paper counts over
//! the *ground-truth* pixels, so a method is not rewarded for leaving hard pixels empty: here
//! the denominator is every pixel with a valid ground truth (finite, > 0), and a pixel the
//! estimate leaves without depth (0, negative or non-finite) counts as wrong. Monocular depth has
//! no metric scale; the caller passes the scale to apply (the paper uses the trajectory's
//! optimal Sim(3) scale times the keyframe's own Sim(3) scale).

use std::path::Path;

use serde::Serialize;

use crate::dataset::DEPTH_SCALE;
use crate::image::ImageF32;
use crate::{Error, Result};

/// Relative error below which a depth counts as correct: 10 % (CNN-SLAM, the paper §V.A).
pub const DEFAULT_DEPTH_THRESHOLD: f64 = 0.1;

/// Result of [`percent_correct_depth`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct DepthAccuracy {
    /// 100 · correct / valid_gt.
    pub percent: f64,
    /// Pixels with a valid ground truth (finite and > 0): the denominator.
    pub valid_gt: usize,
    /// Of those, pixels where the estimate has a depth (finite and > 0).
    pub evaluated: usize,
    /// Of those, pixels with |s·d_est − d_gt| / d_gt < threshold.
    pub correct: usize,
}

/// Percentage of correct depth of `est_depth` (scaled by `scale`) against `gt_depth`, both in
/// depth units (not inverse depth), same size. `threshold` is the relative error bound
/// ([`DEFAULT_DEPTH_THRESHOLD`] = 0.1 in the paper).
///
/// Fails on a size mismatch, a non-positive scale or threshold, or a ground truth without any
/// valid pixel (a percentage of nothing).
pub fn percent_correct_depth(
    est_depth: &ImageF32,
    gt_depth: &ImageF32,
    scale: f64,
    threshold: f64,
) -> Result<DepthAccuracy> {
    if (est_depth.width, est_depth.height) != (gt_depth.width, gt_depth.height) {
        return Err(Error::Shape(format!(
            "estimated depth is {}x{}, ground truth {}x{}",
            est_depth.width, est_depth.height, gt_depth.width, gt_depth.height
        )));
    }
    if !(scale.is_finite() && scale > 0.0) {
        return Err(Error::Eval(format!(
            "depth scale must be finite and > 0, got {scale}"
        )));
    }
    if !(threshold.is_finite() && threshold > 0.0) {
        return Err(Error::Eval(format!(
            "threshold must be finite and > 0, got {threshold}"
        )));
    }
    let valid = |d: f32| d.is_finite() && d > 0.0;
    let (mut valid_gt, mut evaluated, mut correct) = (0, 0, 0);
    for (&e, &g) in est_depth.data.iter().zip(&gt_depth.data) {
        if !valid(g) {
            continue;
        }
        valid_gt += 1;
        if !valid(e) {
            continue;
        }
        evaluated += 1;
        let g = f64::from(g);
        if (scale * f64::from(e) - g).abs() < threshold * g {
            correct += 1;
        }
    }
    if valid_gt == 0 {
        return Err(Error::Eval("ground-truth depth has no valid pixel".into()));
    }
    Ok(DepthAccuracy {
        percent: 100.0 * correct as f64 / valid_gt as f64,
        valid_gt,
        evaluated,
        correct,
    })
}

/// Reads a depth map in metres: `.npy` (float32, as written by [`crate::npy::write_f32`]) as
/// is, or a 16-bit PNG divided by `png_scale` ([`DEPTH_SCALE`] = 5000 for TUM; 0 stays "no
/// depth"). Other extensions are refused.
pub fn read_depth_map(path: &Path, png_scale: f64) -> Result<ImageF32> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("npy") => crate::npy::read_f32(path),
        Some("png") => {
            if !(png_scale.is_finite() && png_scale > 0.0) {
                return Err(Error::Config(format!(
                    "PNG depth scale must be > 0, got {png_scale}"
                )));
            }
            let img = ::image::open(path).map_err(|source| Error::Image {
                path: path.to_path_buf(),
                source,
            })?;
            let buf = match img {
                ::image::DynamicImage::ImageLuma16(buf) => buf,
                other => {
                    return Err(Error::Dataset(format!(
                        "{}: expected a 16-bit grey depth PNG, got {:?}",
                        path.display(),
                        other.color()
                    )));
                }
            };
            let (w, h) = buf.dimensions();
            let data = buf
                .pixels()
                .map(|p| (f64::from(p[0]) / png_scale) as f32)
                .collect();
            ImageF32::from_vec(w as usize, h as usize, data).map_err(Into::into)
        }
        _ => Err(Error::Config(format!(
            "{}: depth maps must be .npy (float32 metres) or 16-bit .png",
            path.display()
        ))),
    }
}

/// TUM's PNG depth scale, re-exported for callers of [`read_depth_map`].
pub const TUM_PNG_DEPTH_SCALE: f64 = DEPTH_SCALE;

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> ImageF32 {
        let data = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| f(x, y))
            .collect();
        ImageF32::from_vec(w, h, data).expect("size")
    }

    #[test]
    fn eval_depth_counts_over_ground_truth_pixels() {
        // 10×10 ground truth, a 10-pixel column invalid. The estimate is half the truth (scale 2)
        // except: row 0 off by +20 % (wrong), row 1 off by +5 % (right), row 2 missing (wrong),
        // row 3 NaN (wrong).
        let gt = img(10, 10, |x, y| {
            if x == 9 {
                0.0
            } else {
                1.0 + 0.1 * (x + y) as f32
            }
        });
        let est = img(10, 10, |x, y| {
            let g = 1.0 + 0.1 * (x + y) as f32;
            match y {
                0 => 0.5 * g * 1.2,
                1 => 0.5 * g * 1.05,
                2 => 0.0,
                3 => f32::NAN,
                _ => 0.5 * g,
            }
        });
        let acc = percent_correct_depth(&est, &gt, 2.0, DEFAULT_DEPTH_THRESHOLD).expect("acc");
        assert_eq!(acc.valid_gt, 90);
        assert_eq!(acc.evaluated, 90 - 18);
        assert_eq!(acc.correct, 90 - 9 * 3);
        assert!((acc.percent - 100.0 * 63.0 / 90.0).abs() < 1e-12);
        // The wrong scale makes everything wrong; a 25 % threshold accepts row 0.
        assert_eq!(
            percent_correct_depth(&est, &gt, 1.0, 0.1)
                .expect("acc")
                .correct,
            0
        );
        assert_eq!(
            percent_correct_depth(&est, &gt, 2.0, 0.25)
                .expect("acc")
                .correct,
            90 - 18
        );
    }

    #[test]
    fn eval_depth_rejects_bad_inputs() {
        let a = ImageF32::filled(4, 3, 1.0);
        let b = ImageF32::filled(3, 4, 1.0);
        assert!(matches!(
            percent_correct_depth(&a, &b, 1.0, 0.1),
            Err(Error::Shape(_))
        ));
        assert!(percent_correct_depth(&a, &a, 0.0, 0.1).is_err());
        assert!(percent_correct_depth(&a, &a, 1.0, -0.1).is_err());
        assert!(percent_correct_depth(&a, &ImageF32::filled(4, 3, 0.0), 1.0, 0.1).is_err());
    }

    #[test]
    fn eval_read_depth_map_png_and_npy() {
        let dir = std::env::temp_dir().join(format!("relfusion_depth_{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let png = dir.join("d.png");
        let buf = ::image::ImageBuffer::<::image::Luma<u16>, Vec<u16>>::from_fn(4, 2, |x, y| {
            ::image::Luma([(x * 5000 + y * 2500) as u16])
        });
        buf.save(&png).expect("write png");
        let d = read_depth_map(&png, TUM_PNG_DEPTH_SCALE).expect("png");
        assert_eq!((d.width, d.height), (4, 2));
        assert_eq!((d.at(0, 0), d.at(3, 0), d.at(1, 1)), (0.0, 3.0, 1.5));
        let npy = dir.join("d.npy");
        crate::npy::write_f32(&npy, &d).expect("write npy");
        assert_eq!(read_depth_map(&npy, 1.0).expect("npy"), d);
        assert!(read_depth_map(&dir.join("d.exr"), 1.0).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
