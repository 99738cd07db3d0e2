//! Synthetic RGB-D sequences with exact ground truth: a textured room ray-cast on the CPU and
//! written in the TUM layout, so the whole pipeline can be tested deterministically (the
//! role ICL-NUIM plays in the paper's evaluation, which is not available here).
//!
//! - [`scene`]: the room, furniture, intersection and Lambertian shading;
//! - [`texture`]: procedural textures (strong gradients plus deliberate uniform areas);
//! - [`trajectory`]: the motion presets.
//!
//! Output is bit-identical for a seed: all randomness comes from `rand_chacha` streams seeded
//! by [`SynthConfig::seed`], textures are stateless hashes, and every frame is rendered
//! independently (threads only change which core renders it).

pub mod nuisance;
pub mod scene;
pub mod texture;
pub mod trajectory;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

pub use nuisance::Nuisances;
pub use scene::Scene;
pub use trajectory::{Motion, Trajectory, max_rotation_deg, path_length};

use super::DEPTH_SCALE;
use super::trajectory::{StampedPose, format_tum_trajectory};
use crate::geometry::{PinholeCamera, SE3};
use crate::image::ImageF32;
use crate::{Error, Result};

/// Parameters of a synthetic sequence. Every field has a default (`#[serde(default)]`), so a
/// config file only lists what it changes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SynthConfig {
    /// Number of frames. Default 300 (10 s at 30 Hz, one period of every motion preset).
    pub frames: usize,
    /// Seed of textures, furniture layout and trajectory phases. Default 0.
    pub seed: u64,
    /// Motion preset. Default `orbit`.
    pub motion: Motion,
    /// Image width in pixels. Default 640.
    pub width: u32,
    /// Image height in pixels. Default 480.
    pub height: u32,
    /// Frame rate, Hz (timestamps are `i / fps`). Default 30.
    pub fps: f64,
    /// Colour samples per pixel along each axis (n × n supersampling against texture
    /// aliasing). Default 2. Depth is always taken at the pixel centre.
    pub supersample: u32,
    /// Rendering threads (frames are distributed over them). Default 2.
    pub threads: usize,
    /// Photometric nuisances of a real camera ([`Nuisances`]). Default: none (ideal camera).
    pub nuisances: Nuisances,
}

impl Default for SynthConfig {
    fn default() -> Self {
        Self {
            frames: 300,
            seed: 0,
            motion: Motion::Orbit,
            width: 640,
            height: 480,
            fps: 30.0,
            supersample: 2,
            threads: 2,
            nuisances: Nuisances::default(),
        }
    }
}

/// Focal length at the reference width of 640 pixels (the TUM/Kinect nominal 525).
pub const REFERENCE_FOCAL: f64 = 525.0;

impl SynthConfig {
    /// The camera: f = 525 · width/640 (a 62° horizontal field of view at every size),
    /// principal point at the image centre `((w−1)/2, (h−1)/2)`, no distortion. At the
    /// default 640×480 that is 525 525 319.5 239.5.
    pub fn camera(&self) -> Result<PinholeCamera> {
        let f = REFERENCE_FOCAL * f64::from(self.width) / 640.0;
        let cx = (f64::from(self.width) - 1.0) / 2.0;
        let cy = (f64::from(self.height) - 1.0) / 2.0;
        PinholeCamera::new(f, f, cx, cy, self.width, self.height).map_err(Into::into)
    }

    /// The camera poses (camera-to-world) of all frames.
    pub fn poses(&self) -> Vec<SE3> {
        Trajectory::new(self.motion, self.seed).poses(self.frames, self.fps)
    }

    /// The file extension of the colour images (`jpg` with JPEG compression on).
    pub fn rgb_extension(&self) -> &'static str {
        if self.nuisances.jpeg_quality > 0 {
            "jpg"
        } else {
            "png"
        }
    }

    /// Refuses sizes, rates and sample counts outside their ranges.
    pub fn validate(&self) -> Result<()> {
        if self.frames == 0 {
            return Err(Error::Config("synth: frames must be at least 1".into()));
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(Error::Config(format!(
                "synth: fps must be positive, got {}",
                self.fps
            )));
        }
        if !(1..=8).contains(&self.supersample) {
            return Err(Error::Config(format!(
                "synth: supersample must be 1..=8, got {}",
                self.supersample
            )));
        }
        if !(8..=8192).contains(&self.width) || !(8..=8192).contains(&self.height) {
            return Err(Error::Config(format!(
                "synth: image size {}x{} outside 8..=8192",
                self.width, self.height
            )));
        }
        self.nuisances.validate()
    }
}

