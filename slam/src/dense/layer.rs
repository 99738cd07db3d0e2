//! The dense layer, per finished keyframe (paper Fig. 1): depth prior → eq. (3) alignment →
//! adaptive filter → densification → two-view consistency, whose result refines the pose
//! graph.
//!
//! [`DenseLayer`] does one keyframe at a time. As a [`Service`] the pipeline runs it on its own
//! thread behind a bounded queue, so that the network and the kernels never hold up tracking
//! (the paper runs prediction and densification in separate processes, §IV); a full queue
//! skips the keyframe rather than waiting (counted by the caller).
//!
//! This is the one place that chooses between the CPU references and their GPU kernels: each
//! algorithm module takes its step as a trait object ([`FilterStep`], [`DensifySolver`],
//! [`InverseDepthWarp`]) and knows nothing of the runners.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use super::densify::{CpuDensifier, DensifySolver};
use super::filter::{CpuFilter, FilterInputs, FilterStep, filter_semidense};
use super::gpu_densify::GpuDensifier;
use super::gpu_filter::GpuAdaptiveFilter;
use super::gpu_warp::GpuWarp;
use super::keyframe::{DenseKeyframe, DenseMode, DenseStages, DenseTimings};
use super::prior::DepthPrior;
use super::resample::{box_downsample, downsample_depth, working_camera, working_size};
use super::two_view::{
    CpuWarp, InverseDepthWarp, TwoViewInputs, pose_variance, sensor_depth_map, to_depth_map,
    two_view_consistency,
};
use super::{DenseCompute, DenseConfig, ScaleShift, densify, fit_scale_shift_robust, support};
use crate::background::Service;
use crate::frame::Frame;
use crate::geometry::{Matrix7, PinholeCamera, Sim3};
use crate::gpu::GpuContext;
use crate::graph::KeyframeId;
use crate::image::ImageF32;
use crate::mapping::DepthMap;
use crate::metric_scale::{self, ScaleObservation};
use crate::{Error, Result};

/// A depth prior shared by the tracking thread (first-keyframe initialisation, hole filling)
/// and the dense worker.
pub type SharedPrior = Arc<Mutex<Box<dyn DepthPrior>>>;

/// One finished keyframe to densify.
#[derive(Clone, Debug)]
pub struct DenseJob {
    pub keyframe_id: KeyframeId,
    pub frame: Arc<Frame>,
    /// Its final semi-dense map (full resolution, keyframe gauge).
    pub depth: Arc<DepthMap>,
    /// Current pose estimates of this keyframe and the ones before it (the two-view check
    /// needs the previous densified keyframe's).
    pub poses: Vec<(KeyframeId, Sim3)>,
    /// Σ_ξ of the keyframe's pose (eq. 16): the inverse information of its tracking edge.
    pub pose_covariance: Matrix7,
    /// The prior's raw output for this image, if the tracking thread already ran the network
    /// (hole filling), so that it is not run twice.
    pub prior: Option<Arc<ImageF32>>,
}

/// The layer's answer for one keyframe.
#[derive(Clone, Debug)]
pub struct DenseOutput {
    pub keyframe: Arc<DenseKeyframe>,
    /// The two-view consistent depth at the keyframe's resolution, for
    /// `Backend::update_keyframe_depth` (None when the check was off, had no previous keyframe
    /// or kept fewer than `two_view.min_pixels`).
    pub refined_depth: Option<Arc<DepthMap>>,
    /// With a metric prior: the keyframe's scale as the prior sees it on its semi-dense pixels
    /// (for the pose graph's unary scale factor, `backend.metric_scale`).
    pub scale: Option<ScaleObservation>,
}

/// What the previous densified keyframe leaves for the next two-view check.
#[derive(Debug)]
struct Previous {
    id: KeyframeId,
    filtered: ImageF32,
    dense: Arc<ImageF32>,
}

