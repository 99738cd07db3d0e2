//! A metric depth model inside the window (issue 39): every point the window activates takes a
//! weak, robust prior on its inverse depth from the model's prediction for its host keyframe,
//! in the window's units (D3VO, Yang et al. CVPR 2020; CNN-SVO, Loo et al. ICRA 2019).
//!
//! Why: a pose-graph factor per keyframe (the back end's metric factor) corrects the scale
//! after the fact, keyframe by keyframe; in the window the photometric terms leave the depths'
//! scale free, so it drifts from keyframe to keyframe. A prior on each point pulls the depths,
//! and through them the poses of the keyframes tracked against them, to the model's metres
//! while they are estimated; weak and Huber-robust, so that the photometric terms keep the
//! depth *shape* where they measure it (the model's is poor: 43 % correct on redkitchen).
//! The window's gauge projection is unchanged: keeping the scale out of it (the priors observe
//! it) made TUM fr1/rpy diverge.
//!
//! The window's unit stays the initialiser's (mean inverse depth 1); the model's metres enter
//! through the first keyframe's scale `s` (`ρ_window = s · ρ_metric`), the median ratio on the
//! initialiser's points, as the pipeline's first keyframe takes it.
//!
//! Off by default ([`OdometryConfig::metric_prior_weight`] 0): it takes redkitchen 0-299 from
//! 0.027 to 0.019 m but makes fr1/rpy worse (docs/tuning.md, 2026-12-07, fiftieth stop).

use std::sync::Arc;

use nalgebra::Vector2;

use super::{DepthPrior, OdometryConfig};
use crate::Result;
use crate::frame::Frame;
use crate::image::ImageF32;

/// A metric depth model: a keyframe's inverse depth in metres⁻¹ at its level 0 (0 or less:
/// no prediction), `None` for a frame it cannot see (no colour image).
pub type MetricModel = Arc<dyn Fn(&Frame) -> Result<Option<ImageF32>> + Send + Sync>;

/// The model and the window's unit in its metres.
pub struct MetricPrior {
    model: MetricModel,
    /// `ρ_window = scale · ρ_metric`, once the first keyframe has set it.
    scale: Option<f64>,
}

impl std::fmt::Debug for MetricPrior {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MetricPrior")
            .field("scale", &self.scale)
            .finish_non_exhaustive()
    }
}

impl MetricPrior {
    pub fn new(model: MetricModel) -> Self {
        Self { model, scale: None }
    }

    /// The window's unit, from the first keyframe `frame` and its initialised `points`
    /// (level-0 pixel, inverse depth): the median ratio of their inverse depths to the
    /// model's ([`crate::metric_scale::observe`]); and the first keyframe's prior. `None`
    /// (and the unit unset) when the model sees nothing there.
    pub fn start(
        &mut self,
        frame: &Frame,
        points: &[(Vector2<f64>, f64)],
    ) -> Result<Option<ImageF32>> {
        let Some(metric) = (self.model)(frame)? else {
            return Ok(None);
        };
        let seed = points_image(frame, points)?;
        self.scale = crate::metric_scale::observe(&seed, &metric).map(|o| o.scale());
        Ok(self.scaled(metric))
    }

    /// The model's inverse depth of a new keyframe `frame` in the window's units; `None`
    /// before the unit is known or when the model sees nothing.
    pub fn keyframe(&self, frame: &Frame) -> Result<Option<ImageF32>> {
        if self.scale.is_none() {
            return Ok(None);
        }
        Ok((self.model)(frame)?.and_then(|metric| self.scaled(metric)))
    }

    /// `metric` in the window's units.
    fn scaled(&self, mut metric: ImageF32) -> Option<ImageF32> {
        let factor = self.scale? as f32;
        for v in &mut metric.data {
            *v *= factor;
        }
        Some(metric)
    }
}

/// The model's inverse depth in `image` at level-0 pixel `uv` (bilinear), when positive.
pub fn sample(image: &ImageF32, uv: &Vector2<f64>) -> Option<f64> {
    let v = image.bilinear(uv.x as f32, uv.y as f32)?;
    (v.is_finite() && v > 0.0).then_some(f64::from(v))
}

/// The prior a point whose model inverse depth is `model_idepth` takes into the window:
/// information [`OdometryConfig::metric_prior_weight`] on the relative error, Huber past
/// [`OdometryConfig::metric_prior_huber`]; `None` when that weight is 0.
pub fn point_prior(config: &OdometryConfig, model_idepth: f64) -> Option<DepthPrior> {
    let lambda = config.metric_prior_weight;
    (lambda > 0.0 && model_idepth > 0.0).then(|| DepthPrior {
        idepth: model_idepth,
        weight: lambda / (model_idepth * model_idepth),
        huber: lambda.sqrt() * config.metric_prior_huber,
    })
}

