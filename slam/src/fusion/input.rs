//! What the fusion integrates for one keyframe: depth in the keyframe's own units, a weight and
//! a colour per pixel, at the dense working resolution. Built from a densified keyframe (the
//! pipeline) or from a metric ground-truth depth map (the upper-bound mesh of `eval mesh`).

use nalgebra::{Vector2, Vector3};

use crate::dense::DenseKeyframe;
use crate::dense::store::DenseStore;
use crate::geometry::{PinholeCamera, Sim3};
use crate::graph::KeyframeId;
use crate::image::ImageF32;
use crate::spill::{Reader, Spillable, Writer};
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

/// Inputs past the re-integration budget spill to the session's store (issue 37) and are
/// read back, bit-identical, when their keyframe moves.
impl Spillable for FusionInput {
    fn encode(&self, out: &mut Writer) {
        out.u64(self.keyframe_id as u64);
        out.f64(self.timestamp);
        out.camera(&self.camera);
        out.f32s(&self.depth);
        out.f32s(&self.weight);
        out.u32s(&self.color);
        out.f64(f64::from(self.median_depth));
    }

    fn decode(input: &mut Reader<'_>) -> Result<Self> {
        let value = Self {
            keyframe_id: input.usize()?,
            timestamp: input.f64()?,
            camera: input.camera()?,
            depth: input.f32s()?,
            weight: input.f32s()?,
            color: input.u32s()?,
            median_depth: input.f64()? as f32,
        };
        let n = value.camera.width as usize * value.camera.height as usize;
        if [value.depth.len(), value.weight.len(), value.color.len()] != [n; 3] {
            return Err(Error::Spill(
                "a spilled fusion input has maps of the wrong size".into(),
            ));
        }
        Ok(value)
    }

    fn heap_bytes(&self) -> usize {
        self.bytes()
    }
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
        let grazing = grazing_pixels(&camera, &depth, config.min_view_cosine);
        for ((d, w), g) in depth.iter_mut().zip(weight.iter_mut()).zip(grazing) {
            if *d > far || *w <= 0.0 || g {
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

/// Pixels whose surface, as the depth map's own neighbours span it, is seen at a grazing angle:
/// `|cos|` between the viewing ray and the surface normal below `min_cosine`. A smoothed
/// densified map ramps across an occlusion edge instead of jumping; back-projected, the few
/// ramp pixels span a skin between foreground and background that is large in 3-D (it grows
/// with the depth gap, not with the pixel count), and no later keyframe carves it away because
/// it lies inside the truncation band of the surfaces it joins. The normal comes from central
/// differences where both neighbours are valid, one-sided otherwise; pixels without a valid
/// neighbour in x or in y are kept.
fn grazing_pixels(camera: &PinholeCamera, depth: &[f32], min_cosine: f32) -> Vec<bool> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = vec![false; depth.len()];
    if min_cosine <= 0.0 || depth.len() != w * h {
        return out;
    }
    // Each valid pixel back-projected once.
    let points: Vec<Option<Vector3<f64>>> = depth
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            let uv = Vector2::new((i % w) as f64, (i / w) as f64);
            (d > 0.0).then(|| camera.unproject(&uv, f64::from(d)))
        })
        .collect();
    // Difference of the valid neighbours along one axis (central, else one-sided).
    let span = |before: Option<usize>, i: usize, after: Option<usize>| {
        let (b, a) = (
            before.and_then(|j| points[j]),
            after.and_then(|j| points[j]),
        );
        match (b, a) {
            (Some(b), Some(a)) => Some(a - b),
            (None, Some(a)) => points[i].map(|p| a - p),
            (Some(b), None) => points[i].map(|p| p - b),
            (None, None) => None,
        }
    };
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let Some(p) = points[i] else { continue };
            let dx = span((x > 0).then(|| i - 1), i, (x + 1 < w).then(|| i + 1));
            let dy = span((y > 0).then(|| i - w), i, (y + 1 < h).then(|| i + w));
            let (Some(a), Some(b)) = (dx, dy) else {
                continue;
            };
            let n = a.cross(&b);
            out[i] = n.dot(&p).abs() < f64::from(min_cosine) * n.norm() * p.norm();
        }
    }
    out
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

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> PinholeCamera {
        PinholeCamera::new(100.0, 100.0, 31.5, 23.5, 64, 48).expect("camera")
    }

    /// Depth of the plane `n·X = 1` along each pixel's ray.
    fn plane_depth(camera: &PinholeCamera, n: [f64; 3]) -> Vec<f32> {
        let mut depth = Vec::new();
        for y in 0..camera.height {
            for x in 0..camera.width {
                let ray = [
                    (f64::from(x) - camera.cx) / camera.fx,
                    (f64::from(y) - camera.cy) / camera.fy,
                    1.0,
                ];
                let dot = n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2];
                depth.push((1.0 / dot) as f32);
            }
        }
        depth
    }

    #[test]
    fn grazing_test_keeps_planes_seen_head_on_and_at_60_degrees() {
        let camera = camera();
        let head_on = plane_depth(&camera, [0.0, 0.0, 0.5]);
        assert!(!grazing_pixels(&camera, &head_on, 0.15).contains(&true));
        // Tilted 60° about the y axis: cos to the central ray 0.5.
        let (s, c) = 60f64.to_radians().sin_cos();
        let tilted = plane_depth(&camera, [0.5 * s, 0.0, 0.5 * c]);
        assert!(!grazing_pixels(&camera, &tilted, 0.15).contains(&true));
        // The same plane is grazing for a bound above its cosine.
        let strict = grazing_pixels(&camera, &tilted, 0.6);
        assert!(strict.iter().filter(|&&g| g).count() > strict.len() / 2);
    }

    #[test]
    fn grazing_test_drops_the_ramp_of_a_smoothed_occlusion_edge() {
        let camera = camera();
        let (w, h) = (camera.width as usize, camera.height as usize);
        // Foreground at depth 1 left of x = 30, background at 3 from x = 34, a linear ramp
        // between (what a smoothed dense map puts across the edge); one pixel has no depth.
        let mut depth = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let t = ((x as f32 - 30.0) / 4.0).clamp(0.0, 1.0);
                depth[y * w + x] = 1.0 + 2.0 * t;
            }
        }
        depth[10 * w + 5] = 0.0;
        let grazing = grazing_pixels(&camera, &depth, 0.15);
        for y in 0..h {
            // The ramp's end pixels (30 and 34) straddle the corner; the rest is decided.
            for x in (0..w).filter(|x| !(30..=34).contains(x)) {
                assert!(!grazing[y * w + x], "flat pixel ({x}, {y}) dropped");
            }
            assert!((31..=33).all(|x| grazing[y * w + x]), "ramp row {y} kept");
        }
        // Off: nothing is dropped.
        assert!(!grazing_pixels(&camera, &depth, 0.0).contains(&true));
        // The input drops them too, and keeps the rest.
        let config = FusionConfig::default();
        let image = ImageF32::filled(w, h, 0.0);
        let mut idepth = image.clone();
        for (v, d) in idepth.data.iter_mut().zip(&depth) {
            *v = if *d > 0.0 { 1.0 / d } else { 0.0 };
        }
        let input = FusionInput::from_idepth(1, 0.0, camera, &idepth, &image, None, &config)
            .expect("input");
        assert_eq!(input.depth[10 * w + 32], 0.0);
        assert!(input.depth[10 * w + 20] > 0.0 && input.depth[10 * w + 50] > 0.0);
    }
}
