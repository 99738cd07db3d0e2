//! Initialisation without a prior shape: the first frame's points start at inverse depth 1
//! and are optimised jointly with the pose of each following frame, coarse to fine, until the
//! translation gives enough parallax (DSO's coarse initialiser, TPAMI 2018 §3.1,
//! `CoarseInitializer.cpp`, in our own words).
//!
//! Why: a first keyframe whose shape is taken from a single-image prior or random depths is
//! almost flat, and the LSD-style loop never recovers from it (issue 35: slope 0.10-0.15 for
//! 5 s). Here the shape is measured: by the time the first keyframe is made, every point's
//! depth is what the parallax of the first frames says.
//!
//! Alone, that optimisation falls at its small baselines into the inverted map of the
//! bas-relief ambiguity in about half the starts, and every such start fails (docs/tuning.md,
//! 2026-12-07). So by default ([`OdometryConfig::init_two_view`]) the hand-over waits for the
//! two-view geometry of tracked corners ([`super::two_view`], ORB-SLAM's rule): its
//! triangulated depths start the map again, and the frames so far are posed from them; when
//! the corners are lost or give no clear solution, the initialisation starts again from the
//! newest frame, as ORB-SLAM's does.

use std::sync::Arc;

use nalgebra::Vector2;

use super::residual::FrameState;
use super::select::select_candidates;
use super::two_view::{self, TwoView, TwoViewSolution};
use super::{Anchor, DepthPrior, OdometryConfig, SlidingWindow, SolveReport};
use crate::frame::Frame;
use crate::geometry::SE3;

/// Weight of the prior that keeps the handed-over depths near the initialiser's values in
/// the window (DSO's `setting_idepthFixPrior` = 50², with inverse depths of mean 1): until
/// the keyframes that measured them leave, they hold the scale the initialiser chose.
pub const HANDOVER_PRIOR_WEIGHT: f64 = 50.0 * 50.0;
/// Coarsest pyramid level the initialiser starts on (80×60 at 640×480).
const COARSEST: usize = 3;
/// The initialiser has parallax once `ALPHA_WEIGHT · (mean (ρ − 1)² + |t|²)` exceeds this
/// (DSO's `alphaK` = 2.5²): with the translation charged [`ALPHA_WEIGHT`] per point, it only
/// grows that far when the images demand it.
const ALPHA_LIMIT: f64 = 2.5 * 2.5;
/// Frames optimised after parallax was reached before the first keyframe is made (DSO: 5).
const FRAMES_AFTER_SNAP: usize = 5;
/// Weight pulling every inverse depth to 1 until there is parallax (DSO's `alphaW` = 150²):
/// without translation a depth is unobservable, and left free it wanders off by orders of
/// magnitude (measured: log-inverse-depth spread 4.9 on a near-planar synthetic scene whose
/// true spread is 0.06), a start from which the later frames do not recover.
const ALPHA_WEIGHT: f64 = 150.0 * 150.0;
/// Weight coupling each inverse depth to its smoothed neighbourhood once there is parallax
/// (DSO's `couplingWeight` = 1): it decides only the points the photometric error leaves
/// unconstrained (no gradient along their epipolar line).
const COUPLING_WEIGHT: f64 = 1.0;
/// Frames kept for [`Initialiser::score`] at most: when one more comes, every other is
/// dropped (the newest kept), so that they span the whole baseline at any length and a
/// camera that turns in place for minutes holds no more than these.
pub const SCORE_FRAMES: usize = 12;
/// Gauss–Newton iterations per level of [`Initialiser::score`].
const SCORE_ITERATIONS: usize = 10;
/// Frames after the corners' snap ([`TwoView::had_parallax`]) the initialiser waits for their
/// two-view geometry to become clear (2 s at 30 Hz); a camera whose tracks give none by then
/// starts again from its newest frame, whose motion may give one (ORB-SLAM's initialiser
/// restarts too).
const TWO_VIEW_WAIT: usize = 60;
/// Neighbours of a point in its smoothed target (DSO: 10) and the share of their median in it
/// (DSO's `regWeight` = 0.8).
const NEIGHBOURS: usize = 10;
const NEIGHBOUR_SHARE: f64 = 0.8;

