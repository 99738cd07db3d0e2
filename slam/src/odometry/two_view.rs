//! The two-view geometry the initialiser's first map must agree with: corners of the first
//! frame tracked to the current one ([`super::klt`]), an essential matrix by RANSAC over the
//! normalised eight-point algorithm, its four decompositions tested by triangulation, and the
//! winner accepted only when it is clear and the parallax enough (ORB-SLAM's initialiser,
//! Mur-Artal et al., T-RO 2015 §IV: a clear winner among the reconstructions, at least 50
//! points, 50 of them with a parallax of 1°).
//!
//! Why: the photometric initialiser ([`super::init`]) optimises one frame at a time from a
//! flat map, and at the small baselines it snaps at it falls into the inverted map of the
//! bas-relief ambiguity in about half the starts, rendered video included; every such start
//! fails (docs/tuning.md, 2026-12-07). The essential matrix is a global solution: once the
//! parallax is a degree, it has the map's sign right on those same starts.

use std::sync::Arc;

use nalgebra::{DMatrix, Matrix3, SVD, Vector2, Vector3};

use super::klt;
use crate::frame::Frame;
use crate::geometry::{SE3, SO3};

/// Grid cell (level-0 pixels) of the first frame's corners: about 1200 at 640×480.
pub const CORNER_CELL: usize = 16;
/// RANSAC hypotheses (ORB-SLAM: 200 of eight points each).
const RANSAC_ITERATIONS: usize = 200;
/// Sampson distance, in pixels, of an inlier (about two standard deviations of tracks that
/// come back within half a pixel).
const INLIER_PIXELS: f64 = 1.0;
/// Reprojection error, in pixels, of a triangulated point that counts for its decomposition
/// (ORB-SLAM: 2 px at σ = 1).
const REPROJECTION_PIXELS: f64 = 2.0;
/// Fewest triangulated points a solution needs, and fewest tracks worth going on with
/// (ORB-SLAM's `minTriangulated`).
pub const MIN_POINTS: usize = 50;
/// Parallax, degrees, that the point ranked [`MIN_POINTS`] + 1 by parallax must have
/// (ORB-SLAM's `minParallax`, there of the point at index 50). The median's instead waits
/// longer: worse on forward motion (rendered f11 0.0011 → 0.0014 m over six starts;
/// docs/tuning.md, 2026-12-07).
const MIN_PARALLAX_DEGREES: f64 = 1.0;
/// The runner-up decomposition must triangulate fewer than this share of the winner's points
/// (ORB-SLAM: 0.7), and the winner at least [`WINNER_SHARE`] of the inliers (ORB-SLAM: 0.9).
const RUNNER_UP_SHARE: f64 = 0.7;
const WINNER_SHARE: f64 = 0.9;
/// Nearest triangulated corners whose median inverse depth a photometric point takes.
const NEAREST: usize = 5;
/// Frames of track history kept at most (5 s at 30 Hz): a camera that turns in place longer
/// gives no two-view solution, and the initialiser starts again from its newest frame.
pub const MAX_FRAMES: usize = 150;
/// Gauss–Newton iterations of a frame's pose from the triangulated corners.
const POSE_ITERATIONS: usize = 10;

/// A relative pose and map from two views.
#[derive(Clone, Debug)]
pub struct TwoViewSolution {
    /// The current frame's pose in the first frame's coordinates, `|t|` = 1.
    pub world_from_camera: SE3,
    /// The poses of the frames between the first and the current one (oldest first), from
    /// the same points.
    pub between: Vec<SE3>,
    /// Level-0 pixels of the first frame and the inverse depths there (same units).
    pub points: Vec<(Vector2<f64>, f64)>,
}

impl TwoViewSolution {
    /// The inverse depth at each of `pixels` of the first frame: the median of its
    /// [`NEAREST`] triangulated neighbours (1 without any).
    pub fn inverse_depths_at(&self, pixels: &[Vector2<f64>]) -> Vec<f64> {
        pixels
            .iter()
            .map(|p| {
                let mut near: Vec<(f64, f64)> = self
                    .points
                    .iter()
                    .map(|(q, d)| ((q - p).norm_squared(), *d))
                    .collect();
                let k = NEAREST.min(near.len());
                if k == 0 {
                    return 1.0;
                }
                near.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
                let mut depths: Vec<f64> = near[..k].iter().map(|n| n.1).collect();
                depths.sort_by(f64::total_cmp);
                depths[k / 2]
            })
            .collect()
    }
}

