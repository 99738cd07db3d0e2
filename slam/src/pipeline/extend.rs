//! Extending a saved map (`relfusion run SEQ --map MAP --mode extend`): the map's keyframes
//! become the pipeline's first keyframes, and the new camera maps on from where it is found
//! in them.
//!
//! - **Loading.** Each map keyframe enters the pipeline (its tracking reference rebuilt from
//!   its semi-dense depth), the back end (a vertex at its saved pose, with the map's Sim(3)
//!   edges) and, when it was densified, the fusion. New keyframes get the ids after the map's.
//! - **Starting.** Until a frame is found in the map (the localiser's place recognition over
//!   all keyframes and its verification by a second keyframe, [`crate::map::Localizer`]),
//!   frames are reported lost: mapping in a frame of its own would give a second, unconnected
//!   map. A found frame becomes a new keyframe whose depth is propagated from the map keyframe
//!   it was aligned to, exactly as after LSD-SLAM's relocalisation; its parent edge and the
//!   back end's constraint search (pose proximity, appearance) link the new keyframes to the
//!   old ones: loop closures across sessions.
//! - **Relocalising.** When tracking is lost and the recent keyframes do not find the camera
//!   again, the map's place recognition runs over all map keyframes.
//! - **Optimising.** The map's keyframes stay where the map put them ([`ExtendConfig::fix_map`]),
//!   so the new keyframes are pulled onto the old map rather than the old map bent towards the
//!   new keyframes' drift; the fusion integrates old and new keyframes into one mesh, and the
//!   merged map is saved like any other ([`Pipeline::saved_map`]).
//! - **Scale.** A map made in metres ([`SavedMap::metric`]) keeps them: the extension reports
//!   `"scale": "metric"` and maps on in the map's unit; the map keyframes' scale factors go back
//!   into the pose graph when their poses may move (`fix_map` off) and into the merged map
//!   either way. New keyframes observe no scale of their own (measured, docs/tuning.md), and a
//!   map of arbitrary scale is never called metric.

use std::sync::Arc;

use super::Pipeline;
use super::events::{Event, TrackingState};
use super::keyframes::KeyframeRecord;
use crate::dense::{DenseKeyframe, DenseMode, DenseTimings, DepthPrior};
use crate::frame::Frame;
use crate::fusion::worker::FusionJob;
use crate::geometry::{PinholeCamera, SE3};
use crate::gpu::GpuContext;
use crate::graph::Backend;
use crate::graph::{KeyframeData, KeyframeId, ScalePrior};
use crate::map::{Localizer, SavedMap};
use crate::spill::{Spill, Stored};
use crate::{Error, Result};

/// Settings of map extension.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ExtendConfig {
    /// Hold the loaded map's keyframe poses fixed in the pose graph. Default true: the map was
    /// optimised over its own loop closures; a new session's keyframes, tracked from one view,
    /// carry its scale drift, which the old map should correct rather than absorb
    /// (docs/tuning.md, "Extending a saved map").
    pub fix_map: bool,
}

impl Default for ExtendConfig {
    fn default() -> Self {
        Self { fix_map: true }
    }
}

/// The loaded map a pipeline extends.
#[derive(Debug)]
pub(super) struct MapOrigin {
    /// Place recognition over the map's keyframes.
    localizer: Localizer,
    /// Keyframes that came with the map (ids `0..keyframes`).
    pub keyframes: usize,
    /// Their scale factors (a metric map's), by id, kept for the merged map.
    scale_priors: Vec<Option<ScalePrior>>,
}

impl MapOrigin {
    /// The saved scale factor of map keyframe `id`.
    pub fn scale_prior(&self, id: KeyframeId) -> Option<ScalePrior> {
        self.scale_priors.get(id).copied().flatten()
    }
}