/// The first keyframe and what the initialiser measured.
#[derive(Clone, Debug)]
pub struct Initialised {
    pub first: Arc<Frame>,
    /// Level-0 pixels of the first frame's points and their inverse depths.
    pub points: Vec<(Vector2<f64>, f64)>,
    /// `world_from_camera` of the frames given so far (the first is the identity).
    pub poses: Vec<SE3>,
    /// Frames given before `first`, not in `poses`: the initialisation started again from
    /// `first` when they gave no two-view solution (ORB-SLAM's initialiser does the same).
    pub skipped: usize,
}

/// Replaces the initialiser's first map before the window starts from it: a probe, not an
/// estimator (`relfusion bench odometry --oracle-first-map` gives it the sensor's depth shape to
/// measure how much a run owes to its first map). Given the first frame and the handed-over
/// `(pixel, inverse depth)` points (mean 1), it returns the points to start from.
#[derive(Clone)]
pub struct FirstMap(
    pub Arc<dyn Fn(&Frame, &[(Vector2<f64>, f64)]) -> Vec<(Vector2<f64>, f64)> + Send + Sync>,
);

impl std::fmt::Debug for FirstMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FirstMap")
    }
}

/// The `k` nearest other points of each of `points` (image distance).
fn nearest_neighbours(points: &[Vector2<f64>], k: usize) -> Vec<Vec<usize>> {
    points
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let mut by_distance: Vec<(f64, usize)> = points
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(j, b)| ((a - b).norm_squared(), j))
                .collect();
            let k = k.min(by_distance.len());
            if k > 0 {
                by_distance.select_nth_unstable_by(k - 1, |x, y| x.0.total_cmp(&y.0));
            }
            by_distance.truncate(k);
            by_distance.into_iter().map(|(_, j)| j).collect()
        })
        .collect()
}

/// Coarse initialiser state.
#[derive(Debug)]
pub struct Initialiser {
    config: OdometryConfig,
    first: Arc<Frame>,
    points: Vec<(Vector2<f64>, f64)>,
    /// Each point's [`NEIGHBOURS`] nearest points in the first image.
    neighbours: Vec<Vec<usize>>,
    /// Each point's smoothed inverse depth, the target of [`COUPLING_WEIGHT`].
    smoothed: Vec<f64>,
    poses: Vec<SE3>,
    frames_since_snap: Option<usize>,
    /// Frames after the first for [`Initialiser::score`] with their index in `poses`; kept
    /// only when `config.focal_candidates` asks for a comparison.
    scored: Vec<(usize, Arc<Frame>)>,
    /// The corners of the first frame followed for the two-view check; `None` once it seeded
    /// the map, or when it is off.
    two_view: Option<TwoView>,
    /// Points asked for at the start (kept for a restart).
    target: usize,
    /// Frames before `first` given no pose ([`Initialised::skipped`]).
    skipped: usize,
}

impl Initialiser {
    /// Starts from `first` with about `points` candidates at inverse depth 1.
    pub fn new(config: &OdometryConfig, first: Arc<Frame>, points: usize) -> Self {
        let candidates = select_candidates(first.level(0), points);
        let neighbours = nearest_neighbours(&candidates, NEIGHBOURS);
        Self {
            config: config.clone(),
            smoothed: vec![1.0; candidates.len()],
            points: candidates.into_iter().map(|uv| (uv, 1.0)).collect(),
            neighbours,
            first: first.clone(),
            poses: vec![SE3::identity()],
            frames_since_snap: None,
            scored: Vec::new(),
            two_view: config.init_two_view.then(|| TwoView::new(first.clone())),
            target: points,
            skipped: 0,
        }
    }

