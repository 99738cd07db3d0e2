//! A probe that asks where the window's energy has its minimum relative to the ground truth
//! (issue 35: on real video more iterations made the trajectory worse, on rendered video they
//! changed nothing). For one window it compares the photometric energy at the estimate with
//! the energy at the true poses (in the window's gauge, every depth searched again), and lets
//! the window optimise freely, without its prior, from either start.
//!
//! A benchmark tool: it costs about two extra optimisations per keyframe.

use nalgebra::{Matrix3, Vector3};

use super::energy;
use super::residual::{FrameState, PATTERN};
use super::select::select_candidates;
use super::{SlidingWindow, WindowPoint, point_energy, refine_depth, solve};
use crate::geometry::{SE3, SO3, Sim3};
use crate::image::ImageF32;

/// Iterations of the free optimisations: enough to reach the minimum near each start.
const FREE_ITERATIONS: usize = 20;
/// Inverse depths tried per point at the true poses, log-spaced over ±8× the estimate: the
/// estimate's depth may be an outlier at other poses, and Gauss–Newton never leaves one.
const DEPTH_SEARCH: usize = 61;
/// Levenberg–Marquardt steps on each depth after the search.
const DEPTH_ITERATIONS: usize = 10;
/// Points of the fresh probe over the whole window: DSO's active-point density.
const FRESH_POINTS: usize = 2000;

/// The similarity that maps the poses `from` onto `to`: the rotation from the poses'
/// rotations (chordal mean), scale and translation from their centres. Windows span little
/// motion, so centres alone (Umeyama) would leave the rotation ill-defined.
fn fit_similarity(from: &[SE3], to: &[SE3]) -> Sim3 {
    let mut m = Matrix3::zeros();
    for (f, t) in from.iter().zip(to) {
        m += t.rotation.matrix() * f.rotation.matrix().transpose();
    }
    let svd = m.svd(true, true);
    let (u, v_t) = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => (u, v_t),
        _ => (Matrix3::identity(), Matrix3::identity()),
    };
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * v_t;
    let n = from.len().max(1) as f64;
    let cf = from.iter().map(|p| p.translation).sum::<Vector3<f64>>() / n;
    let ct = to.iter().map(|p| p.translation).sum::<Vector3<f64>>() / n;
    let (mut num, mut den) = (0.0, 0.0);
    for (f, t) in from.iter().zip(to) {
        let a = r * (f.translation - cf);
        num += a.dot(&(t.translation - ct));
        den += a.norm_squared();
    }
    let scale = if den > 1e-18 { num / den } else { 1.0 };
    Sim3::new(SO3::from_matrix(&r), ct - scale * (r * cf), scale)
}

/// The camera pose `pose` moved by the similarity `s` (its centre scaled, its axes turned).
fn moved(s: &Sim3, pose: &SE3) -> SE3 {
    (s * &Sim3::from_se3(pose, 1.0)).to_se3_and_scale().0
}

/// The window at one set of poses.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Standing {
    /// Photometric energy (outlier pairs at their constant cost).
    pub energy: f64,
    /// Inlier pattern residuals.
    pub residuals: usize,
    /// Mean rotation error against the truth after a similarity alignment, degrees.
    pub rotation_deg: f64,
    /// RMS position error after the alignment over the RMS spread of the true positions.
    pub translation_rel: f64,
}

/// One window seen against the truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruthProbe {
    /// The newest keyframe.
    pub keyframe: u64,
    pub points: usize,
    /// As the window left its optimisation.
    pub estimate: Standing,
    /// At the true poses, depths searched again, nothing else moved.
    pub truth: Standing,
    /// Optimised freely (no prior) from the truth, and from the estimate.
    pub from_truth: Standing,
    pub from_estimate: Standing,
    /// The points that are inliers in every other keyframe both at the estimate and at the
    /// truth: how many, and their energy at each. The window keeps the points that agree with
    /// its estimate; on this common set that choice cannot favour either.
    pub common_points: usize,
    pub common_estimate: f64,
    pub common_truth: f64,
}

impl SlidingWindow {
    fn poses(&self) -> Vec<SE3> {
        self.frames
            .iter()
            .map(|f| f.state.world_from_camera)
            .collect()
    }