/// What [`render_sequence`] produced.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SynthSummary {
    /// Frames written.
    pub frames: usize,
    /// Camera-centre path length, metres.
    pub path_length_m: f64,
    /// Largest rotation relative to the first frame, degrees.
    pub max_rotation_deg: f64,
}

/// Renders one view with 2×2 supersampling: the colour image and the exact z-depth (metres)
/// at each pixel centre (0 where a ray hits nothing, which cannot happen inside the room).
/// Lens distortion of `camera` is ignored: the synthetic camera is an ideal pinhole.
pub fn render_frame(
    scene: &Scene,
    camera: &PinholeCamera,
    world_from_camera: &SE3,
) -> (::image::RgbImage, ImageF32) {
    render_frame_with(scene, camera, world_from_camera, 2)
}

/// [`render_frame`] with `n × n` colour samples per pixel (`n` ≥ 1).
pub fn render_frame_with(
    scene: &Scene,
    camera: &PinholeCamera,
    world_from_camera: &SE3,
    n: u32,
) -> (::image::RgbImage, ImageF32) {
    render_rows(scene, camera, &|_| *world_from_camera, false, n)
}

/// A rolling-shutter view: row `y` seen from `pose_of_row(y)` (a real sensor reads its rows
/// one after another while the camera moves), `n × n` colour samples per pixel.
pub fn render_rolling(
    scene: &Scene,
    camera: &PinholeCamera,
    pose_of_row: &dyn Fn(u32) -> SE3,
    n: u32,
) -> (::image::RgbImage, ImageF32) {
    render_rows(scene, camera, pose_of_row, true, n)
}

/// Ray-casts every row from `pose_of_row`; `per_row`: the pose changes from row to row (the
/// blocks' image bounds are then recomputed per row, else once).
fn render_rows(
    scene: &Scene,
    camera: &PinholeCamera,
    pose_of_row: &dyn Fn(u32) -> SE3,
    per_row: bool,
    n: u32,
) -> (::image::RgbImage, ImageF32) {
    let (w, h) = (camera.width, camera.height);
    let n = n.max(1);
    let inv_samples = 1.0 / (n * n) as f32;
    let mut rgb = ::image::RgbImage::new(w, h);
    let mut depth = ImageF32::filled(w as usize, h as usize, 0.0);
    let first = pose_of_row(0);
    let mut bounds = scene.block_pixel_bounds(camera, &first);
    for y in 0..h {
        let world_from_camera = if per_row && y > 0 {
            let pose = pose_of_row(y);
            bounds = scene.block_pixel_bounds(camera, &pose);
            pose
        } else {
            first
        };
        let rot = world_from_camera.rotation.matrix();
        let origin = world_from_camera.translation;
        // Ray through image point (x, y) with camera-frame z = 1: the hit parameter is z-depth.
        let ray = |x: f64, y: f64| {
            rot * Vector3::new(
                (x - camera.cx) / camera.fx,
                (y - camera.cy) / camera.fy,
                1.0,
            )
        };
        let py = f64::from(y);
        let row_mask = bounds
            .iter()
            .enumerate()
            .filter(|(_, r)| py >= r[2] && py <= r[3])
            .fold(0u64, |m, (k, _)| m | (1u64 << k.min(63)));
        for x in 0..w {
            let px = f64::from(x);
            let mask = bounds
                .iter()
                .enumerate()
                .filter(|(k, r)| row_mask & (1u64 << (*k).min(63)) != 0 && px >= r[0] && px <= r[1])
                .fold(0u64, |m, (k, _)| m | (1u64 << k.min(63)));
            let centre = ray(px, py);
            if let Some(hit) = scene.intersect_blocks(&origin, &centre, mask) {
                *depth.at_mut(x as usize, y as usize) = hit.t as f32;
            }
            let mut acc = [0.0f32; 3];
            for sy in 0..n {
                for sx in 0..n {
                    let ox = (f64::from(sx) + 0.5) / f64::from(n) - 0.5;
                    let oy = (f64::from(sy) + 0.5) / f64::from(n) - 0.5;
                    let dir = ray(px + ox, py + oy);
                    if let Some(hit) = scene.intersect_blocks(&origin, &dir, mask) {
                        let c = scene.shade(&origin, &dir, &hit);
                        for k in 0..3 {
                            acc[k] += c[k];
                        }
                    }
                }
            }
            let px = acc.map(|c| (c * inv_samples * 255.0).round().clamp(0.0, 255.0) as u8);
            rgb.put_pixel(x, y, ::image::Rgb(px));
        }
    }
    (rgb, depth)
}

