//! The map on disk (format version 2, `docs/map-format.md`):
//!
//! ```text
//! MAP/manifest.json                      format, version, camera, voxel size, keyframes, edges
//! MAP/keyframes/<id:06>/image.png        undistorted RGB
//! MAP/keyframes/<id:06>/semidense_idepth.npy, semidense_var.npy   full resolution
//! MAP/keyframes/<id:06>/dense_idepth.npy,     dense_var.npy       dense working resolution
//! ```
//!
//! File names follow from the keyframe ids, never from the manifest, so a hostile manifest
//! cannot name a path outside the map. A map is written into a sibling temporary folder,
//! every file synced, and renamed into place: a reader sees the old map or the new one whole.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::{DenseDepth, FORMAT_VERSION, MapKeyframe, OLDEST_READABLE_VERSION, SavedMap};
use crate::frame::Frame;
use crate::geometry::{Matrix7, PinholeCamera, Sim3};
use crate::graph::{Constraint, ScalePrior, Thumbnail};
use crate::image::ImageF32;
use crate::mapping::{CompactDepth, DepthMap, InverseDepth};
use crate::{Error, Result, npy};

/// The manifest's `format` field: says what the folder is.
const FORMAT_NAME: &str = "relfusion-map";
/// Most keyframes a map may list (a reader's bound on hostile manifests: one keyframe costs
/// about 10 MB loaded, so this is far beyond what a machine holds).
pub const MAX_KEYFRAMES: usize = 100_000;
/// Largest image side a map may hold.
const MAX_SIDE: u32 = 8192;

#[derive(Deserialize)]
struct VersionProbe {
    format: String,
    version: u32,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    format: String,
    version: u32,
    camera: PinholeCamera,
    voxel_size: Option<f32>,
    /// Since version 2; absent (false) in version 1.
    #[serde(default)]
    metric: bool,
    keyframes: Vec<ManifestKeyframe>,
    edges: Vec<ManifestEdge>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ManifestKeyframe {
    id: usize,
    timestamp: f64,
    world_from_keyframe: Sim3,
    /// The dense maps' camera, when the keyframe was densified.
    dense_camera: Option<PinholeCamera>,
    thumbnail: Vec<f32>,
    /// Since version 2, in metric maps only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    scale_prior: Option<ScalePrior>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ManifestEdge {
    from: usize,
    to: usize,
    to_from_from: Sim3,
    /// 7×7, row-major, Sim(3) tangent order (ρ, φ, σ).
    information: Vec<f64>,
}

fn keyframe_dir(root: &Path, id: usize) -> PathBuf {
    root.join("keyframes").join(format!("{id:06}"))
}

/// Writes `map` to the folder `dir` atomically (replacing a map already there).
pub fn write_map(dir: &Path, map: &SavedMap) -> Result<()> {
    map.validate()?;
    write_map_streamed(dir, map, map.keyframes.len(), |i| {
        Ok(map.keyframes[i].clone())
    })
}

/// [`write_map`] of `header` (camera, edges, voxel size; its `keyframes` are ignored) with
/// `count` keyframes that `keyframe(i)` makes one at a time: a session of an hour has thousands
/// of keyframes, most of them spilled, and its map is written without holding them all in
/// memory (issue 37). Each keyframe is checked as it comes.
pub fn write_map_streamed(
    dir: &Path,
    header: &SavedMap,
    count: usize,
    keyframe: impl FnMut(usize) -> Result<MapKeyframe>,
) -> Result<()> {
    header.check_edges(count)?;
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| Error::io(&parent, e))?;
    let name = dir
        .file_name()
        .ok_or_else(|| Error::Map(format!("{}: not a folder name", dir.display())))?
        .to_string_lossy()
        .into_owned();
    let unique = format!(
        "{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos())
    );
    let tmp = parent.join(format!(".{name}.tmp-{unique}"));
    let result = write_contents(&tmp, header, count, keyframe)
        .and_then(|()| replace_dir(&tmp, dir, &parent, &name, &unique));
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result
}

