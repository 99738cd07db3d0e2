//! Synthetic test fixture: a short orbit through the textured room with exact depth and
//! poses, rendered once per test binary and shared by the mapping tests.

use std::sync::{Arc, OnceLock};

use crate::dataset::synth::{Motion, Scene, SynthConfig, render_frame_with};
use crate::frame::Frame;
use crate::geometry::{PinholeCamera, SE3};
use crate::image::ImageF32;
use crate::mapping::DepthMap;

/// Rendered frames with their ground truth.
pub(crate) struct SynthScene {
    pub camera: PinholeCamera,
    pub frames: Vec<Arc<Frame>>,
    /// `world_from_camera` of each frame.
    pub poses: Vec<SE3>,
    /// Exact z-depth (metres) of each frame.
    pub depths: Vec<ImageF32>,
}

impl SynthScene {
    /// Renders `n` frames of `motion` at `width × height` (2 threads, 2×2 supersampling).
    pub fn render(motion: Motion, n: usize, width: u32, height: u32) -> Self {
        let config = SynthConfig {
            frames: n,
            seed: 3,
            motion,
            width,
            height,
            ..SynthConfig::default()
        };
        let camera = config.camera().expect("valid synthetic camera");
        let poses = config.poses();
        let scene = Scene::generate(config.seed);
        let mut rendered: Vec<Option<(Arc<Frame>, ImageF32)>> = (0..n).map(|_| None).collect();
        std::thread::scope(|s| {
            for (part, chunk) in rendered.chunks_mut(n.div_ceil(2)).enumerate() {
                let (scene, poses) = (&scene, &poses);
                s.spawn(move || {
                    for (j, slot) in chunk.iter_mut().enumerate() {
                        let i = part * n.div_ceil(2) + j;
                        let (rgb, depth) = render_frame_with(scene, &camera, &poses[i], 2);
                        let gray = ImageF32::from_rgb8(&rgb);
                        let frame = Frame::new(i as u64, i as f64 / 30.0, camera, &gray, None)
                            .expect("frame from rendered image");
                        *slot = Some((Arc::new(frame), depth));
                    }
                });
            }
        });
        let (frames, depths) = rendered
            .into_iter()
            .map(|r| r.expect("every frame rendered"))
            .unzip();
        Self {
            camera,
            frames,
            poses,
            depths,
        }
    }

    /// Pose of frame `i` relative to frame `kf` (maps frame-`i` points into frame `kf`).
    pub fn relative(&self, kf: usize, i: usize) -> SE3 {
        self.poses[kf].inverse() * self.poses[i]
    }

    /// Exact inverse depth of frame `i`.
    pub fn idepth(&self, i: usize) -> ImageF32 {
        let d = &self.depths[i];
        let data = d
            .data
            .iter()
            .map(|&z| if z > 0.0 { 1.0 / z } else { 0.0 })
            .collect();
        ImageF32::from_vec(d.width, d.height, data).expect("same size")
    }
}

/// 40 frames of the orbit preset at 320×240 (about 0.35 m of translation), shared.
pub(crate) fn orbit_320() -> &'static SynthScene {
    static SCENE: OnceLock<SynthScene> = OnceLock::new();
    SCENE.get_or_init(|| SynthScene::render(Motion::Orbit, 40, 320, 240))
}

/// Relative inverse-depth errors |ρ − ρ_gt|/ρ_gt of all published estimates.
pub(crate) fn relative_errors(map: &DepthMap, gt_idepth: &ImageF32) -> Vec<f64> {
    map.pixels
        .iter()
        .zip(&gt_idepth.data)
        .filter_map(|(p, &gt)| {
            let (d, _) = p.estimate()?;
            (gt > 0.0).then(|| f64::from((d - gt).abs() / gt))
        })
        .collect()
}

/// Median of a non-empty sample (NaN when empty).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Fraction of values above `t`.
pub(crate) fn share_above(v: &[f64], t: f64) -> f64 {
    v.iter().filter(|&&e| e > t).count() as f64 / v.len().max(1) as f64
}