    /// Optimises `frame`'s pose with the first frame's depths (DSO's initialiser alone, or
    /// after the two-view seed); `Some` once there has been parallax for [`FRAMES_AFTER_SNAP`]
    /// frames and the baseline is `init_min_parallax` mean depths. Before the snap the depths
    /// are held at 1 and `|t|` is that ratio; after it the scale is free (the mean inverse
    /// depth drifted to 0.04 on redkitchen 0-299, where the five frames alone hand over at
    /// 0.0097 mean depths and an inverted first map). Like DSO's, it waits as long as the
    /// camera does not translate: without parallax a monocular camera has no map to start
    /// from. With the two-view check on, the hand-over comes with its solution instead
    /// ([`Self::seed`]), and until then a frame costs only its corner tracking (7-63 ms at
    /// 640×480 on fr1/rpy; the photometric step's 80-130 ms left a live camera seconds behind
    /// at the hand-over, docs/tuning.md 2026-12-07); when its corners are lost, followed for
    /// [`two_view::MAX_FRAMES`] frames or for [`TWO_VIEW_WAIT`] after their snap without one,
    /// the initialisation starts again from `frame`.
    pub fn push(&mut self, frame: Arc<Frame>) -> Option<Initialised> {
        let pose = if self.two_view.is_some() {
            // Posed from the corners at the seed.
            SE3::identity()
        } else {
            let n = self.poses.len();
            let guess = match n {
                1 => SE3::identity(),
                _ => {
                    let (a, b) = (self.poses[n - 2], self.poses[n - 1]);
                    b * (a.inverse() * b)
                }
            };
            self.optimize(&frame, guess)
        };
        self.poses.push(pose);
        if self.config.focal_candidates.len() > 1 {
            self.scored.push((self.poses.len() - 1, frame.clone()));
            if self.scored.len() > SCORE_FRAMES {
                let newest = self.scored.len() - 1;
                let mut i = 0;
                self.scored.retain(|_| {
                    i += 1;
                    (newest + 1 - i) % 2 == 0
                });
            }
        }
        if let Some(view) = self.two_view.as_mut() {
            let solution = view.push(&frame);
            if view.had_parallax() {
                *self.frames_since_snap.get_or_insert(0) += 1;
            }
            if let Some(solution) = solution {
                self.seed(&solution, &frame);
            } else if view.tracks() < two_view::MIN_POINTS
                || view.frames() >= two_view::MAX_FRAMES
                || self.frames_since_snap.is_some_and(|s| s > TWO_VIEW_WAIT)
            {
                let skipped = self.skipped + self.poses.len() - 1;
                *self = Self::new(&self.config, frame, self.target);
                self.skipped = skipped;
                return None;
            }
        } else if self.frames_since_snap.is_some() || self.alpha_energy(&pose) > ALPHA_LIMIT {
            let since = self.frames_since_snap.get_or_insert(0);
            *since += 1;
        }
        let pose = *self.poses.last().expect("a pose per frame");
        if self.two_view.is_none()
            && self
                .frames_since_snap
                .is_some_and(|s| s >= FRAMES_AFTER_SNAP)
            && self.parallax(&pose) >= self.config.init_min_parallax
        {
            return Some(self.finish());
        }
        None
    }

    /// Starts the map again from the two-view `solution` for `frame` (the newest): every
    /// point's inverse depth from the corners triangulated near it, rescaled to a mean of 1,
    /// and the frame's pose from the essential matrix, refined with them; the frames between
    /// take the poses the solution gives them. The map is then handed over at once, as
    /// ORB-SLAM's two-view map is: the window refines it with every frame that follows.
    fn seed(&mut self, solution: &TwoViewSolution, frame: &Arc<Frame>) {
        let pixels: Vec<Vector2<f64>> = self.points.iter().map(|p| p.0).collect();
        let depths = solution.inverse_depths_at(&pixels);
        let mean = depths.iter().sum::<f64>() / depths.len().max(1) as f64;
        if !(mean.is_finite() && mean > 0.0) {
            return;
        }
        for (p, d) in self.points.iter_mut().zip(depths) {
            p.1 = d / mean;
        }
        self.smooth();
        let guess = SE3::new(
            solution.world_from_camera.rotation,
            solution.world_from_camera.translation * mean,
        );
        self.frames_since_snap = Some(FRAMES_AFTER_SNAP);
        self.two_view = None;
        let pose = self.optimize(frame, guess);
        let last = self.poses.len() - 1;
        for (slot, between) in self.poses[1..last].iter_mut().zip(&solution.between) {
            *slot = SE3::new(between.rotation, between.translation * mean);
        }
        self.poses[last] = pose;
    }

