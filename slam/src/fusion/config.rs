//! Parameters of the TSDF fusion (`[fusion]` in the pipeline config).
//!
//! The paper fuses its dense keyframes "into a TSDF" (§III-F, following DeepFusion/CNN-SLAM)
//! without giving a voxel size: a monocular map has no metres, so sizes here are relative to
//! the scene's median depth by default (measured on the first fused keyframe) and can be fixed
//! in map units instead.

use serde::{Deserialize, Serialize};

use crate::dense::DenseCompute;
use crate::{Error, Result};

/// TSDF volume, integration weights, re-integration and meshing. Its user settings are listed
/// in [`crate::pipeline::user_config`]; the rest is expert level.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FusionConfig {
    /// Fuse densified keyframes into a TSDF and mesh it. Default true (needs the dense layer).
    pub enabled: bool,
    /// Where integration and marching cubes run (`gpu`: WGSL kernels, lavapipe without a GPU;
    /// `cpu`: the reference implementations).
    pub compute: DenseCompute,
    /// Voxel edge in map units; `None` (default) = the first fused keyframe's median depth
    /// divided by `voxels_per_median_depth`.
    pub voxel_size: Option<f64>,
    /// Voxels across the median depth when `voxel_size` is automatic. Default 64 (about 3 cm
    /// at 2 m): the monocular dense depth and poses are off by several centimetres, and finer
    /// voxels resolve mostly noise (docs/tuning.md, "Fusion").
    pub voxels_per_median_depth: f64,
    /// Truncation distance in voxels. Default 4.
    pub truncation_voxels: f64,
    /// Voxel weights are capped here so that the volume keeps adapting. Default 128;
    /// de-integration is exact while a voxel's weight stays below the cap (each keyframe adds
    /// at most 1 per voxel).
    pub max_weight: f32,
    /// Relative depth standard deviation σ₀ of the integration weight
    /// `w = σ₀² / (σ₀² + (σ_ρ/ρ)²)` (σ_ρ² the dense variance, ρ the inverse depth: δd/d = δρ/ρ,
    /// so the weight does not depend on the keyframe's scale). Default 0.05.
    pub weight_sigma: f32,
    /// Pixels whose relative depth standard deviation exceeds this are not integrated.
    /// Default 0.5.
    pub max_relative_sigma: f32,
    /// Pixels farther than this many median depths are not integrated (sky, far walls seen at
    /// grazing angles). Default 4.
    pub max_depth_factor: f64,
    /// Pixels whose surface normal (from their neighbours' depth) is more than
    /// `acos(min_view_cosine)` from the viewing ray are not integrated: a smoothed dense map
    /// ramps across occlusion edges, and those ramp pixels span large skins in 3-D between
    /// foreground and background. 0 turns the test off. Default 0.15 (81°).
    pub min_view_cosine: f32,
    /// A cell is meshed only where all eight corners have more than this weight. Default 0.5:
    /// one confident observation (relative σ below `weight_sigma`) or two uncertain ones, so
    /// surfaces that a single uncertain keyframe put in free space are not meshed
    /// (docs/tuning.md, "Fusion").
    pub min_mesh_weight: f32,
    /// Most voxel blocks the pool may hold (8³ voxels, 12 bytes each: 6 KiB per block).
    /// Default 65536 (33.5 M voxels, 384 MiB).
    pub max_blocks: u32,
    /// Blocks the pool keeps in memory when the session has a store (issue 37): past it, the
    /// chunks of 4×4×4 blocks used least recently go to the store with their meshes and come
    /// back when something reads them, bit-identical. A soft limit: the chunks of the newest
    /// keyframe always stay. Default 16384 (96 MiB of voxels), 2.4-9 times what the shared
    /// 10-s room sequences fill (1755-6852 blocks; docs/tuning.md "Bounded fusion"), so a
    /// session in one room rarely spills and one that explores keeps its volume bounded.
    pub resident_blocks: u32,
    /// Memory for the keyframe depths kept for re-integration (depth, weight, colour at the
    /// dense working resolution: about 0.9 MiB per keyframe at 320×240). Default 512 MiB.
    /// Past it the oldest keyframes' inputs are dropped and they stay fused where they are.
    pub keyframe_memory_mb: f64,
    /// Re-integrate a keyframe when the pose graph moved it by more than this many voxels
    /// (camera-centre shift plus rotation times the keyframe's median depth). Default 0.5.
    pub reintegrate_voxels: f64,
    /// Keyframes waiting for fusion on its thread before new ones are dropped (counted, never
    /// blocking tracking). Default 8.
    pub queue: usize,
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            compute: DenseCompute::Gpu,
            voxel_size: None,
            voxels_per_median_depth: 64.0,
            truncation_voxels: 4.0,
            max_weight: 128.0,
            weight_sigma: 0.05,
            max_relative_sigma: 0.5,
            max_depth_factor: 4.0,
            min_view_cosine: 0.15,
            min_mesh_weight: 0.5,
            max_blocks: 65536,
            resident_blocks: 16384,
            keyframe_memory_mb: 512.0,
            reintegrate_voxels: 0.5,
            queue: 8,
        }
    }
}

impl FusionConfig {
    pub fn validate(&self) -> Result<()> {
        let positive = |v: f64, name: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(Error::Config(format!(
                    "fusion.{name} must be > 0 (got {v})"
                )))
            }
        };
        if let Some(v) = self.voxel_size {
            positive(v, "voxel_size")?;
        }
        positive(self.voxels_per_median_depth, "voxels_per_median_depth")?;
        positive(self.truncation_voxels, "truncation_voxels")?;
        positive(self.max_weight as f64, "max_weight")?;
        positive(self.weight_sigma as f64, "weight_sigma")?;
        positive(self.max_relative_sigma as f64, "max_relative_sigma")?;
        positive(self.max_depth_factor, "max_depth_factor")?;
        positive(self.keyframe_memory_mb, "keyframe_memory_mb")?;
        positive(self.reintegrate_voxels, "reintegrate_voxels")?;
        if !(self.min_view_cosine.is_finite() && (0.0..1.0).contains(&self.min_view_cosine)) {
            return Err(Error::Config(
                "fusion.min_view_cosine must be in [0, 1)".into(),
            ));
        }
        if !(self.min_mesh_weight.is_finite() && self.min_mesh_weight >= 0.0) {
            return Err(Error::Config("fusion.min_mesh_weight must be ≥ 0".into()));
        }
        if self.max_blocks == 0 || self.queue == 0 || self.resident_blocks == 0 {
            return Err(Error::Config(
                "fusion.max_blocks, fusion.resident_blocks and fusion.queue must be ≥ 1".into(),
            ));
        }
        Ok(())
    }
}