/// The layer's three swappable steps: the GPU kernels, or the CPU references.
struct Steps {
    filter: Box<dyn FilterStep + Send>,
    densify: Box<dyn DensifySolver + Send>,
    warp: Box<dyn InverseDepthWarp + Send>,
    gpu: bool,
}

impl Steps {
    fn cpu() -> Self {
        Self {
            filter: Box::new(CpuFilter),
            densify: Box::new(CpuDensifier),
            warp: Box::new(CpuWarp),
            gpu: false,
        }
    }

    fn gpu(ctx: Arc<GpuContext>) -> Result<Self> {
        Ok(Self {
            filter: Box::new(GpuAdaptiveFilter::new(ctx.clone())?),
            densify: Box::new(GpuDensifier::new(ctx.clone())?),
            warp: Box::new(GpuWarp::new(ctx)?),
            gpu: true,
        })
    }
}

impl std::fmt::Debug for Steps {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.gpu {
            "gpu kernels"
        } else {
            "cpu references"
        })
    }
}

/// The dense layer of one session.
#[derive(Debug)]
pub struct DenseLayer {
    config: DenseConfig,
    prior: Option<SharedPrior>,
    steps: Steps,
    previous: Option<Previous>,
    no_model_reported: bool,
    /// The prior predicts metres (its model config says `metric`).
    metric: bool,
}

impl DenseLayer {
    /// A layer with `config`; the kernels run on `gpu` (the session's GPU; the process's
    /// shared context when `None`) unless `config.compute` is `Cpu` or no adapter can be
    /// opened (then the CPU references, with a warning).
    pub fn new(
        config: DenseConfig,
        prior: Option<SharedPrior>,
        gpu: Option<Arc<GpuContext>>,
    ) -> Result<Self> {
        config.validate()?;
        let steps = match config.compute {
            DenseCompute::Cpu => Steps::cpu(),
            DenseCompute::Gpu => match gpu.map_or_else(crate::gpu::shared_context, Ok) {
                Ok(ctx) => match Steps::gpu(ctx) {
                    Ok(steps) => steps,
                    Err(e) => {
                        tracing::warn!(error = %e, "dense layer: GPU kernels unavailable, using the CPU references");
                        Steps::cpu()
                    }
                },
                Err(e) => {
                    tracing::warn!(error = %e, "dense layer: no GPU, using the CPU references");
                    Steps::cpu()
                }
            },
        };
        if prior.is_none() {
            tracing::info!(
                "dense layer: no depth model loaded; densifying from the filtered semi-dense \
                 depth with edge-aware smoothness"
            );
        }
        let metric = prior.as_ref().is_some_and(is_metric);
        Ok(Self {
            config,
            prior,
            steps,
            previous: None,
            no_model_reported: false,
            metric,
        })
    }

    /// Whether the kernels run on the GPU.
    pub fn uses_gpu(&self) -> bool {
        self.steps.gpu
    }

