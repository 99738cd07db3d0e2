//! Finding and verifying keyframe-to-keyframe constraints (LSD-SLAM §3.5 "Constraint search";
//! `TrackableKeyFrameSearch` and `SlamSystem::{findConstraintsForNewKeyFrames, testConstraint,
//! tryTrackSim3}` in tum-vision/lsd_slam).
//!
//! Candidates for a new keyframe come from two sources: keyframes whose pose is close (distance
//! in units of scene depth, viewing directions within a fraction of the field of view), and —
//! for loop closures whose drifted poses are far apart — keyframes that *look* alike (a tiny
//! normalised thumbnail compared by correlation, standing in for LSD-SLAM's optional FAB-MAP).
//! Every candidate is verified by the *reciprocal* test: Sim(3) alignment in both directions,
//! coarse-to-fine in three stages, each accepted only if both alignments are good and their
//! composition `T_ba·T_ab` is the identity within the propagated uncertainty (Mahalanobis
//! distance below a threshold), which rejects the wrong minima single alignments fall into.

use std::sync::{Arc, Weak};

use super::KeyframeId;
use super::config::BackendConfig;
use super::points::KeyframeLevels;
use super::pose_graph::Constraint;
use super::sim3_tracker::{Sim3TrackResult, Sim3Tracker};
use crate::Result;
use crate::frame::{CompactFrame, Frame, PYRAMID_LEVELS};
use crate::geometry::{Matrix7, PinholeCamera, Sim3};
use crate::mapping::{CompactDepth, DepthMap};
use crate::spill::{Spill, Stored};

/// Thumbnail size of the appearance descriptor (columns × rows).
pub const THUMBNAIL_SIZE: (usize, usize) = (32, 24);

/// Largest shift (cells, each axis) tried when comparing thumbnails: ±4 cells of 32 is ±1/8 of
/// the image, about ±8° of yaw or pitch at a 62° field of view.
pub const THUMBNAIL_MAX_SHIFT: usize = 4;

/// A cheap global image descriptor standing in for FAB-MAP: the image box-averaged into
/// [`THUMBNAIL_SIZE`] cells and smoothed by a binomial filter. Two views of one place from
/// nearby viewpoints differ by roughly a shift of the thumbnail, so [`Thumbnail::score`] is the
/// best normalised cross-correlation over shifts up to [`THUMBNAIL_MAX_SHIFT`] cells. It is
/// neither rotation- nor scale-invariant, which is acceptable because a proposal is verified by
/// Sim(3) alignment from the identity anyway.
///
/// Every keyframe keeps one for the whole session and each full constraint search scores all
/// of them, so the cells are stored as 8-bit codes over the descriptor's own range (768 B, was
/// 3 kB of f32) and scored in integers: exact, and several times faster. The correlation is
/// invariant to each side's offset and scale, so the codes change it only by their rounding
/// (under 1/255 of the range). The codes are shared: the pipeline's record and the back end's
/// keyframe hold one copy (issue 37).
#[derive(Clone, Debug)]
pub struct Thumbnail {
    codes: Arc<[u8]>,
    /// Value of code 0, and of one code step (0 for a uniform image).
    offset: f32,
    step: f32,
}

/// Two descriptors are equal when their codes are: the score reads nothing else.
impl PartialEq for Thumbnail {
    fn eq(&self, other: &Self) -> bool {
        self.codes == other.codes
    }
}

