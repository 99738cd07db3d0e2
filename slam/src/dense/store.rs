//! The on-disk store of densified keyframes, `OUT/keyframes/`, written by `relfusion run` and
//! read by `relfusion eval depth` and `relfusion eval ablation`.
//!
//! Layout (every map float32 `.npy`, H×W at the working resolution, row-major; `<ts>` is the
//! keyframe's timestamp printed `{:.6}`, the precision of TUM list files):
//!
//! | file | content |
//! |---|---|
//! | `<ts>.depth.npy` | depth in the *trajectory's* scale: `s_kf / D_opt`, `s_kf` the scale of the final (optimised) `world_from_keyframe`; 0 = invalid. Multiply by the Sim(3) scale of the trajectory alignment for metres (the paper §V.A). |
//! | `<ts>.idepth.npy`, `<ts>.variance.npy` | the dense result `D_opt` and its variance, in the keyframe's gauge |
//! | `<ts>.intensity.npy` | keyframe intensity 0..255 (only with stages) |
//! | `<ts>.prior.npy`, `<ts>.prior_aligned.npy` | `D_CNN` and `D'_CNN` (eq. 2–3), when they exist |
//! | `<ts>.semidense.npy`, `<ts>.semidense_var.npy` | raw semi-dense inverse depth and variance |
//! | `<ts>.filtered.npy`, `<ts>.filtered_var.npy` | after the adaptive filter (eqs. 4–9) |
//!
//! `index.json` (written last, through a rename, so that a reader never sees an index naming
//! maps that are not there yet) holds the working size, the pinhole camera at that size, and per
//! keyframe its id, timestamp, file stem, final pose and its scale, the densification mode, the
//! eq. (3) fit (or why there was none), the two-view consistent pixel count, the timings and the
//! list of maps written.

use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::keyframe::{DenseKeyframe, DenseMode, DenseTimings};
use crate::geometry::{PinholeCamera, SO3, Sim3};
use crate::graph::KeyframeId;
use crate::image::ImageF32;
use crate::scale_shift::ScaleShift;
use crate::{Error, Result};

/// Name of the index inside the store folder.
pub const INDEX_FILE: &str = "index.json";

/// Version of the index layout; bumped on incompatible changes.
pub const STORE_VERSION: u32 = 1;

/// Every map a keyframe can have, in the order they are written.
pub const MAP_NAMES: [&str; 10] = [
    "depth",
    "idepth",
    "variance",
    "intensity",
    "prior",
    "prior_aligned",
    "semidense",
    "semidense_var",
    "filtered",
    "filtered_var",
];

/// The file stem of a keyframe: its timestamp with six decimals.
pub fn keyframe_stem(timestamp: f64) -> String {
    format!("{timestamp:.6}")
}

/// Writes every keyframe's maps into `dir` (created if needed) and then `index.json`.
///
/// `keyframes` pairs each densified keyframe with its *final* optimised `world_from_keyframe`:
/// the back end keeps moving poses (and their scales) after densification, and the depth map is
/// written in the scale of the pose the trajectory files report. All keyframes must share one
/// working size and camera. Existing files of the same names are overwritten.
pub fn write_dense_keyframes(dir: &Path, keyframes: &[(DenseKeyframe, Sim3)]) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let (width, height, camera) = match keyframes.first() {
        Some((kf, _)) => (
            kf.idepth.width,
            kf.idepth.height,
            Some(CameraRecord::from(&kf.camera)),
        ),
        None => (0, 0, None),
    };
    let mut records = Vec::with_capacity(keyframes.len());
    for (kf, world_from_keyframe) in keyframes {
        check_keyframe(kf, width, height, camera.as_ref())?;
        let scale = world_from_keyframe.scale;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(Error::Shape(format!(
                "keyframe {}: final pose scale {scale} is not a positive number",
                kf.keyframe_id
            )));
        }
        let stem = keyframe_stem(kf.timestamp);
        let mut maps: Vec<(&str, &ImageF32)> = Vec::new();
        let depth = depth_from_idepth(&kf.idepth, scale);
        maps.push(("depth", &depth));
        maps.push(("idepth", &kf.idepth));
        maps.push(("variance", &kf.variance));
        if let Some(st) = &kf.stages {
            maps.push(("intensity", &st.intensity));
            if let Some(p) = &st.prior {
                maps.push(("prior", p));
            }
            if let Some(p) = &st.prior_aligned {
                maps.push(("prior_aligned", p));
            }
            maps.push(("semidense", &st.semidense));
            maps.push(("semidense_var", &st.semidense_var));
            maps.push(("filtered", &st.filtered));
            maps.push(("filtered_var", &st.filtered_var));
        }
        for (name, map) in &maps {
            if (map.width, map.height) != (width, height) {
                return Err(Error::Shape(format!(
                    "keyframe {} map `{name}` is {}x{}, the store {width}x{height}",
                    kf.keyframe_id, map.width, map.height
                )));
            }
            map.check_size()?;
            crate::npy::write_f32(&dir.join(map_file(&stem, name)), map)?;
        }
        records.push(KeyframeRecord {
            id: kf.keyframe_id,
            timestamp: kf.timestamp,
            stem,
            scale,
            world_from_keyframe: pose_record(world_from_keyframe),
            mode: mode_name(kf.mode).to_string(),
            align: kf.align.map(|a| AlignRecord {
                a: a.a,
                b: a.b,
                used: a.used,
            }),
            align_error: kf.align_error.clone(),
            consistent_pixels: kf.consistent_pixels,
            timings: kf.timings,
            maps: maps.iter().map(|(n, _)| n.to_string()).collect(),
        });
    }
    let index = IndexFile {
        version: STORE_VERSION,
        width,
        height,
        camera,
        keyframes: records,
    };
    let text = serde_json::to_string_pretty(&index)
        .map_err(|e| Error::Config(format!("serialising {INDEX_FILE}: {e}")))?;
    let tmp = dir.join(format!("{INDEX_FILE}.tmp"));
    std::fs::write(&tmp, text).map_err(|e| Error::io(&tmp, e))?;
    let path = dir.join(INDEX_FILE);
    std::fs::rename(&tmp, &path).map_err(|e| Error::io(&path, e))
}

