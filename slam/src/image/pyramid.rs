//! Image pyramids with per-level gradients: the CPU reference (twin) of the GPU kernels
//! `pyramid_downsample.wgsl` and `image_gradient.wgsl` (run by [`crate::gpu::PyramidKernel`]).
//!
//! LSD-SLAM's direct image alignment (Engel et al., ECCV 2014) is solved coarse-to-fine: each
//! level halves the previous one by averaging 2×2 blocks (`Frame::buildImage` in its source),
//! and every level carries the intensity gradients used by the Jacobian of the photometric
//! residual and by the selection of high-gradient (semi-dense) pixels (`Frame::buildGradients`).
//!
//! Definitions shared bit-for-bit in intent with the WGSL kernels:
//! - level `L+1` is `floor(w/2) × floor(h/2)`; pixel `(x, y)` is
//!   `0.25 · ((I(2x, 2y) + I(2x+1, 2y)) + (I(2x, 2y+1) + I(2x+1, 2y+1)))`; for odd sizes the
//!   last source column/row is dropped;
//! - `gx = 0.5 · (I(x+1, y) − I(x−1, y))`, `gy = 0.5 · (I(x, y+1) − I(x, y−1))`,
//!   `grad_mag = sqrt(gx² + gy²)`;
//! - **border rule**: neighbour coordinates are clamped to the image (clamp-to-edge), so on the
//!   first/last column `gx` is half the one-sided difference, and `gx = 0` on a 1-pixel-wide
//!   image (likewise for rows and `gy`).

use super::ImageF32;
use crate::{Error, Result};

/// One pyramid level: the intensity image and its gradients, all of the same size.
#[derive(Clone, Debug, PartialEq)]
pub struct PyramidLevel {
    /// Intensities in 8-bit units (0..255).
    pub image: ImageF32,
    /// Horizontal central difference ∂I/∂x (clamp-to-edge at the borders).
    pub gx: ImageF32,
    /// Vertical central difference ∂I/∂y (clamp-to-edge at the borders).
    pub gy: ImageF32,
    /// Gradient magnitude `sqrt(gx² + gy²)`.
    pub grad_mag: ImageF32,
}

impl PyramidLevel {
    /// Level width in pixels.
    pub fn width(&self) -> usize {
        self.image.width
    }

    /// Level height in pixels.
    pub fn height(&self) -> usize {
        self.image.height
    }
}

/// An image pyramid, finest level first (`levels[0]` has the input's size).
#[derive(Clone, Debug, PartialEq)]
pub struct Pyramid {
    pub levels: Vec<PyramidLevel>,
}

impl Pyramid {
    /// Builds `levels` levels on the CPU (the reference the GPU kernel is tested against).
    ///
    /// Fails with [`Error::Shape`] when `levels` is 0 or when a level would be empty
    /// (see [`level_sizes`]).
    pub fn build_cpu(image: &ImageF32, levels: usize) -> Result<Self> {
        let sizes = level_sizes(image.width, image.height, levels)?;
        image.check_size()?;
        let mut out = Vec::with_capacity(sizes.len());
        let mut current = image.clone();
        for level in 0..sizes.len() {
            if level > 0 {
                current = downsample_cpu(&current);
            }
            let (gx, gy, grad_mag) = gradients_cpu(&current);
            out.push(PyramidLevel {
                image: current.clone(),
                gx,
                gy,
                grad_mag,
            });
        }
        Ok(Self { levels: out })
    }

    /// Largest absolute difference between two pyramids over every level and every output
    /// (image, gx, gy, grad_mag); fails if their level counts or sizes differ.
    pub fn max_abs_diff(&self, other: &Pyramid) -> Result<f32> {
        if self.levels.len() != other.levels.len() {
            return Err(Error::Shape(format!(
                "pyramids with {} and {} levels",
                self.levels.len(),
                other.levels.len()
            )));
        }
        let mut worst = 0.0f32;
        for (l, (a, b)) in self.levels.iter().zip(&other.levels).enumerate() {
            for (name, x, y) in [
                ("image", &a.image, &b.image),
                ("gx", &a.gx, &b.gx),
                ("gy", &a.gy, &b.gy),
                ("grad_mag", &a.grad_mag, &b.grad_mag),
            ] {
                if (x.width, x.height) != (y.width, y.height) || x.data.len() != y.data.len() {
                    return Err(Error::Shape(format!(
                        "level {l} {name}: {}x{} vs {}x{}",
                        x.width, x.height, y.width, y.height
                    )));
                }
                for (p, q) in x.data.iter().zip(&y.data) {
                    let d = (p - q).abs();
                    // NaN must not hide behind `max`: report it as an infinite difference.
                    worst = if d.is_nan() {
                        f32::INFINITY
                    } else {
                        worst.max(d)
                    };
                }
            }
        }
        Ok(worst)
    }
}

/// Sizes `(width, height)` of the `levels` levels of a pyramid over a `width × height` image,
/// finest first; each level is `floor(w/2) × floor(h/2)` of the previous one.
///
/// Fails with [`Error::Shape`] when `levels == 0` or when any level would have a zero side
/// (e.g. 5 levels need at least 16×16 input pixels).
pub fn level_sizes(width: usize, height: usize, levels: usize) -> Result<Vec<(usize, usize)>> {
    if levels == 0 {
        return Err(Error::Shape("a pyramid needs at least one level".into()));
    }
    let mut sizes = Vec::with_capacity(levels);
    let (mut w, mut h) = (width, height);
    for level in 0..levels {
        if w == 0 || h == 0 {
            return Err(Error::Shape(format!(
                "a {width}x{height} image has no pyramid level {level} (of {levels} requested)"
            )));
        }
        sizes.push((w, h));
        w /= 2;
        h /= 2;
    }
    Ok(sizes)
}