impl Thumbnail {
    /// The descriptor of `frame`, computed on the coarsest pyramid level that still has at
    /// least 2×2 pixels per cell.
    pub fn new(frame: &Frame) -> Self {
        let (tw, th) = THUMBNAIL_SIZE;
        let levels = frame.pyramid.levels.len().min(PYRAMID_LEVELS);
        let level = (0..levels)
            .rev()
            .find(|&l| {
                let img = &frame.level(l).image;
                img.width >= 2 * tw && img.height >= 2 * th
            })
            .unwrap_or(0);
        let img = &frame.level(level).image;
        let mut sum = vec![0.0f32; tw * th];
        let mut count = vec![0u32; tw * th];
        for y in 0..img.height {
            let cy = (y * th / img.height.max(1)).min(th - 1);
            for x in 0..img.width {
                let cx = (x * tw / img.width.max(1)).min(tw - 1);
                sum[cy * tw + cx] += img.at(x, y);
                count[cy * tw + cx] += 1;
            }
        }
        let mut v: Vec<f32> = sum
            .iter()
            .zip(&count)
            .map(|(s, &n)| if n > 0 { s / n as f32 } else { 0.0 })
            .collect();
        // Two passes of the separable [1 2 1]/4 filter (clamped borders): shift tolerance.
        for _ in 0..2 {
            let src = v.clone();
            for y in 0..th {
                for x in 0..tw {
                    let at = |xx: usize| src[y * tw + xx];
                    v[y * tw + x] =
                        0.25 * (at(x.saturating_sub(1)) + 2.0 * at(x) + at((x + 1).min(tw - 1)));
                }
            }
            let src = v.clone();
            for y in 0..th {
                for x in 0..tw {
                    let at = |yy: usize| src[yy * tw + x];
                    v[y * tw + x] =
                        0.25 * (at(y.saturating_sub(1)) + 2.0 * at(y) + at((y + 1).min(th - 1)));
                }
            }
        }
        Self::quantise(&v)
    }

    /// 8-bit codes of `values` over their range (all finite).
    fn quantise(values: &[f32]) -> Self {
        let (lo, hi) = values
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let step = if hi > lo { (hi - lo) / 255.0 } else { 0.0 };
        let codes = values
            .iter()
            .map(|&v| {
                if step > 0.0 {
                    ((v - lo) / step).round().clamp(0.0, 255.0) as u8
                } else {
                    0
                }
            })
            .collect();
        Self {
            codes,
            offset: lo,
            step,
        }
    }

    /// The descriptor's cells, row-major ([`THUMBNAIL_SIZE`]), as the values its codes stand
    /// for.
    pub fn values(&self) -> Vec<f32> {
        (self.codes.iter())
            .map(|&c| self.offset + f32::from(c) * self.step)
            .collect()
    }

    /// A descriptor from stored cells; `None` unless there are exactly
    /// [`THUMBNAIL_SIZE`] finite ones. Cells [`Thumbnail::values`] gave come back as the same
    /// codes.
    pub fn from_values(values: Vec<f32>) -> Option<Self> {
        (values.len() == THUMBNAIL_SIZE.0 * THUMBNAIL_SIZE.1
            && values.iter().all(|v| v.is_finite()))
        .then(|| Self::quantise(&values))
    }

    /// Best normalised cross-correlation in [−1, 1] over shifts of up to
    /// [`THUMBNAIL_MAX_SHIFT`] cells; 0 for a shift where either side is uniform.
    pub fn score(&self, other: &Thumbnail) -> f64 {
        let (a, b) = (Moments::of(&self.codes), Moments::of(&other.codes));
        let m = THUMBNAIL_MAX_SHIFT as isize;
        let mut best = f64::NEG_INFINITY;
        for dy in -m..=m {
            for dx in -m..=m {
                best = best.max(self.correlation(other, &a, &b, dx, dy));
            }
        }
        best
    }