/// Depth in metres → TUM 16-bit PNG values (metres × 5000, rounded; 0 = none; saturates at
/// 13.1 m, far beyond the room).
fn depth_to_u16(depth: &ImageF32) -> Result<::image::ImageBuffer<::image::Luma<u16>, Vec<u16>>> {
    let data = depth
        .data
        .iter()
        .map(|&d| {
            if d > 0.0 {
                (f64::from(d) * DEPTH_SCALE).round().clamp(1.0, 65535.0) as u16
            } else {
                0
            }
        })
        .collect();
    ::image::ImageBuffer::from_raw(depth.width as u32, depth.height as u32, data)
        .ok_or_else(|| Error::Shape("depth buffer size".into()))
}

fn timestamp(i: usize, fps: f64) -> String {
    format!("{:.6}", i as f64 / fps)
}

/// Renders the sequence of `config` into `out_dir` in the TUM layout: `rgb/<t>.png`,
/// `depth/<t>.png`, `rgb.txt`, `depth.txt`, `associations.txt`, `groundtruth.txt`
/// (camera-to-world) and `calibration.txt`. Frames are rendered on `config.threads` threads.
pub fn render_sequence(config: &SynthConfig, out_dir: &Path) -> Result<SynthSummary> {
    config.validate()?;
    let camera = config.camera()?;
    let scene = Scene::generate(config.seed);
    let trajectory = Trajectory::new(config.motion, config.seed);
    let poses = config.poses();
    for (i, p) in poses.iter().enumerate() {
        if !scene.is_free(&p.translation, 0.3) {
            return Err(Error::Config(format!(
                "synth: camera {i} is not in free space (bug)"
            )));
        }
    }
    for sub in ["rgb", "depth"] {
        let dir = out_dir.join(sub);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    }

    let next = AtomicUsize::new(0);
    let first_error: Mutex<Option<Error>> = Mutex::new(None);
    let worker = || {
        loop {
            let i = next.fetch_add(1, Ordering::Relaxed);
            if i >= poses.len() {
                break;
            }
            if let Err(e) = write_frame(&scene, &camera, &trajectory, config, i, out_dir) {
                if let Ok(mut slot) = first_error.lock() {
                    slot.get_or_insert(e);
                }
                next.store(poses.len(), Ordering::Relaxed);
                break;
            }
        }
    };
    std::thread::scope(|s| {
        for _ in 0..config.threads.max(1) {
            s.spawn(worker);
        }
    });
    if let Some(e) = first_error.into_inner().ok().flatten() {
        return Err(e);
    }

    write_lists(config, &camera, &poses, out_dir)?;
    Ok(SynthSummary {
        frames: poses.len(),
        path_length_m: path_length(&poses),
        max_rotation_deg: max_rotation_deg(&poses),
    })
}