    /// The baseline from the first frame to `pose` times the first frame's mean inverse
    /// depth: the parallax the depths rest on, whatever scale the optimisation drifted to.
    fn parallax(&self, pose: &SE3) -> f64 {
        pose.translation.norm() * self.mean_idepth()
    }

    /// The baseline of the latest frame in mean depths of the first ([`Self::parallax`]).
    pub fn baseline(&self) -> f64 {
        self.poses.last().map_or(0.0, |p| self.parallax(p))
    }

    fn mean_idepth(&self) -> f64 {
        self.points.iter().map(|(_, d)| d).sum::<f64>() / self.points.len().max(1) as f64
    }

    /// The result with the inverse depths rescaled to a mean of 1 and the translations with
    /// them: DSO's units, in which [`HANDOVER_PRIOR_WEIGHT`] means the same in every scene.
    /// DSO hands over the smoothed depths; the optimised ones did better here
    /// (docs/tuning.md, 2026-11-28).
    pub fn finish(&self) -> Initialised {
        let mean = self.mean_idepth();
        let factor = if mean.is_finite() && mean > 0.0 {
            1.0 / mean
        } else {
            1.0
        };
        Initialised {
            first: self.first.clone(),
            points: self
                .points
                .iter()
                .map(|(uv, d)| (*uv, d * factor))
                .collect(),
            poses: self
                .poses
                .iter()
                .map(|p| SE3::new(p.rotation, p.translation / factor))
                .collect(),
            skipped: self.skipped,
        }
    }

    /// Joint optimisation of the first frame's depths and `frame`'s pose, coarse to fine.
    fn optimize(&mut self, frame: &Arc<Frame>, guess: SE3) -> SE3 {
        let mut pose = guess;
        let top = COARSEST.min(frame.pyramid.levels.len() - 1);
        let snapped = self.frames_since_snap.is_some();
        let translation_weight = if snapped {
            0.0
        } else {
            ALPHA_WEIGHT * self.points.len() as f64
        };
        for level in (0..=top).rev() {
            let depths: Vec<f64> = self.points.iter().map(|p| p.1).collect();
            let prior = |i: usize| {
                if snapped {
                    DepthPrior::quadratic(self.smoothed[i], COUPLING_WEIGHT)
                } else {
                    DepthPrior::quadratic(1.0, ALPHA_WEIGHT)
                }
            };
            let Some((poses, depths, _)) = self.solve_level(
                level,
                8,
                &[(frame, pose)],
                &depths,
                prior,
                translation_weight,
            ) else {
                return pose;
            };
            pose = poses[0];
            for (p, d) in self.points.iter_mut().zip(depths) {
                p.1 = d;
            }
            self.smooth();
        }
        pose
    }