impl Pipeline {
    /// A pipeline that extends `map` (see the module docs). The map must be of `camera`.
    pub fn extending(
        config: super::Config,
        camera: PinholeCamera,
        prior: Option<Box<dyn DepthPrior>>,
        gpu: Option<Arc<GpuContext>>,
        map: &SavedMap,
    ) -> Result<Self> {
        if map.camera != camera {
            return Err(Error::Map(
                "the map was made with another camera than this sequence's".into(),
            ));
        }
        map.validate()?;
        let localizer = Localizer::new(map, config.tracking.clone(), config.localize.clone())?;
        let fix_map = config.extend.fix_map;
        let mut backend = Backend::new(config.backend.clone())?;
        let spill = Spill::default();
        let mut data = Vec::with_capacity(map.keyframes.len());
        for kf in &map.keyframes {
            let kept = KeyframeData {
                image: Stored::new(&spill, Arc::new(kf.image.clone())),
                depth: Stored::new(&spill, Arc::clone(&kf.depth)),
            };
            backend.add_map_keyframe(
                kf.id,
                Arc::new(kf.image.rebuild()?),
                Arc::new(kf.depth.expand()),
                Some(kept.clone()),
                kf.world_from_keyframe,
                fix_map,
            )?;
            // A fixed keyframe with a factor would get its scale freed (`PoseGraph::optimize`).
            if let (false, Some(prior)) = (fix_map, kf.scale_prior) {
                backend.add_map_scale_prior(kf.id, prior)?;
            }
            data.push(kept);
        }
        for edge in &map.edges {
            backend.add_map_edge(edge.clone())?;
        }
        let mut pipeline = Self::build(config, camera, prior, gpu, Some(backend), spill)?;
        // The map's keyframes carry its metres; new keyframes are not anchored to a metric
        // prior of their own: on redkitchen that made one extension 57 % worse and another 8 %
        // better (docs/tuning.md, "Metric maps").
        pipeline.metric = false;
        pipeline.metres = map.metric;
        pipeline.stats.scale = super::scale_name(map.metric);
        pipeline.load_keyframes(map, data)?;
        pipeline.map = Some(MapOrigin {
            localizer,
            keyframes: map.keyframes.len(),
            scale_priors: map.keyframes.iter().map(|kf| kf.scale_prior).collect(),
        });
        Ok(pipeline)
    }

    /// The map's keyframes as the pipeline's first ones; their dense depth to the fusion.
    fn load_keyframes(&mut self, map: &SavedMap, data: Vec<KeyframeData>) -> Result<()> {
        for (kf, data) in map.keyframes.iter().zip(data) {
            self.keyframes.push(KeyframeRecord {
                timestamp: kf.timestamp,
                frame_id: None,
                camera: kf.image.camera,
                data,
                thumbnail: kf.thumbnail.clone(),
                frame: None,
                depth: None,
                world_from_keyframe: kf.world_from_keyframe,
                reference: None,
                parent: None,
                handover: None,
                mean_idepth: kf.depth.mean_idepth(),
                prior: None,
            });
            if let Some(dense) = &kf.dense {
                let dense = Arc::new(DenseKeyframe {
                    keyframe_id: kf.id,
                    timestamp: kf.timestamp,
                    camera: dense.camera,
                    world_from_keyframe: kf.world_from_keyframe,
                    idepth: dense.idepth.clone(),
                    variance: dense.variance.clone(),
                    // How the map densified it is not stored; only its depth is used again.
                    mode: DenseMode::NoModel,
                    align: None,
                    align_error: None,
                    consistent_pixels: 0,
                    timings: DenseTimings::default(),
                    stages: None,
                });
                self.dense_keyframes
                    .insert(kf.id, Stored::new(&self.spill, dense.clone()));
                if let Some(fusion) = &mut self.fusion {
                    fusion.send(FusionJob {
                        keyframe: dense,
                        rgb: kf.image.rgb.clone(),
                        pose: kf.world_from_keyframe,
                    })?;
                }
            }
        }
        self.stats.keyframes = self.keyframes.len();
        // New frames are numbered after the map's keyframe frames (`Frame::id`).
        self.next_frame_id = map.keyframes.len() as u64;
        self.lost = true;
        Ok(())
    }

    /// Keyframes that came with an extended map (0 for a new map).
    pub fn map_keyframes(&self) -> usize {
        self.map.as_ref().map_or(0, |m| m.keyframes)
    }

    /// The frame before any keyframe of an extended map was found: a new keyframe where the
    /// map's place recognition finds it, else lost.
    pub(super) fn start_in_map(&mut self, frame: Arc<Frame>) -> Result<Vec<Event>> {
        if let Some(events) = self.relocalise_in_map(&frame)? {
            return Ok(events);
        }
        self.stats.frames_lost += 1;
        Ok(vec![self.record_frame(
            &frame,
            0,
            SE3::identity(),
            TrackingState::Lost,
        )])
    }

    /// Place recognition over the extended map's keyframes: on success the frame becomes a new
    /// keyframe with the depth of the map keyframe it was found in; `None` without a map or
    /// when the frame was not found.
    pub(super) fn relocalise_in_map(&mut self, frame: &Arc<Frame>) -> Result<Option<Vec<Event>>> {
        let Some(map) = &mut self.map else {
            return Ok(None);
        };
        let Some((kf, result)) = map.localizer.relocalise(frame) else {
            return Ok(None);
        };
        self.relocalised_at(frame, kf, &result).map(Some)
    }
}
