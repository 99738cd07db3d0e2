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
//! - **Untrusted folders** (uploads): every file a sequence names must resolve inside its
//!   folder ([`SequenceFolder`]), images are size-checked from their headers before decoding,
//!   and errors name files relative to the folder, so they reveal nothing of the machine.
//!   [`SequenceLimits`] bound what opening and reading may cost: entries per list (checked
//!   while parsing), bytes per file (checked from the file's size before reading), and the
//!   association considers a bounded number of partners per stamp, so no cost grows faster
//!   than the lists themselves (a list that names one file 30 000 times costs 30 000 entries,
//!   not 30 000² candidate pairs).

use std::path::{Path, PathBuf};

use super::DEPTH_SCALE;
use super::folder::{SequenceFolder, read_at_most};
use super::trajectory::{StampedPose, parse_tum_trajectory_bounded};
use crate::geometry::{Distortion, PinholeCamera, SE3, SO3};
use crate::image::ImageF32;
use crate::{Error, Result};

/// Largest time difference (seconds) for an RGB/depth pair and for bracketing ground-truth
/// poses; `associate.py`'s default `--max_difference 0.02`.
pub const MAX_ASSOCIATION_DT: f64 = 0.02;

/// Two stamps closer than this (seconds) are the same instant (files print 6 decimals).
pub const SAME_STAMP_DT: f64 = 1e-6;

/// Partners an RGB stamp considers on each side in the association. `associate.py` considers
/// every depth stamp within [`MAX_ASSOCIATION_DT`]; with fewer than this many per side (any
/// depth stream under 200 Hz) the result is the same, and the cost stays linear whatever the
/// stamps are.
pub const ASSOCIATION_NEIGHBOURS: usize = 4;

/// `groundtruth.txt` may hold this many poses per listed frame (motion capture runs at 100 Hz
/// or more beside a 30 Hz camera; 7-Scenes has one pose per frame).
pub const GROUNDTRUTH_PER_FRAME: usize = 16;

/// What opening and reading a sequence may cost. The defaults fit any real sequence on local
/// disk; a server opens uploads with its own, tighter `[limits]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SequenceLimits {
    /// Most entries in `rgb.txt` and in `depth.txt` each (checked while parsing);
    /// `groundtruth.txt` may hold [`GROUNDTRUTH_PER_FRAME`] times as many.
    pub max_frames: usize,
    /// Largest text file (lists, calibration) read, in bytes, checked before reading it.
    pub max_text_bytes: u64,
    /// Largest image file read, in bytes, checked from its size before a byte is read.
    pub max_image_bytes: u64,
}

impl Default for SequenceLimits {
    fn default() -> Self {
        Self {
            // Nine hours at 30 Hz.
            max_frames: 1_000_000,
            max_text_bytes: 1 << 30,
            max_image_bytes: 256 << 20,
        }
    }
}

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
    limits: SequenceLimits,
}

impl TumSequence {
    /// Parses the sequence in `dir`. `camera` is used when the folder has no `calibration.txt`;
    /// without either, a Freiburg preset must be recognisable (see the module docs).
    pub fn open(dir: &Path, camera: Option<PinholeCamera>) -> Result<Self> {
        Self::open_bounded(dir, camera, SequenceLimits::default())
    }

