//! `relfusion bench fusion --run OUT`: TSDF fusion of the keyframes a `relfusion run` saved
//! (`OUT/keyframes/`, at their optimised poses), once on the GPU kernels and once on the CPU
//! references: integration time per keyframe, meshing time per update (changed blocks only),
//! re-integration time per moved keyframe, and memory per million voxels. Prints one JSON
//! object.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::dense::DenseCompute;
use relfusion_slam::dense::store::DenseStore;
use relfusion_slam::fusion::fuser::Fuser;
use relfusion_slam::fusion::input::{FusionInput, store_inputs};
use relfusion_slam::fusion::{BLOCK_VOXELS, FusionConfig};
use relfusion_slam::geometry::Sim3;
use relfusion_slam::pipeline::Config;
use serde_json::json;

use super::gpu_info::adapter_json;
use super::timing::{median, ms};

#[derive(Debug, clap::Args)]
pub struct FusionArgs {
    /// Output folder of `relfusion run` (reads `keyframes/`).
    #[arg(long)]
    pub run: PathBuf,
    /// Pipeline config whose `[fusion]` section is used (defaults without one).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Skip the CPU reference (it is slow on large volumes).
    #[arg(long)]
    pub gpu_only: bool,
}

/// Fuses every input, meshing after each (as the pipeline does), then moves every keyframe by
/// two voxels and re-integrates. Returns the figures of one compute kind.
fn run_kind(
    config: &FusionConfig,
    inputs: &[(FusionInput, Sim3)],
    compute: DenseCompute,
) -> anyhow::Result<serde_json::Value> {
    let config = FusionConfig {
        compute,
        ..config.clone()
    };
    let mut fuser = Fuser::new(config.clone(), None)?;
    let (mut integrate, mut mesh, mut changed) = (Vec::new(), Vec::new(), Vec::new());
    for (input, pose) in inputs {
        let t = Instant::now();
        fuser.add_keyframe(input.clone(), *pose)?;
        integrate.push(ms(t));
        let t = Instant::now();
        let delta = fuser.take_delta()?;
        mesh.push(ms(t));
        changed.push(delta.map_or(0, |d| d.changed.len() + d.removed.len()) as f64);
    }
    let stats = fuser.stats();
    let voxel = stats.voxel_size;
    let shift = Sim3::new(
        relfusion_slam::geometry::SO3::identity(),
        nalgebra::Vector3::new(2.0 * voxel, 0.0, 0.0),
        1.0,
    );
    let moved: Vec<_> = fuser
        .fused_poses()
        .into_iter()
        .map(|(id, pose)| (id, shift * pose))
        .collect();
    let t = Instant::now();
    let n_moved = fuser.update_poses(&moved)?;
    let reintegrate_ms = ms(t) / n_moved.max(1) as f64;
    let t = Instant::now();
    fuser.take_delta()?;
    let remesh_ms = ms(t);
    let full = fuser.mesh()?;
    let voxels = stats.blocks as f64 * BLOCK_VOXELS as f64;
    Ok(json!({
        "compute": stats.compute,
        "keyframes": inputs.len(),
        "median_integrate_ms_per_keyframe": median(integrate.clone()),
        "mean_integrate_ms_per_keyframe": integrate.iter().sum::<f64>() / integrate.len() as f64,
        "median_mesh_ms_per_update": median(mesh.clone()),
        "median_blocks_per_update": median(changed),
        "reintegrate_ms_per_keyframe": reintegrate_ms,
        "remesh_after_move_ms": remesh_ms,
        "blocks": stats.blocks,
        "voxels": voxels,
        "pool_bytes": stats.pool_bytes,
        "pool_mib_per_million_allocated_voxels": stats.pool_bytes as f64 / voxels * 1e6 / 1048576.0,
        "voxel_size": voxel,
        "triangles": full.triangle_count(),
        "vertices": full.vertex_count(),
    }))
}

pub fn fusion(args: &FusionArgs) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    }
    .fusion;
    let store = DenseStore::open(&args.run.join("keyframes"))
        .with_context(|| format!("opening {}/keyframes", args.run.display()))?;
    let inputs = store_inputs(&store, &config)?;
    anyhow::ensure!(!inputs.is_empty(), "no keyframes in {}", args.run.display());
    let ctx = relfusion_slam::gpu::shared_context()?;
    // Warm-up: pipeline compilation and the first buffers are not per-keyframe costs.
    run_kind(&config, &inputs[..1], DenseCompute::Gpu)?;
    let gpu = run_kind(&config, &inputs, DenseCompute::Gpu)?;
    let cpu = if args.gpu_only {
        serde_json::Value::Null
    } else {
        run_kind(&config, &inputs, DenseCompute::Cpu)?
    };
    println!(
        "{}",
        serde_json::to_string_pretty(&json!({
            "bench": "fusion",
            "build": if cfg!(debug_assertions) { "debug" } else { "release" },
            "adapter": adapter_json(&ctx),
            "width": store.width,
            "height": store.height,
            "gpu": gpu,
            "cpu_reference": cpu,
        }))?
    );
    Ok(())
}