    /// Normalised cross-correlation of the overlap of `self` and `other` shifted by (dx, dy)
    /// cells (`a`, `b`: their [`Moments`]).
    fn correlation(
        &self,
        other: &Thumbnail,
        a: &Moments,
        b: &Moments,
        dx: isize,
        dy: isize,
    ) -> f64 {
        let tw = THUMBNAIL_SIZE.0 as isize;
        // Self's overlap is columns x0..x1, rows y0..y1; other's is the same shifted by −(dx, dy).
        let (x0, x1) = (dx.max(0), (tw + dx).min(tw));
        let (y0, y1) = (
            dy.max(0),
            (THUMBNAIL_SIZE.1 as isize + dy).min(THUMBNAIL_SIZE.1 as isize),
        );
        if x1 <= x0 || y1 <= y0 {
            return 0.0;
        }
        let width = (x1 - x0) as usize;
        let mut sab = 0u64;
        for y in y0..y1 {
            let ra = (y * tw + x0) as usize;
            let rb = ((y - dy) * tw + x0 - dx) as usize;
            let row: u32 = (self.codes[ra..ra + width].iter())
                .zip(&other.codes[rb..rb + width])
                .map(|(&p, &q)| u32::from(p) * u32::from(q))
                .sum();
            sab += u64::from(row);
        }
        let n = ((x1 - x0) * (y1 - y0)) as i64;
        let (sa, saa) = a.sums(x0, x1, y0, y1);
        let (sb, sbb) = b.sums(x0 - dx, x1 - dx, y0 - dy, y1 - dy);
        let (var_a, var_b) = (n * saa - sa * sa, n * sbb - sb * sb);
        if var_a <= 0 || var_b <= 0 {
            return 0.0;
        }
        (n * sab as i64 - sa * sb) as f64 / ((var_a as f64) * (var_b as f64)).sqrt()
    }
}

/// Summed-area tables of a descriptor's codes and their squares, so that the sums over any
/// overlap cost four reads (exact integers).
struct Moments {
    sum: Vec<i64>,
    squares: Vec<i64>,
}

impl Moments {
    fn of(codes: &[u8]) -> Self {
        let (tw, th) = THUMBNAIL_SIZE;
        let stride = tw + 1;
        let mut sum = vec![0i64; stride * (th + 1)];
        let mut squares = vec![0i64; stride * (th + 1)];
        for y in 0..th {
            let (mut row, mut row_sq) = (0i64, 0i64);
            for x in 0..tw {
                let c = i64::from(codes[y * tw + x]);
                row += c;
                row_sq += c * c;
                sum[(y + 1) * stride + x + 1] = sum[y * stride + x + 1] + row;
                squares[(y + 1) * stride + x + 1] = squares[y * stride + x + 1] + row_sq;
            }
        }
        Self { sum, squares }
    }

    /// Sums of the codes and of their squares over columns x0..x1, rows y0..y1.
    fn sums(&self, x0: isize, x1: isize, y0: isize, y1: isize) -> (i64, i64) {
        let stride = THUMBNAIL_SIZE.0 + 1;
        let at = |t: &[i64], x: isize, y: isize| t[y as usize * stride + x as usize];
        let rect = |t: &[i64]| at(t, x1, y1) - at(t, x0, y1) - at(t, x1, y0) + at(t, x0, y0);
        (rect(&self.sum), rect(&self.squares))
    }
}

/// A keyframe as the back end keeps it: image, published depth, depth pyramid and descriptor.
#[derive(Clone, Debug)]
pub struct Keyframe {
    pub id: KeyframeId,
    pub frame: Arc<Frame>,
    pub depth: Arc<DepthMap>,
    pub levels: KeyframeLevels,
    pub thumbnail: Thumbnail,
    /// The finest level `levels` holds ([`KeyframeLevels::from_level`]).
    pub finest_level: usize,
}

impl Keyframe {
    /// Builds the depth pyramid and descriptor (fails when depth and frame sizes differ).
    pub fn new(id: KeyframeId, frame: Arc<Frame>, depth: Arc<DepthMap>) -> Result<Self> {
        Self::from_level(id, frame, depth, 0)
    }

    /// [`Keyframe::new`] with alignment levels from `finest` up only
    /// ([`KeyframeLevels::from_level`]).
    pub fn from_level(
        id: KeyframeId,
        frame: Arc<Frame>,
        depth: Arc<DepthMap>,
        finest: usize,
    ) -> Result<Self> {
        let levels = KeyframeLevels::from_level(&frame, &depth, finest)?;
        let thumbnail = Thumbnail::new(&frame);
        Ok(Self {
            id,
            frame,
            depth,
            levels,
            thumbnail,
            finest_level: finest,
        })
    }

    /// What the back end keeps of this keyframe while it is not in use.
    pub fn compact(&self) -> CompactKeyframe {
        self.compact_sharing(None)
    }