/// Moves the finished `tmp` to `dir`: an existing map is renamed aside first and removed after.
fn replace_dir(tmp: &Path, dir: &Path, parent: &Path, name: &str, unique: &str) -> Result<()> {
    let old = parent.join(format!(".{name}.old-{unique}"));
    let had_old = dir.exists();
    if had_old {
        std::fs::rename(dir, &old).map_err(|e| Error::io(dir, e))?;
    }
    std::fs::rename(tmp, dir).map_err(|e| Error::io(dir, e))?;
    sync_dir(parent)?;
    if had_old {
        std::fs::remove_dir_all(&old).map_err(|e| Error::io(&old, e))?;
    }
    Ok(())
}

fn write_contents(
    root: &Path,
    map: &SavedMap,
    count: usize,
    mut keyframe: impl FnMut(usize) -> Result<MapKeyframe>,
) -> Result<()> {
    std::fs::create_dir_all(root.join("keyframes")).map_err(|e| Error::io(root, e))?;
    let mut keyframes = Vec::with_capacity(count);
    for i in 0..count {
        let kf = keyframe(i)?;
        map.check_keyframe(i, &kf)?;
        let dir = keyframe_dir(root, kf.id);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let rgb = match (&kf.image.rgb, kf.image.gray()) {
            (Some(rgb), _) => (**rgb).clone(),
            (None, Some(gray)) => grey_to_rgb(gray),
            (None, None) => {
                return Err(Error::Map(format!("keyframe {} has no image", kf.id)));
            }
        };
        let image_path = dir.join("image.png");
        rgb.save(&image_path).map_err(|source| Error::Image {
            path: image_path.clone(),
            source,
        })?;
        sync_file(&image_path)?;
        let (idepth, var) = split_depth(&kf.depth.expand())?;
        write_npy(&dir.join("semidense_idepth.npy"), &idepth)?;
        write_npy(&dir.join("semidense_var.npy"), &var)?;
        if let Some(dense) = &kf.dense {
            write_npy(&dir.join("dense_idepth.npy"), &dense.idepth)?;
            write_npy(&dir.join("dense_var.npy"), &dense.variance)?;
        }
        sync_dir(&dir)?;
        keyframes.push(ManifestKeyframe {
            id: kf.id,
            timestamp: kf.timestamp,
            world_from_keyframe: kf.world_from_keyframe,
            dense_camera: kf.dense.as_ref().map(|d| d.camera),
            thumbnail: kf.thumbnail.values(),
            scale_prior: kf.scale_prior,
        });
    }
    sync_dir(&root.join("keyframes"))?;
    let manifest = Manifest {
        format: FORMAT_NAME.into(),
        version: FORMAT_VERSION,
        camera: map.camera,
        voxel_size: map.voxel_size,
        metric: map.metric,
        keyframes,
        edges: map
            .edges
            .iter()
            .map(|e| ManifestEdge {
                from: e.from,
                to: e.to,
                to_from_from: e.to_from_from,
                information: e.information.matrix().transpose().iter().copied().collect(),
            })
            .collect(),
    };
    let path = root.join("manifest.json");
    let json = serde_json::to_vec_pretty(&manifest)
        .map_err(|e| Error::Map(format!("encoding the manifest: {e}")))?;
    let mut file = std::fs::File::create(&path).map_err(|e| Error::io(&path, e))?;
    file.write_all(&json)
        .and_then(|()| file.sync_all())
        .map_err(|e| Error::io(&path, e))?;
    sync_dir(root)
}

/// The keyframes' timestamps and poses from the manifest alone (listing, evaluation), without
/// reading their images and depth.
pub fn read_keyframe_poses(dir: &Path) -> Result<Vec<(f64, Sim3)>> {
    Ok(read_manifest(dir)?
        .keyframes
        .iter()
        .map(|kf| (kf.timestamp, kf.world_from_keyframe))
        .collect())
}

fn read_manifest(dir: &Path) -> Result<Manifest> {
    let path = dir.join("manifest.json");
    let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
    let probe: VersionProbe = serde_json::from_slice(&bytes)
        .map_err(|e| Error::Map(format!("{}: not a map manifest ({e})", path.display())))?;
    if probe.format != FORMAT_NAME {
        return Err(Error::Map(format!(
            "{}: format {:?}, expected {FORMAT_NAME:?}",
            path.display(),
            probe.format
        )));
    }
    if !(OLDEST_READABLE_VERSION..=FORMAT_VERSION).contains(&probe.version) {
        return Err(Error::Map(format!(
            "{} is map format version {}; this relfusion reads versions \
             {OLDEST_READABLE_VERSION} to {FORMAT_VERSION}",
            dir.display(),
            probe.version
        )));
    }
    serde_json::from_slice(&bytes).map_err(|e| Error::Map(format!("{}: {e}", path.display())))
}

