//! The keyframe at the dense layer's working resolution (the paper resizes to 320×240 before
//! prediction and densification, §IV).
//!
//! Every source pixel belongs to exactly one working pixel (`x_w = ⌊x · w / W⌋`), so a 2×
//! reduction is the 2×2 box of the image pyramid and other ratios still use every pixel once.
//! The camera follows the pyramid's pixel-centre convention (`cx' = (cx + ½)/s − ½`).

use crate::geometry::PinholeCamera;
use crate::image::ImageF32;
use crate::mapping::DepthMap;
use crate::{Error, Result};

/// Working size for a `width`×`height` keyframe: the configured width (never more than the
/// image's), the height following the image's aspect ratio.
pub fn working_size(width: usize, height: usize, max_width: usize) -> (usize, usize) {
    let w = max_width.min(width).max(1);
    let h = ((height as f64 * w as f64 / width as f64).round() as usize).clamp(1, height.max(1));
    (w, h)
}

/// The camera of a `w`×`h` resampling of `camera`'s image.
pub fn working_camera(camera: &PinholeCamera, w: usize, h: usize) -> PinholeCamera {
    let sx = f64::from(camera.width) / w as f64;
    let sy = f64::from(camera.height) / h as f64;
    PinholeCamera {
        fx: camera.fx / sx,
        fy: camera.fy / sy,
        cx: (camera.cx + 0.5) / sx - 0.5,
        cy: (camera.cy + 0.5) / sy - 0.5,
        width: w as u32,
        height: h as u32,
        distortion: None,
    }
}

/// Working-pixel index of every source column (or row).
fn bins(src: usize, dst: usize) -> Vec<usize> {
    (0..src).map(|i| i * dst / src).collect()
}

fn check_reduction(what: &str, src: (usize, usize), dst: (usize, usize)) -> Result<()> {
    if dst.0 == 0 || dst.1 == 0 || dst.0 > src.0 || dst.1 > src.1 {
        return Err(Error::Shape(format!(
            "{what}: cannot resample {}x{} to {}x{} (only reductions)",
            src.0, src.1, dst.0, dst.1
        )));
    }
    Ok(())
}

/// Box average of an image (intensity, or a dense prior whose every pixel is valid).
pub fn box_downsample(src: &ImageF32, w: usize, h: usize) -> Result<ImageF32> {
    check_reduction("image", (src.width, src.height), (w, h))?;
    let (bx, by) = (bins(src.width, w), bins(src.height, h));
    let mut sum = vec![0.0f64; w * h];
    let mut count = vec![0u32; w * h];
    for (y, &ty) in by.iter().enumerate() {
        let row = &src.data[y * src.width..(y + 1) * src.width];
        for (&v, &tx) in row.iter().zip(&bx) {
            sum[ty * w + tx] += f64::from(v);
            count[ty * w + tx] += 1;
        }
    }
    let data = sum
        .iter()
        .zip(&count)
        .map(|(&s, &n)| (s / f64::from(n.max(1))) as f32)
        .collect();
    ImageF32::from_vec(w, h, data).map_err(Into::into)
}

/// The semi-dense map at the working resolution: per working pixel, the inverse-variance
/// weighted mean of the estimates in its block and the *mean* of their variances (neighbouring
/// estimates share their stereo observations, so averaging them does not shrink the
/// uncertainty as independent measurements would). `(idepth, variance)`, 0 = no estimate.
pub fn downsample_depth(depth: &DepthMap, w: usize, h: usize) -> Result<(ImageF32, ImageF32)> {
    check_reduction("depth map", (depth.width, depth.height), (w, h))?;
    let (bx, by) = (bins(depth.width, w), bins(depth.height, h));
    let mut wsum = vec![0.0f64; w * h];
    let mut dsum = vec![0.0f64; w * h];
    let mut vsum = vec![0.0f64; w * h];
    let mut count = vec![0u32; w * h];
    for (y, &ty) in by.iter().enumerate() {
        for (x, &tx) in bx.iter().enumerate() {
            let Some((d, v)) = depth.pixels[y * depth.width + x].estimate() else {
                continue;
            };
            if !(d.is_finite() && d > 0.0 && v.is_finite() && v > 0.0) {
                continue;
            }
            let i = ty * w + tx;
            let weight = 1.0 / f64::from(v);
            wsum[i] += weight;
            dsum[i] += weight * f64::from(d);
            vsum[i] += f64::from(v);
            count[i] += 1;
        }
    }
    let mut idepth = ImageF32::filled(w, h, 0.0);
    let mut var = ImageF32::filled(w, h, 0.0);
    for i in 0..w * h {
        if count[i] > 0 {
            idepth.data[i] = (dsum[i] / wsum[i]) as f32;
            var.data[i] = (vsum[i] / f64::from(count[i])) as f32;
        }
    }
    Ok((idepth, var))
}

