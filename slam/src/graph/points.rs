//! Per-level inverse-depth pyramids and reference point clouds of a keyframe, the input of
//! Sim(3) alignment (LSD-SLAM's `TrackingReference::makePointCloud` and
//! `Frame::buildIDepthAndIDepthVar`).
//!
//! A keyframe plays both roles in a keyframe-to-keyframe alignment: as *reference* it provides
//! 3-D points (pixels with an inverse-depth estimate, unprojected) at each pyramid level; as
//! *frame* it provides its image and an inverse-depth map to compare the warped points' depth
//! against. Both are built once per keyframe and reused by every constraint it takes part in.

use nalgebra::{Vector2, Vector3};

use crate::frame::{Frame, PYRAMID_LEVELS};
use crate::geometry::PinholeCamera;
use crate::mapping::DepthMap;
use crate::{Error, Result};

/// Inverse depth and variance of one pyramid level; `var ≤ 0` marks "no estimate".
#[derive(Clone, Debug, PartialEq)]
pub struct DepthLevel {
    pub width: usize,
    pub height: usize,
    pub idepth: Vec<f32>,
    pub var: Vec<f32>,
}

impl DepthLevel {
    /// Level 0 straight from the published [`DepthMap`]: estimates with `idepth > 0` and a
    /// positive finite variance (LSD-SLAM's maps may hold negative inverse depths; the graph
    /// ignores them, they carry no usable scale).
    fn from_depth_map(depth: &DepthMap) -> Self {
        let n = depth.width * depth.height;
        let (mut idepth, mut var) = (vec![0.0; n], vec![-1.0; n]);
        for (i, p) in depth.pixels.iter().enumerate() {
            if let Some((d, v)) = p.estimate()
                && d > 0.0
                && d.is_finite()
                && v > 0.0
                && v.is_finite()
            {
                idepth[i] = d;
                var[i] = v;
            }
        }
        Self {
            width: depth.width,
            height: depth.height,
            idepth,
            var,
        }
    }

    /// The next coarser level (`floor(w/2) × floor(h/2)`, like the image pyramid): each pixel is
    /// the inverse-variance-weighted mean of its valid 2×2 children, with variance
    /// `n / Σ(1/vᵢ)` — the children's harmonic-mean variance, *not* reduced by averaging,
    /// because neighbouring estimates of a regularised map are strongly correlated
    /// (`Frame::buildIDepthAndIDepthVar`).
    fn downsample(&self) -> Self {
        let (w, h) = (self.width / 2, self.height / 2);
        let (mut idepth, mut var) = (vec![0.0; w * h], vec![-1.0; w * h]);
        for y in 0..h {
            for x in 0..w {
                let (mut sum_iv, mut sum_div, mut n) = (0.0f64, 0.0f64, 0u32);
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let i = (2 * y + dy) * self.width + 2 * x + dx;
                    if self.var[i] > 0.0 {
                        let iv = 1.0 / f64::from(self.var[i]);
                        sum_iv += iv;
                        sum_div += f64::from(self.idepth[i]) * iv;
                        n += 1;
                    }
                }
                if n > 0 {
                    idepth[y * w + x] = (sum_div / sum_iv) as f32;
                    var[y * w + x] = (f64::from(n) / sum_iv) as f32;
                }
            }
        }
        Self {
            width: w,
            height: h,
            idepth,
            var,
        }
    }

    /// `(idepth, var)` at a sub-pixel position: the nearest pixel must hold an estimate (as in
    /// LSD-SLAM, which reads the rounded position), and the value is the bilinear interpolation
    /// over those of the four neighbours that hold one (weights renormalised), so it moves
    /// continuously along a semi-dense edge without bleeding across holes.
    pub fn sample(&self, uv: &Vector2<f64>) -> Option<(f64, f64)> {
        let (x, y) = (uv.x, uv.y);
        if !(x >= 0.0 && y >= 0.0 && x <= (self.width - 1) as f64 && y <= (self.height - 1) as f64)
        {
            return None;
        }
        let (xn, yn) = ((x + 0.5) as usize, (y + 0.5) as usize);
        if self.var[yn.min(self.height - 1) * self.width + xn.min(self.width - 1)] <= 0.0 {
            return None;
        }
        // x, y ≥ 0 here, so truncation is the floor (and no call into libm's `floor`).
        let x0 = (x as usize).min(self.width.saturating_sub(2));
        let y0 = (y as usize).min(self.height.saturating_sub(2));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let (mut wsum, mut dsum, mut vsum) = (0.0, 0.0, 0.0);
        for (dx, dy, w) in [
            (0, 0, (1.0 - fx) * (1.0 - fy)),
            (1, 0, fx * (1.0 - fy)),
            (0, 1, (1.0 - fx) * fy),
            (1, 1, fx * fy),
        ] {
            let (xi, yi) = (
                (x0 + dx).min(self.width - 1),
                (y0 + dy).min(self.height - 1),
            );
            let i = yi * self.width + xi;
            if self.var[i] > 0.0 && w > 0.0 {
                wsum += w;
                dsum += w * f64::from(self.idepth[i]);
                vsum += w * f64::from(self.var[i]);
            }
        }
        (wsum > 0.0).then(|| (dsum / wsum, vsum / wsum))
    }
}