/// One `(R, t)` of an essential matrix and the inliers it triangulates: index, point in the
/// first camera, cosine of its parallax.
struct Decomposition {
    r: Matrix3<f64>,
    t: Vector3<f64>,
    points: Vec<(usize, Vector3<f64>, f64)>,
}

/// Corners of a first frame followed to the newest frame.
#[derive(Debug)]
pub struct TwoView {
    first: Arc<Frame>,
    previous: Arc<Frame>,
    /// Each live track: its corner in the first frame and where it is in `previous`.
    tracks: Vec<(Vector2<f64>, Vector2<f64>)>,
    /// Each live track's positions in the frames after the first (the last is in `tracks`).
    history: Vec<Vec<Vector2<f32>>>,
    /// Seed of the RANSAC sampler (xorshift): the same frames give the same solution.
    state: u64,
    /// Whether a frame has given the best decomposition [`MIN_PARALLAX_DEGREES`] of
    /// parallax, clear or not ([`Self::had_parallax`]).
    had_parallax: bool,
}

impl TwoView {
    pub fn new(first: Arc<Frame>) -> Self {
        let tracks: Vec<(Vector2<f64>, Vector2<f64>)> = klt::corners(first.level(0), CORNER_CELL)
            .into_iter()
            .map(|c| (c, c))
            .collect();
        Self {
            previous: first.clone(),
            first,
            history: vec![Vec::new(); tracks.len()],
            tracks,
            state: 0x9e37_79b9_7f4a_7c15,
            had_parallax: false,
        }
    }

    /// Whether the corners have had [`MIN_PARALLAX_DEGREES`] of parallax, the solution clear
    /// or not: DSO's snap (its parallax test, 2.5/150 ≈ 1° at the mean depth) measured on
    /// the corners, so the initialiser needs no photometric step per frame to time its wait.
    pub fn had_parallax(&self) -> bool {
        self.had_parallax
    }

    /// Tracks still followed.
    pub fn tracks(&self) -> usize {
        self.tracks.len()
    }

    /// Frames followed after the first.
    pub fn frames(&self) -> usize {
        self.history.first().map_or(0, Vec::len)
    }

    /// Follows the tracks into `frame`; the solution once it is clear and has parallax.
    pub fn push(&mut self, frame: &Arc<Frame>) -> Option<TwoViewSolution> {
        let now: Vec<Vector2<f64>> = self.tracks.iter().map(|t| t.1).collect();
        let found = klt::track(&self.previous.pyramid, &frame.pyramid, &now);
        let mut history = std::mem::take(&mut self.history).into_iter();
        let (tracks, history) = self
            .tracks
            .iter()
            .zip(found)
            .filter_map(|(t, f)| {
                let mut h = history.next().unwrap_or_default();
                let f = f?;
                h.push(f.cast());
                Some(((t.0, f), h))
            })
            .unzip();
        (self.tracks, self.history) = (tracks, history);
        self.previous = frame.clone();
        if self.tracks.len() < MIN_POINTS {
            return None;
        }
        self.solve(frame)
    }