    /// [`Self::open`] within `limits` (an untrusted folder: an upload); images read later are
    /// held to the same limits.
    pub fn open_bounded(
        dir: &Path,
        camera: Option<PinholeCamera>,
        limits: SequenceLimits,
    ) -> Result<Self> {
        if !dir.is_dir() {
            return Err(Error::Dataset(format!("{} is not a folder", dir.display())));
        }
        let folder = SequenceFolder::new(dir)?;
        let read = |name: &str| folder.read_own(name, limits.max_text_bytes);
        let rgb_list = match read("rgb.txt")? {
            Some(text) => parse_file_list(&text, "rgb.txt", limits.max_frames)?,
            None => return Err(Error::Dataset("rgb.txt is missing".into())),
        };
        if rgb_list.is_empty() {
            return Err(Error::Dataset("rgb.txt lists no images".into()));
        }
        let depth_list = match read("depth.txt")? {
            Some(text) => parse_file_list(&text, "depth.txt", limits.max_frames)?,
            None => Vec::new(),
        };
        let max_poses = limits.max_frames.saturating_mul(GROUNDTRUTH_PER_FRAME);
        let mut groundtruth: Vec<(f64, SE3)> = match read("groundtruth.txt")? {
            Some(text) => parse_tum_trajectory_bounded(&text, "groundtruth.txt", max_poses)?
                .into_iter()
                .map(|p| (p.timestamp, p.world_from_camera))
                .collect(),
            None => Vec::new(),
        };
        groundtruth.sort_by(|a, b| a.0.total_cmp(&b.0));

        let resolve = |list: &[(f64, String)], name: &str| -> Result<Vec<PathBuf>> {
            list.iter()
                .enumerate()
                .map(|(i, (_, rel))| folder.listed(rel, name, i + 1))
                .collect()
        };
        let rgb_paths = resolve(&rgb_list, "rgb.txt")?;
        let depth_paths = resolve(&depth_list, "depth.txt")?;

        let rgb_stamps: Vec<f64> = rgb_list.iter().map(|(t, _)| *t).collect();
        let depth_stamps: Vec<f64> = depth_list.iter().map(|(t, _)| *t).collect();
        let depth_of = associate(&rgb_stamps, &depth_stamps, MAX_ASSOCIATION_DT);
        let frames = rgb_stamps
            .iter()
            .zip(rgb_paths)
            .zip(depth_of)
            .map(|((t, rgb), d)| TumFrame {
                timestamp: *t,
                rgb,
                depth: d.map(|j| depth_paths[j].clone()),
                world_from_camera: interpolate_pose(&groundtruth, *t, MAX_ASSOCIATION_DT),
            })
            .collect::<Vec<_>>();

        let camera = resolve_camera(&folder, camera, &frames[0].rgb, limits.max_text_bytes)?;
        Ok(Self {
            root: dir.to_path_buf(),
            camera,
            frames,
            groundtruth,
            limits,
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

    /// The same ground truth as stamped poses, the form trajectories are compared in.
    pub fn groundtruth_poses(&self) -> Vec<StampedPose> {
        self.groundtruth
            .iter()
            .map(|&(timestamp, world_from_camera)| StampedPose {
                timestamp,
                world_from_camera,
            })
            .collect()
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
        Ok(self.decode(&self.frame(i)?.rgb)?.into_rgb8())
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
        let img = match self.decode(path)? {
            ::image::DynamicImage::ImageLuma16(buf) => buf,
            other => {
                return Err(Error::Dataset(format!(
                    "depth {} is {:?}, expected a 16-bit grey PNG",
                    self.name(path).display(),
                    other.color()
                )));
            }
        };
        let scale = (1.0 / DEPTH_SCALE) as f32;
        let data = img.as_raw().iter().map(|&v| f32::from(v) * scale).collect();
        ImageF32::from_vec(img.width() as usize, img.height() as usize, data).map(Some)
    }

    /// `path` as the sequence names it (relative to its folder), for error messages.
    fn name<'a>(&self, path: &'a Path) -> &'a Path {
        path.strip_prefix(&self.root).unwrap_or(path)
    }

    /// Reads and decodes one image; a file larger than the limits is refused from its size
    /// before a byte is read, an image whose header gives another size than the camera's
    /// before any pixel is decoded (a small file can claim gigapixels). The format is guessed
    /// from the content, so extensions do not matter.
    fn decode(&self, path: &Path) -> Result<::image::DynamicImage> {
        let name = self.name(path);
        let bytes = read_at_most(path, self.limits.max_image_bytes)
            .map_err(|e| e.named(name, "an image"))?;
        let (w, h) = (self.camera.width, self.camera.height);
        decode_sized(&bytes, w, h).map_err(|e| match e {
            SizedDecodeError::Size(iw, ih) => Error::Dataset(format!(
                "{} is {iw}x{ih} but the camera is {w}x{h}",
                name.display()
            )),
            SizedDecodeError::Image(source) => Error::Image {
                path: name.to_path_buf(),
                source,
            },
        })
    }
}

/// Why [`decode_sized`] refused an image.
#[derive(Debug)]
pub enum SizedDecodeError {
    /// The header gives this size, not the expected one.
    Size(u32, u32),
    /// The bytes are no image of a known format, or are corrupt.
    Image(::image::ImageError),
}

/// Decodes an encoded image (format from its bytes) that must be `width`×`height`: the size is
/// read from the header first, and the decoder may allocate no more than that size needs.
pub fn decode_sized(
    bytes: &[u8],
    width: u32,
    height: u32,
) -> std::result::Result<::image::DynamicImage, SizedDecodeError> {
    let reader = || {
        ::image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| SizedDecodeError::Image(::image::ImageError::IoError(e)))
    };
    let size = reader()?
        .into_dimensions()
        .map_err(SizedDecodeError::Image)?;
    if size != (width, height) {
        return Err(SizedDecodeError::Size(size.0, size.1));
    }
    let mut reader = reader()?;
    let mut limits = ::image::Limits::default();
    limits.max_image_width = Some(width);
    limits.max_image_height = Some(height);
    // 16-bit RGBA is the widest layout we read, plus the decoders' own buffers.
    limits.max_alloc = Some(u64::from(width) * u64::from(height) * 8 + (4 << 20));
    reader.limits(limits);
    reader.decode().map_err(SizedDecodeError::Image)
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
    folder: &SequenceFolder,
    camera: Option<PinholeCamera>,
    first_rgb: &Path,
    max_text_bytes: u64,
) -> Result<PinholeCamera> {
    if let Some(text) = folder.read_own("calibration.txt", max_text_bytes)? {
        let (w, h) = ::image::image_dimensions(first_rgb).map_err(|source| Error::Image {
            path: folder.name(first_rgb).to_path_buf(),
            source,
        })?;
        return parse_calibration(&text, w, h);
    }
    if let Some(cam) = camera {
        return Ok(cam);
    }
    let mut hints = vec![folder.folder_name()];
    for name in ["rgb.txt", "depth.txt", "groundtruth.txt"] {
        if let Some(text) = folder.read_own(name, max_text_bytes)? {
            hints.extend(
                text.lines()
                    .filter(|l| l.trim_start().starts_with('#'))
                    .map(String::from),
            );
        }
    }
    hints.iter().find_map(|h| preset(h)).ok_or_else(|| {
        Error::Dataset(
            "no intrinsics: add calibration.txt (fx fy cx cy [k1 k2 p1 p2 k3]), pass a camera, \
             or name the folder after a TUM camera (freiburg1/2/3)"
                .into(),
        )
    })
}