/// One reference point of a pyramid level, in the keyframe's camera frame and scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefPoint {
    /// 3-D point `K⁻¹·(u, v, 1) / idepth`.
    pub point: Vector3<f64>,
    /// Inverse depth and its variance.
    pub idepth: f64,
    pub var: f64,
    /// Reference intensity (8-bit units).
    pub intensity: f64,
}

/// Everything of one keyframe at one pyramid level that Sim(3) alignment reads.
#[derive(Clone, Debug, PartialEq)]
pub struct KeyframeLevel {
    pub camera: PinholeCamera,
    /// Pixels with an estimate, unprojected (interior pixels only: the warp needs a 1-pixel
    /// margin for gradients).
    pub points: Vec<RefPoint>,
    pub depth: DepthLevel,
}

/// The per-level depth pyramid and point clouds of a keyframe.
#[derive(Clone, Debug, PartialEq)]
pub struct KeyframeLevels {
    pub levels: Vec<KeyframeLevel>,
    /// Mean inverse depth of the level-0 estimates (LSD-SLAM's `meanIdepth`, used to express
    /// distances between keyframes in units of scene depth); 1 for a map without estimates.
    pub mean_idepth: f64,
    /// Number of usable level-0 estimates (a keyframe without any cannot be aligned).
    pub estimates: usize,
}

impl KeyframeLevels {
    /// Bytes of the points and depth pyramids of every level.
    pub fn heap_bytes(&self) -> usize {
        self.levels
            .iter()
            .map(|l| {
                l.points.len() * std::mem::size_of::<RefPoint>()
                    + (l.depth.idepth.len() + l.depth.var.len()) * 4
            })
            .sum()
    }

    /// Builds all [`PYRAMID_LEVELS`] levels. Fails when the depth map and frame sizes differ.
    pub fn new(frame: &Frame, depth: &DepthMap) -> Result<Self> {
        Self::from_level(frame, depth, 0)
    }