/// Colour of every working pixel: the box average of the keyframe's RGB image (for
/// colouring the dense point cloud and the fused mesh).
pub fn box_downsample_rgb(rgb: &::image::RgbImage, w: usize, h: usize) -> Result<Vec<[u8; 3]>> {
    let (sw, sh) = (rgb.width() as usize, rgb.height() as usize);
    check_reduction("colour image", (sw, sh), (w, h))?;
    let (bx, by) = (bins(sw, w), bins(sh, h));
    let mut sum = vec![[0u32; 3]; w * h];
    let mut count = vec![0u32; w * h];
    for (y, &ty) in by.iter().enumerate() {
        for (x, &tx) in bx.iter().enumerate() {
            let p = rgb.get_pixel(x as u32, y as u32).0;
            let i = ty * w + tx;
            for c in 0..3 {
                sum[i][c] += u32::from(p[c]);
            }
            count[i] += 1;
        }
    }
    Ok(sum
        .iter()
        .zip(&count)
        .map(|(s, &n)| {
            let n = n.max(1);
            [
                ((s[0] + n / 2) / n) as u8,
                ((s[1] + n / 2) / n) as u8,
                ((s[2] + n / 2) / n) as u8,
            ]
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::pyramid::downsample_cpu;
    use crate::mapping::depth_map::InverseDepth;

    #[test]
    fn halving_is_the_pyramid_box_and_the_pyramid_camera() {
        let data: Vec<f32> = (0..64 * 48).map(|i| ((i * 37) % 251) as f32).collect();
        let img = ImageF32::from_vec(64, 48, data).expect("valid");
        let ours = box_downsample(&img, 32, 24).expect("valid");
        let pyramid = downsample_cpu(&img);
        for (a, b) in ours.data.iter().zip(&pyramid.data) {
            assert!((a - b).abs() < 1e-4, "{a} vs {b}");
        }
        let cam = PinholeCamera::new(525.0, 520.0, 319.5, 239.5, 640, 480).expect("valid");
        let half = working_camera(&cam, 320, 240);
        let level1 = cam.scaled(1);
        assert!((half.fx - level1.fx).abs() < 1e-12 && (half.cx - level1.cx).abs() < 1e-12);
        assert!((half.fy - level1.fy).abs() < 1e-12 && (half.cy - level1.cy).abs() < 1e-12);
        assert_eq!(working_size(640, 480, 320), (320, 240));
        assert_eq!(working_size(320, 240, 320), (320, 240));
        assert_eq!(working_size(200, 100, 320), (200, 100));
        assert!(box_downsample(&img, 65, 10).is_err());
    }

    #[test]
    fn depth_blocks_weight_by_inverse_variance_and_keep_holes() {
        let mut map = DepthMap::unknown(4, 2);
        map.pixels[0] = InverseDepth::Estimate {
            idepth: 1.0,
            var: 0.01,
        };
        map.pixels[1] = InverseDepth::Estimate {
            idepth: 2.0,
            var: 0.03,
        };
        map.pixels[4] = InverseDepth::Discarded;
        let (d, v) = downsample_depth(&map, 2, 1).expect("valid");
        // weights 100 and 33.3: (100·1 + 33.3·2) / 133.3 = 1.25
        assert!((d.data[0] - 1.25).abs() < 1e-5, "{}", d.data[0]);
        assert!((v.data[0] - 0.02).abs() < 1e-6);
        assert_eq!((d.data[1], v.data[1]), (0.0, 0.0));
    }
}
