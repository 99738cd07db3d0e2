//! The per-keyframe semi-dense inverse-depth filter (Engel et al., ICCV 2013 §2–3; LSD-SLAM
//! `DepthMap`).
//!
//! Each high-gradient keyframe pixel carries a Gaussian inverse-depth hypothesis. Every tracked
//! frame is used for small-baseline epipolar stereo ([`DepthFilter::observe`]): new pixels
//! are searched over the whole depth range, existing ones within ±2σ, and results are fused
//! by a one-dimensional Kalman update (eq. 7). [`DepthFilter::regularize`] smooths the map and
//! removes unsupported hypotheses (§2.3), [`DepthFilter::propagate_to`] carries it to the next
//! keyframe (§2.2), and [`DepthFilter::normalize_scale`] fixes the monocular scale gauge (LSD
//! `createKeyFrame`: mean inverse depth 1).

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::bands::map_row_bands;
use super::hypothesis::{Estimate, Pixel, unzero};
use super::stereo::{Intrinsics, StereoFailure, StereoPair};
use super::{DepthMap, InverseDepth, MappingConfig, propagate, regularize};
use crate::frame::Frame;
use crate::geometry::SE3;
use crate::image::ImageF32;
use crate::{Error, Result};

/// What one [`DepthFilter::observe`] did, for logging and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ObserveStats {
    /// Pixels without hypothesis searched over the full range.
    pub create_attempted: usize,
    /// New hypotheses.
    pub created: usize,
    /// Existing hypotheses searched within ±2σ.
    pub update_attempted: usize,
    /// Successful Kalman updates.
    pub updated: usize,
    /// Observations inconsistent with the prior (variance inflated).
    pub inconsistent: usize,
    /// Ambiguous searches on existing hypotheses (validity decreased).
    pub failed: usize,
    /// Hypotheses removed (variance above `max_var`, or gradient too weak).
    pub removed: usize,
    /// Pixels skipped because the epipolar line was degenerate (tiny baseline, weak or
    /// orthogonal gradient).
    pub skipped_epl: usize,
    /// Hypotheses skipped because a recent short-baseline update made this frame redundant.
    pub skipped_recent: usize,
}

impl std::ops::AddAssign for ObserveStats {
    fn add_assign(&mut self, o: Self) {
        self.create_attempted += o.create_attempted;
        self.created += o.created;
        self.update_attempted += o.update_attempted;
        self.updated += o.updated;
        self.inconsistent += o.inconsistent;
        self.failed += o.failed;
        self.removed += o.removed;
        self.skipped_epl += o.skipped_epl;
        self.skipped_recent += o.skipped_recent;
    }
}

/// The semi-dense inverse-depth filter of one keyframe (full resolution, pyramid level 0).
#[derive(Debug, Clone)]
pub struct DepthFilter {
    pub(super) keyframe: Arc<Frame>,
    pub(super) config: MappingConfig,
    pub(super) k: Intrinsics,
    /// Max of |∇I| over each pixel's 3×3 neighbourhood (LSD `maxGradients`): a pixel is used
    /// when some neighbour is textured, so thin edges get a 3-pixel-wide band.
    pub(super) max_grad: ImageF32,
    pub(super) pixels: Vec<Pixel>,
    pub(super) frames_observed: usize,
    /// Reused buffers of [`Self::regularize`] (no per-frame allocation).
    scratch: regularize::Planes,
}

impl DepthFilter {
    /// An empty filter (no hypotheses) on `keyframe`; fails on an invalid config or an image
    /// too small for the 7-pixel search border.
    pub fn new(keyframe: Arc<Frame>, config: MappingConfig) -> Result<Self> {
        config.validate()?;
        let level = keyframe.level(0);
        let (w, h) = (level.width(), level.height());
        if w < 16 || h < 16 {
            return Err(Error::Shape(format!(
                "depth filter needs ≥ 16×16 pixels, got {w}x{h}"
            )));
        }
        let k = Intrinsics::new(&keyframe.camera);
        let max_grad = max3x3(&level.grad_mag);
        Ok(Self {
            keyframe,
            config,
            k,
            max_grad,
            pixels: vec![Pixel::default(); w * h],
            frames_observed: 0,
            scratch: regularize::Planes::default(),
        })
    }

    /// The keyframe this map belongs to.
    pub fn keyframe(&self) -> &Arc<Frame> {
        &self.keyframe
    }

    /// The configuration in use.
    pub fn config(&self) -> &MappingConfig {
        &self.config
    }