    /// Densifies one keyframe.
    pub fn process(&mut self, job: DenseJob) -> Result<DenseOutput> {
        let mut timings = DenseTimings::default();
        let frame = &job.frame;
        let full = &frame.pyramid.levels[0].image;
        let (w, h) = working_size(full.width, full.height, self.config.width);
        let camera = working_camera(&frame.camera, w, h);
        let intensity = box_downsample(full, w, h)?;
        let (semidense, semidense_var) = downsample_depth(&job.depth, w, h)?;
        let prior = self.aligned_prior(&job, &semidense, (w, h), &mut timings)?;
        let scale = match (&prior.raw, self.metric) {
            (Some(raw), true) => metric_scale::observe(&semidense, raw),
            _ => None,
        };

        // §III-C: the adaptive filter.
        let t = Instant::now();
        let inputs = FilterInputs {
            intensity: &intensity,
            semidense: &semidense,
            variance: &semidense_var,
            prior: prior.aligned.as_ref(),
        };
        let filter_step = self.steps.filter.as_ref();
        let (filtered, filtered_var) = filter_semidense(&inputs, &self.config.filter, filter_step)?;
        timings.filter_ms = ms(t);

        let t = Instant::now();
        let dense = Arc::new(self.densify(&intensity, &prior, &filtered, &filtered_var)?);
        timings.densify_ms = ms(t);

        let t = Instant::now();
        let semi = Semidense {
            full: &job.depth,
            filtered: &filtered,
            variance: &filtered_var,
        };
        let consistency = self.consistency(&job, &camera, &semi, &dense)?;
        timings.two_view_ms = ms(t);
        let Consistency {
            world_from_keyframe,
            mut variance,
            consistent_pixels,
            refined_depth,
        } = consistency;
        // The published variance (what the fusion weighs by) also grows away from the
        // semi-dense support; the back end's constraints above keep the paper's V_c.
        let growth = self.config.support_variance;
        support::grow_with_distance(&mut variance, &dense, &filtered, growth);

        let mode = prior.mode();
        let AlignedPrior {
            raw: prior,
            fit: align,
            error: align_error,
            aligned: prior_aligned,
        } = prior;
        let stages = self.config.keep_stages.then(|| {
            Arc::new(DenseStages {
                intensity,
                prior,
                prior_aligned,
                semidense,
                semidense_var,
                filtered: filtered.clone(),
                filtered_var,
            })
        });
        self.previous = Some(Previous {
            id: job.keyframe_id,
            filtered,
            dense: dense.clone(),
        });
        Ok(DenseOutput {
            keyframe: Arc::new(DenseKeyframe {
                keyframe_id: job.keyframe_id,
                timestamp: frame.timestamp,
                camera,
                world_from_keyframe,
                idepth: dense,
                variance: Arc::new(variance),
                mode,
                align,
                align_error,
                consistent_pixels,
                timings,
                stages,
            }),
            refined_depth,
            scale,
        })
    }

    /// §III-B: the prior at the working size (given with the job, else predicted) and its
    /// eq. (3) alignment onto the semi-dense map.
    fn aligned_prior(
        &mut self,
        job: &DenseJob,
        semidense: &ImageF32,
        (w, h): (usize, usize),
        timings: &mut DenseTimings,
    ) -> Result<AlignedPrior> {
        let cfg = &self.config;
        let t = Instant::now();
        let raw = match (&job.prior, &self.prior, job.frame.rgb.as_ref()) {
            (Some(p), _, _) => Some(box_downsample(p, w, h)?),
            (None, Some(model), Some(rgb)) => Some(box_downsample(&predict(model, rgb)?, w, h)?),
            _ => None,
        };
        timings.prior_ms = ms(t);
        let t = Instant::now();
        let (fit, error) = match &raw {
            Some(p) => match fit_scale_shift_robust(p, semidense, &cfg.align) {
                Ok(fit) => (Some(fit), None),
                Err(e) => (None, Some(e.to_string())),
            },
            None => (None, None),
        };
        let aligned = match (&raw, &fit) {
            (Some(p), Some(fit)) => Some(clamped(fit, p, cfg.densify.min_idepth)),
            _ => None,
        };
        timings.align_ms = ms(t);
        let prior = AlignedPrior {
            raw,
            fit,
            error,
            aligned,
        };
        if let Some(reason) = &prior.error {
            tracing::warn!(keyframe = job.keyframe_id, %reason, "dense layer: prior not used");
        } else if prior.mode() == DenseMode::NoModel && !self.no_model_reported {
            self.no_model_reported = true;
            tracing::info!("dense layer running without a depth model (no_model mode)");
        }
        Ok(prior)
    }

    /// §III-D: densification, from the aligned prior or, without one, from the image.
    fn densify(
        &self,
        intensity: &ImageF32,
        prior: &AlignedPrior,
        filtered: &ImageF32,
        filtered_var: &ImageF32,
    ) -> Result<ImageF32> {
        let params = &self.config.densify;
        let problem = match &prior.aligned {
            Some(p) => densify::DensifyProblem::with_prior(p, filtered, filtered_var, params)?,
            None => {
                densify::DensifyProblem::without_prior(intensity, filtered, filtered_var, params)?
            }
        };
        densify::densify(&problem, params, self.steps.densify.as_ref())
    }

