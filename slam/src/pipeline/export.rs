//! What a run leaves behind, at the current keyframe poses (optimised after
//! [`Pipeline::finish`]): the trajectories, the semi-dense and dense point clouds and the map.
//!
//! A map fragment that was never merged (`pipeline.new_fragment_after_lost_s`) has its poses in
//! a frame of its own, so only the main fragment is exported: the one with the most keyframes,
//! with every fragment merged into it (ORB-SLAM3 likewise saves the trajectory of its largest
//! map). The final mesh leaves the others out too (`Pipeline::finish_fusion`).

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use nalgebra::{Vector2, Vector3};

use super::Pipeline;
use crate::export::ColoredPoint;
use crate::frame::CompactFrame;
use crate::geometry::{PinholeCamera, Sim3};
use crate::graph::{Constraint, KeyframeData, KeyframeId, ScalePrior};
use crate::map::{DenseDepth, MapKeyframe, SavedMap};
use crate::mapping::{CompactDepth, DepthMap};
use crate::{Error, Result};

/// Grey for points of keyframes without a colour image.
const NO_COLOUR: [u8; 3] = [200, 200, 200];

/// The semi-dense cloud's inputs at one moment ([`Pipeline::semidense_snapshot`]). Building
/// the points reads every spilled keyframe back, so a live session does it off its frame path:
/// a 1280-keyframe session stalled 19 s doing it in line, lost tracking and began a new map
/// fragment (issue 37).
#[derive(Debug)]
pub struct SemidenseSnapshot {
    keyframes: Vec<SnapshotKeyframe>,
}

#[derive(Debug)]
struct SnapshotKeyframe {
    camera: PinholeCamera,
    world_from_kf: Sim3,
    /// Its depth when in memory (the current keyframe's as last published, or a resident
    /// one's); else `data`'s compact depth is expanded.
    depth: Option<Arc<DepthMap>>,
    data: KeyframeData,
}

impl SemidenseSnapshot {
    /// The points, at most `max_points`: each keyframe gives an equal share, every k-th of its
    /// points. A session of an hour has billions of semi-dense points; its checkpoints and
    /// downloads stay bounded this way (issue 37).
    pub fn points(&self, max_points: usize) -> Result<Vec<ColoredPoint>> {
        let share = max_points / self.keyframes.len().max(1);
        let mut points = Vec::new();
        for kf in &self.keyframes {
            let depth = match &kf.depth {
                Some(depth) => depth.clone(),
                None => Arc::new(kf.data.depth_map()?),
            };
            let image = kf.data.image.get()?;
            let rgb = image.rgb.as_deref();
            let start = points.len();
            back_project(
                &kf.camera,
                &kf.world_from_kf,
                depth.width,
                depth.height,
                |x, y| depth.at(x, y).estimate().map(|(idepth, _)| idepth),
                |x, y| rgb.map_or(NO_COLOUR, |rgb| rgb.get_pixel(x as u32, y as u32).0),
                &mut points,
            );
            let added = points.len() - start;
            if added > share {
                let step = added.div_ceil(share.max(1));
                let mut kept = start;
                for i in (start..points.len()).step_by(step) {
                    points[kept] = points[i];
                    kept += 1;
                }
                points.truncate(kept);
            }
        }
        Ok(points)
    }
}

impl Pipeline {
    /// Whether each keyframe belongs to the main fragment (see the module docs). All do while
    /// the back end is on its thread (it knows the fragments) or when there is one fragment.
    pub(super) fn exported(&self) -> Vec<bool> {
        let n = self.keyframes.len();
        let Some(fragments) = self.backend.backend().map(|b| b.fragments()) else {
            return vec![true; n];
        };
        let mut sizes: BTreeMap<KeyframeId, usize> = BTreeMap::new();
        for fragment in fragments.values() {
            *sizes.entry(*fragment).or_default() += 1;
        }
        // The largest; of equals, the oldest.
        let main = sizes
            .iter()
            .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
            .map(|(f, _)| *f);
        (0..n)
            .map(|id| fragments.get(&id).is_none_or(|f| Some(*f) == main))
            .collect()
    }