    fn solve(&mut self, frame: &Frame) -> Option<TwoViewSolution> {
        let (c0, c1) = (&self.first.camera, &frame.camera);
        let a: Vec<Vector3<f64>> = self
            .tracks
            .iter()
            .map(|t| c0.unproject(&t.0, 1.0))
            .collect();
        let b: Vec<Vector3<f64>> = self
            .tracks
            .iter()
            .map(|t| c1.unproject(&t.1, 1.0))
            .collect();
        let focal = 0.5 * (c1.fx + c1.fy);
        let threshold = INLIER_PIXELS / focal;
        let (essential, inliers) =
            essential_ransac(&a, &b, threshold, RANSAC_ITERATIONS, &mut self.state)?;
        let inlier_count = inliers.iter().filter(|i| **i).count();
        let limit = REPROJECTION_PIXELS / focal;
        // Each decomposition with the inliers it triangulates: (index, point, parallax cosine).
        let mut solutions: Vec<Decomposition> = decompose(&essential)
            .into_iter()
            .map(|(r, t)| Decomposition {
                points: (0..a.len())
                    .filter(|&i| inliers[i])
                    .filter_map(|i| {
                        triangulate(&r, &t, &a[i], &b[i], limit).map(|(x, cos)| (i, x, cos))
                    })
                    .collect(),
                r,
                t,
            })
            .collect();
        solutions.sort_by_key(|s| std::cmp::Reverse(s.points.len()));
        let Decomposition { r, t, points } = solutions.swap_remove(0);
        let good = points.len();
        let runner_up = solutions.iter().map(|s| s.points.len()).max().unwrap_or(0);
        if good < MIN_POINTS {
            return None;
        }
        let mut parallax: Vec<f64> = points.iter().map(|p| p.2.clamp(-1.0, 1.0).acos()).collect();
        parallax.sort_by(f64::total_cmp);
        let parallax_degrees = parallax[parallax.len().saturating_sub(MIN_POINTS + 1)].to_degrees();
        if parallax_degrees < MIN_PARALLAX_DEGREES {
            return None;
        }
        self.had_parallax = true;
        if (good as f64) < WINNER_SHARE * inlier_count as f64
            || runner_up as f64 >= RUNNER_UP_SHARE * good as f64
        {
            return None;
        }
        let camera_from_first = SE3::new(SO3::from_matrix(&r), t);
        // Every frame in between posed from the same points, starting from the identity.
        let frames = self.frames();
        let mut between = Vec::with_capacity(frames.saturating_sub(1));
        let mut guess = SE3::identity();
        for k in 0..frames.saturating_sub(1) {
            let seen: Vec<(Vector3<f64>, Vector3<f64>)> = points
                .iter()
                .map(|(i, x, _)| (*x, c1.unproject(&self.history[*i][k].cast(), 1.0)))
                .collect();
            guess = pose_from_points(&seen, guess, limit);
            between.push(guess.inverse());
        }
        Some(TwoViewSolution {
            between,
            world_from_camera: camera_from_first.inverse(),
            points: points
                .iter()
                .map(|(i, x, _)| (self.tracks[*i].0, 1.0 / x.z))
                .collect(),
        })
    }
}

/// The pose (`camera_from_world`) that projects the points `seen` (world point, bearing with
/// `z` = 1) best, by Gauss–Newton from `guess` with Huber weights of width `huber`.
fn pose_from_points(seen: &[(Vector3<f64>, Vector3<f64>)], guess: SE3, huber: f64) -> SE3 {
    let mut pose = guess;
    for _ in 0..POSE_ITERATIONS {
        let mut h = nalgebra::Matrix6::<f64>::zeros();
        let mut g = nalgebra::Vector6::<f64>::zeros();
        for (x, bearing) in seen {
            let c = pose.act(x);
            if c.z <= 1e-9 {
                continue;
            }
            let r = c.xy() / c.z - bearing.xy();
            let norm = r.norm();
            let w = if norm <= huber { 1.0 } else { huber / norm };
            let projection = nalgebra::Matrix2x3::new(
                1.0 / c.z,
                0.0,
                -c.x / (c.z * c.z),
                0.0,
                1.0 / c.z,
                -c.y / (c.z * c.z),
            );
            // A left perturbation exp(δ)·pose moves c by v + ω × c.
            let mut motion = nalgebra::Matrix3x6::<f64>::zeros();
            motion.fixed_view_mut::<3, 3>(0, 0).fill_with_identity();
            motion
                .fixed_view_mut::<3, 3>(0, 3)
                .copy_from(&(-c.cross_matrix()));
            let j = projection * motion;
            h += w * j.transpose() * j;
            g += w * j.transpose() * r;
        }
        let Some(step) = h.cholesky().map(|c| c.solve(&-g)) else {
            break;
        };
        pose = SE3::exp(&step) * pose;
        if step.norm() < 1e-10 {
            break;
        }
    }
    pose
}

/// xorshift64*: uniform index below `n`.
fn next_index(state: &mut u64, n: usize) -> usize {
    *state ^= *state >> 12;
    *state ^= *state << 25;
    *state ^= *state >> 27;
    (state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 33) as usize % n
}

/// Sampson distance of the pair `(a, b)` (bearings, `z` = 1) under `e` (`b' E a = 0`).
fn sampson(e: &Matrix3<f64>, a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let ea = e * a;
    let eb = e.transpose() * b;
    let num = b.dot(&ea);
    let den = ea.x * ea.x + ea.y * ea.y + eb.x * eb.x + eb.y * eb.y;
    if den <= 0.0 {
        return f64::INFINITY;
    }
    num.abs() / den.sqrt()
}