    /// §III-E: the keyframe's variance from its pose uncertainty, and its two-view consistency
    /// with the previous densified keyframe (or, as the baseline, the sensor's depth).
    fn consistency(
        &self,
        job: &DenseJob,
        camera: &PinholeCamera,
        semi: &Semidense<'_>,
        dense: &ImageF32,
    ) -> Result<Consistency> {
        let cfg = &self.config;
        let pose_of = |id: KeyframeId| job.poses.iter().find(|(k, _)| *k == id).map(|(_, p)| *p);
        let world_from_keyframe = pose_of(job.keyframe_id).ok_or_else(|| {
            Error::Config(format!(
                "dense job for keyframe {} has no pose",
                job.keyframe_id
            ))
        })?;
        let floor = dense_variance_floor(semi.variance);
        let mut variance = pose_variance(dense, camera, &job.pose_covariance);
        merge_variances(&mut variance, semi.filtered, semi.variance, floor);
        let mut consistent_pixels = 0;
        let mut refined_depth = None;
        let previous = self
            .previous
            .as_ref()
            .and_then(|p| pose_of(p.id).map(|pose| (p, pose)));
        if let (true, Some((prev, world_from_prev))) = (cfg.two_view.enabled, previous) {
            let result = two_view_consistency(
                &TwoViewInputs {
                    camera,
                    prev_semi: &prev.filtered,
                    prev_dense: &prev.dense,
                    cur_semi: semi.filtered,
                    cur_semi_var: semi.variance,
                    cur_dense: dense,
                    cur_from_prev: world_from_keyframe.inverse() * world_from_prev,
                    pose_covariance: job.pose_covariance,
                },
                &cfg.two_view,
                self.steps.warp.as_ref(),
            )?;
            consistent_pixels = result.consistent_semi + result.consistent_dense;
            if consistent_pixels >= cfg.two_view.min_pixels {
                let mut consistent_var = result.variance;
                merge_variances(&mut consistent_var, semi.filtered, semi.variance, floor);
                let full = &job.frame.pyramid.levels[0].image;
                let consistent =
                    to_depth_map(&result.idepth, &consistent_var, full.width, full.height)?;
                refined_depth = Some(Arc::new(keep_semidense(semi.full, consistent)));
            }
        }
        if let (true, Some(sensor)) = (cfg.two_view.ground_truth_depth, &job.frame.sensor_depth) {
            match sensor_depth_map(semi.full, sensor)? {
                Some(map) => refined_depth = Some(Arc::new(map)),
                None => tracing::warn!(
                    keyframe = job.keyframe_id,
                    "ground-truth refinement: too few semi-dense pixels with a sensor depth"
                ),
            }
        }
        Ok(Consistency {
            world_from_keyframe,
            variance,
            consistent_pixels,
            refined_depth,
        })
    }
}

/// The prior of one keyframe at the working size: as predicted, its eq. (3) fit (or why
/// there is none) and the aligned, clamped result.
struct AlignedPrior {
    raw: Option<ImageF32>,
    fit: Option<ScaleShift>,
    error: Option<String>,
    aligned: Option<ImageF32>,
}

impl AlignedPrior {
    fn mode(&self) -> DenseMode {
        if self.aligned.is_some() {
            DenseMode::Prior
        } else {
            DenseMode::NoModel
        }
    }
}

/// A keyframe's semi-dense depth: the full-resolution map and, at the working size, its
/// filtered inverse depth and variance.
struct Semidense<'a> {
    full: &'a DepthMap,
    filtered: &'a ImageF32,
    variance: &'a ImageF32,
}

