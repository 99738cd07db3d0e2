//! Tests of the back end on synthetic data with exact ground truth: keyframes are rendered with
//! `dataset::synth` (320×240, the room of seed 0) and given depth maps made from the exact depth
//! at high-gradient pixels, in a per-keyframe depth scale like LSD-SLAM's normalised maps.

mod backend_tests;
mod pose_graph_tests;
mod real_tests;
mod thumbnail_tests;
mod tracker_tests;

use std::sync::{Arc, OnceLock};

use nalgebra::{Matrix3, Vector3};

use crate::dataset::synth::{Scene, SynthConfig, render_frame};
use crate::frame::Frame;
use crate::geometry::{PinholeCamera, SE3, SO3, Sim3};
use crate::image::ImageF32;
use crate::mapping::{DepthMap, InverseDepth};

/// Test image size (a quarter of VGA keeps every test fast).
pub(super) const WIDTH: u32 = 320;
pub(super) const HEIGHT: u32 = 240;

/// Pixels whose level-0 gradient magnitude exceeds this get a depth estimate (a semi-dense map).
const MIN_GRAD: f32 = 6.0;

pub(super) fn camera() -> PinholeCamera {
    SynthConfig {
        width: WIDTH,
        height: HEIGHT,
        ..SynthConfig::default()
    }
    .camera()
    .expect("valid synthetic camera")
}

pub(super) fn scene() -> &'static Scene {
    static SCENE: OnceLock<Scene> = OnceLock::new();
    SCENE.get_or_init(|| Scene::generate(0))
}

/// How the keyframe's depth map is scaled relative to metres.
#[derive(Clone, Copy, Debug)]
pub(super) enum DepthScale {
    /// Keyframe coordinates = factor × metric coordinates.
    Fixed(f64),
    /// Normalised to mean inverse depth 1, as LSD-SLAM does for every new keyframe.
    Normalised,
}

/// A rendered keyframe with its exact pose and the scale of its depth map.
#[derive(Clone, Debug)]
pub(super) struct SynthKeyframe {
    pub frame: Arc<Frame>,
    pub depth: Arc<DepthMap>,
    pub world_from_camera: SE3,
    /// Keyframe coordinates = `depth_scale` × metric camera coordinates.
    pub depth_scale: f64,
}

impl SynthKeyframe {
    /// The exact `world_from_keyframe` (metric world, keyframe depth units).
    pub fn world_from_keyframe(&self) -> Sim3 {
        Sim3::from_se3(&self.world_from_camera, 1.0 / self.depth_scale)
    }
}

/// Renders a view of the room of seed 0 and builds its semi-dense depth map from the exact
/// depth.
pub(super) fn render(id: u64, world_from_camera: SE3, scale: DepthScale) -> SynthKeyframe {
    render_in(scene(), id, world_from_camera, scale)
}

/// [`render`] in another room.
pub(super) fn render_in(
    scene: &Scene,
    id: u64,
    world_from_camera: SE3,
    scale: DepthScale,
) -> SynthKeyframe {
    let cam = camera();
    let (rgb, depth) = render_frame(scene, &cam, &world_from_camera);
    let gray = ImageF32::from_rgb8(&rgb);
    let frame = Frame::new(id, id as f64, cam, &gray, None).expect("frame of the camera's size");
    let grad = &frame.level(0).grad_mag;
    let selected: Vec<(usize, f64)> = (0..depth.data.len())
        .filter(|&i| grad.data[i] > MIN_GRAD && depth.data[i] > 0.0)
        .map(|i| (i, 1.0 / f64::from(depth.data[i])))
        .collect();
    let depth_scale = match scale {
        DepthScale::Fixed(s) => s,
        DepthScale::Normalised => {
            // mean(idepth_metric / s) = 1.
            selected.iter().map(|(_, d)| d).sum::<f64>() / selected.len().max(1) as f64
        }
    };
    let mut map = DepthMap::unknown(depth.width, depth.height);
    for (i, idepth_metric) in selected {
        let idepth = idepth_metric / depth_scale;
        map.pixels[i] = InverseDepth::Estimate {
            idepth: idepth as f32,
            var: (0.02 * idepth).powi(2) as f32,
        };
    }
    SynthKeyframe {
        frame: Arc::new(frame),
        depth: Arc::new(map),
        world_from_camera,
        depth_scale,
    }
}

/// A view from the middle of the room's free space, (−0.25, 0, 1.3) m, looking along world +x
/// (z up, as the synthetic trajectories' base view), yawed by `yaw_deg` about world z and moved
/// by `offset` (metres, world frame).
pub(super) fn view(yaw_deg: f64, offset: Vector3<f64>) -> SE3 {
    // Columns: camera right, down, forward in world coordinates.
    let base = SO3::from_matrix(&Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0));
    let yaw = SO3::exp(&Vector3::new(0.0, 0.0, yaw_deg.to_radians()));
    SE3::new(yaw * base, Vector3::new(-0.25, 0.0, 1.3) + offset)
}

/// Rotation angle (degrees) and relative scale/translation errors between two similarities.
pub(super) fn sim3_errors(estimate: &Sim3, truth: &Sim3) -> (f64, f64, Vector3<f64>) {
    let angle = (estimate.rotation * truth.rotation.inverse())
        .log()
        .norm()
        .to_degrees();
    let scale = estimate.scale / truth.scale - 1.0;
    (angle, scale, estimate.translation - truth.translation)
}