/// Depth in the trajectory's scale, `scale / D` (the keyframe's points `p_k` with depth
/// `1/D` land at `s·R·p_k + t` in the world, so world distances along the ray are `s/D`);
/// 0 where the inverse depth is not a positive finite number.
pub fn depth_from_idepth(idepth: &ImageF32, scale: f64) -> ImageF32 {
    let data = idepth
        .data
        .iter()
        .map(|&d| {
            let z = scale / f64::from(d);
            if d.is_finite() && d > 0.0 && z.is_finite() {
                z as f32
            } else {
                0.0
            }
        })
        .collect();
    ImageF32 {
        width: idepth.width,
        height: idepth.height,
        data,
    }
}

fn check_keyframe(
    kf: &DenseKeyframe,
    width: usize,
    height: usize,
    camera: Option<&CameraRecord>,
) -> Result<()> {
    let cam = CameraRecord::from(&kf.camera);
    if (kf.idepth.width, kf.idepth.height) != (width, height) || camera != Some(&cam) {
        return Err(Error::Shape(format!(
            "keyframe {}: {}x{} with camera {cam:?}; the store holds {width}x{height} with \
             camera {camera:?} (one working size and camera per store)",
            kf.keyframe_id, kf.idepth.width, kf.idepth.height
        )));
    }
    Ok(())
}

fn map_file(stem: &str, name: &str) -> String {
    format!("{stem}.{name}.npy")
}

/// The name `DenseMode` has in the index (its serde name).
pub fn mode_name(mode: DenseMode) -> &'static str {
    match mode {
        DenseMode::Prior => "prior",
        DenseMode::NoModel => "no_model",
    }
}

/// `[tx, ty, tz, qx, qy, qz, qw, s]`: the TUM pose order plus the Sim(3) scale.
fn pose_record(pose: &Sim3) -> [f64; 8] {
    let q = pose.rotation.quaternion();
    let t = pose.translation;
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w, pose.scale]
}

