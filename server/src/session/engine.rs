//! A session's [`Engine`]: the pipeline's one driver (`relfusion_slam::pipeline::engine`,
//! which `relfusion run` uses too) started from the session's request — a saved map fetched
//! from the store for `MapMode::Extend` or `MapMode::Localize` (issue 24) — and what the
//! service keeps of its results: files in the session's store, its memory in the session's
//! info.

use relfusion_proto::http::{MapMode, MapStart};
use relfusion_slam::dense::DepthPrior;
use relfusion_slam::geometry::PinholeCamera;
use relfusion_slam::map::read_map;
use relfusion_slam::pipeline::{Config, Engine, Start};

use crate::convert::points_ply;
use crate::storage::ObjectStore;

/// Most points of a session's `pointcloud.ply`: 4 M points (64 MB as PLY, about 200 keyframes
/// at 640×480 in full); longer sessions keep an equal share of every keyframe's points, so the
/// file and the memory to build it stay bounded however long the session runs (issue 37).
pub const POINTCLOUD_MAX_POINTS: usize = 4_000_000;

/// A mapping session's trajectory and keyframes (TUM text) and point cloud (PLY).
pub type ResultFiles = (String, String, Vec<u8>);

/// The session's engine: a pipeline, a pipeline extending the saved map `map` (its folder in
/// `store`), or a localiser over it; the map must serve `camera`.
pub fn start(
    config: &Config,
    camera: &PinholeCamera,
    prior: Option<Box<dyn DepthPrior>>,
    gpu: Option<std::sync::Arc<relfusion_slam::gpu::GpuContext>>,
    map: Option<&MapStart>,
    store: &dyn ObjectStore,
) -> Result<Engine, String> {
    let Some(start) = map else {
        return Engine::start(config, camera, prior, gpu, Start::New)
            .map_err(|e| format!("starting the pipeline: {e}"));
    };
    let dir = crate::folders::fetch(store, &crate::maps::map_prefix(&start.id))
        .map_err(|e| format!("fetching map {}: {e}", start.id))?;
    let map =
        read_map(dir.path(), Some(camera)).map_err(|e| format!("loading map {}: {e}", start.id))?;
    let (from, doing) = match start.mode {
        MapMode::Extend => (Start::Extend(&map), "extending"),
        MapMode::Localize => (Start::Localize(&map), "localising in"),
    };
    Engine::start(config, camera, prior, gpu, from)
        .map_err(|e| format!("{doing} map {}: {e}", start.id))
}

/// Where a mapping engine's keyframes and fusion data live, for the session's info.
pub fn memory(engine: &Engine) -> Option<relfusion_proto::http::SessionMemory> {
    let pipeline = engine.pipeline()?;
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
        fusion_keyframe_blocks: fusion.keyframe_blocks as u64,
        fusion_keyframe_block_bytes: fusion.keyframe_block_bytes as u64,
        // The session's mesh copy: filled in by the worker, which holds the session.
        mesh_blocks: 0,
        mesh_blocks_spilled: 0,
        far_edges: m.backend.map_or(0, |b| b.far_edges as u64),
        searches_deferred: m.backend.map_or(0, |b| b.searches_deferred as u64),
        searches_given_up: m.backend.map_or(0, |b| b.searches_given_up as u64),
        optimizations_full: m.backend.map_or(0, |b| b.optimizations_full as u64),
        optimizations_bounded: m.backend.map_or(0, |b| b.optimizations_bounded as u64),
        backend_commands_waiting: m.backend.map_or(0, |b| b.commands_waiting as u64),
        keyframes_reactivated: pipeline.stats().keyframes_reactivated as u64,
    })
}

/// The final trajectory, keyframes and semi-dense cloud (at most [`POINTCLOUD_MAX_POINTS`]) as
/// result files; `None` for a localiser (whose trajectory is the poses it reported).
pub fn result_files(engine: &Engine) -> Result<Option<ResultFiles>, String> {
    let Some((trajectory, keyframes)) = engine
        .trajectories_tum()
        .map_err(|e| format!("the trajectory: {e}"))?
    else {
        return Ok(None);
    };
    let points = match engine.semidense_snapshot() {
        Some(snapshot) => snapshot
            .points(POINTCLOUD_MAX_POINTS)
            .map_err(|e| format!("the point cloud: {e}"))?,
        None => Vec::new(),
    };
    Ok(Some((trajectory, keyframes, points_ply(&points))))
}

/// Writes the session's map under `key` of `store` (after [`Engine::finish`]); returns its
/// bytes. A localiser, or a pipeline without keyframes, made no map.
pub fn write_map(engine: &Engine, store: &dyn ObjectStore, key: &str) -> Result<u64, String> {
    let Some(pipeline) = engine.pipeline() else {
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