    /// [`Keyframe::compact`] with `data`, this keyframe's image and depth in compact form,
    /// when the caller already has them (one copy, spilled once: `crate::spill`).
    pub fn compact_sharing(&self, data: Option<KeyframeData>) -> CompactKeyframe {
        CompactKeyframe {
            id: self.id,
            data: data.unwrap_or_else(|| {
                KeyframeData::new(
                    &Spill::default(),
                    self.frame.compact(),
                    CompactDepth::of(&self.depth),
                )
            }),
            camera: self.frame.camera,
            thumbnail: self.thumbnail.clone(),
            mean_idepth: self.levels.mean_idepth,
            estimates: self.levels.estimates,
            finest_level: self.finest_level,
        }
    }

    /// Bytes of the working data a resident keyframe adds to its compact form: the frame's
    /// pyramid, the full depth map and the alignment levels.
    pub fn heap_bytes(&self) -> usize {
        self.frame.heap_bytes() + self.depth.heap_bytes() + self.levels.heap_bytes()
    }
}

/// A keyframe's image and depth in compact form, each held in memory or spilled to the
/// session's store (`crate::spill`); one copy shared by the pipeline and the back end.
#[derive(Clone, Debug)]
pub struct KeyframeData {
    pub image: Arc<Stored<CompactFrame>>,
    pub depth: Arc<Stored<CompactDepth>>,
}

impl KeyframeData {
    /// Both held, spilling with `spill`.
    pub fn new(spill: &Spill, image: CompactFrame, depth: CompactDepth) -> Self {
        let image = Stored::new(spill, Arc::new(image));
        let depth = image.sibling(Arc::new(depth));
        Self { image, depth }
    }

    /// The same image with another depth (a refined or final one).
    pub fn with_depth(&self, depth: CompactDepth) -> Self {
        Self {
            image: Arc::clone(&self.image),
            depth: self.image.sibling(Arc::new(depth)),
        }
    }

    /// The full frame, its pyramid recomputed (read back first when spilled).
    pub fn frame(&self) -> Result<Frame> {
        self.image.get()?.rebuild()
    }

    /// The full depth map (read back first when spilled).
    pub fn depth_map(&self) -> Result<DepthMap> {
        Ok(self.depth.get()?.expand())
    }

    /// Spills both to the session's store; a failing store keeps them in memory (logged).
    pub fn spill(&self) {
        if let Err(e) = self.image.spill().and_then(|()| self.depth.spill()) {
            tracing::warn!(error = %e, "keyframe kept in memory: spilling failed");
        }
    }

    /// Whether the image is in memory (not spilled).
    pub fn is_held(&self) -> bool {
        self.image.is_held()
    }

    /// Bytes held in memory (shared buffers counted in full).
    pub fn held_bytes(&self) -> usize {
        self.image.held_bytes() + self.depth.held_bytes()
    }
}

/// A new keyframe's full frame and depth map as the command that hands it to the back end
/// holds them.
#[derive(Clone, Debug)]
pub enum KeyframeMaps {
    /// Held by the command; `data` is their compact form when the caller keeps one.
    Held {
        frame: Arc<Frame>,
        depth: Arc<DepthMap>,
        data: Option<KeyframeData>,
    },
    /// Shared with the front end, which keeps the full maps of its newest keyframes only:
    /// a command waiting in a long queue (a back end fallen behind) does not keep them alive,
    /// and they are rebuilt, identical, from `data` when the front end has let go of them.
    /// Queued keyframes so cost their compact form alone (issue 37: at 640×480 the full maps
    /// are about 8 MB a keyframe, and a queue of 256 commands held 1.2 GB).
    Shared {
        frame: Weak<Frame>,
        depth: Weak<DepthMap>,
        data: KeyframeData,
    },
}

impl KeyframeMaps {
    /// The full frame and depth map (rebuilt when shared and let go of) and the compact form.
    pub fn resolve(self) -> Result<(Arc<Frame>, Arc<DepthMap>, Option<KeyframeData>)> {
        match self {
            KeyframeMaps::Held { frame, depth, data } => Ok((frame, depth, data)),
            KeyframeMaps::Shared { frame, depth, data } => {
                let frame = match frame.upgrade() {
                    Some(frame) => frame,
                    None => Arc::new(data.frame()?),
                };
                let depth = match depth.upgrade() {
                    Some(depth) => depth,
                    None => Arc::new(data.depth_map()?),
                };
                Ok((frame, depth, Some(data)))
            }
        }
    }
}

