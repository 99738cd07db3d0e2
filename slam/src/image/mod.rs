//! Grayscale float images (the type lives in `relfusion-core`) and their pyramids and
//! gradients, the CPU references of the GPU kernels.

pub mod pyramid;

pub use relfusion_core::image::ImageF32;

/// A smooth test image (so that bilinear interpolation and the sampled gradient agree
/// closely), shifted by `phase`: the photometric Jacobian tests compare against it.
#[cfg(test)]
pub(crate) fn smooth_test_image(w: usize, h: usize, phase: f32) -> ImageF32 {
    let mut img = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let (xf, yf) = (x as f32, y as f32);
            *img.at_mut(x, y) = 120.0
                + 50.0 * (0.035 * xf + phase).sin() * (0.03 * yf).cos()
                + 30.0 * (0.02 * xf + 0.025 * yf + 2.0 * phase).sin();
        }
    }
    img
}