    /// The true poses of the window's keyframes and the similarity that maps them into the
    /// window's gauge; `None` for a window of fewer than 4 keyframes or a keyframe without
    /// truth.
    fn true_poses(&self, truth: &dyn Fn(u64) -> Option<SE3>) -> Option<(Vec<SE3>, Sim3)> {
        if self.frames.len() < 4 {
            return None;
        }
        let truth: Vec<SE3> = self
            .frames
            .iter()
            .map(|f| truth(f.id))
            .collect::<Option<_>>()?;
        let into_window = fit_similarity(&truth, &self.poses());
        Some((truth, into_window))
    }

    /// Puts every keyframe at its true pose, in the window's gauge (linearised there too).
    fn move_to(&mut self, truth: &[SE3], into_window: &Sim3) {
        for (f, t) in self.frames.iter_mut().zip(truth) {
            f.state.world_from_camera = moved(into_window, t);
            f.first_estimate = f.state;
        }
    }

    fn standing(&self, truth: &[SE3]) -> Standing {
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        let views = solve::views(&self.config, &self.frames, &states);
        let (energy, residuals) =
            energy::photometric_energy(&self.config, &self.points, &self.hosts(), &views);
        let est = self.poses();
        let align = fit_similarity(&est, truth);
        let n = truth.len().max(1) as f64;
        let centre = truth.iter().map(|p| p.translation).sum::<Vector3<f64>>() / n;
        let spread = (truth
            .iter()
            .map(|p| (p.translation - centre).norm_squared())
            .sum::<f64>()
            / n)
            .sqrt();
        let (mut position, mut rotation) = (0.0, 0.0);
        for (e, t) in est.iter().zip(truth) {
            let a = moved(&align, e);
            position += (a.translation - t.translation).norm_squared();
            rotation += (a.rotation.inverse() * t.rotation).angle().to_degrees();
        }
        Standing {
            energy,
            residuals,
            rotation_deg: rotation / n,
            translation_rel: (position / n).sqrt() / spread.max(1e-12),
        }
    }

    /// Every point's photometric energy, and whether it is an inlier in every other keyframe.
    fn point_energies(&self) -> Vec<(f64, bool)> {
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        let views = solve::views(&self.config, &self.frames, &states);
        let full = PATTERN.len() * (views.len() - 1);
        self.points
            .iter()
            .zip(self.hosts())
            .map(|(p, h)| {
                let (e, n) =
                    energy::photometric_energy(&self.config, std::slice::from_ref(p), &[h], &views);
                (e, n == full)
            })
            .collect()
    }

    /// Every point's inverse depth alone, poses and brightness fixed: a log-spaced search,
    /// then Levenberg–Marquardt.
    fn search_depths(&mut self) {
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        let views = solve::views(&self.config, &self.frames, &states);
        let hosts = self.hosts();
        let config = &self.config;
        for (point, &k) in self.points.iter_mut().zip(&hosts) {
            let half = (DEPTH_SEARCH / 2) as f64;
            let start = point.idepth;
            let mut best = (point_energy(config, point, k, &views), start);
            for i in 0..DEPTH_SEARCH {
                let trial = WindowPoint {
                    idepth: start * 8f64.powf((i as f64 - half) / half),
                    ..point.clone()
                };
                let e = point_energy(config, &trial, k, &views);
                if e < best.0 {
                    best = (e, trial.idepth);
                }
            }
            point.idepth = best.1;
            refine_depth(config, point, k, &views, DEPTH_ITERATIONS);
        }
    }

    /// The same window without its marginalisation prior or anchor, linearised where it
    /// stands, to be optimised freely.
    fn unprimed(&self) -> Self {
        let mut w = self.clone();
        w.prior.h.fill(0.0);
        w.prior.b.fill(0.0);
        w.anchor = None;
        for f in &mut w.frames {
            f.first_estimate = f.state;
        }
        w.config.iterations = FREE_ITERATIONS;
        w
    }
}

