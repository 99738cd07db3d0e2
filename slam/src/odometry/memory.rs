//! The most memory the odometry holds, for the server's admission (`memory::SessionCost`).
//!
//! What it holds beyond the pipeline's own keyframes (the window's keyframes are the
//! pipeline's newest, their frames shared) is bounded by its settings: the window thread's
//! queue of frames ([`WINDOW_QUEUE`]), each window keyframe's interleaved samples at the
//! window's level, the candidates and active points, and while it initialises two frames
//! and the corners' tracks. The figure is a bound, not what a run typically holds: the queue
//! is full only while the window lags its camera by half a second.

use std::mem::size_of;

use super::immature::ImmaturePoint;
use super::init::SCORE_FRAMES;
use super::residual::Interleaved;
use super::system::WINDOW_QUEUE;
use super::{OdometryConfig, WindowPoint, two_view};
use crate::frame::PYRAMID_LEVELS;
use crate::image::pyramid::level_sizes;

/// Bytes a frame of `width`×`height` holds: its pyramid (image and three gradient maps of
/// `f32` on every level) and its colour image (3 B a pixel), as [`crate::frame::Frame::
/// heap_bytes`] counts them.
pub fn frame_bytes(width: usize, height: usize) -> u64 {
    let pyramid: usize = level_sizes(width, height, PYRAMID_LEVELS).map_or_else(
        // Too small for every level: the full level's 16 B a pixel, times 4/3, bounds it.
        |_| 22 * width * height,
        |sizes| {
            sizes
                .iter()
                .map(|(w, h)| 4 * size_of::<f32>() * w * h)
                .sum()
        },
    );
    (pyramid + 3 * width * height) as u64
}

/// Per-point scratch of one optimisation beyond the point itself (its residuals' Jacobians
/// and Schur blocks against each target keyframe), rounded up.
const SOLVE_BYTES_PER_RESIDUAL: usize = 256;

/// The most bytes the odometry of `config` holds for a `width`×`height` camera, beyond the
/// keyframes the pipeline holds anyway.
pub fn memory_bound(config: &OdometryConfig, width: usize, height: usize) -> u64 {
    let frames = config.max_frames.max(1);
    let queue = WINDOW_QUEUE as u64 * frame_bytes(width, height);
    let (lw, lh) = level_sizes(width, height, config.level + 1)
        .ok()
        .and_then(|s| s.last().copied())
        .unwrap_or((width, height));
    let samples = frames * lw * lh * Interleaved::BYTES_PER_PIXEL;
    let points = frames * config.candidate_points * size_of::<ImmaturePoint>()
        + config.active_points * (size_of::<WindowPoint>() + frames * SOLVE_BYTES_PER_RESIDUAL);
    // The initialiser (one per candidate focal length, on the same frames): the first and
    // latest frames, each corner's position in every frame it follows them through, and with
    // several candidates the frames kept to compare them.
    let initialisers = config.focal_candidates.len().max(1);
    let corners = (width / two_view::CORNER_CELL + 1) * (height / two_view::CORNER_CELL + 1);
    let kept_frames = 2 + if initialisers > 1 { SCORE_FRAMES } else { 0 };
    let initialiser = kept_frames as u64 * frame_bytes(width, height)
        + (initialisers * corners * two_view::MAX_FRAMES * size_of::<[f32; 2]>()) as u64;
    queue + (samples + points) as u64 + initialiser
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::Frame;
    use crate::geometry::PinholeCamera;
    use crate::image::ImageF32;
    use std::sync::Arc;

    #[test]
    fn a_frames_bytes_are_what_a_real_frame_holds_and_the_bound_scales_with_its_settings() {
        let (w, h) = (640, 480);
        let camera =
            PinholeCamera::new(525.0, 525.0, 319.5, 239.5, w as u32, h as u32).expect("camera");
        let gray = ImageF32::filled(w, h, 0.0);
        let rgb = Arc::new(image::RgbImage::new(w as u32, h as u32));
        let frame = Frame::new(0, 0.0, camera, &gray, Some(rgb)).expect("frame");
        assert_eq!(frame_bytes(w, h), frame.heap_bytes() as u64);
        let config = OdometryConfig::default();
        let vga = memory_bound(&config, w, h);
        // The queue alone is 16 frames of 7.5 MB; the whole stays within what it holds.
        assert!(vga >= WINDOW_QUEUE as u64 * frame.heap_bytes() as u64);
        assert!(vga < 256 << 20, "{vga}");
        // A quarter of the pixels, about a quarter of the bytes; more keyframes, more bytes.
        let qvga = memory_bound(&config, w / 2, h / 2);
        assert!(qvga < vga / 3 && qvga > vga / 5, "{qvga} {vga}");
        let wider = OdometryConfig {
            max_frames: 10,
            ..config
        };
        assert!(memory_bound(&wider, w, h) > vga);
        let compared = OdometryConfig {
            focal_candidates: vec![0.9, 1.0, 1.1],
            ..OdometryConfig::default()
        };
        assert!(memory_bound(&compared, w, h) > vga + 12 * frame.heap_bytes() as u64);
    }
}