fn pose_from_record(r: &[f64; 8], path: &Path) -> Result<Sim3> {
    let q = Quaternion::new(r[6], r[3], r[4], r[5]);
    let norm = q.norm();
    if !(r.iter().all(|v| v.is_finite()) && norm > 1e-9 && r[7] > 0.0) {
        return Err(Error::Dataset(format!(
            "{}: invalid keyframe pose {r:?}",
            path.display()
        )));
    }
    Ok(Sim3::new(
        SO3::from_quaternion(UnitQuaternion::from_quaternion(q)),
        Vector3::new(r[0], r[1], r[2]),
        r[7],
    ))
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraRecord {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

impl From<&PinholeCamera> for CameraRecord {
    fn from(c: &PinholeCamera) -> Self {
        Self {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
        }
    }
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct AlignRecord {
    a: f64,
    b: f64,
    used: usize,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyframeRecord {
    id: KeyframeId,
    timestamp: f64,
    stem: String,
    scale: f64,
    /// `[tx, ty, tz, qx, qy, qz, qw, s]` of the final optimised pose.
    world_from_keyframe: [f64; 8],
    mode: String,
    align: Option<AlignRecord>,
    align_error: Option<String>,
    consistent_pixels: usize,
    timings: DenseTimings,
    maps: Vec<String>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct IndexFile {
    version: u32,
    width: usize,
    height: usize,
    /// None only for a store without keyframes.
    camera: Option<CameraRecord>,
    keyframes: Vec<KeyframeRecord>,
}

/// One keyframe as recorded in `index.json`.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredKeyframe {
    pub id: KeyframeId,
    pub timestamp: f64,
    /// File stem of its maps (`<stem>.<map>.npy`).
    pub stem: String,
    /// Scale of the final `world_from_keyframe` (the depth map is already multiplied by it).
    pub scale: f64,
    /// The final optimised pose.
    pub world_from_keyframe: Sim3,
    /// `"prior"` or `"no_model"` (see [`DenseMode`]).
    pub mode: String,
    /// The eq. (3) fit of the prior onto the semi-dense map, when there was one.
    pub align: Option<ScaleShift>,
    pub align_error: Option<String>,
    pub consistent_pixels: usize,
    pub timings: DenseTimings,
    /// Names of the maps written for this keyframe (see [`MAP_NAMES`]).
    pub maps: Vec<String>,
}

impl StoredKeyframe {
    /// Whether the map `name` was written.
    pub fn has_map(&self, name: &str) -> bool {
        self.maps.iter().any(|m| m == name)
    }

    /// Whether the evaluation stages (intensity, semi-dense, filtered) were kept.
    pub fn has_stages(&self) -> bool {
        [
            "intensity",
            "semidense",
            "semidense_var",
            "filtered",
            "filtered_var",
        ]
        .iter()
        .all(|m| self.has_map(m))
    }

    /// Whether the keyframe was densified without the prior.
    pub fn is_no_model(&self) -> bool {
        self.mode == mode_name(DenseMode::NoModel)
    }
}

/// A store opened for reading.
#[derive(Clone, Debug, PartialEq)]
pub struct DenseStore {
    pub dir: PathBuf,
    /// Working size of every map.
    pub width: usize,
    pub height: usize,
    /// `(fx, fy, cx, cy)` of the undistorted pinhole camera at the working size (zeros for a
    /// store without keyframes).
    pub camera: (f64, f64, f64, f64),
    /// In the order written (keyframe order of the run).
    pub keyframes: Vec<StoredKeyframe>,
}

impl DenseStore {
    /// Reads `dir/index.json`. Fails with a message naming the folder when it is not a store.
    pub fn open(dir: &Path) -> Result<Self> {
        let path = dir.join(INDEX_FILE);
        if !dir.is_dir() {
            return Err(Error::Dataset(format!(
                "{} is not a folder of densified keyframes (written by `relfusion run` with \
                 the dense layer on)",
                dir.display()
            )));
        }
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let index: IndexFile = serde_json::from_str(&text)
            .map_err(|e| Error::Dataset(format!("{}: {e}", path.display())))?;
        if index.version != STORE_VERSION {
            return Err(Error::Dataset(format!(
                "{}: store version {} (this build reads {STORE_VERSION})",
                path.display(),
                index.version
            )));
        }
        let camera = index
            .camera
            .map_or((0.0, 0.0, 0.0, 0.0), |c| (c.fx, c.fy, c.cx, c.cy));
        if !index.keyframes.is_empty()
            && (index.camera.is_none() || index.width * index.height == 0)
        {
            return Err(Error::Dataset(format!(
                "{}: keyframes without a working size and camera",
                path.display()
            )));
        }
        let keyframes = index
            .keyframes
            .into_iter()
            .map(|r| {
                if let Some(bad) = r.maps.iter().find(|m| !MAP_NAMES.contains(&m.as_str())) {
                    return Err(Error::Dataset(format!(
                        "{}: keyframe {} lists unknown map `{bad}`",
                        path.display(),
                        r.id
                    )));
                }
                Ok(StoredKeyframe {
                    id: r.id,
                    timestamp: r.timestamp,
                    world_from_keyframe: pose_from_record(&r.world_from_keyframe, &path)?,
                    stem: r.stem,
                    scale: r.scale,
                    mode: r.mode,
                    align: r.align.map(|a| ScaleShift {
                        a: a.a,
                        b: a.b,
                        used: a.used,
                    }),
                    align_error: r.align_error,
                    consistent_pixels: r.consistent_pixels,
                    timings: r.timings,
                    maps: r.maps,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            dir: dir.to_path_buf(),
            width: index.width,
            height: index.height,
            camera,
            keyframes,
        })
    }

    /// The undistorted pinhole camera of the maps.
    pub fn pinhole(&self) -> Result<PinholeCamera> {
        let (fx, fy, cx, cy) = self.camera;
        PinholeCamera::new(fx, fy, cx, cy, self.width as u32, self.height as u32)
            .map_err(Into::into)
    }

    /// Reads the map `name` of `kf` (one of [`MAP_NAMES`]): `None` when it was not written
    /// (e.g. `prior` of a keyframe densified without a model); an error for an unknown name, a
    /// missing or malformed file, or a map of the wrong size.
    pub fn read_map(&self, kf: &StoredKeyframe, name: &str) -> Result<Option<ImageF32>> {
        if !MAP_NAMES.contains(&name) {
            return Err(Error::Config(format!(
                "unknown keyframe map `{name}` (known: {})",
                MAP_NAMES.join(", ")
            )));
        }
        if !kf.has_map(name) {
            return Ok(None);
        }
        let path = self.dir.join(map_file(&kf.stem, name));
        let map = crate::npy::read_f32(&path)?;
        if (map.width, map.height) != (self.width, self.height) {
            return Err(Error::Shape(format!(
                "{} is {}x{}, the store {}x{}",
                path.display(),
                map.width,
                map.height,
                self.width,
                self.height
            )));
        }
        Ok(Some(map))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::dense::DenseStages;

    fn ramp(w: usize, h: usize, offset: f32) -> ImageF32 {
        let data = (0..w * h).map(|i| offset + (i % 7) as f32 * 0.1).collect();
        ImageF32::from_vec(w, h, data).expect("size")
    }

    fn keyframe(id: KeyframeId, timestamp: f64, with_prior: bool) -> DenseKeyframe {
        let (w, h) = (9, 5);
        let mut idepth = ramp(w, h, 0.5);
        idepth.data[0] = 0.0;
        idepth.data[1] = f32::NAN;
        idepth.data[2] = -1.0;
        let stages = DenseStages {
            intensity: ramp(w, h, 100.0),
            prior: with_prior.then(|| ramp(w, h, 2.0)),
            prior_aligned: with_prior.then(|| ramp(w, h, 0.7)),
            semidense: ramp(w, h, 0.6),
            semidense_var: ramp(w, h, 0.01),
            filtered: ramp(w, h, 0.65),
            filtered_var: ramp(w, h, 0.02),
        };
        DenseKeyframe {
            keyframe_id: id,
            timestamp,
            camera: PinholeCamera::new(8.0, 8.5, 4.0, 2.0, w as u32, h as u32).expect("camera"),
            world_from_keyframe: Sim3::identity(),
            idepth: Arc::new(idepth),
            variance: Arc::new(ramp(w, h, 0.001)),
            mode: if with_prior {
                DenseMode::Prior
            } else {
                DenseMode::NoModel
            },
            align: with_prior.then_some(ScaleShift {
                a: 0.25,
                b: -0.1,
                used: 30,
            }),
            align_error: (!with_prior).then(|| "no model".to_string()),
            consistent_pixels: 17,
            timings: DenseTimings {
                prior_ms: 1.0,
                align_ms: 2.0,
                filter_ms: 3.0,
                densify_ms: 4.0,
                two_view_ms: 5.0,
            },
            stages: Some(Arc::new(stages)),
        }
    }

    fn temp(tag: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("relfusion_store_{tag}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn dense_store_round_trips_every_map_and_the_index() {
        let dir = temp("round_trip");
        let a = keyframe(3, 1305031229.528748, true);
        let mut b = keyframe(7, 2.5, false);
        // A keyframe written without stages has only the result.
        let c = DenseKeyframe {
            stages: None,
            ..keyframe(9, 3.0, true)
        };
        b.consistent_pixels = 0;
        let pose_a = Sim3::new(
            SO3::exp(&Vector3::new(0.1, -0.2, 0.3)),
            Vector3::new(1.0, 2.0, 3.0),
            2.0,
        );
        let pose_b = Sim3::new(SO3::identity(), Vector3::zeros(), 0.5);
        write_dense_keyframes(
            &dir,
            &[
                (a.clone(), pose_a),
                (b.clone(), pose_b),
                (c, Sim3::identity()),
            ],
        )
        .expect("write");
        assert!(!dir.join(format!("{INDEX_FILE}.tmp")).exists());

        let store = DenseStore::open(&dir).expect("open");
        assert_eq!((store.width, store.height), (9, 5));
        assert_eq!(store.camera, (8.0, 8.5, 4.0, 2.0));
        assert_eq!(store.pinhole().expect("camera").fy, 8.5);
        assert_eq!(store.keyframes.len(), 3);
        let ka = &store.keyframes[0];
        assert_eq!((ka.id, ka.stem.as_str()), (3, "1305031229.528748"));
        assert_eq!(ka.timestamp, a.timestamp);
        assert_eq!((ka.scale, ka.mode.as_str()), (2.0, "prior"));
        assert_eq!(ka.align, a.align);
        assert_eq!((ka.consistent_pixels, ka.timings), (17, a.timings));
        assert!(ka.has_stages() && !ka.is_no_model());
        let back = ka.world_from_keyframe;
        assert!((back.matrix() - pose_a.matrix()).abs().max() < 1e-12);

        // Depth in the trajectory's scale: s / D, 0 where D is not a positive number.
        let depth = store.read_map(ka, "depth").expect("read").expect("depth");
        assert_eq!(&depth.data[..3], &[0.0, 0.0, 0.0]);
        for (z, d) in depth.data.iter().zip(&a.idepth.data).skip(3) {
            assert!((z - 2.0 / d).abs() < 1e-6, "{z} vs 2/{d}");
        }
        let st = a.stages.as_ref().expect("stages");
        for (name, want) in [
            ("intensity", &st.intensity),
            ("prior", st.prior.as_ref().expect("prior")),
            ("prior_aligned", st.prior_aligned.as_ref().expect("aligned")),
            ("semidense", &st.semidense),
            ("semidense_var", &st.semidense_var),
            ("filtered", &st.filtered),
            ("filtered_var", &st.filtered_var),
        ] {
            let got = store.read_map(ka, name).expect("read").expect(name);
            assert_eq!(&got, want, "{name}");
        }
        let idepth = store.read_map(ka, "idepth").expect("read").expect("idepth");
        assert_eq!(idepth.data[3..], a.idepth.data[3..]);

        // Without a model: no prior maps, mode no_model, the reason kept.
        let kb = &store.keyframes[1];
        assert!(kb.is_no_model() && kb.align.is_none());
        assert_eq!(kb.align_error.as_deref(), Some("no model"));
        assert_eq!(store.read_map(kb, "prior").expect("read"), None);
        assert_eq!(store.read_map(kb, "prior_aligned").expect("read"), None);
        assert!(store.read_map(kb, "filtered").expect("read").is_some());
        let depth_b = store.read_map(kb, "depth").expect("read").expect("depth");
        assert!((depth_b.data[5] - 0.5 / b.idepth.data[5]).abs() < 1e-6);

        // Without stages: only the result.
        let kc = &store.keyframes[2];
        assert!(!kc.has_stages());
        assert_eq!(kc.maps, vec!["depth", "idepth", "variance"]);
        assert_eq!(store.read_map(kc, "semidense").expect("read"), None);
        assert!(store.read_map(kc, "bogus").is_err());

        // A map deleted behind the index's back is an error, not a silent None.
        std::fs::remove_file(dir.join(format!("{}.variance.npy", kc.stem))).expect("rm");
        assert!(store.read_map(kc, "variance").is_err());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn dense_store_rejects_mixed_sizes_bad_scales_and_missing_index() {
        let dir = temp("reject");
        let a = keyframe(1, 1.0, true);
        let mut small = keyframe(2, 2.0, true);
        small.idepth = Arc::new(ImageF32::filled(4, 4, 1.0));
        assert!(matches!(
            write_dense_keyframes(
                &dir,
                &[(a.clone(), Sim3::identity()), (small, Sim3::identity())]
            ),
            Err(Error::Shape(_))
        ));
        let zero_scale = Sim3::new(SO3::identity(), Vector3::zeros(), 0.0);
        assert!(write_dense_keyframes(&dir, &[(a, zero_scale)]).is_err());
        // Neither attempt left an index behind.
        let err = DenseStore::open(&dir).expect_err("no index");
        assert!(err.to_string().contains(INDEX_FILE), "{err}");
        assert!(DenseStore::open(&dir.join("absent")).is_err());

        // An empty run writes an empty, readable store.
        write_dense_keyframes(&dir, &[]).expect("empty");
        let empty = DenseStore::open(&dir).expect("open empty");
        assert!(empty.keyframes.is_empty());
        std::fs::remove_dir_all(&dir).ok();
    }
}
