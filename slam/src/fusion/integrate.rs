//! Integration and de-integration of one depth map into the TSDF (CPU reference), and the
//! blocks a depth map touches.
//!
//! The update is the classic weighted running average (Curless & Levoy), projective: every
//! voxel of a listed block is projected into the depth map and compared with the depth of the
//! pixel it falls in. De-integration subtracts exactly what integration added, so a keyframe
//! whose pose the pose graph moved can be taken out and put back in its new place (as in
//! BundleFusion); this is exact while a voxel's weight stays below the cap.
//!
//! [`integrate_cpu`] defines the arithmetic; the kernel `tsdf_integrate.wgsl`
//! ([`super::gpu_volume::GpuVoxels::integrate`]) performs the same f32 operations in the same
//! order, so the two agree to rounding except for voxels whose projection falls within an ulp
//! of a pixel boundary or whose signed distance is within an ulp of −truncation.

use std::collections::HashSet;

use nalgebra::{Matrix3, Vector3};

use super::block::{BLOCK_SIDE, BLOCK_VOXELS, BlockIndex, pack_rgb, unpack_rgb};
use super::voxels::CpuVoxels;
use crate::geometry::{PinholeCamera, Sim3};
use crate::{Error, Result};

/// One keyframe's depth map ready for integration: intrinsics, pose and per-pixel inputs, all
/// f32 so that the CPU reference and the kernel start from bit-identical numbers.
#[derive(Clone, Copy, Debug)]
pub struct DepthView<'a> {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    /// Rows of the 3×4 matrix `[R/s | t]` mapping world points to camera points (`p_c =
    /// M·[p_w; 1]`), the Sim(3) scale included: a similarity whose linear part scales by 1/s.
    pub camera_from_world: [[f32; 4]; 3],
    /// The keyframe's Sim(3) scale `s` (world units per camera unit): signed distances measured
    /// along the camera's z in camera units are multiplied by it to get world units.
    pub scale: f32,
    /// Depth along the camera's z in camera units, row-major; 0 (or NaN) = no depth.
    pub depth: &'a [f32],
    /// Integration weight per pixel; 0 = skip the pixel.
    pub weight: &'a [f32],
    /// Pixel colour packed `r | g << 8 | b << 16`.
    pub color: &'a [u32],
}

impl<'a> DepthView<'a> {
    /// The view of a keyframe at `world_from_camera` (its Sim(3) pose) seen through `camera`
    /// (an undistorted pinhole camera of the depth map's size: the dense maps are rectified).
    ///
    /// Errors: [`Error::Shape`] if a slice does not hold `width · height` pixels,
    /// [`Error::InvalidCamera`] if the camera has lens distortion or the scale is not a
    /// finite positive number.
    pub fn new(
        camera: &PinholeCamera,
        world_from_camera: &Sim3,
        depth: &'a [f32],
        weight: &'a [f32],
        color: &'a [u32],
    ) -> Result<Self> {
        if camera.distortion.is_some() {
            return Err(Error::InvalidCamera(
                "TSDF integration needs the undistorted (rectified) camera of the depth map".into(),
            ));
        }
        let s = world_from_camera.scale;
        if !(s.is_finite() && s > 0.0) {
            return Err(Error::InvalidCamera(format!(
                "keyframe scale must be finite and > 0, got {s}"
            )));
        }
        let m = world_from_camera.inverse().matrix();
        let row = |r: usize| {
            [
                m[(r, 0)] as f32,
                m[(r, 1)] as f32,
                m[(r, 2)] as f32,
                m[(r, 3)] as f32,
            ]
        };
        let view = Self {
            fx: camera.fx as f32,
            fy: camera.fy as f32,
            cx: camera.cx as f32,
            cy: camera.cy as f32,
            width: camera.width,
            height: camera.height,
            camera_from_world: [row(0), row(1), row(2)],
            scale: s as f32,
            depth,
            weight,
            color,
        };
        view.check()?;
        Ok(view)
    }

    /// Pixels of the depth map.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// [`Error::Shape`] unless depth, weight and colour each hold `width · height` pixels.
    pub fn check(&self) -> Result<()> {
        let n = self.pixels();
        for (name, len) in [
            ("depth", self.depth.len()),
            ("weight", self.weight.len()),
            ("color", self.color.len()),
        ] {
            if len != n {
                return Err(Error::Shape(format!(
                    "{name} has {len} pixels, the {}x{} view needs {n}",
                    self.width, self.height
                )));
            }
        }
        Ok(())
    }