    /// One level of a joint optimisation of the first frame's point depths (from `depths`,
    /// each pulled to `prior(i)`) and the poses of `views` (frames with their poses relative
    /// to the first frame, which is held; later translations charged `translation_weight`).
    /// Returns the views' poses re-expressed in the first frame's coordinates (the gauge-free
    /// step may move it), the depths (unchanged for points outside the level) and the
    /// solver's report; `None` when the window cannot be built.
    fn solve_level(
        &self,
        level: usize,
        iterations: usize,
        views: &[(&Arc<Frame>, SE3)],
        depths: &[f64],
        prior: impl Fn(usize) -> DepthPrior,
        translation_weight: f64,
    ) -> Option<(Vec<SE3>, Vec<f64>, SolveReport)> {
        let config = OdometryConfig {
            level,
            iterations,
            ..self.config.clone()
        };
        let mut window = SlidingWindow::new(config).ok()?;
        let state = |pose: SE3| FrameState {
            world_from_camera: pose,
            affine: (0.0, 0.0),
        };
        window
            .add_frame(0, self.first.clone(), state(SE3::identity()))
            .ok()?;
        for (k, (frame, pose)) in views.iter().enumerate() {
            window
                .add_frame(k as u64 + 1, (*frame).clone(), state(*pose))
                .ok()?;
        }
        window.set_anchor(Some(Anchor { translation_weight }));
        let factor = f64::from(1u32 << level);
        let mut kept = Vec::new();
        for (i, ((uv, _), idepth)) in self.points.iter().zip(depths).enumerate() {
            if window.add_point(0, uv / factor, *idepth, Some(prior(i))) {
                kept.push(i);
            }
        }
        let report = window.optimize();
        let first = window.frames()[0].state.world_from_camera.inverse();
        let poses = (1..=views.len())
            .map(|k| first * window.frames()[k].state.world_from_camera)
            .collect();
        let mut depths = depths.to_vec();
        for (&i, p) in kept.iter().zip(window.points()) {
            depths[i] = p.idepth;
        }
        Some((poses, depths, report))
    }

    /// How well the first frame's depths and the frames' poses fit the images together: the
    /// photometric energy per inlier residual after a joint optimisation of the depths and
    /// the poses of the kept frames ([`SCORE_FRAMES`]), coarse to fine, on a copy. Why:
    /// under a wrong focal length no map and poses fit every frame at once, so the energy is
    /// least at the right one (rendered and real sequences, docs/tuning.md, 2026-12-07); the
    /// initialiser's own optimisation sees one frame at a time. Infinite without frames
    /// (only kept when `focal_candidates` asks for a comparison).
    pub fn score(&self) -> f64 {
        if self.scored.is_empty() {
            return f64::INFINITY;
        }
        let mut depths: Vec<f64> = self.points.iter().map(|p| p.1).collect();
        let mut poses: Vec<SE3> = self.scored.iter().map(|(i, _)| self.poses[*i]).collect();
        let mut energy = f64::INFINITY;
        let top = COARSEST.min(self.first.pyramid.levels.len() - 1);
        // The first frame held, every other pose free: the scale stays where the initialiser
        // put it, the depths' smoothed values as weak priors.
        let prior = |i: usize| DepthPrior::quadratic(self.smoothed[i], COUPLING_WEIGHT);
        for level in (0..=top).rev() {
            let views: Vec<(&Arc<Frame>, SE3)> = self
                .scored
                .iter()
                .zip(&poses)
                .map(|((_, frame), pose)| (frame, *pose))
                .collect();
            let Some((solved, solved_depths, report)) =
                self.solve_level(level, SCORE_ITERATIONS, &views, &depths, prior, 0.0)
            else {
                return f64::INFINITY;
            };
            energy = report.final_energy / report.residuals.max(1) as f64;
            (poses, depths) = (solved, solved_depths);
        }
        energy
    }

    /// Each point's smoothed inverse depth: its own blended with its neighbours' median
    /// (DSO's `optReg`).
    fn smooth(&mut self) {
        for (i, near) in self.neighbours.iter().enumerate() {
            let mut values: Vec<f64> = near.iter().map(|&j| self.points[j].1).collect();
            if values.is_empty() {
                self.smoothed[i] = self.points[i].1;
                continue;
            }
            values.sort_by(f64::total_cmp);
            let median = values[values.len() / 2];
            self.smoothed[i] =
                (1.0 - NEIGHBOUR_SHARE) * self.points[i].1 + NEIGHBOUR_SHARE * median;
        }
    }