/// An inverse-depth image of `frame`'s size holding `points` (level-0 pixel, inverse depth)
/// at their nearest pixels, 0 (no estimate) elsewhere.
pub fn points_image(frame: &Frame, points: &[(Vector2<f64>, f64)]) -> Result<ImageF32> {
    let level = frame.level(0);
    let (w, h) = (level.width(), level.height());
    let mut data = vec![0.0f32; w * h];
    for (uv, idepth) in points {
        let (x, y) = (uv.x.round(), uv.y.round());
        if x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h && *idepth > 0.0 {
            data[y as usize * w + x as usize] = *idepth as f32;
        }
    }
    Ok(ImageF32::from_vec(w, h, data)?)
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;
    use std::sync::Mutex;

    use super::super::{Odometry, WindowObserver};
    use super::*;
    use crate::dataset::synth::{Scene, SynthConfig, render_frame_with};

    /// Per window point that carries the model's prior: its inverse depth over the prior's,
    /// the prior's weight times its inverse depth squared, and its inverse depth over the
    /// true one in metres; seen over a rendered orbit whose model is the true inverse depth.
    fn metric_points(weight: f64) -> Vec<(f64, f64, f64)> {
        let synth = SynthConfig {
            width: 640,
            height: 480,
            seed: 11,
            frames: 50,
            ..SynthConfig::default()
        };
        let camera = synth.camera().expect("camera");
        let scene = Scene::generate(synth.seed);
        let mut frames = Vec::new();
        let mut truth = HashMap::new();
        for (i, pose) in synth.poses().iter().enumerate() {
            let (rgb, depth) = render_frame_with(&scene, &camera, pose, 1);
            let gray = ImageF32::from_rgb8(&rgb);
            let frame = Frame::new(i as u64, i as f64 / 30.0, camera, &gray, None);
            frames.push(Arc::new(frame.expect("frame")));
            let inverse = depth
                .data
                .iter()
                .map(|&d| if d > 0.0 { 1.0 / d } else { 0.0 })
                .collect();
            let inverse = ImageF32::from_vec(depth.width, depth.height, inverse);
            truth.insert(i as u64, inverse.expect("image"));
        }
        let truth = Arc::new(truth);
        let metres = truth.clone();
        let model: MetricModel = Arc::new(move |f: &Frame| Ok(truth.get(&f.id).cloned()));
        let seen = Arc::new(Mutex::new(Vec::new()));
        let sink = seen.clone();
        let observer = WindowObserver(Arc::new(move |window: &super::super::SlidingWindow| {
            let mut sink = sink.lock().expect("lock");
            for p in window.points() {
                let true_idepth = sample(&metres[&p.host], &p.uv);
                if let (Some(prior), Some(t)) =
                    (p.prior.filter(|q| q.huber.is_finite()), true_idepth)
                {
                    let weight = prior.weight * prior.idepth.powi(2);
                    sink.push((p.idepth / prior.idepth, weight, p.idepth / t));
                }
            }
        }));
        let config = OdometryConfig {
            metric_prior_weight: weight,
            ..OdometryConfig::default()
        };
        let mut odometry =
            Odometry::start_observed(config, 0, false, Some(observer), Some(model)).expect("start");
        for frame in frames {
            odometry.push(frame).expect("push");
        }
        std::mem::take(&mut *seen.lock().expect("lock"))
    }

    #[test]
    fn the_models_depths_reach_the_windows_points_in_its_units() {
        let mut points = metric_points(100.0);
        assert!(
            points.len() > 1000,
            "{} points with a metric prior",
            points.len()
        );
        // The window's unit is the initialiser's (mean inverse depth 1), not the metre: the
        // priors must have been brought to it, so the points agree with them.
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
        let median = points[points.len() / 2].0;
        eprintln!(
            "{} points, median inverse depth over the prior {median:.4}",
            points.len()
        );
        assert!((median - 1.0).abs() < 0.05, "median ratio {median}");
        assert!(points.iter().all(|p| (p.1 - 100.0).abs() < 1e-6 * 100.0));
        // …and that unit is far from the metre, so the conversion was needed.
        points.sort_by(|a, b| a.2.total_cmp(&b.2));
        let unit = points[points.len() / 2].2;
        eprintln!("the window's inverse depth over the metric one: {unit:.4}");
        assert!((unit - 1.0).abs() > 0.2, "the window's unit is {unit} m⁻¹");
        // Weight 0: the model is not used in the window.
        assert!(metric_points(0.0).is_empty());
    }

    #[test]
    fn the_point_prior_is_relative_and_robust() {
        let config = OdometryConfig {
            metric_prior_weight: 100.0,
            metric_prior_huber: 0.2,
            ..OdometryConfig::default()
        };
        // The same relative error costs the same at any depth.
        let near = point_prior(&config, 2.0).expect("prior");
        let far = point_prior(&config, 0.1).expect("prior");
        let e_near = near.energy(2.0 * 1.1);
        let e_far = far.energy(0.1 * 1.1);
        assert!(
            (e_near - e_far).abs() < 1e-9 * e_near,
            "{e_near} vs {e_far}"
        );
        assert!((e_near - 0.5 * 100.0 * 0.01).abs() < 1e-9);
        // Inside 20 % quadratic, past it linear: a point 3× off pulls no harder than at 20 %.
        assert_eq!(near.weight_at(2.0 * 1.19), near.weight);
        let pull = |x: f64| near.weight_at(x) * (x - near.idepth);
        assert!((pull(6.0) - pull(2.0 * 1.2)).abs() < 1e-9 * pull(6.0));
        // Off: no prior.
        let off = OdometryConfig {
            metric_prior_weight: 0.0,
            ..config
        };
        assert!(point_prior(&off, 2.0).is_none());
    }
}
