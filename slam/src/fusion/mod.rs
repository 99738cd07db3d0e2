//! TSDF fusion of the dense keyframes and meshing (paper §III-F; issue 5).
//!
//! - [`config`]: `[fusion]` parameters.
//! - [`block`]: sparse voxel blocks, the block table, meshing jobs.
//! - [`voxels`]: the voxel pool layout (CPU reference pool, GPU buffers).
//! - [`integrate`]: integration / de-integration of one depth map (CPU reference), the blocks
//!   a depth map touches.
//! - [`gpu_volume`]: the GPU pool and the integration kernel runner.
//! - [`mc_table`]: the marching-cubes case table, generated from first principles.
//! - [`marching`]: marching cubes over blocks (CPU reference); [`gpu_marching`] the kernel.
//! - [`mesh`]: block meshes and the welded whole-scene mesh; [`weld`] welds them a block at a
//!   time, so a long session's mesh is written without holding it all.
//! - [`input`]: what is integrated per keyframe (depth, weight from the dense variance, colour).
//! - `pool`: the voxel pool the fuser uses, CPU reference or GPU buffers and kernels.
//! - [`chunks`]: chunks of blocks spilled to the session's store and read back (bounded
//!   memory for long sessions).
//! - [`fuser`]: one session's fusion: integration, re-integration on pose-graph moves, mesh
//!   deltas; [`worker`] runs it on its own thread.

pub mod block;
pub mod block_list;
pub mod chunks;
pub mod config;
pub mod fuser;
pub mod gpu_marching;
pub mod gpu_volume;
pub mod input;
pub mod integrate;
pub mod marching;
pub mod mc_table;
pub mod mesh;
mod pool;
pub mod voxels;
pub mod weld;
pub mod worker;

pub use block::{BLOCK_SIDE, BLOCK_VOXELS, BlockIndex, BlockTable, MeshJob};
pub use config::FusionConfig;
pub use fuser::{Fuser, FusionStats, MeshDelta};
pub use mesh::{BlockMesh, EdgeKey, Mesh};
pub use voxels::{CpuVoxels, VoxelBuffers};
