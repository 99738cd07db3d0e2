//! What a session's worker drives: the SLAM pipeline (a map made from nothing, or extending a
//! saved map: `MapMode::Extend`) or a localiser in a saved map (`MapMode::Localize`, issue 24).
//! One interface for the worker: frames in, pipeline events out, result files at the end.

use relfusion_proto::http::{MapMode, MapStart};
use relfusion_slam::dense::DepthPrior;
use relfusion_slam::geometry::{PinholeCamera, Sim3};
use relfusion_slam::map::{LocalizationState, Localizer, read_map};
use relfusion_slam::pipeline::{
    Config, Event, FrameInput, KeyframePose, Pipeline, PoseEvent, Stats, TrackingState,
};

use crate::convert::points_ply;
use crate::storage::ObjectStore;

/// Most points of a session's `pointcloud.ply`: 4 M points (64 MB as PLY, about 200 keyframes
/// at 640×480 in full); longer sessions keep an equal share of every keyframe's points, so the
/// file and the memory to build it stay bounded however long the session runs (issue 37).
pub const POINTCLOUD_MAX_POINTS: usize = 4_000_000;

/// A mapping session's trajectory and keyframes (TUM text) and point cloud (PLY; `None` when
/// not rebuilt).
pub type ResultFiles = (String, String, Option<Vec<u8>>);

/// The optimised keyframe poses and the events finishing produced.
type Finished = (Vec<KeyframePose>, Vec<Event>);

/// The session's engine.
pub(crate) enum Engine {
    /// Mapping: tracking, mapping, pose graph, dense layer, fusion (from nothing, or on from a
    /// saved map).
    Map(Box<Pipeline>),
    /// Localising every frame in a saved map, which stays as it is.
    Localize {
        localizer: Box<Localizer>,
        stats: Stats,
    },
}

impl Engine {
    /// The session's engine: a pipeline, a pipeline extending the saved map `map` (its folder
    /// in `store`), or a localiser over it; the map must serve `camera`.
    pub fn start(
        config: &Config,
        camera: &PinholeCamera,
        prior: Option<Box<dyn DepthPrior>>,
        gpu: Option<std::sync::Arc<relfusion_slam::gpu::GpuContext>>,
        map: Option<&MapStart>,
        store: &dyn ObjectStore,
    ) -> Result<Self, String> {
        let Some(start) = map else {
            return Pipeline::with_gpu(config.clone(), *camera, prior, gpu)
                .map(|p| Engine::Map(Box::new(p)))
                .map_err(|e| format!("starting the pipeline: {e}"));
        };
        let dir = crate::folders::fetch(store, &crate::maps::map_prefix(&start.id))
            .map_err(|e| format!("fetching map {}: {e}", start.id))?;
        let map = read_map(dir.path(), Some(camera))
            .map_err(|e| format!("loading map {}: {e}", start.id))?;
        if start.mode == MapMode::Extend {
            return Pipeline::extending(config.clone(), *camera, prior, gpu, &map)
                .map(|p| Engine::Map(Box::new(p)))
                .map_err(|e| format!("extending map {}: {e}", start.id));
        }
        let localizer = Localizer::new(&map, config.tracking.clone(), config.localize.clone())
            .map_err(|e| format!("map {}: {e}", start.id))?;
        Ok(Engine::Localize {
            localizer: Box::new(localizer),
            stats: Stats {
                dense_mode: "off",
                scale: "arbitrary",
                ..Stats::default()
            },
        })
    }

    /// What a mapping engine's keyframes hold in memory and in the store.
    pub fn keyframe_memory(&self) -> Option<relfusion_slam::pipeline::KeyframeMemory> {
        match self {
            Engine::Map(pipeline) => Some(pipeline.keyframe_memory()),
            Engine::Localize { .. } => None,
        }
    }

    /// Where a mapping engine's keyframes and fusion data live, for the session's info.
    pub fn memory(&self) -> Option<relfusion_proto::http::SessionMemory> {
        let Engine::Map(pipeline) = self else {
            return None;
        };
        let m = pipeline.keyframe_memory();
        let fusion = pipeline.fusion_stats().unwrap_or_default();
        Some(relfusion_proto::http::SessionMemory {
            keyframes_resident: m.resident as u64,
            keyframes_spilled: m.spilled as u64,
            keyframe_bytes: (m.compact_bytes + m.resident_bytes + m.dense_bytes) as u64,
            spilled_bytes: m.spill.spilled_bytes,
            fusion_blocks: fusion.blocks as u64,
            fusion_blocks_spilled: fusion.blocks_spilled as u64,
            fusion_chunk_loads: fusion.chunk_loads as u64,
            fusion_inputs_spilled: fusion.inputs_spilled as u64,
            // The session's mesh copy: filled in by the worker, which holds the session.
            mesh_blocks: 0,
            mesh_blocks_spilled: 0,
            far_edges: m.backend.map_or(0, |b| b.far_edges as u64),
            searches_deferred: m.backend.map_or(0, |b| b.searches_deferred as u64),
            searches_given_up: m.backend.map_or(0, |b| b.searches_given_up as u64),
            keyframes_reactivated: pipeline.stats().keyframes_reactivated as u64,
        })
    }