/// One 2×2 box-filter downsampling step, `floor(w/2) × floor(h/2)` (twin of
/// `pyramid_downsample.wgsl`; same summation order).
pub fn downsample_cpu(src: &ImageF32) -> ImageF32 {
    let (w, h) = (src.width / 2, src.height / 2);
    let mut dst = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        let top = &src.data[2 * y * src.width..];
        let bottom = &src.data[(2 * y + 1) * src.width..];
        for x in 0..w {
            let t = top[2 * x] + top[2 * x + 1];
            let b = bottom[2 * x] + bottom[2 * x + 1];
            dst.data[y * w + x] = 0.25 * (t + b);
        }
    }
    dst
}

/// Central-difference gradients and their magnitude with the clamp-to-edge border rule (twin of
/// `image_gradient.wgsl`). Returns `(gx, gy, grad_mag)`.
pub fn gradients_cpu(img: &ImageF32) -> (ImageF32, ImageF32, ImageF32) {
    let (w, h) = (img.width, img.height);
    let mut gx = ImageF32::filled(w, h, 0.0);
    let mut gy = ImageF32::filled(w, h, 0.0);
    let mut mag = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        let yu = y.saturating_sub(1);
        let yd = (y + 1).min(h - 1);
        for x in 0..w {
            let xl = x.saturating_sub(1);
            let xr = (x + 1).min(w - 1);
            let dx = 0.5 * (img.at(xr, y) - img.at(xl, y));
            let dy = 0.5 * (img.at(x, yd) - img.at(x, yu));
            let i = y * w + x;
            gx.data[i] = dx;
            gy.data[i] = dy;
            mag.data[i] = (dx * dx + dy * dy).sqrt();
        }
    }
    (gx, gy, mag)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pyramid_level_sizes_floor_and_reject_empty_levels() {
        let sizes = level_sizes(641, 479, 5).expect("5 levels of 641x479 exist");
        assert_eq!(
            sizes,
            vec![(641, 479), (320, 239), (160, 119), (80, 59), (40, 29)]
        );
        assert!(level_sizes(640, 480, 0).is_err());
        assert!(
            level_sizes(15, 100, 5).is_err(),
            "15 px wide has only 4 levels"
        );
        assert!(level_sizes(16, 16, 5).is_ok());
    }

    #[test]
    fn pyramid_downsample_averages_blocks_and_drops_odd_edge() {
        // 3x3 with a distinctive last row/column that must be ignored.
        let img = ImageF32::from_vec(
            3,
            3,
            vec![1.0, 3.0, 100.0, 5.0, 7.0, 100.0, 100.0, 100.0, 100.0],
        )
        .expect("3x3");
        let d = downsample_cpu(&img);
        assert_eq!((d.width, d.height), (1, 1));
        assert_eq!(d.data, vec![4.0]);
    }

    #[test]
    fn pyramid_gradients_of_a_linear_ramp_are_exact_inside_and_halved_on_borders() {
        // I(x, y) = 3x + 2y: interior gx = 3, gy = 2; borders are one-sided halves (1.5, 1).
        let (w, h) = (6, 5);
        let data = (0..h)
            .flat_map(|y| (0..w).map(move |x| (3 * x + 2 * y) as f32))
            .collect();
        let img = ImageF32::from_vec(w, h, data).expect("ramp");
        let (gx, gy, mag) = gradients_cpu(&img);
        assert_eq!(gx.at(2, 2), 3.0);
        assert_eq!(gy.at(2, 2), 2.0);
        assert!((mag.at(2, 2) - 13f32.sqrt()).abs() < 1e-6);
        assert_eq!(gx.at(0, 2), 1.5);
        assert_eq!(gx.at(w - 1, 2), 1.5);
        assert_eq!(gy.at(3, 0), 1.0);
        assert_eq!(gy.at(3, h - 1), 1.0);
    }

    #[test]
    fn pyramid_build_cpu_chains_levels_and_keeps_constant_images_flat() {
        let img = ImageF32::filled(37, 23, 42.0);
        let pyr = Pyramid::build_cpu(&img, 3).expect("3 levels");
        assert_eq!(pyr.levels.len(), 3);
        assert_eq!((pyr.levels[2].width(), pyr.levels[2].height()), (9, 5));
        for level in &pyr.levels {
            assert!(level.image.data.iter().all(|&v| v == 42.0));
            assert!(level.grad_mag.data.iter().all(|&v| v == 0.0));
        }
        assert_eq!(pyr.max_abs_diff(&pyr).expect("same shape"), 0.0);
    }

    #[test]
    fn pyramid_max_abs_diff_sees_changes_and_nan() {
        let img = ImageF32::from_vec(4, 4, (0..16).map(|v| v as f32).collect()).expect("4x4");
        let a = Pyramid::build_cpu(&img, 2).expect("2 levels");
        let mut b = a.clone();
        b.levels[1].gy.data[0] += 0.25;
        assert_eq!(a.max_abs_diff(&b).expect("same shape"), 0.25);
        b.levels[0].image.data[3] = f32::NAN;
        assert_eq!(a.max_abs_diff(&b).expect("same shape"), f32::INFINITY);
        let c = Pyramid::build_cpu(&img, 1).expect("1 level");
        assert!(a.max_abs_diff(&c).is_err());
    }
}
