//! `relfusion gpu-info`: which wgpu adapter the pipeline would run on, and its limits, as JSON.
//!
//! Useful first step on a new machine: a CPU adapter (`"device_type": "Cpu"`, llvmpipe) means
//! the kernels run on Mesa lavapipe; no adapter at all means mesa-vulkan-drivers is missing.

use relfusion_slam::gpu::{AdapterChoice, GpuConfig, GpuContext};
use serde_json::json;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Adapter kind: auto (real GPU if any, else CPU), gpu or cpu. With auto (the default) the
    /// RELFUSION_GPU environment variable may force gpu or cpu.
    #[arg(long)]
    pub adapter: Option<AdapterChoice>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let ctx = open_context(args.adapter)?;
    println!("{}", serde_json::to_string_pretty(&adapter_json(&ctx))?);
    Ok(())
}

/// Opens the GPU context: an explicit `--adapter gpu|cpu` wins over `RELFUSION_GPU`, which
/// wins over `auto` (see `GpuConfig::effective_adapter`).
pub(crate) fn open_context(adapter: Option<AdapterChoice>) -> anyhow::Result<GpuContext> {
    let config = GpuConfig {
        adapter: adapter.unwrap_or_default(),
        ..GpuConfig::default()
    };
    Ok(GpuContext::new(&config)?)
}

/// Adapter identity and the limits that bound our kernels (buffer sizes, workgroup shapes).
pub(crate) fn adapter_json(ctx: &GpuContext) -> serde_json::Value {
    let info = ctx.adapter_info();
    let limits = ctx.limits();
    json!({
        "name": info.name,
        "backend": format!("{:?}", info.backend),
        "device_type": format!("{:?}", info.device_type),
        "driver": info.driver,
        "driver_info": info.driver_info,
        "vendor_id": info.vendor,
        "device_id": info.device,
        "timestamp_queries": ctx.supports_timestamps(),
        "limits": {
            "max_buffer_size": limits.max_buffer_size,
            "max_storage_buffer_binding_size": limits.max_storage_buffer_binding_size,
            "max_uniform_buffer_binding_size": limits.max_uniform_buffer_binding_size,
            "max_storage_buffers_per_shader_stage": limits.max_storage_buffers_per_shader_stage,
            "max_compute_workgroup_size_x": limits.max_compute_workgroup_size_x,
            "max_compute_workgroup_size_y": limits.max_compute_workgroup_size_y,
            "max_compute_workgroup_size_z": limits.max_compute_workgroup_size_z,
            "max_compute_invocations_per_workgroup": limits.max_compute_invocations_per_workgroup,
            "max_compute_workgroups_per_dimension": limits.max_compute_workgroups_per_dimension,
            "max_compute_workgroup_storage_size": limits.max_compute_workgroup_storage_size,
            "min_uniform_buffer_offset_alignment": limits.min_uniform_buffer_offset_alignment,
        },
    })
}