/// A keyframe as the back end keeps it between uses (issue 37): its image without the pyramid
/// and its depth (in memory or spilled), its descriptor and the figures the candidate search
/// reads. The [`Keyframe`] it was made from comes back with [`CompactKeyframe::rebuild`],
/// identical.
#[derive(Clone, Debug)]
pub struct CompactKeyframe {
    pub id: KeyframeId,
    pub data: KeyframeData,
    /// Undistorted camera of level 0.
    pub camera: PinholeCamera,
    pub thumbnail: Thumbnail,
    /// [`KeyframeLevels::mean_idepth`].
    pub mean_idepth: f64,
    /// [`KeyframeLevels::estimates`].
    pub estimates: usize,
    /// [`Keyframe::finest_level`].
    pub finest_level: usize,
}

impl CompactKeyframe {
    /// The full keyframe: pyramid and alignment levels recomputed.
    pub fn rebuild(&self) -> Result<Keyframe> {
        Keyframe::from_level(
            self.id,
            Arc::new(self.data.frame()?),
            Arc::new(self.data.depth_map()?),
            self.finest_level,
        )
    }

    /// Horizontal and vertical field of view (radians).
    pub fn field_of_view(&self) -> (f64, f64) {
        let c = &self.camera;
        (
            2.0 * (f64::from(c.width) / (2.0 * c.fx)).atan(),
            2.0 * (f64::from(c.height) / (2.0 * c.fy)).atan(),
        )
    }

    /// Bytes held in memory: the compact image and the depth map unless spilled.
    pub fn heap_bytes(&self) -> usize {
        self.data.held_bytes()
    }
}

/// Whether two keyframes are close enough to try a constraint (LSD-SLAM's
/// `findEuclideanOverlapFrames` with `checkBothScales`): the squared distance between the
/// camera centres, in units of the smaller of the two mean scene depths, is at most
/// `close_distance / kf_dist_weight²`, and the optical axes differ by at most
/// `close_angle_fraction` of the mean field of view. Returns the squared distance when close.
pub fn pose_proximity(
    config: &BackendConfig,
    a: &CompactKeyframe,
    world_from_a: &Sim3,
    b: &CompactKeyframe,
    world_from_b: &Sim3,
) -> Option<f64> {
    // World distances × (mean inverse depth / world scale) = distances in units of the depth.
    let fac_a = a.mean_idepth / world_from_a.scale;
    let fac_b = b.mean_idepth / world_from_b.scale;
    let dist2 = (world_from_a.translation - world_from_b.translation).norm_squared()
        * fac_a.min(fac_b).powi(2);
    let limit = config.close_distance / (config.kf_dist_weight * config.kf_dist_weight);
    if dist2.is_nan() || dist2 > limit {
        return None;
    }
    let (fx, fy) = a.field_of_view();
    let cos_limit = (config.close_angle_fraction * 0.5 * (fx + fy)).cos();
    let axis_a = world_from_a.rotation.matrix().column(2).into_owned();
    let axis_b = world_from_b.rotation.matrix().column(2).into_owned();
    (axis_a.dot(&axis_b) >= cos_limit).then_some(dist2)
}

/// Squared Mahalanobis distance of `b_from_a · a_from_b` from the identity, for estimates with
/// right-perturbation informations `info_ba`, `info_ab`: `d = log(T_ba·T_ab)` varies as
/// `Ad(T_ab⁻¹)·δ_ba + δ_ab`, so `Σ_d = Ad(T_ab⁻¹)·Ω_ba⁻¹·Ad(T_ab⁻¹)ᵀ + Ω_ab⁻¹` and the result is
/// `dᵀ Σ_d⁻¹ d` (LSD-SLAM's `reciprocalConsistency`). `None` when an information is singular.
pub fn reciprocal_consistency(
    b_from_a: &Sim3,
    info_ba: &Matrix7,
    a_from_b: &Sim3,
    info_ab: &Matrix7,
) -> Option<f64> {
    let d = (*b_from_a * *a_from_b).log();
    let adj = a_from_b.inverse().adjoint();
    let cov = adj * info_ba.try_inverse()? * adj.transpose() + info_ab.try_inverse()?;
    let cov = 0.5 * (cov + cov.transpose());
    let m = d.dot(&(cov.try_inverse()? * d));
    m.is_finite().then_some(m)
}