    /// What voxel `v` sees: `(t, w, c)` = truncated signed distance in units of the truncation,
    /// pixel weight and pixel colour, or `None` when the voxel is not updated (behind the
    /// camera, outside the image, no depth or weight, or more than the truncation behind the
    /// surface). The arithmetic the kernel mirrors.
    fn sample(&self, p: &IntegrateParams, v: [i32; 3]) -> Option<(f32, f32, u32)> {
        let pw = [
            v[0] as f32 * p.voxel_size,
            v[1] as f32 * p.voxel_size,
            v[2] as f32 * p.voxel_size,
        ];
        let m = &self.camera_from_world;
        let row = |r: &[f32; 4]| ((r[0] * pw[0] + r[1] * pw[1]) + r[2] * pw[2]) + r[3];
        let (x, y, z) = (row(&m[0]), row(&m[1]), row(&m[2]));
        if z.is_nan() || z <= 0.0 {
            return None;
        }
        let u = self.fx * (x / z) + self.cx;
        let vv = self.fy * (y / z) + self.cy;
        // Nearest pixel, halves rounded up (the kernel's floor(u + 0.5)); NaN fails the test.
        let (ur, vr) = ((u + 0.5).floor(), (vv + 0.5).floor());
        if !(ur >= 0.0
            && vr >= 0.0
            && ur <= (self.width - 1) as f32
            && vr <= (self.height - 1) as f32)
        {
            return None;
        }
        let pix = vr as usize * self.width as usize + ur as usize;
        let (d, w) = (self.depth[pix], self.weight[pix]);
        if !(d > 0.0 && w > 0.0) {
            return None;
        }
        let sdf = (d - z) * self.scale;
        if sdf < -p.truncation {
            return None;
        }
        Some(((sdf / p.truncation).min(1.0), w, self.color[pix]))
    }

    /// `world_from_camera` as (linear part, translation) in f64, inverted from
    /// [`DepthView::camera_from_world`]; `None` if that matrix is singular.
    fn world_from_camera(&self) -> Option<(Matrix3<f64>, Vector3<f64>)> {
        let m = &self.camera_from_world;
        let a = Matrix3::from_fn(|r, c| f64::from(m[r][c]));
        let b = Vector3::new(f64::from(m[0][3]), f64::from(m[1][3]), f64::from(m[2][3]));
        let inv = a.try_inverse()?;
        Some((inv, -(inv * b)))
    }
}

/// Integration parameters (world units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IntegrateParams {
    pub voxel_size: f32,
    /// Truncation distance: signed distances are clamped to it (stored as tsdf = 1) in front of
    /// the surface and voxels farther behind the surface are not updated.
    pub truncation: f32,
    /// Voxel weights are capped here (the volume keeps adapting to new keyframes).
    pub max_weight: f32,
}

/// Weight below which a de-integrated voxel is empty (reset to zero). Taking every
/// observation out again leaves f32 rounding residues of the weight sums, simulated up to
/// 4·10⁻⁵ after 100 observations; a voxel that kept such a residue kept its block allocated,
/// so every loop-closure move left the keyframes' old surfaces behind as blocks (issue 37).
/// A thousandth of one confident observation is a tenth of the weakest pixel's weight
/// (`fusion.max_relative_sigma`), and far below `fusion.min_mesh_weight`. The kernel
/// `tsdf_integrate.wgsl` uses the same value.
pub const EMPTY_WEIGHT: f32 = 1e-3;