/// The essential matrix of the pairs `indices` by the normalised eight-point algorithm
/// (Hartley 1997), projected onto essential matrices (two equal singular values, one zero).
fn eight_point(a: &[Vector3<f64>], b: &[Vector3<f64>], indices: &[usize]) -> Option<Matrix3<f64>> {
    let normaliser = |points: &mut dyn Iterator<Item = &Vector3<f64>>| {
        let p: Vec<Vector2<f64>> = points.map(|v| v.xy()).collect();
        let n = p.len() as f64;
        let mean = p.iter().sum::<Vector2<f64>>() / n;
        let spread = p.iter().map(|q| (q - mean).norm()).sum::<f64>() / n;
        let s = if spread > 1e-12 {
            2f64.sqrt() / spread
        } else {
            1.0
        };
        Matrix3::new(s, 0.0, -s * mean.x, 0.0, s, -s * mean.y, 0.0, 0.0, 1.0)
    };
    let ta = normaliser(&mut indices.iter().map(|&i| &a[i]));
    let tb = normaliser(&mut indices.iter().map(|&i| &b[i]));
    let mut m = DMatrix::zeros(indices.len().max(9), 9);
    for (row, &i) in indices.iter().enumerate() {
        let (p, q) = (ta * a[i], tb * b[i]);
        for r in 0..3 {
            for c in 0..3 {
                m[(row, 3 * r + c)] = q[r] * p[c];
            }
        }
    }
    let svd = SVD::new(m, false, true);
    let v_t = svd.v_t?;
    let smallest = svd
        .singular_values
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))?
        .0;
    let e = Matrix3::from_row_slice(v_t.row(smallest).transpose().as_slice());
    let e = tb.transpose() * e * ta;
    let svd = e.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let s = 0.5 * (svd.singular_values[0] + svd.singular_values[1]);
    let mut sigma = svd.singular_values;
    // nalgebra sorts singular values in decreasing order.
    sigma[0] = s;
    sigma[1] = s;
    sigma[2] = 0.0;
    let e = u * Matrix3::from_diagonal(&sigma) * v_t;
    (s > 0.0 && e.iter().all(|x| x.is_finite())).then(|| e / e.norm())
}

/// RANSAC over [`eight_point`]: the essential matrix with most pairs within `threshold`
/// (Sampson, normalised units), refitted on them; `None` with fewer than eight pairs.
pub fn essential_ransac(
    a: &[Vector3<f64>],
    b: &[Vector3<f64>],
    threshold: f64,
    iterations: usize,
    state: &mut u64,
) -> Option<(Matrix3<f64>, Vec<bool>)> {
    let n = a.len();
    if n < 8 || b.len() != n {
        return None;
    }
    let is_inlier = |e: &Matrix3<f64>, i: usize| sampson(e, &a[i], &b[i]) <= threshold;
    let inliers_of = |e: &Matrix3<f64>| -> Vec<bool> { (0..n).map(|i| is_inlier(e, i)).collect() };
    let mut best: Option<(usize, Matrix3<f64>)> = None;
    for _ in 0..iterations {
        let mut sample = Vec::with_capacity(8);
        while sample.len() < 8 {
            let i = next_index(state, n);
            if !sample.contains(&i) {
                sample.push(i);
            }
        }
        let Some(e) = eight_point(a, b, &sample) else {
            continue;
        };
        let count = (0..n).filter(|&i| is_inlier(&e, i)).count();
        if best.as_ref().is_none_or(|(c, _)| count > *c) {
            best = Some((count, e));
        }
    }
    let (_, e) = best?;
    let inliers = inliers_of(&e);
    let chosen: Vec<usize> = (0..n).filter(|&i| inliers[i]).collect();
    let refit = (chosen.len() >= 8)
        .then(|| eight_point(a, b, &chosen))
        .flatten()
        .unwrap_or(e);
    let refit_inliers = inliers_of(&refit);
    if refit_inliers.iter().filter(|i| **i).count() >= chosen.len() {
        Some((refit, refit_inliers))
    } else {
        Some((e, inliers))
    }
}