/// Reads the map in `dir`. With `camera`, refuses a map made with another camera.
pub fn read_map(dir: &Path, camera: Option<&PinholeCamera>) -> Result<SavedMap> {
    let manifest = read_manifest(dir)?;
    if let Some(expected) = camera {
        check_camera(&manifest.camera, expected)?;
    }
    check_side(&manifest.camera)?;
    if manifest.keyframes.len() > MAX_KEYFRAMES {
        return Err(Error::Map(format!(
            "{} keyframes, more than the {MAX_KEYFRAMES} a map may hold",
            manifest.keyframes.len()
        )));
    }
    let undistorted = manifest.camera.undistorted();
    let keyframes = manifest
        .keyframes
        .iter()
        .map(|kf| read_keyframe(dir, kf, &undistorted))
        .collect::<Result<Vec<_>>>()?;
    let edges = manifest
        .edges
        .iter()
        .map(|e| {
            if e.information.len() != 49 || e.information.iter().any(|v| !v.is_finite()) {
                return Err(Error::Map(format!(
                    "edge {} → {}: information is not 49 finite numbers",
                    e.from, e.to
                )));
            }
            Ok(Constraint {
                from: e.from,
                to: e.to,
                to_from_from: e.to_from_from,
                information: Matrix7::from_row_slice(&e.information).into(),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let map = SavedMap {
        camera: manifest.camera,
        keyframes,
        edges,
        voxel_size: manifest.voxel_size,
        metric: manifest.metric,
    };
    map.validate()?;
    Ok(map)
}

/// A map serves only frames of the camera it was made with (intrinsics, size, distortion).
pub fn check_camera(map: &PinholeCamera, frames: &PinholeCamera) -> Result<()> {
    if map != frames {
        return Err(Error::Map(format!(
            "the map was made with camera {map:?}, the frames come from {frames:?}"
        )));
    }
    Ok(())
}

fn read_keyframe(
    root: &Path,
    kf: &ManifestKeyframe,
    camera: &PinholeCamera,
) -> Result<MapKeyframe> {
    let dir = keyframe_dir(root, kf.id);
    let image_path = dir.join("image.png");
    let reader = ::image::ImageReader::open(&image_path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| Error::io(&image_path, e))?;
    let (w, h) = reader.into_dimensions().map_err(|source| Error::Image {
        path: image_path.clone(),
        source,
    })?;
    if (w, h) != (camera.width, camera.height) {
        return Err(Error::Map(format!(
            "{}: {w}x{h}, the camera is {}x{}",
            image_path.display(),
            camera.width,
            camera.height
        )));
    }
    let rgb = ::image::open(&image_path)
        .map_err(|source| Error::Image {
            path: image_path.clone(),
            source,
        })?
        .into_rgb8();
    let gray = ImageF32::from_rgb8(&rgb);
    let frame = Frame::new(
        kf.id as u64,
        kf.timestamp,
        *camera,
        &gray,
        Some(Arc::new(rgb)),
    )?;
    let idepth = read_npy(&dir.join("semidense_idepth.npy"), w, h)?;
    let var = read_npy(&dir.join("semidense_var.npy"), w, h)?;
    let depth = join_depth(&idepth, &var);
    let dense = match &kf.dense_camera {
        Some(dense_camera) => {
            check_side(dense_camera)?;
            let (dw, dh) = (dense_camera.width, dense_camera.height);
            Some(DenseDepth {
                camera: *dense_camera,
                idepth: Arc::new(read_npy(&dir.join("dense_idepth.npy"), dw, dh)?),
                variance: Arc::new(read_npy(&dir.join("dense_var.npy"), dw, dh)?),
            })
        }
        None => None,
    };
    let thumbnail = Thumbnail::from_values(kf.thumbnail.clone()).ok_or_else(|| {
        Error::Map(format!(
            "keyframe {}: the thumbnail is not 32×24 finite cells",
            kf.id
        ))
    })?;
    if !kf.timestamp.is_finite() {
        return Err(Error::Map(format!(
            "keyframe {}: timestamp is not finite",
            kf.id
        )));
    }
    Ok(MapKeyframe {
        id: kf.id,
        timestamp: kf.timestamp,
        world_from_keyframe: kf.world_from_keyframe,
        image: frame.compact(),
        depth: Arc::new(CompactDepth::of(&depth)),
        dense,
        thumbnail,
        scale_prior: kf.scale_prior,
    })
}

fn check_side(camera: &PinholeCamera) -> Result<()> {
    if camera.width > MAX_SIDE || camera.height > MAX_SIDE {
        return Err(Error::Map(format!(
            "a {}x{} camera: a map holds images of at most {MAX_SIDE} pixels a side",
            camera.width, camera.height
        )));
    }
    Ok(())
}

/// The semi-dense map as two arrays: an estimate is (idepth, var); unknown (0, 0); discarded
/// (0, −1).
fn split_depth(depth: &DepthMap) -> Result<(ImageF32, ImageF32)> {
    let (idepth, var) = depth
        .pixels
        .iter()
        .map(|p| match p {
            InverseDepth::Estimate { idepth, var } => (*idepth, *var),
            InverseDepth::Unknown => (0.0, 0.0),
            InverseDepth::Discarded => (0.0, -1.0),
        })
        .unzip();
    Ok((
        ImageF32::from_vec(depth.width, depth.height, idepth)?,
        ImageF32::from_vec(depth.width, depth.height, var)?,
    ))
}

fn join_depth(idepth: &ImageF32, var: &ImageF32) -> DepthMap {
    let pixels = idepth
        .data
        .iter()
        .zip(&var.data)
        .map(|(&d, &v)| {
            if d > 0.0 && v > 0.0 && d.is_finite() && v.is_finite() {
                InverseDepth::Estimate { idepth: d, var: v }
            } else if v < 0.0 {
                InverseDepth::Discarded
            } else {
                InverseDepth::Unknown
            }
        })
        .collect();
    DepthMap {
        width: idepth.width,
        height: idepth.height,
        pixels,
    }
}

fn write_npy(path: &Path, image: &ImageF32) -> Result<()> {
    npy::write_f32(path, image)?;
    sync_file(path)
}

/// Reads an array that must be `w`×`h` (its size is checked against the file's before the
/// data is trusted).
fn read_npy(path: &Path, w: u32, h: u32) -> Result<ImageF32> {
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    // Header ≤ 64 KiB plus the data.
    if len > 65_536 + u64::from(w) * u64::from(h) * 4 {
        return Err(Error::Map(format!(
            "{}: larger than a {w}x{h} map",
            path.display()
        )));
    }
    let image = npy::read_f32(path)?;
    if (image.width, image.height) != (w as usize, h as usize) {
        return Err(Error::Map(format!(
            "{}: {}x{}, expected {w}x{h}",
            path.display(),
            image.width,
            image.height
        )));
    }
    Ok(image)
}

fn grey_to_rgb(gray: &ImageF32) -> ::image::RgbImage {
    ::image::RgbImage::from_fn(gray.width as u32, gray.height as u32, |x, y| {
        let v = gray.at(x as usize, y as usize).round().clamp(0.0, 255.0) as u8;
        ::image::Rgb([v, v, v])
    })
}

/// Bytes on disk of the map in `dir` by file name (`manifest.json`, `image.png`, …), summed
/// over keyframes: what quotas and the benchmark count.
pub fn disk_bytes_by_file(dir: &Path) -> Result<std::collections::BTreeMap<String, u64>> {
    let mut parts = std::collections::BTreeMap::<String, u64>::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).map_err(|e| Error::io(&d, e))? {
            let entry = entry.map_err(|e| Error::io(&d, e))?;
            let meta = entry.metadata().map_err(|e| Error::io(entry.path(), e))?;
            if meta.is_dir() {
                stack.push(entry.path());
            } else {
                *parts
                    .entry(entry.file_name().to_string_lossy().into_owned())
                    .or_default() += meta.len();
            }
        }
    }
    Ok(parts)
}

fn sync_file(path: &Path) -> Result<()> {
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(|e| Error::io(path, e))
}

fn sync_dir(path: &Path) -> Result<()> {
    // Directories cannot be opened for syncing on every platform; where they can, a new entry
    // is durable only once its folder is synced.
    match std::fs::File::open(path) {
        Ok(f) => f.sync_all().or(Ok(())),
        Err(e) => Err(Error::io(path, e)),
    }
}