/// One voxel's update `(T, W, C) → (T', W', C')` with the sample `(t, w, c)`; `sign > 0`
/// integrates, otherwise de-integrates. Colours are rounded half up (`floor(x + 0.5)`, the
/// same in WGSL, whose `round` rounds halves to even).
fn update(
    (tsdf, weight, color): (f32, f32, u32),
    (t, w, c): (f32, f32, u32),
    sign: f32,
    max_weight: f32,
) -> (f32, f32, u32) {
    let (old, new) = (unpack_rgb(color), unpack_rgb(c));
    if sign > 0.0 {
        let w1 = weight + w;
        let t1 = (tsdf * weight + t * w) / w1;
        let mix = |k: usize| {
            let v = (f32::from(old[k]) * weight + f32::from(new[k]) * w) / w1;
            (v.clamp(0.0, 255.0) + 0.5).floor() as u8
        };
        (t1, w1.min(max_weight), pack_rgb([mix(0), mix(1), mix(2)]))
    } else {
        let w1 = weight - w;
        if w1 <= EMPTY_WEIGHT {
            return (0.0, 0.0, 0);
        }
        let t1 = (tsdf * weight - t * w) / w1;
        let unmix = |k: usize| {
            let v = (f32::from(old[k]) * weight - f32::from(new[k]) * w) / w1;
            (v.clamp(0.0, 255.0) + 0.5).floor() as u8
        };
        (t1, w1, pack_rgb([unmix(0), unmix(1), unmix(2)]))
    }
}

/// Integrates (`sign > 0`) or de-integrates (`sign ≤ 0`) `view` into the voxels of `blocks`
/// (block, slot); blocks must have distinct slots. Voxels in front of the surface are updated
/// however far (tsdf 1: free space), those more than the truncation behind it are not.
///
/// # Panics
/// If a slot is beyond `voxels.capacity()` or the view's slices do not hold `width · height`
/// pixels ([`DepthView::new`] checks that).
pub fn integrate_cpu(
    voxels: &mut CpuVoxels,
    blocks: &[(BlockIndex, u32)],
    view: &DepthView,
    p: &IntegrateParams,
    sign: f32,
) {
    if let Err(e) = view.check() {
        panic!("integrate_cpu: {e}");
    }
    for &(b, slot) in blocks {
        let base = slot as usize * BLOCK_VOXELS;
        for i in 0..BLOCK_VOXELS {
            let local = [i as i32 & 7, (i as i32 >> 3) & 7, i as i32 >> 6];
            let Some(sample) = view.sample(p, b.voxel(local)) else {
                continue;
            };
            let k = base + i;
            let (t, w, c) = update(
                (voxels.tsdf[k], voxels.weight[k], voxels.color[k]),
                sample,
                sign,
                p.max_weight,
            );
            voxels.tsdf[k] = t;
            voxels.weight[k] = w;
            voxels.color[k] = c;
        }
    }
}

