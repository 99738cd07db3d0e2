//! TUM RGB-D sequence reader (Sturm et al., IROS 2012, "File Formats" page of the benchmark).
//!
//! A sequence folder holds `rgb.txt` (required), `depth.txt` and `groundtruth.txt` (optional),
//! the image folders they point into, and optionally `calibration.txt`. Rules, chosen to match
//! the benchmark's own tools:
//! - **RGB ↔ depth association** is TUM's `associate.py`: every pair with
//!   |t_rgb − t_depth| < [`MAX_ASSOCIATION_DT`] is a candidate, candidates are taken greedily in
//!   order of increasing time difference, and each stamp is used at most once. RGB frames left
//!   without a partner keep `depth: None`.
//! - **Ground truth** (100 Hz motion capture for TUM) is interpolated at the RGB stamp between
//!   the two bracketing poses — translation linearly, rotation along the SO(3) geodesic
//!   (slerp) — when *both* are within [`MAX_ASSOCIATION_DT`] of the stamp; a pose whose stamp
//!   coincides with the frame's (within [`SAME_STAMP_DT`], e.g. 7-Scenes' one pose per frame) is
//!   used as is. Otherwise the frame has no pose (`world_from_camera: None`).
//! - **Intrinsics**: `calibration.txt` when present, else the caller's camera, else a Freiburg
//!   preset recognised from the folder name or the text-file headers (see [`preset`]).

use std::path::{Path, PathBuf};

use super::DEPTH_SCALE;
use super::trajectory::read_tum_trajectory;
use crate::geometry::{Distortion, PinholeCamera, SE3, SO3};
use crate::image::ImageF32;
use crate::{Error, Result};

/// Largest time difference (seconds) for an RGB/depth pair and for bracketing ground-truth
/// poses; `associate.py`'s default `--max_difference 0.02`.
pub const MAX_ASSOCIATION_DT: f64 = 0.02;

/// Two stamps closer than this (seconds) are the same instant (files print 6 decimals).
pub const SAME_STAMP_DT: f64 = 1e-6;

/// One RGB frame of a sequence with its associated depth map and ground-truth pose.
#[derive(Clone, Debug)]
pub struct TumFrame {
    /// RGB timestamp in seconds.
    pub timestamp: f64,
    /// Absolute path of the colour image (PNG or JPEG).
    pub rgb: PathBuf,
    /// Absolute path of the associated 16-bit depth PNG, if any.
    pub depth: Option<PathBuf>,
    /// Ground-truth camera-to-world pose at `timestamp`, if the ground truth covers it.
    pub world_from_camera: Option<SE3>,
}

/// A TUM-layout RGB-D sequence, parsed and associated; images are loaded on demand.
#[derive(Clone, Debug)]
pub struct TumSequence {
    /// The sequence folder.
    pub root: PathBuf,
    /// Intrinsics of the RGB camera (and of the registered depth).
    pub camera: PinholeCamera,
    /// RGB frames in file order.
    pub frames: Vec<TumFrame>,
    groundtruth: Vec<(f64, SE3)>,
}

impl TumSequence {
    /// Parses the sequence in `dir`. `camera` is used when the folder has no `calibration.txt`;
    /// without either, a Freiburg preset must be recognisable (see the module docs).
    pub fn open(dir: &Path, camera: Option<PinholeCamera>) -> Result<Self> {
        let root = dir.to_path_buf();
        if !dir.is_dir() {
            return Err(Error::Dataset(format!("{} is not a folder", dir.display())));
        }
        let rgb_txt = dir.join("rgb.txt");
        if !rgb_txt.is_file() {
            return Err(Error::Dataset(format!("{} is missing", rgb_txt.display())));
        }
        let rgb_list = read_file_list(&rgb_txt)?;
        if rgb_list.is_empty() {
            return Err(Error::Dataset(format!(
                "{} lists no images",
                rgb_txt.display()
            )));
        }
        let depth_txt = dir.join("depth.txt");
        let depth_list = if depth_txt.is_file() {
            read_file_list(&depth_txt)?
        } else {
            Vec::new()
        };
        let gt_txt = dir.join("groundtruth.txt");
        let mut groundtruth: Vec<(f64, SE3)> = if gt_txt.is_file() {
            read_tum_trajectory(&gt_txt)?
                .into_iter()
                .map(|p| (p.timestamp, p.world_from_camera))
                .collect()
        } else {
            Vec::new()
        };
        groundtruth.sort_by(|a, b| a.0.total_cmp(&b.0));

        for (_, rel) in rgb_list.iter().chain(depth_list.iter()) {
            let path = dir.join(rel);
            if !path.is_file() {
                return Err(Error::Dataset(format!(
                    "listed file {} does not exist",
                    path.display()
                )));
            }
        }

        let rgb_stamps: Vec<f64> = rgb_list.iter().map(|(t, _)| *t).collect();
        let depth_stamps: Vec<f64> = depth_list.iter().map(|(t, _)| *t).collect();
        let depth_of = associate(&rgb_stamps, &depth_stamps, MAX_ASSOCIATION_DT);
        let frames = rgb_list
            .iter()
            .zip(depth_of)
            .map(|((t, rel), d)| TumFrame {
                timestamp: *t,
                rgb: dir.join(rel),
                depth: d.map(|j| dir.join(&depth_list[j].1)),
                world_from_camera: interpolate_pose(&groundtruth, *t, MAX_ASSOCIATION_DT),
            })
            .collect::<Vec<_>>();

        let camera = resolve_camera(dir, camera, &frames[0].rgb)?;
        Ok(Self {
            root,
            camera,
            frames,
            groundtruth,
        })
    }