fn write_frame(
    scene: &Scene,
    camera: &PinholeCamera,
    trajectory: &Trajectory,
    config: &SynthConfig,
    i: usize,
    out_dir: &Path,
) -> Result<()> {
    let time = i as f64 / config.fps;
    let pose = trajectory.world_from_camera(time);
    let (ideal, depth) = render_frame_with(scene, camera, &pose, config.supersample);
    let t = timestamp(i, config.fps);
    let rgb_path = out_dir.join(format!("rgb/{t}.{}", config.rgb_extension()));
    let nuisances = &config.nuisances;
    let rgb = if nuisances.any() {
        // Mean radiance over the shutter (the centre rendering is the one already made when
        // there is no blur).
        let offsets = nuisances.exposure_offsets(config.fps);
        let mut linear = vec![0.0f32; ideal.as_raw().len()];
        for &dt in &offsets {
            let sub = if nuisances.rolling_shutter > 0.0 {
                let readout = nuisances.rolling_shutter / config.fps;
                let rows = f64::from(camera.height);
                let pose_of_row = |y: u32| {
                    let row = (f64::from(y) + 0.5) / rows - 0.5;
                    trajectory.world_from_camera(time + dt + readout * row)
                };
                render_rolling(scene, camera, &pose_of_row, config.supersample).0
            } else if dt == 0.0 {
                ideal.clone()
            } else {
                let pose = trajectory.world_from_camera(time + dt);
                render_frame_with(scene, camera, &pose, config.supersample).0
            };
            for (acc, &v) in linear.iter_mut().zip(sub.as_raw()) {
                *acc += f32::from(v) / offsets.len() as f32;
            }
        }
        nuisances.apply(&linear, camera.width, camera.height, config.seed, i, time)
    } else {
        ideal
    };
    let bytes = nuisance::encode(&rgb, nuisances.jpeg_quality)?;
    std::fs::write(&rgb_path, bytes).map_err(|e| Error::io(&rgb_path, e))?;
    let depth_path = out_dir.join(format!("depth/{t}.png"));
    depth_to_u16(&depth)?
        .save(&depth_path)
        .map_err(|source| Error::Image {
            path: depth_path.clone(),
            source,
        })
}

fn write_lists(
    config: &SynthConfig,
    camera: &PinholeCamera,
    poses: &[SE3],
    out_dir: &Path,
) -> Result<()> {
    let source = format!(
        "relfusion synth: seed {} motion {} {} frames {}x{} at {} Hz, nuisances {}",
        config.seed,
        config.motion,
        config.frames,
        config.width,
        config.height,
        config.fps,
        serde_json::to_string(&config.nuisances).unwrap_or_default()
    );
    let ext = config.rgb_extension();
    let (mut rgb, mut depth, mut assoc) = (String::new(), String::new(), String::new());
    let _ = writeln!(rgb, "# color images\n# {source}\n# timestamp filename");
    let _ = writeln!(
        depth,
        "# depth maps (16-bit PNG, metres x 5000, 0 = none)\n# {source}\n# timestamp filename"
    );
    for i in 0..poses.len() {
        let t = timestamp(i, config.fps);
        let _ = writeln!(rgb, "{t} rgb/{t}.{ext}");
        let _ = writeln!(depth, "{t} depth/{t}.png");
        let _ = writeln!(assoc, "{t} rgb/{t}.{ext} {t} depth/{t}.png");
    }
    let calib = format!(
        "# fx fy cx cy (ideal pinhole, no distortion)\n{} {} {} {}\n",
        camera.fx, camera.fy, camera.cx, camera.cy
    );
    let files: [(&str, &str); 4] = [
        ("rgb.txt", &rgb),
        ("depth.txt", &depth),
        ("associations.txt", &assoc),
        ("calibration.txt", &calib),
    ];
    for (name, text) in files {
        let path: PathBuf = out_dir.join(name);
        std::fs::write(&path, text).map_err(|e| Error::io(&path, e))?;
    }
    // Stamps go through the same 6-decimal text as rgb.txt, so they compare equal on reading.
    let stamped = poses
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let t = timestamp(i, config.fps);
            let timestamp = t
                .parse::<f64>()
                .map_err(|e| Error::Config(format!("timestamp {t}: {e}")))?;
            Ok(StampedPose {
                timestamp,
                world_from_camera: *p,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let text = format!(
        "# ground truth trajectory (camera-to-world, exact)\n# {source}\n{}",
        format_tum_trajectory(&stamped)
    );
    let path = out_dir.join("groundtruth.txt");
    std::fs::write(&path, text).map_err(|e| Error::io(&path, e))
}

#[cfg(test)]
mod tests;