/// The probe of `window` against `truth` (world_from_camera of a keyframe id, any world and
/// scale); `None` for a window of fewer than 4 keyframes or a keyframe without truth.
pub fn probe(window: &SlidingWindow, truth: &dyn Fn(u64) -> Option<SE3>) -> Option<TruthProbe> {
    let (truth, into_window) = window.true_poses(truth)?;
    let mut at_truth = window.unprimed();
    at_truth.move_to(&truth, &into_window);
    at_truth.search_depths();
    let mut from_truth = at_truth.clone();
    from_truth.optimize();
    let mut from_estimate = window.unprimed();
    from_estimate.optimize();
    let (mut common_points, mut common_estimate, mut common_truth) = (0, 0.0, 0.0);
    for ((e, e_in), (t, t_in)) in window
        .point_energies()
        .into_iter()
        .zip(at_truth.point_energies())
    {
        if e_in && t_in {
            common_points += 1;
            common_estimate += e;
            common_truth += t;
        }
    }
    Some(TruthProbe {
        common_points,
        common_estimate,
        common_truth,
        keyframe: window.frames.last()?.id,
        points: window.points.len(),
        estimate: window.standing(&truth),
        truth: at_truth.standing(&truth),
        from_truth: from_truth.standing(&truth),
        from_estimate: from_estimate.standing(&truth),
    })
}

/// The window's energy on points chosen without it: candidates selected by gradient alone in
/// every keyframe, their depths started from the sensor (the window's median where it has
/// none) and searched again at each standing. The window's own points were chosen, traced and
/// pruned at the estimate, so their energy may favour it; these cannot.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FreshProbe {
    pub keyframe: u64,
    pub points: usize,
    /// Points started from a sensor depth.
    pub with_sensor: usize,
    /// The energy at the estimate's poses and at the truth's, and their inlier residuals.
    pub estimate: f64,
    pub truth: f64,
    pub estimate_residuals: usize,
    pub truth_residuals: usize,
    /// Points that cost less at the truth than at the estimate.
    pub truth_cheaper: usize,
    /// The share of the truth's excess (the sum over points of what each costs more at the
    /// truth) that the tenth of the points with the largest excess carries.
    pub top_tenth_share: f64,
    /// The share of points cheaper at the truth by where they lie in their host: thirds of the
    /// distance from the image centre (a lens or focal-length error grows outwards), and
    /// thirds of the rows from the top (a rolling shutter's error grows down the image).
    pub cheaper_by_radius: [f64; 3],
    pub cheaper_by_row: [f64; 3],
}