    /// Keyframe timestamps with their current poses (for `keyframes.txt`).
    pub fn keyframe_trajectory(&self) -> Vec<(f64, Sim3)> {
        let exported = self.exported();
        self.keyframe_poses()
            .into_iter()
            .filter(|(id, _)| exported[*id])
            .map(|(id, pose)| (self.keyframes[id].timestamp, pose))
            .collect()
    }

    /// Every frame's pose (camera-to-world) through its keyframe's current pose; lost frames
    /// are left out. Spilled records are read back.
    pub fn trajectory(&self) -> Result<Vec<(f64, Sim3)>> {
        let poses = self.keyframe_poses();
        let exported = self.exported();
        let mut out = Vec::with_capacity(self.frames.len());
        self.frames.for_each(|f| {
            if !f.lost && exported[f.keyframe] {
                out.push((
                    f.timestamp,
                    poses[f.keyframe].1 * Sim3::from_se3(&f.keyframe_from_frame, 1.0),
                ));
            }
        })?;
        Ok(out)
    }

    /// The semi-dense points of every keyframe at its current pose, coloured from its image.
    /// Spilled keyframes are read back.
    pub fn semidense_points(&self) -> Result<Vec<ColoredPoint>> {
        self.semidense_snapshot().points(usize::MAX)
    }

    /// What the semi-dense cloud is built from, taken without reading a spilled keyframe back:
    /// each exported keyframe's camera and pose, its depth when in memory, and handles to its
    /// compact image and depth.
    pub fn semidense_snapshot(&self) -> SemidenseSnapshot {
        let poses = self.keyframe_poses();
        let exported = self.exported();
        let current_depth = self.current.zip(self.mapper.latest_depth());
        let keyframes = self
            .keyframes
            .iter()
            .zip(poses)
            .enumerate()
            .filter(|(id, _)| exported[*id])
            .map(|(id, (kf, (_, world_from_kf)))| SnapshotKeyframe {
                camera: kf.camera,
                world_from_kf,
                depth: match &current_depth {
                    Some((current, depth)) if *current == id => Some(depth.clone()),
                    _ => kf.depth.clone(),
                },
                data: kf.data.clone(),
            })
            .collect();
        SemidenseSnapshot { keyframes }
    }

    /// The map as it stands, to save (`map::write_map`): every keyframe of the main fragment
    /// (renumbered `0..n` in order) with its current pose, semi-dense and dense depth and
    /// descriptor, the pose graph's edges between them, the voxel size. Needs the back end at
    /// hand: after [`Pipeline::finish`], or in step. Spilled keyframes are read back; a long
    /// session writes its map with [`Pipeline::write_map`] instead.
    pub fn saved_map(&self) -> Result<SavedMap> {
        let (mut map, ids) = self.map_plan()?;
        let current = self.current.zip(self.mapper.latest_depth());
        map.keyframes = ids
            .iter()
            .enumerate()
            .map(|(new, (old, pose))| self.map_keyframe(*old, new, *pose, current.as_ref()))
            .collect::<Result<_>>()?;
        Ok(map)
    }

    /// Writes [`Pipeline::saved_map`] into `dir` one keyframe at a time: however many keyframes
    /// are spilled, one is read back at a time (issue 37).
    pub fn write_map(&self, dir: &std::path::Path) -> Result<()> {
        let (header, ids) = self.map_plan()?;
        let current = self.current.zip(self.mapper.latest_depth());
        crate::map::write_map_streamed(dir, &header, ids.len(), |new| {
            let (old, pose) = ids[new];
            self.map_keyframe(old, new, pose, current.as_ref())
        })
    }

    /// The saved map without its keyframes (camera, renumbered edges, voxel size), and the
    /// keyframes it takes, in order: their ids in the pipeline and current poses.
    fn map_plan(&self) -> Result<(SavedMap, Vec<(KeyframeId, Sim3)>)> {
        let backend = self.backend.backend().ok_or_else(|| {
            Error::Backend("the pose graph is on its thread: finish the run first".into())
        })?;
        let exported = self.exported();
        let ids: Vec<(KeyframeId, Sim3)> = self
            .keyframe_poses()
            .into_iter()
            .filter(|(id, _)| exported[*id])
            .collect();
        let renumbered: HashMap<KeyframeId, KeyframeId> = ids
            .iter()
            .enumerate()
            .map(|(new, (old, _))| (*old, new))
            .collect();
        let edges = backend
            .graph()
            .edges()
            .iter()
            .filter_map(|e| {
                Some(Constraint {
                    from: *renumbered.get(&e.from)?,
                    to: *renumbered.get(&e.to)?,
                    ..e.clone()
                })
            })
            .collect();
        let header = SavedMap {
            camera: self.camera,
            keyframes: Vec::new(),
            edges,
            voxel_size: self.fusion_stats().map(|f| f.voxel_size as f32),
            metric: self.metres,
        };
        Ok((header, ids))
    }

