//! Maps that outlive a run: what a finished pipeline knows, saved (`store`), loaded and used to
//! localise a new camera in it (`localize`).
//!
//! A [`SavedMap`] holds every keyframe (its undistorted colour image, the semi-dense inverse
//! depth and variance that tracking uses, the dense depth and variance the fusion integrates,
//! the optimised pose and the appearance descriptor place recognition compares), the pose
//! graph's Sim(3) edges with their information, the camera, and the fusion's voxel size: the
//! mesh is rebuilt from the dense keyframes, so no TSDF is stored. A map made with a metric
//! depth prior says so ([`SavedMap::metric`]) and keeps each keyframe's scale factor, so that
//! extending it stays in metres (issue 39). The format on disk is
//! versioned ([`FORMAT_VERSION`]) and documented in `docs/map-format.md`.

pub mod localize;
pub mod store;
#[cfg(test)]
mod tests;

use std::sync::Arc;

use crate::frame::CompactFrame;
use crate::geometry::{PinholeCamera, Sim3};
use crate::graph::{Constraint, KeyframeId, ScalePrior, Thumbnail};
use crate::image::ImageF32;
use crate::mapping::CompactDepth;
use crate::{Error, Result};

pub use localize::{Localization, LocalizationState, LocalizeConfig, Localizer};
pub use store::{disk_bytes_by_file, read_keyframe_poses, read_map, write_map, write_map_streamed};

/// Version of the on-disk layout written; a reader refuses any other than
/// [`OLDEST_READABLE_VERSION`]`..=FORMAT_VERSION` (the layout says what each version holds,
/// `docs/map-format.md`). Version 2 added the metric scale.
pub const FORMAT_VERSION: u32 = 2;

/// Maps of version 1 read as maps of arbitrary scale without scale factors.
pub const OLDEST_READABLE_VERSION: u32 = 1;

/// The dense depth of a keyframe at the dense layer's working resolution.
#[derive(Clone, Debug, PartialEq)]
pub struct DenseDepth {
    /// Undistorted camera of the two maps.
    pub camera: PinholeCamera,
    /// Inverse depth in the keyframe's gauge (0 = invalid).
    pub idepth: Arc<ImageF32>,
    pub variance: Arc<ImageF32>,
}

/// One keyframe of a map.
#[derive(Clone, Debug)]
pub struct MapKeyframe {
    pub id: KeyframeId,
    pub timestamp: f64,
    /// The optimised pose (Sim(3): the keyframe's depth is in its own scale).
    pub world_from_keyframe: Sim3,
    /// The keyframe's image (undistorted), without its pyramid ([`CompactFrame::rebuild`]
    /// gives the frame back).
    pub image: CompactFrame,
    /// Semi-dense inverse depth and variance at full resolution (what tracking aligns to).
    pub depth: Arc<CompactDepth>,
    /// The dense layer's result, when the keyframe was densified.
    pub dense: Option<DenseDepth>,
    /// Appearance descriptor for place recognition.
    pub thumbnail: Thumbnail,
    /// The metric prior's unary factor on the keyframe's scale (`graph::ScalePrior`), when one
    /// observed it: an extension that may move the keyframe keeps it anchored.
    pub scale_prior: Option<ScalePrior>,
}

/// A whole map.
#[derive(Clone, Debug)]
pub struct SavedMap {
    /// The camera as the frames arrive (with its distortion): a map only serves the same camera.
    pub camera: PinholeCamera,
    /// Keyframes by id order.
    pub keyframes: Vec<MapKeyframe>,
    /// The pose graph's edges (odometry, constraints found, loop closures).
    pub edges: Vec<Constraint>,
    /// Voxel size of the fusion (map units), when there was one.
    pub voxel_size: Option<f32>,
    /// The map's unit is the metre: a metric depth prior anchored its scale (the run reported
    /// `"scale": "metric"`). False for a monocular map of arbitrary scale.
    pub metric: bool,
}

impl SavedMap {
    /// Checks what a reader must be able to rely on: keyframe ids `0..n` in order, sizes of
    /// every map equal to the keyframe camera's, edges between existing keyframes, finite poses.
    pub fn validate(&self) -> Result<()> {
        for (i, kf) in self.keyframes.iter().enumerate() {
            self.check_keyframe(i, kf)?;
        }
        self.check_edges(self.keyframes.len())
    }

    /// The checks of [`SavedMap::validate`] on keyframe `i` of this map's camera (a map
    /// written keyframe by keyframe checks each as it comes).
    pub fn check_keyframe(&self, i: usize, kf: &MapKeyframe) -> Result<()> {
        let undistorted = self.camera.undistorted();
        {
            let bad = |why: String| Err(Error::Map(format!("keyframe {i}: {why}")));
            if kf.id != i {
                return bad(format!("has id {}", kf.id));
            }
            if kf.image.camera != undistorted {
                return bad("its camera is not the map's".into());
            }
            let (w, h) = (undistorted.width as usize, undistorted.height as usize);
            if (kf.depth.width, kf.depth.height) != (w, h) || kf.depth.len() != w * h {
                return bad(format!(
                    "depth is {}x{}, camera {w}x{h}",
                    kf.depth.width, kf.depth.height
                ));
            }
            if let Some(dense) = &kf.dense {
                let (dw, dh) = (dense.camera.width as usize, dense.camera.height as usize);
                for img in [&dense.idepth, &dense.variance] {
                    if (img.width, img.height) != (dw, dh) {
                        return bad("dense maps differ from their camera in size".into());
                    }
                }
            }
            if !valid_sim3(&kf.world_from_keyframe) {
                return bad("its pose is not a finite similarity".into());
            }
            if let Some(p) = &kf.scale_prior {
                let positive = |v: f64| v.is_finite() && v > 0.0;
                if !(p.log_scale.is_finite() && positive(p.sigma) && positive(p.huber)) {
                    return bad("its scale factor is not finite with σ, Huber width > 0".into());
                }
                if !self.metric {
                    return bad("it has a scale factor in a map of arbitrary scale".into());
                }
            }
        }
        Ok(())
    }

    /// The edges join existing keyframes of a map of `keyframes` with finite similarities.
    pub fn check_edges(&self, keyframes: usize) -> Result<()> {
        for e in &self.edges {
            if !valid_sim3(&e.to_from_from) {
                return Err(Error::Map(format!(
                    "edge {} → {}: not a finite similarity",
                    e.from, e.to
                )));
            }
            if e.from >= keyframes || e.to >= keyframes || e.from == e.to {
                return Err(Error::Map(format!(
                    "edge {} → {} names a missing keyframe",
                    e.from, e.to
                )));
            }
        }
        Ok(())
    }

    /// Bytes the loaded map holds in memory (images, depth maps), for budgets and the
    /// benchmark.
    pub fn memory_bytes(&self) -> usize {
        self.keyframes
            .iter()
            .map(|kf| {
                let image = kf.image.heap_bytes();
                let depth = kf.depth.heap_bytes();
                let dense = kf
                    .dense
                    .as_ref()
                    .map_or(0, |d| (d.idepth.data.len() + d.variance.data.len()) * 4);
                image + depth + dense
            })
            .sum()
    }
}

/// Finite translation, finite positive scale and a unit quaternion (a manifest's rotation is
/// not normalised on reading).
fn valid_sim3(p: &Sim3) -> bool {
    let q = p.rotation.quaternion().into_inner();
    p.translation.iter().all(|v| v.is_finite())
        && p.scale.is_finite()
        && p.scale > 0.0
        && (q.norm() - 1.0).abs() < 1e-6
}