/// [`FreshProbe`] of `window` against `truth` (as [`probe`]); `sensor` gives a keyframe's
/// sensor depth in the truth's units at the window's level 0 resolution.
pub fn probe_fresh(
    window: &SlidingWindow,
    truth: &dyn Fn(u64) -> Option<SE3>,
    sensor: &dyn Fn(u64) -> Option<ImageF32>,
) -> Option<FreshProbe> {
    let (truth, into_window) = window.true_poses(truth)?;
    let mut idepths: Vec<f64> = window.points.iter().map(|p| p.idepth).collect();
    idepths.sort_by(f64::total_cmp);
    let fallback = idepths.get(idepths.len() / 2).copied().unwrap_or(1.0);
    let mut at_estimate = window.unprimed();
    at_estimate.points.clear();
    let per_keyframe = FRESH_POINTS / window.frames.len();
    let level_scale = f64::from(1u32 << window.config.level);
    let mut with_sensor = 0;
    for f in &window.frames {
        let depth = sensor(f.id);
        for uv in select_candidates(f.frame.level(window.config.level), per_keyframe) {
            let measured = depth.as_ref().and_then(|d| {
                let (x, y) = (uv.x * level_scale, uv.y * level_scale);
                let inside = x >= 0.0 && y >= 0.0 && x < d.width as f64 && y < d.height as f64;
                let v = if inside {
                    f64::from(d.at(x as usize, y as usize))
                } else {
                    0.0
                };
                (v > 0.0).then(|| 1.0 / (into_window.scale * v))
            });
            with_sensor += usize::from(measured.is_some());
            at_estimate.add_point(f.id, uv, measured.unwrap_or(fallback), None);
        }
    }
    let mut at_truth = at_estimate.clone();
    at_truth.move_to(&truth, &into_window);
    at_estimate.search_depths();
    at_truth.search_depths();
    let (e, t) = (at_estimate.standing(&truth), at_truth.standing(&truth));
    let mut excess: Vec<f64> = at_estimate
        .point_energies()
        .into_iter()
        .zip(at_truth.point_energies())
        .map(|((e, _), (t, _))| t - e)
        .collect();
    let truth_cheaper = excess.iter().filter(|&&d| d < 0.0).count();
    let level = window.frames[0].frame.level(window.config.level);
    let (w, h) = (level.width() as f64, level.height() as f64);
    let corner = (0.25 * (w * w + h * h)).sqrt();
    let third = |v: f64| ((3.0 * v) as usize).min(2);
    let (mut by_radius, mut by_row) = ([[0usize; 2]; 3], [[0usize; 2]; 3]);
    for (p, d) in at_estimate.points.iter().zip(&excess) {
        let radius = ((p.uv.x - 0.5 * w).powi(2) + (p.uv.y - 0.5 * h).powi(2)).sqrt() / corner;
        for (bins, at) in [(&mut by_radius, radius), (&mut by_row, p.uv.y / h)] {
            let bin = &mut bins[third(at)];
            bin[0] += usize::from(*d < 0.0);
            bin[1] += 1;
        }
    }
    let shares = |bins: [[usize; 2]; 3]| bins.map(|[c, n]| c as f64 / n.max(1) as f64);
    excess.sort_by(|a, b| b.total_cmp(a));
    let positive: f64 = excess.iter().filter(|&&d| d > 0.0).sum();
    let top: f64 = excess[..excess.len() / 10]
        .iter()
        .filter(|&&d| d > 0.0)
        .sum();
    Some(FreshProbe {
        keyframe: window.frames.last()?.id,
        points: at_estimate.points.len(),
        with_sensor,
        estimate: e.energy,
        truth: t.energy,
        estimate_residuals: e.residuals,
        truth_residuals: t.residuals,
        truth_cheaper,
        top_tenth_share: if positive > 0.0 { top / positive } else { 0.0 },
        cheaper_by_radius: shares(by_radius),
        cheaper_by_row: shares(by_row),
    })
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector6;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use std::sync::Arc;

    use super::super::OdometryConfig;
    use super::super::select::select_candidates;
    use super::super::tests::{add_keyframe, perturbed, render};
    use super::*;

    #[test]
    fn similarity_fit_recovers_a_known_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let known = Sim3::new(
            SO3::exp(&Vector3::new(0.3, -0.2, 0.9)),
            Vector3::new(1.0, -2.0, 0.5),
            2.5,
        );
        let from: Vec<SE3> = (0..5)
            .map(|_| {
                let mut r = || rng.random_range(-1.0..1.0);
                SE3::exp(&Vector6::new(r(), r(), r(), r(), r(), r()))
            })
            .collect();
        let to: Vec<SE3> = from.iter().map(|p| moved(&known, p)).collect();
        let fit = fit_similarity(&from, &to);
        assert!((fit.scale - known.scale).abs() < 1e-9, "{fit:?}");
        assert!((fit.rotation.inverse() * known.rotation).angle() < 1e-9);
        assert!((fit.translation - known.translation).norm() < 1e-9);
    }

    /// On rendered views the energy's minimum is at the truth: the truth costs less than a
    /// perturbed estimate, free optimisation from the truth stays there, and from the
    /// estimate it moves towards it. The truth is given in another world and scale.
    #[test]
    fn on_rendered_views_the_minimum_is_at_the_truth() {
        let r = render(5, &[0, 3, 6, 9, 12]);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut window = SlidingWindow::new(OdometryConfig::default()).expect("config");
        for n in 0..r.frames.len() {
            let pose = perturbed(&r.poses[n], &mut rng, 1.0, 0.5);
            let mut noise = ChaCha8Rng::seed_from_u64(100 + n as u64);
            add_keyframe(&mut window, &r, n, pose, 300, || {
                noise.random_range(0.9..1.1)
            });
        }
        let elsewhere = Sim3::new(
            SO3::exp(&Vector3::new(0.5, 0.1, -0.3)),
            Vector3::new(3.0, 1.0, -1.0),
            0.4,
        );
        let truth = |id: u64| r.poses.get(id as usize).map(|p| moved(&elsewhere, p));
        let p = probe(&window, &truth).expect("a probe");
        assert!(p.estimate.rotation_deg > 0.1, "{p:?}");
        assert!(p.truth.rotation_deg < 1e-6, "{p:?}");
        assert!(p.truth.energy < p.estimate.energy, "{p:?}");
        assert!(p.from_truth.rotation_deg < 0.05, "{p:?}");
        assert!(p.from_truth.translation_rel < 0.02, "{p:?}");
        assert!(
            p.from_estimate.rotation_deg < 0.5 * p.estimate.rotation_deg,
            "{p:?}"
        );
        assert!(probe(&window, &|_| None).is_none());

        // Fresh points, started from the sensor depth in the truth's units: the truth costs
        // less there too, and on most points.
        let sensor = |id: u64| {
            r.depths.get(id as usize).map(|d| ImageF32 {
                data: d.data.iter().map(|v| v * elsewhere.scale as f32).collect(),
                ..d.clone()
            })
        };
        let fresh = probe_fresh(&window, &truth, &sensor).expect("a fresh probe");
        assert!(fresh.points > 1000, "{fresh:?}");
        assert!(fresh.with_sensor * 10 > fresh.points * 9, "{fresh:?}");
        assert!(fresh.truth < fresh.estimate, "{fresh:?}");
        assert!(2 * fresh.truth_cheaper > fresh.points, "{fresh:?}");
        // Without a sensor every depth starts from the window's median and is searched.
        let blind = probe_fresh(&window, &truth, &|_| None).expect("a fresh probe");
        assert_eq!(blind.with_sensor, 0);
        assert!(blind.truth < blind.estimate, "{blind:?}");
    }

    /// Rolling-shutter views of a moving camera (rendered row by row): the window that models
    /// the shutter with the true velocities keeps its minimum at the truth; the one that does
    /// not has it elsewhere.
    #[test]
    fn a_rolling_shutter_moves_the_minimum_unless_it_is_modelled() {
        use crate::dataset::synth::{Motion, Scene, SynthConfig, Trajectory, render_rolling};
        use crate::frame::Frame;
        use crate::image::ImageF32;

        let synth = SynthConfig {
            width: 320,
            height: 240,
            seed: 4,
            motion: Motion::Shake,
            ..SynthConfig::default()
        };
        let camera = synth.camera().expect("camera");
        let scene = Scene::generate(synth.seed);
        let trajectory = Trajectory::new(synth.motion, synth.seed);
        let readout = 0.03;
        let rows = f64::from(camera.height);
        let truth: Vec<SE3> = (0..5)
            .map(|n| trajectory.world_from_camera(0.4 + 0.1 * n as f64))
            .collect();
        let run = |modelled: bool| {
            let mut window = SlidingWindow::new(OdometryConfig {
                rolling_shutter_readout: if modelled { readout } else { 0.0 },
                ..OdometryConfig::default()
            })
            .expect("config");
            for (n, pose) in truth.iter().enumerate() {
                let time = 0.4 + 0.1 * n as f64;
                let pose_of_row = |y: u32| {
                    let row = (f64::from(y) + 0.5) / rows - 0.5;
                    trajectory.world_from_camera(time + readout * row)
                };
                let (rgb, depth) = render_rolling(&scene, &camera, &pose_of_row, 2);
                let gray = ImageF32::from_rgb8(&rgb);
                let frame = Frame::new(n as u64, time, camera, &gray, None).expect("frame");
                let state = FrameState {
                    world_from_camera: *pose,
                    affine: (0.0, 0.0),
                };
                window
                    .add_frame(n as u64, Arc::new(frame), state)
                    .expect("keyframe");
                let dt = 1e-4;
                let velocity =
                    (pose.inverse() * trajectory.world_from_camera(time + dt)).log() / dt;
                window.set_velocity(n as u64, velocity);
                let level = window.frames[n].frame.level(0);
                for uv in select_candidates(level, 300) {
                    let d = depth.at(uv.x as usize, uv.y as usize);
                    if d > 0.0 {
                        window.add_point(n as u64, uv, 1.0 / f64::from(d), None);
                    }
                }
            }
            probe(&window, &|id| truth.get(id as usize).copied()).expect("a probe")
        };
        let (with, without) = (run(true), run(false));
        assert!(
            with.from_truth.rotation_deg < 0.5 * without.from_truth.rotation_deg,
            "modelled {with:?}\nnot modelled {without:?}"
        );
        assert!(
            with.truth.energy < without.truth.energy,
            "modelled {with:?}\nnot modelled {without:?}"
        );
    }
}