    /// Why the session's store refused spilled keyframes, once it has.
    pub fn spill_failure(&self) -> Option<String> {
        match self {
            Engine::Map(pipeline) => pipeline.spill().failure().map(str::to_owned),
            Engine::Localize { .. } => None,
        }
    }

    /// The session's spilling (a mapping engine's; `None` for a localiser).
    pub fn spill(&self) -> Option<relfusion_slam::spill::Spill> {
        match self {
            Engine::Map(pipeline) => Some(pipeline.spill().clone()),
            Engine::Localize { .. } => None,
        }
    }

    /// Old keyframes spill to `store` (a mapping engine; a localiser's map stays as loaded).
    pub fn attach_spill(
        &self,
        store: std::sync::Arc<dyn relfusion_slam::spill::SpillStore>,
    ) -> Result<(), String> {
        match self {
            Engine::Map(pipeline) => pipeline
                .spill()
                .attach(store)
                .map_err(|e| format!("spilling: {e}")),
            Engine::Localize { .. } => Ok(()),
        }
    }

    /// One frame; what happened, as pipeline events (a localised frame is a pose: `tracking`
    /// or `relocalized` in the map's frame; a frame not in the map is `lost`, at the identity).
    pub fn push(&mut self, input: FrameInput) -> relfusion_slam::Result<Vec<Event>> {
        match self {
            Engine::Map(pipeline) => pipeline.push(input),
            Engine::Localize { localizer, stats } => {
                let t0 = std::time::Instant::now();
                let result = localizer.localize(input.timestamp, input.rgb)?;
                stats.frames += 1;
                stats.tracking_s += t0.elapsed().as_secs_f64();
                let state = match result.state {
                    LocalizationState::Tracked => TrackingState::Tracking,
                    LocalizationState::Relocalized => TrackingState::Relocalized,
                    LocalizationState::NotLocalized => TrackingState::Lost,
                };
                if state == TrackingState::Lost {
                    stats.frames_lost += 1;
                }
                Ok(vec![Event::Pose(PoseEvent {
                    frame_id: input.frame_id.unwrap_or(stats.frames as u64 - 1),
                    timestamp: result.timestamp,
                    world_from_camera: result.world_from_camera.unwrap_or_else(Sim3::identity),
                    state,
                    keyframe_id: result.keyframe.unwrap_or(0),
                    is_keyframe: false,
                })])
            }
        }
    }

    /// What the pipeline's background threads finished since the last frame (nothing for a
    /// localiser, which has none).
    pub fn poll(&mut self) -> relfusion_slam::Result<Vec<Event>> {
        match self {
            Engine::Map(pipeline) => pipeline.poll(),
            Engine::Localize { .. } => Ok(Vec::new()),
        }
    }

    /// The keyframes of the map an extending pipeline started from (timestamp and pose, by
    /// id); none otherwise.
    pub fn map_keyframes(&self) -> Vec<(f64, Sim3)> {
        match self {
            Engine::Map(pipeline) => {
                let mut poses = pipeline.keyframe_trajectory();
                poses.truncate(pipeline.map_keyframes());
                poses
            }
            Engine::Localize { .. } => Vec::new(),
        }
    }

    pub fn stats(&self) -> &Stats {
        match self {
            Engine::Map(pipeline) => pipeline.stats(),
            Engine::Localize { stats, .. } => stats,
        }
    }

    /// The pipeline's final optimisation and what it produced after the frames; nothing to do
    /// for a localiser.
    pub fn finish(&mut self) -> relfusion_slam::Result<Finished> {
        match self {
            Engine::Map(pipeline) => {
                let poses = pipeline.finish()?;
                Ok((pipeline.with_frames(poses), pipeline.take_events()))
            }
            Engine::Localize { .. } => Ok((Vec::new(), Vec::new())),
        }
    }

    /// The trajectory, keyframes and semi-dense cloud as result files; `None` for a localiser
    /// (whose trajectory is the poses it reported).
    /// The point cloud (`pointcloud`: else `None`) holds at most [`POINTCLOUD_MAX_POINTS`].
    pub fn result_files(&self, pointcloud: bool) -> Result<Option<ResultFiles>, String> {
        match self {
            Engine::Map(pipeline) => Ok(Some((
                crate::convert::tum_text(
                    &pipeline
                        .trajectory()
                        .map_err(|e| format!("the trajectory: {e}"))?,
                ),
                crate::convert::tum_text(&pipeline.keyframe_trajectory()),
                if pointcloud {
                    Some(points_ply(
                        &pipeline
                            .semidense_points_at_most(POINTCLOUD_MAX_POINTS)
                            .map_err(|e| format!("the point cloud: {e}"))?,
                    ))
                } else {
                    None
                },
            ))),
            Engine::Localize { .. } => Ok(None),
        }
    }

    /// Writes the session's map under `key` of `store` (after [`Engine::finish`]); returns its
    /// bytes. A localiser, or a pipeline without keyframes, made no map.
    pub fn write_map(&self, store: &dyn ObjectStore, key: &str) -> Result<u64, String> {
        let Engine::Map(pipeline) = self else {
            return Ok(0);
        };
        if pipeline.keyframe_poses().is_empty() {
            return Ok(0);
        }
        // Keyframe by keyframe: a long session's spilled keyframes are read back one at a time.
        crate::folders::store(store, key, |dir| {
            pipeline.write_map(dir).map_err(|e| e.to_string())
        })
    }
}