/// The blocks holding every voxel that lies within the truncation of a depth sample (sorted,
/// deduplicated): the blocks to allocate before integrating `view`.
///
/// For every pixel with a finite depth `d > 0` and a weight > 0, the pixel's centre ray is
/// sampled between camera depths `d ± truncation / s` at steps of at most half a block; every
/// block holding a voxel within `r` (per axis) of a sample is marked, where `r` = half a step
/// plus the half-diagonal of the pixel's footprint at the far end of the range. A voxel within
/// the truncation projects into some pixel's footprint at a depth inside that pixel's range, so
/// it lies within `r` of one of the pixel's samples: the cover is complete, including voxels
/// just across a block boundary from the ray (which the block of the sample alone would miss).
pub fn touched_blocks(view: &DepthView, p: &IntegrateParams) -> Vec<BlockIndex> {
    let Some((a, t)) = view.world_from_camera() else {
        return Vec::new();
    };
    let vs = f64::from(p.voxel_size);
    let half_range = f64::from(p.truncation) / f64::from(view.scale);
    let step = 0.5 * f64::from(BLOCK_SIDE) * vs;
    // World length of half a pixel along x and y per unit camera depth.
    let (fx, fy) = (f64::from(view.fx), f64::from(view.fy));
    let footprint = 0.5 / fx * a.column(0).norm() + 0.5 / fy * a.column(1).norm();
    let (cx, cy) = (f64::from(view.cx), f64::from(view.cy));
    let mut marked = HashSet::new();
    // The box of the previous pixel's k-th sample: neighbouring pixels mostly repeat it, and
    // skipping repeats saves most of the hash-set inserts.
    let mut previous: Vec<(Vector3<i32>, Vector3<i32>)> = Vec::new();
    let n = view.pixels().min(view.depth.len()).min(view.weight.len());
    for pix in 0..n {
        let (d, w) = (f64::from(view.depth[pix]), view.weight[pix]);
        if !(d > 0.0 && d.is_finite() && w > 0.0) {
            continue;
        }
        let (u, v) = (
            (pix % view.width as usize) as f64,
            (pix / view.width as usize) as f64,
        );
        let dir = a * Vector3::new((u - cx) / fx, (v - cy) / fy, 1.0);
        let (z0, z1) = ((d - half_range).max(0.0), d + half_range);
        let segments = ((dir.norm() * (z1 - z0)) / step).ceil().max(1.0);
        // Radius in voxels; the 1e-2 absorbs f32 rounding of the kernel's projection.
        let r = ((0.5 * dir.norm() * (z1 - z0) / segments + footprint * z1) / vs + 1e-2).max(1.0);
        for k in 0..=segments as usize {
            let z = z0 + (z1 - z0) * k as f64 / segments;
            let q = (dir * z + t) / vs;
            let lo = (q - Vector3::repeat(r)).map(|c| (c.floor() as i32).div_euclid(BLOCK_SIDE));
            let hi = (q + Vector3::repeat(r)).map(|c| (c.floor() as i32).div_euclid(BLOCK_SIDE));
            if previous.get(k) == Some(&(lo, hi)) {
                continue;
            }
            if k < previous.len() {
                previous[k] = (lo, hi);
            } else {
                previous.push((lo, hi));
            }
            for bz in lo.z..=hi.z {
                for by in lo.y..=hi.y {
                    for bx in lo.x..=hi.x {
                        marked.insert(BlockIndex::new(bx, by, bz));
                    }
                }
            }
        }
    }
    let mut blocks: Vec<BlockIndex> = marked.into_iter().collect();
    blocks.sort_unstable();
    blocks
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::geometry::SO3;
    use rand::{Rng, SeedableRng};

    /// A Sim(3) with a rotation up to ~0.5 rad, a translation up to 1 and scale 0.5–2 (never 1).
    pub(crate) fn random_pose(rng: &mut impl Rng) -> Sim3 {
        let mut v = |a: f64| {
            Vector3::new(
                rng.random_range(-a..a),
                rng.random_range(-a..a),
                rng.random_range(-a..a),
            )
        };
        let (phi, t) = (v(0.3), v(1.0));
        let scale = if rng.random_bool(0.5) {
            rng.random_range(0.5..0.9)
        } else {
            rng.random_range(1.1..2.0)
        };
        Sim3::new(SO3::exp(&phi), t, scale)
    }

    /// Depth, weight and colour maps: depth in `depth` with `holes` of it 0, weights in
    /// [0.1, 1] with 10 % zeros, random colours.
    pub(crate) fn random_maps(
        n: usize,
        depth: std::ops::Range<f32>,
        holes: f64,
        rng: &mut impl Rng,
    ) -> (Vec<f32>, Vec<f32>, Vec<u32>) {
        let d = (0..n)
            .map(|_| {
                if rng.random_bool(holes) {
                    0.0
                } else {
                    rng.random_range(depth.clone())
                }
            })
            .collect();
        let w = (0..n)
            .map(|_| {
                if rng.random_bool(0.1) {
                    0.0
                } else {
                    rng.random_range(0.1f32..=1.0)
                }
            })
            .collect();
        let c = (0..n).map(|_| rng.random_range(0..1u32 << 24)).collect();
        (d, w, c)
    }

    pub(crate) fn camera(w: u32, h: u32) -> PinholeCamera {
        let f = 0.9 * f64::from(w.max(h));
        PinholeCamera::new(
            f,
            1.03 * f,
            0.5 * (f64::from(w) - 1.0) + 0.4,
            0.5 * (f64::from(h) - 1.0) - 0.3,
            w,
            h,
        )
        .expect("valid camera")
    }

    /// Voxels of `blocks` (slot = position in the list), in a pool of exactly that size.
    fn pool_for(blocks: &[BlockIndex]) -> (CpuVoxels, Vec<(BlockIndex, u32)>) {
        let mut voxels = CpuVoxels::default();
        voxels.ensure_capacity(blocks.len() as u32);
        let listed = blocks
            .iter()
            .enumerate()
            .map(|(s, b)| (*b, s as u32))
            .collect();
        (voxels, listed)
    }

    fn voxel_at(voxels: &CpuVoxels, listed: &[(BlockIndex, u32)], v: [i32; 3]) -> (f32, f32) {
        let b = BlockIndex::of_voxel(v);
        let slot = listed
            .iter()
            .find(|(x, _)| *x == b)
            .map(|(_, s)| *s)
            .expect("voxel's block is listed");
        let l = [v[0] - 8 * b.x, v[1] - 8 * b.y, v[2] - 8 * b.z];
        let k = slot as usize * BLOCK_VOXELS + (l[0] + 8 * l[1] + 64 * l[2]) as usize;
        (voxels.tsdf[k], voxels.weight[k])
    }

    #[test]
    fn fronto_parallel_plane_gives_zero_crossing_at_the_plane() {
        // Camera at the origin looking along +z, scale 2: camera depth 1 is world z = 2, i.e.
        // voxel z = 40 at 5 cm voxels; truncation 4 voxels.
        let pose = Sim3::new(SO3::identity(), Vector3::zeros(), 2.0);
        let cam = PinholeCamera::new(32.0, 32.0, 15.5, 11.5, 32, 24).expect("camera");
        let n = 32 * 24;
        let (depth, weight, color) = (
            vec![1.0f32; n],
            vec![1.0f32; n],
            vec![pack_rgb([10, 20, 30]); n],
        );
        let view = DepthView::new(&cam, &pose, &depth, &weight, &color).expect("view");
        let p = IntegrateParams {
            voxel_size: 0.05,
            truncation: 0.2,
            max_weight: 128.0,
        };
        let blocks: Vec<BlockIndex> = (0..7).map(|z| BlockIndex::new(0, 0, z)).collect();
        let (mut voxels, listed) = pool_for(&blocks);
        integrate_cpu(&mut voxels, &listed, &view, &p, 1.0);
        let at = |z: i32| voxel_at(&voxels, &listed, [1, 2, z]);
        assert!(at(40).0.abs() < 1e-5, "plane voxel tsdf {}", at(40).0);
        assert!(
            (at(39).0 - 0.25).abs() < 1e-5,
            "one voxel in front: {}",
            at(39).0
        );
        assert!(
            (at(41).0 + 0.25).abs() < 1e-5,
            "one voxel behind: {}",
            at(41).0
        );
        assert!((at(43).0 + 0.75).abs() < 1e-5);
        assert_eq!(at(10), (1.0, 1.0), "far in front: free space");
        assert_eq!(at(45), (0.0, 0.0), "beyond −truncation: untouched");
        assert_eq!(at(55), (0.0, 0.0));
        // Every updated voxel carries the pixel colour.
        let updated = voxels.weight.iter().filter(|&&w| w > 0.0).count();
        assert!(updated > 0);
        assert!(
            voxels
                .weight
                .iter()
                .zip(&voxels.color)
                .all(|(&w, &c)| (w > 0.0) == (c == pack_rgb([10, 20, 30])))
        );
        // A voxel behind the camera (z < 0) is never updated.
        let behind = [(BlockIndex::new(0, 0, -1), 0u32)];
        let mut empty = CpuVoxels::default();
        empty.ensure_capacity(1);
        integrate_cpu(&mut empty, &behind, &view, &p, 1.0);
        assert!(empty.weight.iter().all(|&w| w == 0.0));
    }

    #[test]
    fn deintegration_restores_the_prior_state_and_the_cap_holds() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (w, h) = (48, 36);
        let cam = camera(w, h);
        let p = IntegrateParams {
            voxel_size: 0.04,
            truncation: 0.16,
            max_weight: 128.0,
        };
        let pose_a = random_pose(&mut rng);
        let pose_b = Sim3::new(
            pose_a.rotation,
            pose_a.translation + Vector3::new(0.05, -0.02, 0.03),
            pose_a.scale * 1.1,
        );
        let n = (w * h) as usize;
        let (da, wa, ca) = random_maps(n, 1.0..1.3, 0.1, &mut rng);
        let (db, wb, cb) = random_maps(n, 1.0..1.3, 0.1, &mut rng);
        let view_a = DepthView::new(&cam, &pose_a, &da, &wa, &ca).expect("view a");
        let view_b = DepthView::new(&cam, &pose_b, &db, &wb, &cb).expect("view b");
        let mut all = touched_blocks(&view_a, &p);
        all.extend(touched_blocks(&view_b, &p));
        all.sort_unstable();
        all.dedup();
        let (mut voxels, listed) = pool_for(&all);
        integrate_cpu(&mut voxels, &listed, &view_b, &p, 1.0);
        let prior = voxels.clone();
        integrate_cpu(&mut voxels, &listed, &view_a, &p, 1.0);
        assert_ne!(voxels.weight, prior.weight, "view a changed nothing");
        integrate_cpu(&mut voxels, &listed, &view_a, &p, -1.0);
        for k in 0..prior.tsdf.len() {
            assert!(
                (voxels.weight[k] - prior.weight[k]).abs() <= 1e-5,
                "weight {k}: {} vs {}",
                voxels.weight[k],
                prior.weight[k]
            );
            assert!(
                (voxels.tsdf[k] - prior.tsdf[k]).abs() <= 1e-5,
                "tsdf {k}: {} vs {}",
                voxels.tsdf[k],
                prior.tsdf[k]
            );
        }

        // The cap: five integrations of weight 1 leave 2.5.
        let capped = IntegrateParams {
            max_weight: 2.5,
            ..p
        };
        let ones = vec![1.0f32; n];
        let view = DepthView::new(&cam, &pose_a, &da, &ones, &ca).expect("view");
        let (mut voxels, listed) = pool_for(&all);
        for _ in 0..5 {
            integrate_cpu(&mut voxels, &listed, &view, &capped, 1.0);
        }
        let max = voxels.weight.iter().fold(0f32, |m, &w| m.max(w));
        assert_eq!(max, 2.5);
        assert!(voxels.weight.iter().all(|&w| w == 0.0 || w == 2.5));
    }

    /// Forty overlapping views taken out again in another order leave every voxel empty
    /// (weight exactly 0), so [`super::super::fuser::Fuser`] can free their blocks: with a
    /// residue threshold of 10⁻⁶ some voxels kept f32 rounding residues of the weight sums.
    #[test]
    fn taking_every_view_out_again_leaves_the_voxels_empty() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (w, h) = (40, 30);
        let cam = camera(w, h);
        let p = IntegrateParams {
            voxel_size: 0.04,
            truncation: 0.16,
            max_weight: 128.0,
        };
        let base = random_pose(&mut rng);
        let n = (w * h) as usize;
        let views: Vec<Maps> = (0..40)
            .map(|_| {
                let shift = Vector3::new(
                    rng.random_range(-0.02..0.02),
                    rng.random_range(-0.02..0.02),
                    rng.random_range(-0.02..0.02),
                );
                let pose = Sim3::new(base.rotation, base.translation + shift, base.scale);
                (pose, random_maps(n, 1.0..1.1, 0.05, &mut rng))
            })
            .collect();
        type Maps = (Sim3, (Vec<f32>, Vec<f32>, Vec<u32>));
        fn view<'a>(cam: &'a PinholeCamera, (pose, (d, wt, c)): &'a Maps) -> DepthView<'a> {
            DepthView::new(cam, pose, d, wt, c).expect("view")
        }
        let mut all: Vec<BlockIndex> = views
            .iter()
            .flat_map(|v| touched_blocks(&view(&cam, v), &p))
            .collect();
        all.sort_unstable();
        all.dedup();
        let (mut voxels, listed) = pool_for(&all);
        for v in &views {
            integrate_cpu(&mut voxels, &listed, &view(&cam, v), &p, 1.0);
        }
        let most = voxels.weight.iter().fold(0f32, |m, &w| m.max(w));
        assert!(most > 10.0, "the views overlap: heaviest voxel {most}");
        // Out in another order than in: every third view from the last, three times.
        for first in [2, 1, 0] {
            for v in views.iter().skip(first).step_by(3).rev() {
                integrate_cpu(&mut voxels, &listed, &view(&cam, v), &p, -1.0);
            }
        }
        let left = voxels.weight.iter().filter(|&&w| w != 0.0).count();
        assert_eq!(
            left, 0,
            "voxels left with a weight after every view was taken out"
        );
    }

    /// Every voxel the integration puts within the truncation (|tsdf| < 1) lies in a block
    /// `touched_blocks` returned: checked exhaustively over every block around the frustum.
    #[test]
    fn touched_blocks_cover_every_voxel_within_the_truncation() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
        let (w, h) = (40, 30);
        let cam = camera(w, h);
        let n = (w * h) as usize;
        for case in 0..3 {
            let pose = random_pose(&mut rng);
            let s = pose.scale as f32;
            // A tilted plane for the first two cases, random depths for the last.
            let (mut depth, weight, color) = random_maps(n, 1.0..2.0, 0.05, &mut rng);
            if case < 2 {
                let (gx, gy) = (rng.random_range(-0.01..0.01), rng.random_range(-0.01..0.01));
                for (i, d) in depth.iter_mut().enumerate() {
                    let (u, v) = ((i % w as usize) as f32, (i / w as usize) as f32);
                    if *d > 0.0 {
                        *d = 1.5 + gx * (u - 20.0) + gy * (v - 15.0);
                    }
                }
            }
            let view = DepthView::new(&cam, &pose, &depth, &weight, &color).expect("view");
            // Voxels of about 1/30 of the depth range; truncation 3 voxels.
            let voxel_size = 0.05 * s;
            let p = IntegrateParams {
                voxel_size,
                truncation: 3.0 * voxel_size,
                max_weight: 128.0,
            };
            let touched = touched_blocks(&view, &p);
            assert!(touched.windows(2).all(|x| x[0] < x[1]), "sorted, unique");
            let set: HashSet<BlockIndex> = touched.iter().copied().collect();
            // Every block of the bounding box of the touched ones, one block wider.
            let lo = touched.iter().fold([i32::MAX; 3], |m, b| {
                [m[0].min(b.x), m[1].min(b.y), m[2].min(b.z)]
            });
            let hi = touched.iter().fold([i32::MIN; 3], |m, b| {
                [m[0].max(b.x), m[1].max(b.y), m[2].max(b.z)]
            });
            let mut all = Vec::new();
            for z in lo[2] - 1..=hi[2] + 1 {
                for y in lo[1] - 1..=hi[1] + 1 {
                    for x in lo[0] - 1..=hi[0] + 1 {
                        all.push(BlockIndex::new(x, y, z));
                    }
                }
            }
            let (mut voxels, listed) = pool_for(&all);
            integrate_cpu(&mut voxels, &listed, &view, &p, 1.0);
            let mut needed = HashSet::new();
            for &(b, slot) in &listed {
                let r = CpuVoxels::slot_range(slot);
                let near = voxels.weight[r.clone()]
                    .iter()
                    .zip(&voxels.tsdf[r])
                    .any(|(&w, &t)| w > 0.0 && t.abs() < 1.0);
                if near {
                    assert!(set.contains(&b), "case {case}: block {b:?} not touched");
                    needed.insert(b);
                }
            }
            assert!(!needed.is_empty());
            eprintln!(
                "case {case}: {} blocks touched, {} hold voxels within the truncation",
                touched.len(),
                needed.len()
            );
        }
    }

    #[test]
    fn depth_view_checks_its_inputs() {
        let cam = camera(8, 6);
        let pose = Sim3::identity();
        let (d, w, c) = (vec![1.0f32; 48], vec![1.0f32; 48], vec![0u32; 48]);
        assert!(DepthView::new(&cam, &pose, &d, &w, &c).is_ok());
        assert!(matches!(
            DepthView::new(&cam, &pose, &d[..47], &w, &c),
            Err(Error::Shape(_))
        ));
        assert!(matches!(
            DepthView::new(&cam, &pose, &d, &w, &c[..1]),
            Err(Error::Shape(_))
        ));
        let distorted = cam
            .with_distortion(crate::geometry::Distortion::new(0.1, 0.0, 0.0, 0.0, 0.0))
            .expect("distortion");
        assert!(matches!(
            DepthView::new(&distorted, &pose, &d, &w, &c),
            Err(Error::InvalidCamera(_))
        ));
        // camera_from_world includes the scale: a world point s·p_c + t maps back to p_c.
        let pose = Sim3::new(
            SO3::exp(&Vector3::new(0.1, -0.2, 0.3)),
            Vector3::new(1.0, 2.0, 3.0),
            1.7,
        );
        let view = DepthView::new(&cam, &pose, &d, &w, &c).expect("view");
        let pc = Vector3::new(0.3, -0.4, 2.0);
        let pw = pose.act(&pc);
        for r in 0..3 {
            let m = view.camera_from_world[r];
            let got = f64::from(m[0]) * pw.x
                + f64::from(m[1]) * pw.y
                + f64::from(m[2]) * pw.z
                + f64::from(m[3]);
            assert!((got - pc[r]).abs() < 1e-5, "row {r}: {got} vs {}", pc[r]);
        }
        assert!((view.scale - 1.7).abs() < 1e-7);
    }
}