/// Result of a reciprocal test between keyframes a and b.
#[derive(Clone, Debug, PartialEq)]
pub struct ReciprocalCheck {
    /// The two constraints `a → b` and `b → a` when accepted.
    pub constraints: Option<(Constraint, Constraint)>,
    /// The stage (0, 1, 2) at which the test stopped, `None` when accepted.
    pub failed_stage: Option<usize>,
    /// Squared Mahalanobis inconsistency of the last stage evaluated (∞ when an alignment
    /// was not good).
    pub consistency: f64,
    /// The two alignments of the last stage run (a as reference, then b as reference).
    pub forward: Option<Sim3TrackResult>,
    pub backward: Option<Sim3TrackResult>,
}

/// The staged reciprocal test of LSD-SLAM's `testConstraint`: for each stage, align b to a and
/// a to b (each from its previous estimate) on the stage's levels, and stop as soon as either is
/// not good or their inconsistency exceeds `stage_thresholds[k]·strictness`. Stage 0 runs from
/// [`BackendConfig::max_level`] down to `stage_levels[0]`, later stages on `stage_levels[k]`
/// alone. The accepted constraints carry the finest stage's informations.
pub fn reciprocal_test(
    tracker: &Sim3Tracker,
    a: &Keyframe,
    b: &Keyframe,
    initial_b_from_a: &Sim3,
    strictness: f64,
) -> ReciprocalCheck {
    let cfg = tracker.config();
    let mut b_from_a = *initial_b_from_a;
    let mut a_from_b = initial_b_from_a.inverse();
    let mut check = ReciprocalCheck {
        constraints: None,
        failed_stage: None,
        consistency: f64::INFINITY,
        forward: None,
        backward: None,
    };
    for (stage, (&level, &threshold)) in cfg
        .stage_levels
        .iter()
        .zip(&cfg.stage_thresholds)
        .enumerate()
    {
        let coarsest = if stage == 0 { cfg.max_level } else { level };
        let forward =
            tracker.track_levels(&a.levels, &b.frame, &b.levels, &b_from_a, coarsest, level);
        let good_forward = forward.good;
        b_from_a = forward.frame_from_reference;
        check.forward = Some(forward);
        if !good_forward {
            check.failed_stage = Some(stage);
            check.consistency = f64::INFINITY;
            return check;
        }
        let backward =
            tracker.track_levels(&b.levels, &a.frame, &a.levels, &a_from_b, coarsest, level);
        let good_backward = backward.good;
        a_from_b = backward.frame_from_reference;
        check.backward = Some(backward);
        if !good_backward {
            check.failed_stage = Some(stage);
            check.consistency = f64::INFINITY;
            return check;
        }
        let (Some(fw), Some(bw)) = (&check.forward, &check.backward) else {
            check.failed_stage = Some(stage);
            return check;
        };
        check.consistency =
            reciprocal_consistency(&b_from_a, &fw.information, &a_from_b, &bw.information)
                .unwrap_or(f64::INFINITY);
        if check.consistency.is_nan() || check.consistency > threshold * strictness {
            check.failed_stage = Some(stage);
            return check;
        }
    }
    if let (Some(fw), Some(bw)) = (&check.forward, &check.backward) {
        check.constraints = Some((
            Constraint {
                from: a.id,
                to: b.id,
                to_from_from: b_from_a,
                information: fw.information.into(),
            },
            Constraint {
                from: b.id,
                to: a.id,
                to_from_from: a_from_b,
                information: bw.information.into(),
            },
        ));
    }
    check
}