/// What §III-E gives a keyframe: its pose, the variance of its dense depth, and the
/// two-view consistent depth when enough pixels agree.
struct Consistency {
    world_from_keyframe: Sim3,
    variance: ImageF32,
    consistent_pixels: usize,
    refined_depth: Option<Arc<DepthMap>>,
}

/// The layer as a background service: one keyframe per job, its answer as the reply.
impl Service for DenseLayer {
    type Job = DenseJob;
    type Reply = (KeyframeId, Result<DenseOutput>);

    fn handle(&mut self, jobs: Vec<DenseJob>, reply: &mut dyn FnMut(Self::Reply)) -> Result<()> {
        for job in jobs {
            let id = job.keyframe_id;
            reply((id, self.process(job)));
        }
        Ok(())
    }

    fn unavailable(job: DenseJob, error: &str) -> Option<Self::Reply> {
        Some((
            job.keyframe_id,
            Err(Error::Config(format!("dense layer: {error}"))),
        ))
    }
}

/// Whether the prior predicts metres (a poisoned lock reads as relative).
pub fn is_metric(prior: &SharedPrior) -> bool {
    prior.lock().is_ok_and(|p| p.describe().metric)
}

/// Runs the shared depth prior on one image (the raw relative inverse depth).
pub fn predict(prior: &SharedPrior, rgb: &::image::RgbImage) -> Result<ImageF32> {
    let mut model = prior
        .lock()
        .map_err(|_| Error::Prior("the depth prior panicked in another thread".into()))?;
    Ok(model.predict(rgb)?.into_image())
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Eq. (2) with the result kept a positive inverse depth (an affine fit can turn the far end
/// of the prior negative; densification needs ln D).
fn clamped(fit: &ScaleShift, prior: &ImageF32, min_idepth: f32) -> ImageF32 {
    let mut out = fit.apply_image(prior);
    for v in &mut out.data {
        *v = if v.is_finite() {
            v.max(min_idepth)
        } else {
            min_idepth
        };
    }
    out
}

/// Floor of the variance of densified (non-semi-dense) pixels: the median filtered semi-dense
/// variance (1e-3, the order of a converged LSD-SLAM estimate, when there is none).
///
/// A departure from the paper, which uses the propagated pose uncertainty alone (eq. 16): that
/// is the uncertainty of a *pose* estimated from tens of thousands of pixels, 100–1000× below a
/// semi-dense pixel's variance, so the back end would weigh each interpolated pixel far above
/// a measured one. A densified pixel is never more certain than the measurements it was
/// interpolated from.
fn dense_variance_floor(filtered_var: &ImageF32) -> f32 {
    let mut v: Vec<f32> = filtered_var
        .data
        .iter()
        .copied()
        .filter(|&v| v > 0.0)
        .collect();
    if v.is_empty() {
        return 1e-3;
    }
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// The variance attached to dense depth (§III-E): the filtered semi-dense variance on
/// semi-dense pixels, the propagated pose uncertainty (floored, see [`dense_variance_floor`])
/// elsewhere.
fn merge_variances(
    variance: &mut ImageF32,
    filtered: &ImageF32,
    filtered_var: &ImageF32,
    floor: f32,
) {
    for ((v, &d), &fv) in variance
        .data
        .iter_mut()
        .zip(&filtered.data)
        .zip(&filtered_var.data)
    {
        *v = if d > 0.0 { fv } else { v.max(floor) };
    }
}

/// The map the back end gets: LSD-SLAM's own semi-dense estimates where it has them, the
/// two-view consistent dense depth elsewhere. The paper keeps the semi-dense structure when
/// warping (§III-E); replacing the semi-dense pixels by their (much smaller) consistent
/// subset weakened the constraints (docs/tuning.md, "Refined depth"), so only the gaps are
/// filled.
fn keep_semidense(semidense: &DepthMap, mut consistent: DepthMap) -> DepthMap {
    for (c, s) in consistent.pixels.iter_mut().zip(&semidense.pixels) {
        if s.estimate().is_some() {
            *c = *s;
        }
    }
    consistent
}