    /// Width of the map (the keyframe's level-0 width).
    pub fn width(&self) -> usize {
        self.max_grad.width
    }

    /// Height of the map.
    pub fn height(&self) -> usize {
        self.max_grad.height
    }

    /// Frames observed since creation.
    pub fn frames_observed(&self) -> usize {
        self.frames_observed
    }

    /// Number of pixels holding a hypothesis.
    pub fn num_estimates(&self) -> usize {
        self.pixels.iter().filter(|p| p.estimate.is_some()).count()
    }

    /// LSD `initializeRandomly`: every pixel with enough gradient gets an inverse depth drawn
    /// uniformly from [0.5, 1.5] with the large variance `var_random_init_initial`; the
    /// first observations then either confirm (within ±2σ) or, after repeated inconsistency,
    /// replace them by full-range searches. Deterministic for a seed.
    pub fn init_random(&mut self, seed: u64) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (w, h) = (self.width(), self.height());
        let cfg = &self.config;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let inner = x >= 1 && x + 1 < w && y >= 1 && y + 1 < h;
                self.pixels[i] = Pixel::default();
                if inner && self.max_grad.data[i] > cfg.min_use_grad {
                    let idepth = 0.5 + rng.random::<f32>();
                    self.pixels[i].set(Estimate::new(
                        idepth,
                        cfg.var_random_init_initial,
                        cfg.validity_counter_init,
                    ));
                }
            }
        }
    }

    /// LSD `initializeFromGTDepth`: hypotheses from a known inverse-depth image (ground truth,
    /// or a scale-normalised depth prior) with variance `var`, on pixels with enough gradient
    /// (the filter is semi-dense: elsewhere stereo could never confirm them) and a finite
    /// positive value. Other pixels are cleared.
    pub fn init_from_depth(&mut self, idepth: &ImageF32, var: f32) -> Result<()> {
        let (w, h) = (self.width(), self.height());
        if (idepth.width, idepth.height) != (w, h) {
            return Err(Error::Shape(format!(
                "inverse depth is {}x{}, keyframe {w}x{h}",
                idepth.width, idepth.height
            )));
        }
        if !(var.is_finite() && var > 0.0) {
            return Err(Error::Config(format!(
                "init_from_depth: variance must be positive, got {var}"
            )));
        }
        let cfg = &self.config;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let d = idepth.data[i];
                let inner = x >= 1 && x + 1 < w && y >= 1 && y + 1 < h;
                self.pixels[i] = Pixel::default();
                if inner && self.max_grad.data[i] >= cfg.min_use_grad && d.is_finite() && d > 0.0 {
                    self.pixels[i].set(Estimate::new(d, var, cfg.validity_counter_init));
                }
            }
        }
        Ok(())
    }

    /// Stereo against one tracked frame with a perfect tracking residual (see
    /// [`Self::observe_with_residual`]).
    pub fn observe(&mut self, frame: &Frame, keyframe_from_frame: &SE3) -> Result<ObserveStats> {
        self.observe_with_residual(frame, keyframe_from_frame, 0.0)
    }

    /// LSD `observeDepth`: epipolar stereo of every usable keyframe pixel in `frame`, whose
    /// pose relative to the keyframe is `keyframe_from_frame`. `tracking_residual` (LSD
    /// `initialTrackedResidual`, ≥ 0) scales the geometric error σ_l = `epipolar_line_noise`
    /// ·(1 + residual) of eq. (5). Frames must be observed in increasing `id` order.
    ///
    /// Pixels whose epipolar line is degenerate (tiny baseline) are skipped, so frames with
    /// almost no translation leave the map untouched.
    pub fn observe_with_residual(
        &mut self,
        frame: &Frame,
        keyframe_from_frame: &SE3,
        tracking_residual: f32,
    ) -> Result<ObserveStats> {
        let kf_level = self.keyframe.level(0);
        let fr_level = frame.level(0);
        if (fr_level.width(), fr_level.height()) != (self.width(), self.height()) {
            return Err(Error::Shape(format!(
                "frame is {}x{}, keyframe {}x{}",
                fr_level.width(),
                fr_level.height(),
                self.width(),
                self.height()
            )));
        }
        if frame.camera != self.keyframe.camera {
            return Err(Error::InvalidCamera(
                "frame and keyframe cameras differ".into(),
            ));
        }
        let pair = StereoPair::new(
            &kf_level.image,
            &kf_level.gx,
            &kf_level.gy,
            &fr_level.image,
            self.k,
            keyframe_from_frame,
            self.config.epipolar_line_noise * (1.0 + tracking_residual.max(0.0)),
        );
        let ctx = ObserveContext {
            pair,
            cfg: &self.config,
            max_grad: &self.max_grad,
            frame_id: frame.id,
        };
        let (w, h) = (self.width(), self.height());
        let threads = self.config.worker_threads();
        let parts = map_row_bands(&mut self.pixels, w, threads, |y0, band| {
            let mut stats = ObserveStats::default();
            for (r, row) in band.chunks_mut(w).enumerate() {
                let y = y0 + r;
                if y < 3 || y + 3 >= h {
                    continue;
                }
                for (x, px) in row.iter_mut().enumerate().take(w - 3).skip(3) {
                    ctx.observe_pixel(x, y, px, &mut stats);
                }
            }
            stats
        });
        self.frames_observed += 1;
        let mut stats = ObserveStats::default();
        for s in parts {
            stats += s;
        }
        Ok(stats)
    }

    /// LSD `updateKeyframe`'s post-processing: fill holes surrounded by confident hypotheses
    /// (`regularizeDepthMapFillHoles`), then smooth every hypothesis with the
    /// inverse-variance-weighted mean of its agreeing 5×5 neighbours and remove those whose
    /// agreeing neighbourhood is too weakly supported (`regularizeDepthMap`, ICCV 2013 §2.3).
    pub fn regularize(&mut self) {
        let (w, h) = (self.width(), self.height());
        let threads = self.config.worker_threads();
        regularize::regularize(
            &mut self.pixels,
            &self.max_grad,
            w,
            h,
            &self.config,
            threads,
            &mut self.scratch,
        );
    }

    /// Carries this map to `new_keyframe`, whose pose relative to this keyframe is
    /// `new_from_old` (maps points of this keyframe into the new one); LSD `createKeyFrame`
    /// without the scale normalisation: forward-warp, occlusion-aware merge, then
    /// regularisation with occlusion removal, hole filling and regularisation (ICCV 2013 §2.2).
    pub fn propagate_to(
        &self,
        new_keyframe: Arc<Frame>,
        new_from_old: &SE3,
    ) -> Result<DepthFilter> {
        if new_keyframe.camera != self.keyframe.camera {
            return Err(Error::InvalidCamera(
                "old and new keyframe cameras differ".into(),
            ));
        }
        let mut next = DepthFilter::new(new_keyframe, self.config.clone())?;
        propagate::warp(self, &mut next, new_from_old);
        let (w, h) = (next.width(), next.height());
        let threads = next.config.worker_threads();
        regularize::smooth(&mut next.pixels, w, h, &next.config, true, threads);
        regularize::regularize(
            &mut next.pixels,
            &next.max_grad,
            w,
            h,
            &next.config,
            threads,
            &mut next.scratch,
        );
        Ok(next)
    }

    /// Rescales all inverse depths so that the mean smoothed inverse depth is 1 (LSD
    /// `createKeyFrame`), which fixes the scale gauge of monocular SLAM per keyframe. Returns
    /// the factor `f` (new idepth = f · old; variances scale by f²): the keyframe's
    /// `parent_from_keyframe` becomes the Sim(3) with the same rotation and translation and
    /// scale `f`. Returns 1 and changes nothing without usable estimates.
    pub fn normalize_scale(&mut self) -> f64 {
        let (sum, n) = self
            .pixels
            .iter()
            .filter_map(|p| p.estimate)
            .fold((0.0f64, 0usize), |(s, n), e| {
                (s + f64::from(e.idepth_smoothed), n + 1)
            });
        if n == 0 || !sum.is_finite() || sum <= 0.0 {
            return 1.0;
        }
        let f = n as f64 / sum;
        let (f1, f2) = (f as f32, (f * f) as f32);
        for e in self.pixels.iter_mut().filter_map(|p| p.estimate.as_mut()) {
            e.idepth *= f1;
            e.idepth_smoothed *= f1;
            e.var *= f2;
            e.var_smoothed *= f2;
        }
        f
    }

    /// The published snapshot (LSD `Frame::setDepth`): smoothed inverse depth and variance
    /// of every positive estimate; blacklisted pixels are [`InverseDepth::Discarded`].
    pub fn depth_map(&self) -> DepthMap {
        let cfg = &self.config;
        let pixels = self
            .pixels
            .iter()
            .map(|p| match p.estimate {
                Some(e)
                    if e.idepth_smoothed > 0.0
                        && e.idepth_smoothed.is_finite()
                        && e.var_smoothed > 0.0 =>
                {
                    InverseDepth::Estimate {
                        idepth: e.idepth_smoothed,
                        var: e.var_smoothed,
                    }
                }
                _ if p.blacklist < cfg.min_blacklist => InverseDepth::Discarded,
                _ => InverseDepth::Unknown,
            })
            .collect();
        DepthMap {
            width: self.width(),
            height: self.height(),
            pixels,
        }
    }

    /// [`DepthMap::mean_idepth`] of [`Self::depth_map`] (same value, same summation order)
    /// without building the map: the keyframe criterion needs it for every tracked frame.
    pub fn mean_idepth(&self) -> Option<f64> {
        let (sum, n) = self
            .pixels
            .iter()
            .filter_map(|p| p.estimate)
            .filter(|e| {
                e.idepth_smoothed > 0.0 && e.idepth_smoothed.is_finite() && e.var_smoothed > 0.0
            })
            .fold((0.0f64, 0usize), |(s, n), e| {
                (s + f64::from(e.idepth_smoothed), n + 1)
            });
        (n > 0).then(|| sum / n as f64)
    }

    /// Raw (unsmoothed) estimate at (x, y): `(idepth, var)`. For diagnostics and tests.
    pub fn raw_estimate(&self, x: usize, y: usize) -> Option<(f32, f32)> {
        self.pixels[y * self.width() + x]
            .estimate
            .map(|e| (e.idepth, e.var))
    }

    /// A filter re-created from a keyframe's published depth (LSD `setFromExistingKF`): each
    /// estimate becomes a hypothesis with the initial validity, so an earlier keyframe can be
    /// propagated into a relocalised frame.
    pub fn from_depth_map(
        keyframe: Arc<Frame>,
        depth: &DepthMap,
        config: MappingConfig,
    ) -> Result<Self> {
        let validity = config.validity_counter_init;
        let mut filter = Self::new(keyframe, config)?;
        if (depth.width, depth.height) != (filter.width(), filter.height()) {
            return Err(Error::Shape(format!(
                "depth map is {}x{}, keyframe {}x{}",
                depth.width,
                depth.height,
                filter.width(),
                filter.height()
            )));
        }
        for y in 0..depth.height {
            for x in 0..depth.width {
                if let Some((idepth, var)) = depth.at(x, y).estimate() {
                    filter.set_estimate(x, y, idepth, var, validity);
                }
            }
        }
        Ok(filter)
    }

    /// Overwrites (or creates) the hypothesis at (x, y) with validity `validity`; for tests
    /// and tools that inject known values.
    pub fn set_estimate(&mut self, x: usize, y: usize, idepth: f32, var: f32, validity: i32) {
        let w = self.width();
        self.pixels[y * w + x].set(Estimate::new(idepth, var, validity));
    }
}