    /// [`KeyframeLevels::new`] with the levels finer than `finest` left without points or
    /// depth: the back end never aligns below [`super::BackendConfig::finest_level`], and
    /// level 0 alone holds about 60 % of the points and depth.
    pub fn from_level(frame: &Frame, depth: &DepthMap, finest: usize) -> Result<Self> {
        let (w, h) = (frame.camera.width as usize, frame.camera.height as usize);
        if (depth.width, depth.height) != (w, h) || depth.pixels.len() != w * h {
            return Err(Error::Shape(format!(
                "depth map {}x{} ({} pixels) for a {w}x{h} frame",
                depth.width,
                depth.height,
                depth.pixels.len()
            )));
        }
        let mut depth_level = DepthLevel::from_depth_map(depth);
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (d, v) in depth_level.idepth.iter().zip(&depth_level.var) {
            if *v > 0.0 {
                sum += f64::from(*d);
                n += 1;
            }
        }
        let levels_available = frame.pyramid.levels.len().min(PYRAMID_LEVELS);
        let mut levels = Vec::with_capacity(levels_available);
        for l in 0..levels_available {
            if l > 0 {
                depth_level = depth_level.downsample();
            }
            let camera = frame.camera_at(l);
            let image = &frame.level(l).image;
            if (image.width, image.height) != (depth_level.width, depth_level.height) {
                return Err(Error::Shape(format!(
                    "level {l}: image {}x{}, depth {}x{}",
                    image.width, image.height, depth_level.width, depth_level.height
                )));
            }
            if l < finest {
                levels.push(KeyframeLevel {
                    camera,
                    points: Vec::new(),
                    depth: DepthLevel {
                        width: depth_level.width,
                        height: depth_level.height,
                        idepth: Vec::new(),
                        var: Vec::new(),
                    },
                });
                continue;
            }
            let mut points = Vec::new();
            for y in 1..depth_level.height.saturating_sub(1) {
                for x in 1..depth_level.width.saturating_sub(1) {
                    let i = y * depth_level.width + x;
                    if depth_level.var[i] <= 0.0 {
                        continue;
                    }
                    let idepth = f64::from(depth_level.idepth[i]);
                    points.push(RefPoint {
                        point: camera.unproject(&Vector2::new(x as f64, y as f64), 1.0 / idepth),
                        idepth,
                        var: f64::from(depth_level.var[i]),
                        intensity: f64::from(image.at(x, y)),
                    });
                }
            }
            levels.push(KeyframeLevel {
                camera,
                points,
                depth: depth_level.clone(),
            });
        }
        let mean_idepth = if n > 0 { sum / n as f64 } else { 1.0 };
        Ok(Self {
            levels,
            mean_idepth,
            estimates: n,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mapping::InverseDepth;

    #[test]
    fn coarse_depth_is_inverse_variance_weighted_with_harmonic_variance() {
        let mut map = DepthMap::unknown(4, 2);
        map.pixels[0] = InverseDepth::Estimate {
            idepth: 1.0,
            var: 1.0,
        };
        map.pixels[1] = InverseDepth::Estimate {
            idepth: 2.0,
            var: 0.25,
        };
        map.pixels[4] = InverseDepth::Discarded;
        map.pixels[5] = InverseDepth::Estimate {
            idepth: -1.0,
            var: 0.1,
        };
        let l0 = DepthLevel::from_depth_map(&map);
        let l1 = l0.downsample();
        assert_eq!((l1.width, l1.height), (2, 1));
        // weights 1 and 4: (1·1 + 2·4)/5 = 1.8; variance 2 / 5.
        assert!((l1.idepth[0] - 1.8).abs() < 1e-6, "{}", l1.idepth[0]);
        assert!((l1.var[0] - 0.4).abs() < 1e-6, "{}", l1.var[0]);
        assert!(l1.var[1] <= 0.0, "a block without estimates stays empty");
    }

    #[test]
    fn depth_sampling_requires_the_nearest_pixel_and_interpolates_valid_neighbours() {
        let level = DepthLevel {
            width: 3,
            height: 2,
            idepth: vec![1.0, 2.0, 0.0, 1.0, 2.0, 0.0],
            var: vec![1.0, 1.0, -1.0, 1.0, 1.0, -1.0],
        };
        let (d, _) = level
            .sample(&Vector2::new(0.25, 0.5))
            .expect("inside the valid block");
        assert!((d - 1.25).abs() < 1e-12, "{d}");
        // Nearest pixel (2, 0) has no estimate.
        assert!(level.sample(&Vector2::new(1.6, 0.0)).is_none());
        // Nearest valid, right neighbour invalid: the valid one alone.
        let (d, _) = level
            .sample(&Vector2::new(1.4, 0.0))
            .expect("nearest (1, 0) valid");
        assert!((d - 2.0).abs() < 1e-12, "{d}");
        assert!(level.sample(&Vector2::new(-0.1, 0.0)).is_none());
    }
}
