//! The voxel pool of one session's fusion: the CPU reference arrays or the GPU buffers with
//! their kernels, behind one interface for the fuser (allocation, integration, marching
//! cubes, and the slot copies that spilled chunks leave and come back through).

use std::sync::Arc;

use crate::Result;
use crate::dense::DenseCompute;
use crate::gpu::GpuContext;

use super::block::{BlockIndex, BlockTable};
use super::config::FusionConfig;
use super::gpu_marching::GpuMarching;
use super::gpu_volume::GpuVoxels;
use super::integrate::{DepthView, IntegrateParams, integrate_cpu};
use super::marching::{MeshParams, extract_blocks};
use super::mesh::BlockMesh;
use super::voxels::{BYTES_PER_VOXEL, CpuVoxels};

/// The voxel pool and its kernels.
pub(super) enum Pool {
    Cpu(CpuVoxels),
    Gpu {
        voxels: Box<GpuVoxels>,
        marching: GpuMarching,
    },
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Pool::Cpu(_) => "Pool::Cpu",
            Pool::Gpu { .. } => "Pool::Gpu",
        })
    }
}

impl Pool {
    pub(super) fn open(config: &FusionConfig, ctx: Option<Arc<GpuContext>>) -> Self {
        if config.compute == DenseCompute::Cpu {
            return Pool::Cpu(CpuVoxels::default());
        }
        let ctx = match ctx.map_or_else(crate::gpu::shared_context, Ok) {
            Ok(ctx) => ctx,
            Err(e) => {
                tracing::warn!(error = %e, "no GPU for fusion: using the CPU reference");
                return Pool::Cpu(CpuVoxels::default());
            }
        };
        let opened = GpuVoxels::new(ctx.clone(), 1024)
            .and_then(|voxels| Ok((voxels, GpuMarching::new(ctx)?)));
        match opened {
            Ok((voxels, marching)) => Pool::Gpu {
                voxels: Box::new(voxels),
                marching,
            },
            Err(e) => {
                tracing::warn!(error = %e, "fusion kernels unavailable: using the CPU reference");
                Pool::Cpu(CpuVoxels::default())
            }
        }
    }

    pub(super) fn prepare(&mut self, table: &BlockTable, fresh: &[u32]) -> Result<()> {
        match self {
            Pool::Cpu(v) => {
                v.ensure_capacity(table.high_water());
                v.reset_slots(fresh);
                Ok(())
            }
            Pool::Gpu { voxels, .. } => {
                voxels.ensure_capacity(table.high_water())?;
                voxels.reset_slots(fresh)
            }
        }
    }

    pub(super) fn integrate(
        &mut self,
        blocks: &[(BlockIndex, u32)],
        view: &DepthView,
        p: &IntegrateParams,
        sign: f32,
    ) -> Result<()> {
        match self {
            Pool::Cpu(v) => {
                integrate_cpu(v, blocks, view, p, sign);
                Ok(())
            }
            Pool::Gpu { voxels, .. } => voxels.integrate(blocks, view, p, sign),
        }
    }

    pub(super) fn max_weights(&self, slots: &[u32]) -> Result<Vec<f32>> {
        match self {
            Pool::Cpu(v) => Ok(v.max_weights(slots)),
            Pool::Gpu { voxels, .. } => voxels.max_weights(slots),
        }
    }

    pub(super) fn extract(
        &self,
        table: &BlockTable,
        blocks: &[BlockIndex],
        p: &MeshParams,
    ) -> Result<Vec<BlockMesh>> {
        let jobs: Vec<_> = blocks.iter().filter_map(|b| table.mesh_job(*b)).collect();
        match self {
            Pool::Cpu(v) => Ok(extract_blocks(v, &jobs, p)),
            Pool::Gpu { voxels, marching } => marching.extract(voxels.buffers(), &jobs, p),
        }
    }

    /// The voxels of `slots` (block `k` in slot `k`), for a chunk leaving the pool.
    pub(super) fn read_slots(&self, slots: &[u32]) -> Result<CpuVoxels> {
        match self {
            Pool::Cpu(v) => Ok(v.read_slots(slots)),
            Pool::Gpu { voxels, .. } => voxels.read_slots(slots),
        }
    }

    /// Writes a chunk read back from the store into `slots` (allocated and prepared).
    pub(super) fn write_slots(&mut self, slots: &[u32], data: &CpuVoxels) -> Result<()> {
        match self {
            Pool::Cpu(v) => {
                v.write_slots(slots, data);
                Ok(())
            }
            Pool::Gpu { voxels, .. } => voxels.write_slots(slots, data),
        }
    }

    pub(super) fn bytes(&self) -> u64 {
        match self {
            Pool::Cpu(v) => (v.tsdf.len() * BYTES_PER_VOXEL) as u64,
            Pool::Gpu { voxels, .. } => voxels.bytes(),
        }
    }

    pub(super) fn name(&self) -> &'static str {
        match self {
            Pool::Cpu(_) => "cpu",
            Pool::Gpu { .. } => "gpu",
        }
    }
}