    /// Number of RGB frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the sequence has no frames (never true for an opened sequence).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// All ground-truth poses of `groundtruth.txt`, sorted by time (empty when absent).
    pub fn groundtruth(&self) -> Vec<(f64, SE3)> {
        self.groundtruth.clone()
    }

    fn frame(&self, i: usize) -> Result<&TumFrame> {
        self.frames.get(i).ok_or_else(|| {
            Error::Dataset(format!(
                "frame {i} out of range ({} frames)",
                self.frames.len()
            ))
        })
    }

    /// The colour image of frame `i` (PNG or JPEG, detected from the bytes).
    pub fn load_rgb(&self, i: usize) -> Result<::image::RgbImage> {
        let path = &self.frame(i)?.rgb;
        let img = decode(path)?.into_rgb8();
        self.check_size(path, img.width(), img.height())?;
        Ok(img)
    }

    /// Frame `i` as grey levels in [0, 255] (BT.601 luma, see [`ImageF32::from_rgb8`]).
    pub fn load_gray(&self, i: usize) -> Result<ImageF32> {
        Ok(ImageF32::from_rgb8(&self.load_rgb(i)?))
    }

    /// The depth map of frame `i` in metres (0 = no measurement), or `None` when no depth
    /// image was associated with it.
    pub fn load_depth(&self, i: usize) -> Result<Option<ImageF32>> {
        let Some(path) = &self.frame(i)?.depth else {
            return Ok(None);
        };
        let img = match decode(path)? {
            ::image::DynamicImage::ImageLuma16(buf) => buf,
            other => {
                return Err(Error::Dataset(format!(
                    "depth {} is {:?}, expected a 16-bit grey PNG",
                    path.display(),
                    other.color()
                )));
            }
        };
        self.check_size(path, img.width(), img.height())?;
        let scale = (1.0 / DEPTH_SCALE) as f32;
        let data = img.as_raw().iter().map(|&v| f32::from(v) * scale).collect();
        ImageF32::from_vec(img.width() as usize, img.height() as usize, data).map(Some)
    }

    fn check_size(&self, path: &Path, w: u32, h: u32) -> Result<()> {
        if (w, h) != (self.camera.width, self.camera.height) {
            return Err(Error::Dataset(format!(
                "{} is {w}x{h} but the camera is {}x{}",
                path.display(),
                self.camera.width,
                self.camera.height
            )));
        }
        Ok(())
    }
}

/// Reads and decodes an image file; I/O failures are `Error::Io`, undecodable bytes
/// `Error::Image`. The format is guessed from the content, so extensions do not matter.
fn decode(path: &Path) -> Result<::image::DynamicImage> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    ::image::load_from_memory(&bytes).map_err(|source| Error::Image {
        path: path.to_path_buf(),
        source,
    })
}

/// The camera of a TUM Freiburg sensor (640×480), from a name that contains `freiburg1` /
/// `fr1`, `freiburg2` / `fr2` or `freiburg3` / `fr3` (case-insensitive). Values are the
/// benchmark's published RGB calibrations; fr3 images are already undistorted.
pub fn preset(name: &str) -> Option<PinholeCamera> {
    let n = name.to_ascii_lowercase();
    let has = |a: &str, b: &str| n.contains(a) || n.contains(b);
    if has("freiburg1", "fr1") {
        Some(PinholeCamera::tum_freiburg1())
    } else if has("freiburg2", "fr2") {
        Some(PinholeCamera::tum_freiburg2())
    } else if has("freiburg3", "fr3") {
        Some(PinholeCamera::tum_freiburg3())
    } else {
        None
    }
}

/// Intrinsics by priority: `calibration.txt`, the caller's camera, a recognised preset.
fn resolve_camera(
    dir: &Path,
    camera: Option<PinholeCamera>,
    first_rgb: &Path,
) -> Result<PinholeCamera> {
    let calib = dir.join("calibration.txt");
    if calib.is_file() {
        let (w, h) = ::image::image_dimensions(first_rgb).map_err(|source| Error::Image {
            path: first_rgb.to_path_buf(),
            source,
        })?;
        return read_calibration(&calib, w, h);
    }
    if let Some(cam) = camera {
        return Ok(cam);
    }
    let mut hints = vec![
        dir.file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default(),
    ];
    for name in ["rgb.txt", "depth.txt", "groundtruth.txt"] {
        if let Ok(text) = std::fs::read_to_string(dir.join(name)) {
            hints.extend(
                text.lines()
                    .filter(|l| l.trim_start().starts_with('#'))
                    .map(String::from),
            );
        }
    }
    hints.iter().find_map(|h| preset(h)).ok_or_else(|| {
        Error::Dataset(format!(
            "{}: no intrinsics: add calibration.txt (fx fy cx cy [k1 k2 p1 p2 k3]), pass a camera, \
             or name the folder after a TUM camera (freiburg1/2/3)",
            dir.display()
        ))
    })
}