    /// DSO's measure of parallax: the per-point energy of the pull to inverse depth 1 and
    /// of the charge on the translation.
    fn alpha_energy(&self, pose: &SE3) -> f64 {
        let n = self.points.len().max(1) as f64;
        let spread = self
            .points
            .iter()
            .map(|(_, d)| (d - 1.0).powi(2))
            .sum::<f64>()
            / n;
        ALPHA_WEIGHT * (spread + pose.translation.norm_squared())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::synth::{Motion, Scene, SynthConfig, render_frame_with};
    use crate::eval::depth_slope::log_slope;
    use crate::image::ImageF32;
    use crate::odometry::system_tests::rendered_frames;

    fn frames(motion: Motion, count: usize) -> Vec<Arc<Frame>> {
        rendered_frames(&SynthConfig {
            width: 320,
            height: 240,
            seed: 4,
            frames: count,
            motion,
            ..SynthConfig::default()
        })
    }

    /// The initialiser after `frames` with the two-view check on or off.
    fn pushed(frames: &[Arc<Frame>], two_view: bool) -> Initialiser {
        let config = OdometryConfig {
            init_two_view: two_view,
            ..OdometryConfig::default()
        };
        let mut init = Initialiser::new(&config, frames[0].clone(), 600);
        for f in &frames[1..] {
            assert!(
                init.push(f.clone()).is_none(),
                "initialised on rotation alone (two-view {two_view})"
            );
        }
        assert!(
            init.frames_since_snap.is_none(),
            "snapped on rotation alone (two-view {two_view})"
        );
        init
    }

    #[test]
    fn without_parallax_the_depths_stay_at_one_and_the_translation_small() {
        let frames = frames(Motion::Rotation, 6);
        // The corners see no parallax either: the two-view check does not snap.
        let corners = pushed(&frames, true);
        assert!(corners.two_view.as_ref().is_some_and(|v| !v.had_parallax()));
        let init = pushed(&frames, false);
        let worst = init
            .points
            .iter()
            .map(|(_, d)| (d - 1.0).abs())
            .fold(0.0, f64::max);
        assert!(
            worst < 0.2,
            "an inverse depth moved {worst} from 1 without parallax"
        );
        let t = init.poses.last().expect("pose").translation.norm();
        assert!(t < (ALPHA_LIMIT / ALPHA_WEIGHT).sqrt(), "translation {t}");
    }

    #[test]
    fn the_frames_kept_for_scoring_are_bounded_and_span_the_baseline() {
        let frames = frames(Motion::Rotation, 30);
        let config = OdometryConfig {
            focal_candidates: vec![0.9, 1.0, 1.1],
            ..OdometryConfig::default()
        };
        let mut init = Initialiser::new(&config, frames[0].clone(), 300);
        for f in &frames[1..] {
            init.push(f.clone());
            assert!(init.scored.len() <= SCORE_FRAMES);
        }
        let kept: Vec<usize> = init.scored.iter().map(|(i, _)| *i).collect();
        assert_eq!(kept.last(), Some(&29), "the newest is kept: {kept:?}");
        assert!(
            kept[0] <= 4,
            "the kept frames start near the first: {kept:?}"
        );
        let alone = Initialiser::new(&OdometryConfig::default(), frames[0].clone(), 300);
        assert!(alone.scored.is_empty() && alone.score().is_infinite());
    }

    #[test]
    fn with_parallax_it_snaps_and_hands_over_depths_of_mean_one() {
        let frames = frames(Motion::Orbit, 40);
        let mut init = Initialiser::new(&OdometryConfig::default(), frames[0].clone(), 600);
        let done = frames[1..]
            .iter()
            .find_map(|f| init.push(f.clone()))
            .expect("initialised within 40 frames of the orbit");
        let mean = done.points.iter().map(|(_, d)| d).sum::<f64>() / done.points.len() as f64;
        assert!((mean - 1.0).abs() < 1e-9, "mean inverse depth {mean}");
        assert_eq!(done.poses.len(), init.poses.len());
    }

    #[test]
    fn with_a_least_parallax_it_waits_for_that_baseline() {
        // On this hand-held start the snap comes early: DSO's five frames alone hand over at a
        // baseline of 0.0157 mean depths.
        let frames = rendered_frames(&SynthConfig {
            width: 320,
            height: 240,
            seed: 1,
            frames: 40,
            motion: Motion::Handheld,
            ..SynthConfig::default()
        });
        // With a mean inverse depth of 1 the last baseline is the parallax handed over.
        let baseline = |least: f64| {
            let config = OdometryConfig {
                init_min_parallax: least,
                init_two_view: false,
                ..OdometryConfig::default()
            };
            let mut init = Initialiser::new(&config, frames[0].clone(), 600);
            let done = frames[1..]
                .iter()
                .find_map(|f| init.push(f.clone()))
                .expect("initialised within 40 frames");
            done.poses.last().expect("pose").translation.norm()
        };
        let dso = baseline(0.0);
        assert!(dso < 1.0 / 60.0, "DSO's rule alone handed over at {dso}");
        let waited = baseline(1.0 / 60.0);
        assert!(waited >= 1.0 / 60.0, "handed over at parallax {waited}");
    }

    /// Slope of the handed-over log inverse depths against the rendered ones at frame
    /// `first` of `config` (1: the right shape; negative: the inverted map of the bas-relief
    /// ambiguity).
    fn slope_against_truth(done: &Initialised, config: &SynthConfig, first: usize) -> f64 {
        let camera = config.camera().expect("camera");
        let pose = config.poses()[first];
        let (_, depth) = render_frame_with(&Scene::generate(config.seed), &camera, &pose, 1);
        let pairs: Vec<(f64, f64)> = done
            .points
            .iter()
            .filter_map(|(uv, d)| {
                let z = f64::from(depth.bilinear(uv.x as f32, uv.y as f32)?);
                (z > 0.0 && *d > 0.0).then(|| (-z.ln(), d.ln()))
            })
            .collect();
        log_slope(&pairs).expect("the rendered depths span a range")
    }

    #[test]
    fn started_from_the_two_view_geometry_the_first_map_has_the_right_shape() {
        // On these starts DSO's initialiser alone hands over slopes of −0.60, −0.06 and 0.01
        // (inverted or flat: 2026-12-07).
        let config = SynthConfig {
            width: 320,
            height: 240,
            seed: 6,
            frames: 60,
            motion: Motion::Handheld,
            ..SynthConfig::default()
        };
        let frames = rendered_frames(&config);
        for start in [0, 5, 10] {
            let mut init = Initialiser::new(&OdometryConfig::default(), frames[start].clone(), 600);
            let done = frames[start + 1..]
                .iter()
                .find_map(|f| init.push(f.clone()))
                .expect("initialised");
            let first = start + done.skipped;
            assert_eq!(done.first.id, first as u64);
            let slope = slope_against_truth(&done, &config, first);
            assert!(
                (0.5..2.0).contains(&slope),
                "start {start}: first map's slope {slope} against the rendered depth"
            );
            assert_eq!(done.poses.len(), init.poses.len());
        }
    }

    #[test]
    fn with_every_track_lost_it_starts_again_and_counts_the_frames_it_skipped() {
        let frames = frames(Motion::Orbit, 60);
        let flat = Arc::new(
            Frame::new(
                99,
                0.0,
                frames[0].camera,
                &ImageF32::filled(320, 240, 90.0),
                None,
            )
            .expect("frame"),
        );
        let mut init = Initialiser::new(&OdometryConfig::default(), frames[0].clone(), 600);
        assert!(init.push(frames[1].clone()).is_none());
        // A blank frame loses every track: the initialisation starts again from it, and
        // from the next frame again, since a blank image has no corners.
        assert!(init.push(flat).is_none());
        let done = frames[2..]
            .iter()
            .find_map(|f| init.push(f.clone()))
            .expect("initialised after the restart");
        assert_eq!(done.skipped, 3, "frames 0, 1 and the blank one are skipped");
        assert_eq!(done.first.id, 2);
    }
}