/// Parses the text of `calibration.txt` for images of `width`×`height`: the first
/// non-comment line is `fx fy cx cy [k1 k2 p1 p2 k3]`.
pub fn parse_calibration(text: &str, width: u32, height: u32) -> Result<PinholeCamera> {
    const SOURCE: &str = "calibration.txt";
    let (lineno, line) = data_lines(text)
        .next()
        .ok_or_else(|| Error::Dataset(format!("{SOURCE}: no calibration line")))?;
    let v = parse_numbers(line, SOURCE, lineno)?;
    if v.len() != 4 && v.len() != 9 {
        return Err(Error::Dataset(format!(
            "{SOURCE}:{lineno}: expected `fx fy cx cy [k1 k2 p1 p2 k3]`, got {} numbers",
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

fn parse_numbers(line: &str, source: &str, lineno: usize) -> Result<Vec<f64>> {
    line.split_whitespace()
        .map(|tok| {
            tok.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    Error::Dataset(format!("{source}:{lineno}: `{tok}` is not a number"))
                })
        })
        .collect()
}

/// Parses the text of an `rgb.txt` / `depth.txt` list (`source` names it in errors):
/// `timestamp relative/path` per line, at most `max_entries` of them (refused at the first
/// line beyond, before it is stored).
pub fn parse_file_list(text: &str, source: &str, max_entries: usize) -> Result<Vec<(f64, String)>> {
    let mut list = Vec::new();
    for (lineno, line) in data_lines(text) {
        if list.len() == max_entries {
            return Err(Error::Dataset(format!(
                "{source}:{lineno}: more than {max_entries} entries"
            )));
        }
        let mut it = line.split_whitespace();
        let stamp = it
            .next()
            .and_then(|s| s.parse::<f64>().ok())
            .filter(|t| t.is_finite());
        match (stamp, it.next(), it.next()) {
            (Some(t), Some(file), None) => list.push((t, file.to_string())),
            _ => {
                return Err(Error::Dataset(format!(
                    "{source}:{lineno}: expected `timestamp filename`, got `{line}`"
                )));
            }
        }
    }
    Ok(list)
}

/// TUM `associate.py`: greedy one-to-one matching of `a` to `b` stamps by increasing time
/// difference, below `max_dt`. Returns, for every `a`, the index of its partner in `b`. Each
/// `a` considers its [`ASSOCIATION_NEIGHBOURS`] nearest `b` on either side (all of them for
/// any real camera), so the candidates are linear in the input: O(n log n) in all.
pub fn associate(a: &[f64], b: &[f64], max_dt: f64) -> Vec<Option<usize>> {
    let mut order: Vec<usize> = (0..b.len()).collect();
    order.sort_by(|&i, &j| b[i].total_cmp(&b[j]));
    let sorted: Vec<f64> = order.iter().map(|&i| b[i]).collect();
    let mut candidates = Vec::new();
    for (ia, &ta) in a.iter().enumerate() {
        let at = sorted.partition_point(|&tb| tb < ta);
        let before = at.saturating_sub(ASSOCIATION_NEIGHBOURS)..at;
        let after = at..(at + ASSOCIATION_NEIGHBOURS).min(sorted.len());
        for k in before.chain(after) {
            let dt = (ta - sorted[k]).abs();
            if dt < max_dt {
                candidates.push((dt, ia, order[k]));
            }
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

/// The pose at time `t` from time-sorted `poses` (rule in the module docs; `max_dt` the
/// farthest a bracketing pose may be).
pub fn interpolate_pose(poses: &[(f64, SE3)], t: f64, max_dt: f64) -> Option<SE3> {
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
