//! The keyframe side of direct image alignment: its semi-dense inverse-depth map turned into a
//! point cloud per pyramid level (LSD-SLAM's `TrackingReference::makePointCloud` over the depth
//! pyramid of `Frame::buildIDepthAndIDepthVar`).

use crate::frame::{Frame, PYRAMID_LEVELS};
use crate::mapping::{DepthMap, InverseDepth};
use crate::{Error, Result};

/// The reference points of one pyramid level, as a struct of arrays so that the tracking inner
/// loop streams through contiguous `f32`s.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReferenceLevel {
    /// 3-D point in keyframe coordinates, x component (keyframe scale).
    pub x: Vec<f32>,
    /// y component.
    pub y: Vec<f32>,
    /// z component (= depth = 1 / inverse depth).
    pub z: Vec<f32>,
    /// Keyframe intensity at the point's pixel (8-bit units).
    pub intensity: Vec<f32>,
    /// Variance of the point's inverse depth.
    pub idepth_var: Vec<f32>,
    /// Pixel index `x + y·width` in the level (for residual images and debugging).
    pub pixel: Vec<u32>,
}

impl ReferenceLevel {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// Whether the level has no point.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Bytes of its point buffers (six values of 4 bytes per point).
    fn heap_bytes(&self) -> usize {
        6 * 4 * self.len()
    }
}

/// A keyframe prepared for tracking: one [`ReferenceLevel`] per pyramid level.
///
/// Coarse levels are not subsampled points of level 0 but points of their own pixels, whose
/// inverse depth is the inverse-variance-weighted mean of the (up to four) estimated 2×2
/// children, so that the depth pyramid lines up with the image pyramid of [`Frame`] (each
/// level-L+1 pixel is the 2×2 average of level L).
#[derive(Clone, Debug)]
pub struct TrackingReference {
    /// Id of the keyframe this reference was built from.
    pub keyframe_id: u64,
    levels: Vec<ReferenceLevel>,
    sizes: Vec<(usize, usize)>,
}

/// Inverse depth and variance of one pixel of the depth pyramid; `var ≤ 0` means "no estimate"
/// (the convention of LSD-SLAM's `idepthVar` buffers).
#[derive(Clone, Copy, Debug)]
struct IdepthVar {
    idepth: f32,
    var: f32,
}

const NONE: IdepthVar = IdepthVar {
    idepth: -1.0,
    var: -1.0,
};

impl TrackingReference {
    /// Bytes of the point buffers of every level.
    pub fn heap_bytes(&self) -> usize {
        self.levels.iter().map(ReferenceLevel::heap_bytes).sum()
    }

    /// Builds the per-level point clouds of `keyframe` from its semi-dense map `depth`.
    ///
    /// Only [`InverseDepth::Estimate`]s with positive inverse depth and variance become points;
    /// the one-pixel image border is skipped (its gradients are one-sided). Fails with
    /// [`Error::Shape`] when the map and the keyframe differ in size.
    pub fn new(keyframe: &Frame, depth: &DepthMap) -> Result<Self> {
        let mut reference = Self {
            keyframe_id: keyframe.id,
            levels: Vec::new(),
            sizes: Vec::new(),
        };
        reference.rebuild(keyframe, depth)?;
        Ok(reference)
    }

    /// [`Self::new`] in place: rebuilds the point clouds (of `keyframe`, possibly another one)
    /// reusing this reference's buffers. The pipeline refreshes the current keyframe's
    /// reference after every mapped frame (LSD-SLAM re-imports the keyframe whenever its depth
    /// changed), so avoiding ~4 MB of fresh allocations per frame matters.
    pub fn rebuild(&mut self, keyframe: &Frame, depth: &DepthMap) -> Result<()> {
        let (w0, h0) = (keyframe.level(0).width(), keyframe.level(0).height());
        if (depth.width, depth.height) != (w0, h0) || depth.pixels.len() != w0 * h0 {
            return Err(Error::Shape(format!(
                "depth map {}x{} for a {w0}x{h0} keyframe",
                depth.width, depth.height
            )));
        }
        let full = |i: usize| match depth.pixels[i] {
            InverseDepth::Estimate { idepth, var }
                if idepth > 0.0 && var > 0.0 && idepth.is_finite() && var.is_finite() =>
            {
                IdepthVar { idepth, var }
            }
            _ => NONE,
        };
        let levels_available = keyframe.pyramid.levels.len().min(PYRAMID_LEVELS);
        self.keyframe_id = keyframe.id;
        self.levels
            .resize_with(levels_available, ReferenceLevel::default);
        self.sizes.clear();
        // Coarser depth levels (level 0 is read from `depth` directly).
        let (mut current, mut coarser) = (Vec::new(), Vec::new());
        for (level, out) in self.levels.iter_mut().enumerate() {
            let image_level = keyframe.level(level);
            let (w, h) = (image_level.width(), image_level.height());
            let camera = keyframe.camera_at(level);
            let image = &image_level.image.data;
            if level == 0 {
                level_points(full, image, &camera, w, h, out);
            } else {
                let (pw, _) = self.sizes[level - 1];
                if level == 1 {
                    downsample_idepth(full, pw, w, h, &mut coarser);
                } else {
                    downsample_idepth(|i| current[i], pw, w, h, &mut coarser);
                }
                std::mem::swap(&mut current, &mut coarser);
                level_points(|i| current[i], image, &camera, w, h, out);
            }
            self.sizes.push((w, h));
        }
        Ok(())
    }