    /// Keyframe `id` as keyframe `new_id` of a saved map, at `world_from_keyframe`; `current`:
    /// the current keyframe and its latest depth (read once per map).
    fn map_keyframe(
        &self,
        id: KeyframeId,
        new_id: KeyframeId,
        world_from_keyframe: Sim3,
        current: Option<&(KeyframeId, Arc<DepthMap>)>,
    ) -> Result<MapKeyframe> {
        let kf = &self.keyframes[id];
        let depth = match current {
            Some((current, depth)) if *current == id => Arc::new(CompactDepth::of(depth)),
            _ => kf.data.depth.get()?,
        };
        let dense = match self.dense_keyframes.get(&id) {
            Some(d) => {
                let d = d.get()?;
                Some(DenseDepth {
                    camera: d.camera,
                    idepth: d.idepth.clone(),
                    variance: d.variance.clone(),
                })
            }
            None => None,
        };
        Ok(MapKeyframe {
            id: new_id,
            timestamp: kf.timestamp,
            world_from_keyframe,
            image: CompactFrame::clone(&*kf.data.image.get()?),
            depth,
            dense,
            thumbnail: kf.thumbnail.clone(),
            scale_prior: self.scale_prior(id),
        })
    }

    /// Keyframe `id`'s scale factor in a map of metres: the pose graph's, or the one a loaded
    /// map came with (its fixed keyframes keep theirs outside the graph, `extend`).
    fn scale_prior(&self, id: KeyframeId) -> Option<ScalePrior> {
        if !self.metres {
            return None;
        }
        let graph = self
            .backend
            .backend()
            .and_then(|b| b.graph().scale_priors().get(&id).copied());
        graph.or_else(|| self.map.as_ref().and_then(|m| m.scale_prior(id)))
    }

    /// Every densified keyframe back-projected at its current pose, coloured from its image:
    /// the dense point cloud (`dense.ply`).
    pub fn dense_points(&self) -> Result<Vec<ColoredPoint>> {
        let mut points = Vec::new();
        let exported = self.exported();
        for (kf, world_from_kf) in self.dense_keyframes()? {
            if !exported[kf.keyframe_id] {
                continue;
            }
            let (w, h) = (kf.idepth.width, kf.idepth.height);
            let colors = match &self.keyframes[kf.keyframe_id].data.image.get()?.rgb {
                Some(rgb) => Some(crate::dense::resample::box_downsample_rgb(rgb, w, h)?),
                None => None,
            };
            back_project(
                &kf.camera,
                &world_from_kf,
                w,
                h,
                |x, y| Some(kf.idepth.at(x, y)),
                |x, y| colors.as_ref().map_or(NO_COLOUR, |c| c[y * w + x]),
                &mut points,
            );
        }
        Ok(points)
    }
}

/// Appends the world point of every pixel of a `width`×`height` inverse-depth map with a
/// finite, positive inverse depth, seen by `camera` at `world_from_camera`.
fn back_project(
    camera: &PinholeCamera,
    world_from_camera: &Sim3,
    width: usize,
    height: usize,
    idepth: impl Fn(usize, usize) -> Option<f32>,
    color: impl Fn(usize, usize) -> [u8; 3],
    points: &mut Vec<ColoredPoint>,
) {
    for y in 0..height {
        for x in 0..width {
            let Some(d) = idepth(x, y).filter(|d| d.is_finite() && *d > 0.0) else {
                continue;
            };
            let p = camera.unproject(&Vector2::new(x as f64, y as f64), 1.0 / f64::from(d));
            let w: Vector3<f64> = world_from_camera.act(&p);
            points.push(ColoredPoint {
                position: [w.x as f32, w.y as f32, w.z as f32],
                color: color(x, y),
            });
        }
    }
}
