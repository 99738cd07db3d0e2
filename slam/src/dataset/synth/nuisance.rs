//! Photometric nuisances of a real camera, applied to the ideal rendering: auto-exposure gain
//! changes, vignetting, motion blur, sensor noise and JPEG compression (issue 22: development
//! data that is not kinder than real video).
//!
//! Order follows the image formation: the scene radiance is integrated over the shutter time
//! (motion blur: the mean of renderings at poses spread over the exposure; with a rolling
//! shutter each rendering sees each row from that row's pose), attenuated by the
//! lens (vignetting, `1 − k·r²` with `r` the distance from the centre over the half diagonal),
//! scaled by the exposure gain, disturbed by noise, quantised to 8 bits and compressed. TUM and
//! 7-Scenes frames show all of these; the direct tracker models only the global affine part
//! (gain), so the rest is what it must be robust to.
//!
//! Every random draw comes from a ChaCha stream seeded by the sequence seed and the frame index:
//! a frame's nuisances do not depend on which thread renders it or on the frame count.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Strength of each nuisance; all zero (the default) renders the ideal camera.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Nuisances {
    /// Amplitude of the natural log of the auto-exposure gain: the gain wanders smoothly
    /// within `exp(±exposure)` (two sinusoids, 7 s and 2.3 s periods, seed-dependent phases).
    pub exposure: f64,
    /// Vignetting strength `k`: brightness falls to `1 − k` in the image corners.
    pub vignetting: f64,
    /// Standard deviation of the additive Gaussian sensor noise, grey levels (0-255).
    pub noise: f64,
    /// Shutter time as a fraction of the frame interval (0 = no motion blur): the frame is
    /// the mean of [`BLUR_SAMPLES`] renderings spread over it.
    pub motion_blur: f64,
    /// JPEG quality of the colour images (1-100); 0 writes lossless PNG.
    pub jpeg_quality: u8,
    /// Rolling shutter: the time the sensor takes to read its rows, as a fraction of the
    /// frame interval (0 = global shutter). Row `y` is seen at the frame's time plus
    /// `(y/h − ½)` of it; the ground truth is the middle row's pose.
    pub rolling_shutter: f64,
}

impl Default for Nuisances {
    fn default() -> Self {
        Self {
            exposure: 0.0,
            vignetting: 0.0,
            noise: 0.0,
            motion_blur: 0.0,
            jpeg_quality: 0,
            rolling_shutter: 0.0,
        }
    }
}

/// Renderings averaged per frame for motion blur.
pub const BLUR_SAMPLES: usize = 3;

impl Nuisances {
    /// A hand-held consumer camera: gain within ±25 %, 30 % darker corners, σ = 2 grey levels
    /// of noise, a half-frame shutter and JPEG at quality 85 (the figures of a phone or a
    /// Kinect-class RGB sensor indoors).
    pub const CAMERA: Nuisances = Nuisances {
        exposure: 0.22,
        vignetting: 0.3,
        noise: 2.0,
        motion_blur: 0.5,
        jpeg_quality: 85,
        rolling_shutter: 0.0,
    };

    /// Whether any nuisance is on.
    pub fn any(&self) -> bool {
        *self != Self::default()
    }

    pub(super) fn validate(&self) -> Result<()> {
        let check = |ok: bool, what: &str| {
            if ok {
                Ok(())
            } else {
                Err(Error::Config(format!("synth nuisances: {what}")))
            }
        };
        check(
            self.exposure.is_finite() && (0.0..=2.0).contains(&self.exposure),
            "exposure must be in 0..=2",
        )?;
        check(
            self.vignetting.is_finite() && (0.0..1.0).contains(&self.vignetting),
            "vignetting must be in 0..1",
        )?;
        check(
            self.noise.is_finite() && (0.0..=64.0).contains(&self.noise),
            "noise must be in 0..=64 grey levels",
        )?;
        check(
            self.motion_blur.is_finite() && (0.0..=1.0).contains(&self.motion_blur),
            "motion_blur must be in 0..=1 frame intervals",
        )?;
        check(
            self.rolling_shutter.is_finite() && (0.0..=1.0).contains(&self.rolling_shutter),
            "rolling_shutter must be in 0..=1 frame intervals",
        )?;
        check(self.jpeg_quality <= 100, "jpeg_quality must be 0..=100")
    }