    /// The points of pyramid level `level` (empty beyond the keyframe's pyramid).
    pub fn level(&self, level: usize) -> &ReferenceLevel {
        static EMPTY: ReferenceLevel = ReferenceLevel {
            x: Vec::new(),
            y: Vec::new(),
            z: Vec::new(),
            intensity: Vec::new(),
            idepth_var: Vec::new(),
            pixel: Vec::new(),
        };
        self.levels.get(level).unwrap_or(&EMPTY)
    }

    /// Number of points at `level`.
    pub fn num_points(&self, level: usize) -> usize {
        self.level(level).len()
    }

    /// Image size `(width, height)` of `level` in the keyframe's pyramid.
    pub fn level_size(&self, level: usize) -> Option<(usize, usize)> {
        self.sizes.get(level).copied()
    }
}

/// One level of the inverse-depth pyramid (LSD-SLAM `Frame::buildIDepthAndIDepthVar`): each
/// output pixel fuses its estimated 2×2 children with inverse-variance weights,
/// `d = Σ(dᵢ/vᵢ) / Σ(1/vᵢ)`, and takes the *harmonic mean* of their variances,
/// `v = n / Σ(1/vᵢ)`, rather than the fused variance `1/Σ(1/vᵢ)`: neighbouring estimates come
/// from the same stereo observations and are far from independent, so averaging them must
/// not make the coarse point look n times more certain.
fn downsample_idepth(
    src: impl Fn(usize) -> IdepthVar,
    src_w: usize,
    w: usize,
    h: usize,
    out: &mut Vec<IdepthVar>,
) {
    out.clear();
    out.resize(w * h, NONE);
    for (y, out_row) in out.chunks_exact_mut(w.max(1)).enumerate().take(h) {
        let (top, bottom) = (2 * y * src_w, (2 * y + 1) * src_w);
        for (x, dest) in out_row.iter_mut().enumerate() {
            let (mut sum_d, mut sum_iv, mut n) = (0.0f32, 0.0f32, 0u32);
            // Same order as LSD: (0,0), (1,0), (0,1), (1,1).
            let children = [
                src(top + 2 * x),
                src(top + 2 * x + 1),
                src(bottom + 2 * x),
                src(bottom + 2 * x + 1),
            ];
            for c in children {
                if c.var > 0.0 {
                    let iv = 1.0 / c.var;
                    sum_d += c.idepth * iv;
                    sum_iv += iv;
                    n += 1;
                }
            }
            if n > 0 && sum_iv.is_finite() && sum_iv > 0.0 {
                *dest = IdepthVar {
                    idepth: sum_d / sum_iv,
                    var: n as f32 / sum_iv,
                };
            }
        }
    }
}

/// The points of one level: every pixel off the one-pixel border with an estimate, unprojected
/// with the level's camera (the arithmetic of [`crate::geometry::PinholeCamera::unproject`],
/// with the per-column and per-row factors computed once).
fn level_points(
    depth: impl Fn(usize) -> IdepthVar,
    image: &[f32],
    camera: &crate::geometry::PinholeCamera,
    w: usize,
    h: usize,
    out: &mut ReferenceLevel,
) {
    for v in [
        &mut out.x,
        &mut out.y,
        &mut out.z,
        &mut out.intensity,
        &mut out.idepth_var,
    ] {
        v.clear();
    }
    out.pixel.clear();
    if w < 3 || h < 3 {
        return;
    }
    let col: Vec<f64> = (0..w).map(|x| (x as f64 - camera.cx) / camera.fx).collect();
    for y in 1..h - 1 {
        let row_factor = (y as f64 - camera.cy) / camera.fy;
        for (x, col_factor) in col.iter().enumerate().take(w - 1).skip(1) {
            let idx = y * w + x;
            let d = depth(idx);
            if d.var <= 0.0 {
                continue;
            }
            let z = 1.0 / f64::from(d.idepth);
            out.x.push((col_factor * z) as f32);
            out.y.push((row_factor * z) as f32);
            out.z.push(z as f32);
            out.intensity.push(image[idx]);
            out.idepth_var.push(d.var);
            out.pixel.push(idx as u32);
        }
    }
}
