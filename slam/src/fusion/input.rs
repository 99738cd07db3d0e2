//! What the fusion integrates for one keyframe: depth in the keyframe's own units, a weight and
//! a colour per pixel, at the dense working resolution. Built from a densified keyframe (the
//! pipeline) or from a metric ground-truth depth map (the upper-bound mesh of `eval mesh`).

use crate::dense::DenseKeyframe;
use crate::dense::store::DenseStore;
use crate::geometry::{PinholeCamera, Sim3};
use crate::graph::KeyframeId;
use crate::image::ImageF32;
use crate::{Error, Result};

use super::block::pack_rgb;
use super::config::FusionConfig;

/// One depth map ready to integrate.
#[derive(Clone, Debug, PartialEq)]
pub struct FusionInput {
    pub keyframe_id: KeyframeId,
    pub timestamp: f64,
    /// Undistorted camera of the maps below.
    pub camera: PinholeCamera,
    /// Depth in the keyframe's units (0 = not integrated).
    pub depth: Vec<f32>,
    /// Integration weight per pixel (0 = not integrated).
    pub weight: Vec<f32>,
    /// Packed colour per pixel (`block::pack_rgb`).
    pub color: Vec<u32>,
    /// Median valid depth (keyframe units): sets the automatic voxel size and the pose-change
    /// test.
    pub median_depth: f32,
}

impl FusionInput {
    /// Bytes this input holds (the re-integration memory budget counts them).
    pub fn bytes(&self) -> usize {
        self.depth.len() * 4 + self.weight.len() * 4 + self.color.len() * 4
    }

    /// A densified keyframe (see [`FusionInput::from_idepth`]). `colors` (row-major at the
    /// dense resolution) default to the keyframe's grey intensity when the frame had no colour.
    pub fn from_dense(
        kf: &DenseKeyframe,
        colors: Option<&[[u8; 3]]>,
        config: &FusionConfig,
    ) -> Result<Self> {
        let grey_colors;
        let colors = match colors {
            Some(c) => Some(c),
            None => {
                grey_colors = kf.stages.as_ref().map(|s| grey(&s.intensity));
                grey_colors.as_deref()
            }
        };
        Self::from_idepth(
            kf.keyframe_id,
            kf.timestamp,
            kf.camera,
            &kf.idepth,
            &kf.variance,
            colors,
            config,
        )
    }

    /// Dense inverse depth ρ and its variance σ_ρ²: depth = 1/ρ, weight
    /// `σ₀² / (σ₀² + (σ_ρ/ρ)²)` (see [`FusionConfig::weight_sigma`]); pixels with a relative σ
    /// above `max_relative_sigma` or beyond `max_depth_factor` median depths are left out.
    pub fn from_idepth(
        keyframe_id: KeyframeId,
        timestamp: f64,
        camera: PinholeCamera,
        idepth: &ImageF32,
        variance: &ImageF32,
        colors: Option<&[[u8; 3]]>,
        config: &FusionConfig,
    ) -> Result<Self> {
        let (w, h) = (idepth.width, idepth.height);
        let n = w * h;
        if variance.data.len() != n
            || (camera.width as usize, camera.height as usize) != (w, h)
            || colors.is_some_and(|c| c.len() != n)
        {
            return Err(Error::Shape(format!(
                "fusion input of keyframe {keyframe_id}: maps and camera are not all {w}×{h}"
            )));
        }
        let sigma0 = config.weight_sigma * config.weight_sigma;
        let mut depth = vec![0f32; n];
        let mut weight = vec![0f32; n];
        for i in 0..n {
            let rho = idepth.data[i];
            let var = variance.data[i];
            if !(rho.is_finite() && rho > 0.0 && var.is_finite() && var >= 0.0) {
                continue;
            }
            let rel = var.sqrt() / rho;
            if rel > config.max_relative_sigma {
                continue;
            }
            depth[i] = 1.0 / rho;
            weight[i] = sigma0 / (sigma0 + rel * rel);
        }
        Self::finish(
            keyframe_id,
            timestamp,
            camera,
            depth,
            weight,
            pack(colors, n),
            config,
        )
    }