    /// Time offsets (seconds) of the renderings averaged into a frame at `fps`: just `[0]`
    /// without blur, else [`BLUR_SAMPLES`] offsets spread evenly over the shutter, centred
    /// on the frame's timestamp (the ground truth is the pose at mid-exposure).
    pub fn exposure_offsets(&self, fps: f64) -> Vec<f64> {
        if self.motion_blur <= 0.0 {
            return vec![0.0];
        }
        let shutter = self.motion_blur / fps;
        (0..BLUR_SAMPLES)
            .map(|j| shutter * ((j as f64 + 0.5) / BLUR_SAMPLES as f64 - 0.5))
            .collect()
    }

    /// The auto-exposure gain at time `t` (seconds) for `seed`.
    pub fn gain(&self, seed: u64, t: f64) -> f64 {
        if self.exposure <= 0.0 {
            return 1.0;
        }
        // Phases from the seed, without a stream that other draws share.
        let phase = |k: u64| {
            let h = seed
                .wrapping_mul(0x9E37_79B9_7F4A_7C15)
                .wrapping_add(k.wrapping_mul(0xBF58_476D_1CE4_E5B9));
            (h >> 11) as f64 / (1u64 << 53) as f64 * std::f64::consts::TAU
        };
        let tau = std::f64::consts::TAU;
        let x = 0.65 * (tau * t / 7.0 + phase(1)).sin() + 0.35 * (tau * t / 2.3 + phase(2)).sin();
        (self.exposure * x).exp()
    }

    /// Applies gain, vignetting and noise to the mean `linear` colour (0-255 per channel,
    /// `width × height × 3`) of frame `index`, and quantises to 8 bits.
    pub fn apply(
        &self,
        linear: &[f32],
        width: u32,
        height: u32,
        seed: u64,
        index: usize,
        t: f64,
    ) -> ::image::RgbImage {
        let gain = self.gain(seed, t) as f32;
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6e75_6973_616e_6365);
        rng.set_stream(index as u64 + 16);
        let sigma = self.noise as f32;
        // Box-Muller: one standard normal per draw (the second of the pair is not kept, so a
        // pixel's noise depends only on its position in the stream).
        let mut normal = move || {
            let u1: f32 = rng.random_range(f32::EPSILON..1.0);
            let u2: f32 = rng.random();
            (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
        };
        let (cx, cy) = ((width as f32 - 1.0) / 2.0, (height as f32 - 1.0) / 2.0);
        let inv_r2 = 1.0 / (cx * cx + cy * cy).max(1.0);
        let k = self.vignetting as f32;
        let mut out = ::image::RgbImage::new(width, height);
        for (i, px) in out.pixels_mut().enumerate() {
            let (x, y) = ((i % width as usize) as f32, (i / width as usize) as f32);
            let r2 = ((x - cx).powi(2) + (y - cy).powi(2)) * inv_r2;
            let scale = gain * (1.0 - k * r2);
            for c in 0..3 {
                let mut v = linear[3 * i + c] * scale;
                if sigma > 0.0 {
                    v += sigma * normal();
                }
                px.0[c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
        out
    }
}

/// The colour image encoded as the nuisances say: JPEG at their quality, or PNG.
pub fn encode(image: &::image::RgbImage, jpeg_quality: u8) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    let result = if jpeg_quality == 0 {
        image.write_with_encoder(::image::codecs::png::PngEncoder::new(&mut bytes))
    } else {
        image.write_with_encoder(::image::codecs::jpeg::JpegEncoder::new_with_quality(
            &mut bytes,
            jpeg_quality,
        ))
    };
    result.map_err(|source| Error::Image {
        path: "synthetic frame".into(),
        source,
    })?;
    Ok(bytes)
}