/// Everything a pixel's observation reads.
struct ObserveContext<'a> {
    pair: StereoPair<'a>,
    cfg: &'a MappingConfig,
    max_grad: &'a ImageF32,
    frame_id: u64,
}

impl ObserveContext<'_> {
    /// LSD `observeDepthRow` for one pixel.
    fn observe_pixel(&self, x: usize, y: usize, px: &mut Pixel, stats: &mut ObserveStats) {
        let cfg = self.cfg;
        let grad = self.max_grad.data[y * self.max_grad.width + x];
        if grad < cfg.min_use_grad {
            if px.estimate.take().is_some() {
                stats.removed += 1;
            }
            return;
        }
        if px.blacklist < cfg.min_blacklist {
            return;
        }
        match px.estimate {
            None => self.create(x, y, px, stats),
            Some(e) => self.update(x, y, e, grad, px, stats),
        }
    }

    /// LSD `observeDepthCreate`: full-range search [0, 1/min_depth].
    fn create(&self, x: usize, y: usize, px: &mut Pixel, stats: &mut ObserveStats) {
        let cfg = self.cfg;
        let Some(epl) = self.pair.epipolar_direction(x, y, cfg) else {
            stats.skipped_epl += 1;
            return;
        };
        stats.create_attempted += 1;
        match self
            .pair
            .search(x as f32, y as f32, epl, 0.0, 1.0, 1.0 / cfg.min_depth, cfg)
        {
            Err(StereoFailure::Ambiguous | StereoFailure::NotFound) => px.blacklist -= 1,
            Err(_) => {}
            Ok(m) if m.var <= cfg.max_var => {
                px.set(Estimate::new(
                    unzero(m.idepth),
                    m.var,
                    cfg.validity_counter_initial_observe,
                ));
                stats.created += 1;
            }
            Ok(_) => {}
        }
    }

    /// LSD `observeDepthUpdate`: search within ±`stereo_epl_var_fac`·σ of the smoothed
    /// estimate, then fuse (eq. 7) or penalise.
    fn update(
        &self,
        x: usize,
        y: usize,
        mut e: Estimate,
        grad: f32,
        px: &mut Pixel,
        stats: &mut ObserveStats,
    ) {
        let cfg = self.cfg;
        if e.next_stereo_frame > self.frame_id {
            stats.skipped_recent += 1;
            return;
        }
        let Some(epl) = self.pair.epipolar_direction(x, y, cfg) else {
            stats.skipped_epl += 1;
            return;
        };
        stats.update_attempted += 1;
        let sd = e.var_smoothed.max(0.0).sqrt();
        let min_idepth = (e.idepth_smoothed - sd * cfg.stereo_epl_var_fac).max(0.0);
        let max_idepth = (e.idepth_smoothed + sd * cfg.stereo_epl_var_fac).min(1.0 / cfg.min_depth);
        let result = self.pair.search(
            x as f32,
            y as f32,
            epl,
            min_idepth,
            e.idepth_smoothed,
            max_idepth,
            cfg,
        );
        match result {
            // Out of bounds, not found (occluded), NaN: no evidence either way.
            Err(
                StereoFailure::OutOfBounds | StereoFailure::NotFound | StereoFailure::Arithmetic,
            ) => {}
            Err(StereoFailure::Ambiguous) => {
                stats.failed += 1;
                e.validity = (e.validity - cfg.validity_counter_dec).max(0);
                e.next_stereo_frame = 0;
                e.var *= cfg.fail_var_inc_fac;
                if e.var > cfg.max_var {
                    px.estimate = None;
                    px.blacklist -= 1;
                    stats.removed += 1;
                } else {
                    px.estimate = Some(e);
                }
            }
            Ok(m) => {
                let diff = m.idepth - e.idepth_smoothed;
                if cfg.diff_fac_observe * diff * diff > m.var + e.var_smoothed {
                    stats.inconsistent += 1;
                    e.var *= cfg.fail_var_inc_fac;
                    if e.var > cfg.max_var {
                        px.estimate = None;
                        stats.removed += 1;
                    } else {
                        px.estimate = Some(e);
                    }
                    return;
                }
                stats.updated += 1;
                // eq. (7) with a small prediction inflation; the variance never grows here.
                let prior_var = e.var * cfg.succ_var_inc_fac;
                let w = m.var / (m.var + prior_var);
                e.idepth = unzero((1.0 - w) * m.idepth + w * e.idepth);
                e.var = e.var.min(prior_var * w);
                let cap =
                    cfg.validity_counter_max + grad * cfg.validity_counter_max_variable / 255.0;
                e.validity = ((e.validity + cfg.validity_counter_inc) as f32).min(cap) as i32;
                if m.epl_length < cfg.min_epl_length_crop {
                    // Short segments: the next frames see nearly the same baseline; skip some
                    // (with a parity jitter so neighbouring pixels do not skip in lockstep).
                    let mut inc = cfg.short_epl_skip_frames + ((m.epl_length * 10000.0) as u64 % 2);
                    if m.epl_length < 0.5 * cfg.min_epl_length_crop {
                        inc *= 3;
                    }
                    e.next_stereo_frame = self.frame_id + inc;
                }
                px.estimate = Some(e);
            }
        }
    }
}

/// 3×3 maximum filter (clamped at the borders), separably: rows, then columns.
fn max3x3(img: &ImageF32) -> ImageF32 {
    let (w, h) = (img.width, img.height);
    let mut rows = ImageF32::filled(w, h, 0.0);
    for (src, dst) in img.data.chunks_exact(w).zip(rows.data.chunks_exact_mut(w)) {
        for (x, d) in dst.iter_mut().enumerate() {
            let a = src[x.saturating_sub(1)];
            let c = src[(x + 1).min(w - 1)];
            *d = a.max(src[x]).max(c);
        }
    }
    let mut out = ImageF32::filled(w, h, 0.0);
    for (y, dst) in out.data.chunks_exact_mut(w).enumerate() {
        let row = |y: usize| &rows.data[y * w..(y + 1) * w];
        let (a, b, c) = (row(y.saturating_sub(1)), row(y), row((y + 1).min(h - 1)));
        for (x, d) in dst.iter_mut().enumerate() {
            *d = a[x].max(b[x]).max(c[x]);
        }
    }
    out
}