/// The four `(R, t)` of an essential matrix (`b = R a + t`, `|t|` = 1).
pub fn decompose(e: &Matrix3<f64>) -> Vec<(Matrix3<f64>, Vector3<f64>)> {
    let svd = e.svd(true, true);
    let (Some(mut u), Some(mut v_t)) = (svd.u, svd.v_t) else {
        return Vec::new();
    };
    if u.determinant() < 0.0 {
        u = -u;
    }
    if v_t.determinant() < 0.0 {
        v_t = -v_t;
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let t: Vector3<f64> = u.column(2).into();
    let r1 = u * w * v_t;
    let r2 = u * w.transpose() * v_t;
    vec![(r1, t), (r1, -t), (r2, t), (r2, -t)]
}

/// The point (first camera's coordinates) seen along bearings `a` (first camera) and `b`
/// (second, `b ∝ R x + t`), by the midpoint of the two rays, with the cosine of its parallax;
/// `None` behind either camera or reprojecting farther than `limit` (normalised units).
fn triangulate(
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    limit: f64,
) -> Option<(Vector3<f64>, f64)> {
    // Rays: x = s·a (first camera), x = c + u·d (second camera's centre and bearing).
    let centre = -r.transpose() * t;
    let d = r.transpose() * b;
    let m = nalgebra::Matrix2::new(a.dot(a), -a.dot(&d), a.dot(&d), -d.dot(&d));
    let rhs = Vector2::new(a.dot(&centre), d.dot(&centre));
    let su = m.try_inverse()? * rhs;
    let x = 0.5 * (a * su.x + centre + d * su.y);
    let y = r * x + t;
    if x.z <= 0.0 || y.z <= 0.0 {
        return None;
    }
    let error_a = (x.xy() / x.z - a.xy()).norm();
    let error_b = (y.xy() / y.z - b.xy()).norm();
    if error_a > limit || error_b > limit {
        return None;
    }
    let cos = x.normalize().dot(&(x - centre).normalize());
    Some((x, cos))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points in front of both cameras of a known motion, as bearings.
    fn scene(r: &Matrix3<f64>, t: &Vector3<f64>) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
        let mut state = 7u64;
        let mut a = Vec::new();
        let mut b = Vec::new();
        for _ in 0..200 {
            let x = (next_index(&mut state, 1000) as f64 / 1000.0 - 0.5) * 2.0;
            let y = (next_index(&mut state, 1000) as f64 / 1000.0 - 0.5) * 1.5;
            let z = 2.0 + next_index(&mut state, 1000) as f64 / 500.0;
            let p = Vector3::new(x, y, z);
            let q = r * p + t;
            a.push(p / p.z);
            b.push(q / q.z);
        }
        (a, b)
    }

    #[test]
    fn the_essential_matrix_and_its_decomposition_recover_a_known_motion() {
        let r = SO3::exp(&Vector3::new(0.02, -0.05, 0.01)).matrix();
        let t = Vector3::new(0.3, 0.05, 0.02);
        let (a, mut b) = scene(&r, &t);
        // A fifth of the pairs wrong.
        for q in b.iter_mut().step_by(5) {
            q.x += 0.05;
        }
        let mut state = 1u64;
        let (e, inliers) = essential_ransac(&a, &b, 1e-3, 200, &mut state).expect("solved");
        let count = inliers.iter().filter(|i| **i).count();
        assert!((155..=161).contains(&count), "{count} inliers of 200");
        let best = decompose(&e)
            .into_iter()
            .max_by_key(|(rr, tt)| {
                (0..a.len())
                    .filter(|&i| inliers[i] && triangulate(rr, tt, &a[i], &b[i], 1e-3).is_some())
                    .count()
            })
            .expect("four decompositions");
        let angle = SO3::from_matrix(&(best.0 * r.transpose())).angle();
        assert!(angle < 1e-6, "rotation off by {angle} rad");
        let direction = best.1.dot(&t.normalize());
        assert!(
            direction > 1.0 - 1e-9,
            "translation direction cos {direction}"
        );
    }

    #[test]
    fn triangulation_refuses_points_behind_a_camera() {
        let r = Matrix3::identity();
        let t = Vector3::new(-0.1, 0.0, 0.0);
        let p = Vector3::new(0.2, 0.1, 2.0);
        let q = r * p + t;
        let (x, cos) = triangulate(&r, &t, &(p / p.z), &(q / q.z), 1e-6).expect("in front");
        assert!((x - p).norm() < 1e-9 && cos < 1.0);
        assert!(triangulate(&r, &-t, &(p / p.z), &(q / q.z), 1e-6).is_none());
    }
}