/// Parses `calibration.txt`: the first non-comment line is `fx fy cx cy [k1 k2 p1 p2 k3]`.
fn read_calibration(path: &Path, width: u32, height: u32) -> Result<PinholeCamera> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let (lineno, line) = data_lines(&text)
        .next()
        .ok_or_else(|| Error::Dataset(format!("{}: no calibration line", path.display())))?;
    let v = parse_numbers(line, path, lineno)?;
    if v.len() != 4 && v.len() != 9 {
        return Err(Error::Dataset(format!(
            "{}:{lineno}: expected `fx fy cx cy [k1 k2 p1 p2 k3]`, got {} numbers",
            path.display(),
            v.len()
        )));
    }
    let mut cam = PinholeCamera::new(v[0], v[1], v[2], v[3], width, height)?;
    if v.len() == 9 && v[4..].iter().any(|&k| k != 0.0) {
        cam = cam.with_distortion(Distortion::new(v[4], v[5], v[6], v[7], v[8]))?;
    }
    Ok(cam)
}

/// Non-empty, non-comment lines with their 1-based line numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn parse_numbers(line: &str, path: &Path, lineno: usize) -> Result<Vec<f64>> {
    line.split_whitespace()
        .map(|tok| {
            tok.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    Error::Dataset(format!(
                        "{}:{lineno}: `{tok}` is not a number",
                        path.display()
                    ))
                })
        })
        .collect()
}

/// Parses an `rgb.txt` / `depth.txt` list: `timestamp relative/path` per line.
fn read_file_list(path: &Path) -> Result<Vec<(f64, String)>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    data_lines(&text)
        .map(|(lineno, line)| {
            let mut it = line.split_whitespace();
            let stamp = it
                .next()
                .and_then(|s| s.parse::<f64>().ok())
                .filter(|t| t.is_finite());
            match (stamp, it.next(), it.next()) {
                (Some(t), Some(file), None) => Ok((t, file.to_string())),
                _ => Err(Error::Dataset(format!(
                    "{}:{lineno}: expected `timestamp filename`, got `{line}`",
                    path.display()
                ))),
            }
        })
        .collect()
}

/// TUM `associate.py`: greedy one-to-one matching of `a` to `b` stamps by increasing time
/// difference, below `max_dt`. Returns, for every `a`, the index of its partner in `b`.
fn associate(a: &[f64], b: &[f64], max_dt: f64) -> Vec<Option<usize>> {
    let mut order: Vec<usize> = (0..b.len()).collect();
    order.sort_by(|&i, &j| b[i].total_cmp(&b[j]));
    let sorted: Vec<f64> = order.iter().map(|&i| b[i]).collect();
    let mut candidates = Vec::new();
    for (ia, &ta) in a.iter().enumerate() {
        let start = sorted.partition_point(|&tb| tb <= ta - max_dt);
        for (k, &tb) in sorted.iter().enumerate().skip(start) {
            if tb >= ta + max_dt {
                break;
            }
            candidates.push(((ta - tb).abs(), ia, order[k]));
        }
    }
    candidates.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)).then(x.2.cmp(&y.2)));
    let mut partner = vec![None; a.len()];
    let mut used = vec![false; b.len()];
    for (_, ia, ib) in candidates {
        if partner[ia].is_none() && !used[ib] {
            partner[ia] = Some(ib);
            used[ib] = true;
        }
    }
    partner
}

/// The pose at time `t` from time-sorted `poses` (rule in the module docs).
fn interpolate_pose(poses: &[(f64, SE3)], t: f64, max_dt: f64) -> Option<SE3> {
    let after = poses.partition_point(|(tp, _)| *tp < t);
    // A pose at the same instant on either side wins (no interpolation error at all).
    for idx in [after.checked_sub(1), Some(after)].into_iter().flatten() {
        if let Some((tp, pose)) = poses.get(idx)
            && (tp - t).abs() <= SAME_STAMP_DT
        {
            return Some(*pose);
        }
    }
    let (t0, p0) = poses.get(after.checked_sub(1)?)?;
    let (t1, p1) = poses.get(after)?;
    if t - t0 > max_dt || t1 - t > max_dt {
        return None;
    }
    let alpha = (t - t0) / (t1 - t0);
    let delta = (p0.rotation.inverse() * p1.rotation).log();
    let rotation = p0.rotation * SO3::exp(&(delta * alpha));
    let translation = p0.translation + (p1.translation - p0.translation) * alpha;
    Some(SE3::new(rotation, translation))
}

#[cfg(test)]
#[path = "tum_tests.rs"]
mod tests;