    /// A metric depth map (ground truth), weight 1 wherever it has a value.
    pub fn from_depth(
        keyframe_id: KeyframeId,
        timestamp: f64,
        camera: PinholeCamera,
        depth: &ImageF32,
        colors: Option<&[[u8; 3]]>,
        config: &FusionConfig,
    ) -> Result<Self> {
        let n = depth.width * depth.height;
        if (depth.width, depth.height) != (camera.width as usize, camera.height as usize)
            || colors.is_some_and(|c| c.len() != n)
        {
            return Err(Error::Shape(
                "fusion input: depth, camera and colours differ in size".into(),
            ));
        }
        let d: Vec<f32> = depth
            .data
            .iter()
            .map(|&v| if v.is_finite() && v > 0.0 { v } else { 0.0 })
            .collect();
        let weight = d.iter().map(|&v| if v > 0.0 { 1.0 } else { 0.0 }).collect();
        Self::finish(
            keyframe_id,
            timestamp,
            camera,
            d,
            weight,
            pack(colors, n),
            config,
        )
    }

    /// Median depth, and the far cut of `max_depth_factor` median depths.
    fn finish(
        keyframe_id: KeyframeId,
        timestamp: f64,
        camera: PinholeCamera,
        mut depth: Vec<f32>,
        mut weight: Vec<f32>,
        color: Vec<u32>,
        config: &FusionConfig,
    ) -> Result<Self> {
        let mut valid: Vec<f32> = depth.iter().copied().filter(|&d| d > 0.0).collect();
        if valid.is_empty() {
            return Err(Error::NothingToFuse(keyframe_id));
        }
        let mid = valid.len() / 2;
        let median_depth = *valid.select_nth_unstable_by(mid, f32::total_cmp).1;
        let far = median_depth * config.max_depth_factor as f32;
        for (d, w) in depth.iter_mut().zip(weight.iter_mut()) {
            if *d > far || *w <= 0.0 {
                *d = 0.0;
                *w = 0.0;
            }
        }
        Ok(Self {
            keyframe_id,
            timestamp,
            camera,
            depth,
            weight,
            color,
            median_depth,
        })
    }
}

/// The keyframes a run stored (`OUT/keyframes/`, `dense::store`) as fusion inputs at their
/// stored (optimised) poses, grey-coloured from their intensity (the store keeps no colour).
pub fn store_inputs(store: &DenseStore, config: &FusionConfig) -> Result<Vec<(FusionInput, Sim3)>> {
    let camera = store.pinhole()?;
    let mut inputs = Vec::new();
    for kf in &store.keyframes {
        let map = |name: &str| {
            store.read_map(kf, name)?.ok_or_else(|| {
                Error::Dataset(format!("stored keyframe {} has no {name} map", kf.stem))
            })
        };
        let (idepth, variance) = (map("idepth")?, map("variance")?);
        let colors = store.read_map(kf, "intensity")?.map(|i| grey(&i));
        let input = match FusionInput::from_idepth(
            kf.id,
            kf.timestamp,
            camera,
            &idepth,
            &variance,
            colors.as_deref(),
            config,
        ) {
            Err(Error::NothingToFuse(id)) => {
                tracing::warn!(keyframe = id, "nothing to fuse: keyframe left out");
                continue;
            }
            other => other?,
        };
        inputs.push((input, kf.world_from_keyframe));
    }
    Ok(inputs)
}

/// Grey RGB from an intensity image (0..255).
pub fn grey(intensity: &ImageF32) -> Vec<[u8; 3]> {
    intensity
        .data
        .iter()
        .map(|&v| {
            let g = v.clamp(0.0, 255.0).round() as u8;
            [g, g, g]
        })
        .collect()
}

/// Packed colours, mid-grey without any.
fn pack(colors: Option<&[[u8; 3]]>, n: usize) -> Vec<u32> {
    match colors {
        Some(c) => c.iter().map(|&rgb| pack_rgb(rgb)).collect(),
        None => vec![pack_rgb([180, 180, 180]); n],
    }
}
