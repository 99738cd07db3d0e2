//! Immature points: candidates whose inverse depth is still an interval, narrowed by an
//! epipolar search in every new frame until it is sharp enough to activate the point in the
//! window (DSO, TPAMI 2018 §3.3; `ImmaturePoint.cpp`, read, not copied).
//!
//! Why: a point enters the joint optimisation only with a depth good enough to lie in the
//! basin of convergence; before that its depth comes from triangulation against frames that
//! the tracker posed, never from a propagated map.

use nalgebra::{Vector2, Vector3};

use super::energy::huber_energy;
use super::residual::PATTERN;
use crate::geometry::{PinholeCamera, SE3};
use crate::image::pyramid::PyramidLevel;

/// Parameters of the epipolar search.
#[derive(Clone, Debug, PartialEq)]
pub struct TraceConfig {
    /// Longest search along the epipolar line, as a share of `width + height`
    /// (`setting_maxPixSearch` = 0.027).
    pub max_pixel_search: f64,
    /// The best match must be this many times better than the best one more than
    /// 2 pixels away (`setting_minTraceQuality` = 3).
    pub min_quality: f64,
    /// A match whose pattern energy is above this is an outlier (12² · 8 with DSO's slack of
    /// 1.2, `setting_trace_extraSlackOnTH`).
    pub outlier_energy: f64,
    /// Huber width of a pattern pixel's residual, grey levels.
    pub huber: f64,
    /// Gauss–Newton steps that refine the match along the line (`setting_trace_GNIterations`).
    pub refine_iterations: usize,
}

impl Default for TraceConfig {
    fn default() -> Self {
        Self {
            max_pixel_search: 0.027,
            min_quality: 3.0,
            outlier_energy: 1.2 * 12.0 * 12.0 * PATTERN.len() as f64,
            huber: 9.0,
            refine_iterations: 3,
        }
    }
}

/// A frame a candidate is traced in.
#[derive(Clone, Copy, Debug)]
pub struct TraceTarget<'a> {
    /// The host keyframe's camera (level 0).
    pub host_camera: &'a PinholeCamera,
    /// The frame's level-0 image and camera.
    pub level: &'a PyramidLevel,
    pub camera: &'a PinholeCamera,
    /// The frame's pose relative to the host.
    pub target_from_host: &'a SE3,
    /// Brightness transfer `I_t ≈ e·(I_h − b_h) + b_t` as `(e, b_h, b_t)`.
    pub affine: (f64, f64, f64),
}

/// What the last trace of a point found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TraceStatus {
    /// Not traced yet.
    Fresh,
    /// A match; the interval was narrowed.
    Good,
    /// The interval is already as narrow as this frame could make it.
    Skipped,
    /// The line runs along an edge: the match is uncertain by many pixels.
    BadCondition,
    /// The point falls outside the frame.
    OutOfBounds,
    /// No match within the outlier energy.
    Outlier,
}

/// A candidate point of a keyframe.
#[derive(Clone, Debug, PartialEq)]
pub struct ImmaturePoint {
    pub host: u64,
    /// Pixel in the host (level 0).
    pub uv: Vector2<f64>,
    pub intensity: [f64; PATTERN.len()],
    /// Host gradients at the pattern pixels (how well a direction is measured).
    pub gradient: [Vector2<f64>; PATTERN.len()],
    pub idepth_min: f64,
    /// `f64::INFINITY` until a first match bounds it.
    pub idepth_max: f64,
    /// Best-to-second-best energy ratio of the last match.
    pub quality: f64,
    /// Length in pixels of the last match's uncertainty along the line.
    pub pixel_interval: f64,
    pub status: TraceStatus,
    pub outliers: u32,
    /// A metric depth model's inverse depth at its pixel, in the window's units, when there
    /// is one: the prior the point takes into the window.
    pub metric_idepth: Option<f64>,
}

impl ImmaturePoint {
    /// A candidate at `uv` of `host` (its level 0); `None` when its pattern leaves the image.
    pub fn new(host: u64, level: &PyramidLevel, uv: Vector2<f64>) -> Option<Self> {
        let mut intensity = [0.0; PATTERN.len()];
        let mut gradient = [Vector2::zeros(); PATTERN.len()];
        for (k, (ox, oy)) in PATTERN.iter().enumerate() {
            let (x, y) = ((uv.x + ox) as f32, (uv.y + oy) as f32);
            intensity[k] = f64::from(level.image.bilinear(x, y)?);
            gradient[k] = Vector2::new(
                f64::from(level.gx.bilinear(x, y)?),
                f64::from(level.gy.bilinear(x, y)?),
            );
        }
        Some(Self {
            host,
            uv,
            intensity,
            gradient,
            idepth_min: 0.0,
            idepth_max: f64::INFINITY,
            quality: 0.0,
            pixel_interval: f64::INFINITY,
            status: TraceStatus::Fresh,
            outliers: 0,
            metric_idepth: None,
        })
    }

    /// Whether the point may join the window: a sharp, unambiguous last match
    /// (DSO's `canActivate`: interval under 8 pixels, quality above the minimum).
    pub fn can_activate(&self, config: &TraceConfig) -> bool {
        matches!(
            self.status,
            TraceStatus::Good | TraceStatus::Skipped | TraceStatus::BadCondition
        ) && self.pixel_interval < 8.0
            && self.quality > config.min_quality
            && self.idepth_max.is_finite()
            && self.idepth_min + self.idepth_max > 0.0
    }

    /// The depth it starts with when activated: the middle of its interval.
    pub fn idepth(&self) -> f64 {
        0.5 * (self.idepth_min + self.idepth_max)
    }

    /// Pattern energy of the host pattern placed at `u` in `target` (Huber, with the
    /// brightness transfer `I_t ≈ e·(I_h − b_h) + b_t` given as `(e, b_h, b_t)`).
    fn energy(
        &self,
        config: &TraceConfig,
        target: &PyramidLevel,
        u: Vector2<f64>,
        affine: (f64, f64, f64),
    ) -> Option<f64> {
        let (e, b_h, b_t) = affine;
        let mut total = 0.0;
        for (k, (ox, oy)) in PATTERN.iter().enumerate() {
            let i = f64::from(
                target
                    .image
                    .bilinear((u.x + ox) as f32, (u.y + oy) as f32)?,
            );
            total += huber_energy(config.huber, i - b_t - e * (self.intensity[k] - b_h));
        }
        Some(total)
    }

    /// Narrows the interval by a search along the epipolar line in `target`.
    pub fn trace(&mut self, config: &TraceConfig, target: &TraceTarget<'_>) -> TraceStatus {
        self.status = self.search(config, target);
        self.status
    }

    fn search(&mut self, config: &TraceConfig, frame: &TraceTarget<'_>) -> TraceStatus {
        let line = match self.epipolar_line(config, frame) {
            Ok(line) => line,
            Err(status) => return status,
        };
        // Discrete search, one pixel per step.
        let energies: Vec<f64> = (0..line.steps())
            .map(|i| {
                let u = line.at(i as f64);
                if line.inside(&u) {
                    self.energy(config, frame.level, u, frame.affine)
                        .unwrap_or(f64::INFINITY)
                } else {
                    f64::INFINITY
                }
            })
            .collect();
        let Some((best_i, &best)) = energies
            .iter()
            .enumerate()
            .min_by(|x, y| x.1.total_cmp(y.1))
        else {
            return TraceStatus::OutOfBounds;
        };
        if !best.is_finite() {
            return TraceStatus::OutOfBounds;
        }
        let second = energies
            .iter()
            .enumerate()
            .filter(|(i, _)| i.abs_diff(best_i) > 2)
            .map(|(_, e)| *e)
            .fold(f64::INFINITY, f64::min);
        let (s, energy) = self.refine_along(config, frame, &line, best_i as f64, best);
        if energy > config.outlier_energy {
            self.outliers += 1;
            return TraceStatus::Outlier;
        }
        self.quality = second / energy.max(1e-9);
        self.narrow_to(frame, &line, s)
    }

    /// The stretch of the frame's epipolar line that the interval maps to, from its far end,
    /// and how well the host pattern's gradients measure along it; or why there is nothing
    /// to search.
    fn epipolar_line(
        &self,
        config: &TraceConfig,
        frame: &TraceTarget<'_>,
    ) -> Result<EpipolarLine, TraceStatus> {
        let target = frame.level;
        let (w, h) = (target.width() as f64, target.height() as f64);
        let ray = frame
            .target_from_host
            .rotation
            .act(&frame.host_camera.unproject(&self.uv, 1.0));
        let t = frame.target_from_host.translation;
        let project = |p: Vector3<f64>| (p.z > 1e-6).then(|| frame.camera.project(&p));
        let mut line = EpipolarLine {
            ray,
            t,
            u_min: project(ray + t * self.idepth_min).ok_or(TraceStatus::OutOfBounds)?,
            dir: Vector2::zeros(),
            dist: 0.0,
            error_in_pixel: 0.0,
            size: (w, h),
        };
        if !line.inside(&line.u_min) {
            return Err(TraceStatus::OutOfBounds);
        }
        let max_search = config.max_pixel_search * (w + h);
        let (dir, dist) = if self.idepth_max.is_finite() {
            let u_max = project(ray + t * self.idepth_max).ok_or(TraceStatus::OutOfBounds)?;
            let d = u_max - line.u_min;
            (d.try_normalize(1e-12), d.norm().min(max_search))
        } else {
            // Unbounded: search the longest allowed stretch from the far end.
            let u_near =
                project(ray + t * (self.idepth_min + 0.01)).ok_or(TraceStatus::OutOfBounds)?;
            ((u_near - line.u_min).try_normalize(1e-12), max_search)
        };
        let dir = dir.ok_or(TraceStatus::BadCondition)?;
        // How well the line's direction is measured by the host pattern's gradients.
        let perp = Vector2::new(-dir.y, dir.x);
        let (a, b) = self.gradient.iter().fold((0.0, 0.0), |(a, b), g| {
            (a + g.dot(&dir).powi(2), b + g.dot(&perp).powi(2))
        });
        let error_in_pixel = (0.2 + 0.2 * (a + b) / a.max(1e-12)).min(10.0);
        if self.idepth_max.is_finite() && dist < 1.5
            || (self.idepth_max.is_finite() && 2.0 * error_in_pixel > dist)
        {
            return Err(TraceStatus::Skipped);
        }
        line.dir = dir;
        line.dist = dist;
        line.error_in_pixel = error_in_pixel;
        Ok(line)
    }

    /// Gauss–Newton on the step length along the line from step `s` (energy `energy`); the
    /// best step and its energy.
    fn refine_along(
        &self,
        config: &TraceConfig,
        frame: &TraceTarget<'_>,
        line: &EpipolarLine,
        mut s: f64,
        mut energy: f64,
    ) -> (f64, f64) {
        let (target, dir) = (frame.level, line.dir);
        for _ in 0..config.refine_iterations {
            let u = line.at(s);
            let (e, b_h, b_t) = frame.affine;
            let (mut hs, mut gs) = (0.0, 0.0);
            for (k, (ox, oy)) in PATTERN.iter().enumerate() {
                let (x, y) = ((u.x + ox) as f32, (u.y + oy) as f32);
                let (Some(i), Some(gx), Some(gy)) = (
                    target.image.bilinear(x, y),
                    target.gx.bilinear(x, y),
                    target.gy.bilinear(x, y),
                ) else {
                    continue;
                };
                let r = f64::from(i) - b_t - e * (self.intensity[k] - b_h);
                let j = f64::from(gx) * dir.x + f64::from(gy) * dir.y;
                let wh = if r.abs() <= config.huber {
                    1.0
                } else {
                    config.huber / r.abs()
                };
                hs += wh * j * j;
                gs += wh * j * r;
            }
            if hs <= 1e-12 {
                break;
            }
            let candidate = s - (gs / hs).clamp(-0.5, 0.5);
            let u_c = line.at(candidate);
            match line
                .inside(&u_c)
                .then(|| self.energy(config, target, u_c, frame.affine))
                .flatten()
            {
                Some(e) if e < energy => {
                    energy = e;
                    s = candidate;
                }
                _ => break,
            }
        }
        (s, energy)
    }

    /// The interval: the inverse depths at the match (step `s`) ± its uncertainty along the
    /// line.
    fn narrow_to(&mut self, frame: &TraceTarget<'_>, line: &EpipolarLine, s: f64) -> TraceStatus {
        let (camera, dir, pr, t) = (frame.camera, line.dir, line.ray, line.t);
        let idepth_at = |s: f64| {
            let u = line.at(s);
            // Solve along the axis the line moves most in.
            if dir.x.abs() > dir.y.abs() {
                let q = (u.x - camera.cx) / camera.fx;
                (pr.x - q * pr.z) / (q * t.z - t.x)
            } else {
                let q = (u.y - camera.cy) / camera.fy;
                (pr.y - q * pr.z) / (q * t.z - t.y)
            }
        };
        let error_in_pixel = line.error_in_pixel;
        let (d1, d2) = (idepth_at(s - error_in_pixel), idepth_at(s + error_in_pixel));
        let (lo, hi) = (d1.min(d2), d1.max(d2));
        if !(lo.is_finite() && hi.is_finite()) || hi <= 0.0 {
            self.outliers += 1;
            return TraceStatus::Outlier;
        }
        self.idepth_min = lo.max(0.0);
        self.idepth_max = hi;
        self.pixel_interval = 2.0 * error_in_pixel;
        if error_in_pixel >= 10.0 {
            TraceStatus::BadCondition
        } else {
            TraceStatus::Good
        }
    }
}

/// The stretch of a frame's epipolar line one trace searches.
struct EpipolarLine {
    /// The host pixel's ray rotated into the frame, and the frame's translation from the host:
    /// the point at inverse depth d is `ray + t·d` (up to scale).
    ray: Vector3<f64>,
    t: Vector3<f64>,
    /// The far end (the interval's smallest inverse depth) in frame pixels.
    u_min: Vector2<f64>,
    /// Unit direction towards the near end, and the length searched.
    dir: Vector2<f64>,
    dist: f64,
    /// The match's uncertainty along the line (pixels).
    error_in_pixel: f64,
    /// The frame's size.
    size: (f64, f64),
}

impl EpipolarLine {
    /// Pixels this far from the border are searched.
    const MARGIN: f64 = 4.0;

    fn at(&self, s: f64) -> Vector2<f64> {
        self.u_min + self.dir * s
    }

    fn steps(&self) -> usize {
        self.dist.floor() as usize + 1
    }

    fn inside(&self, u: &Vector2<f64>) -> bool {
        let ((w, h), m) = (self.size, Self::MARGIN);
        u.x > m && u.y > m && u.x < w - m - 1.0 && u.y < h - m - 1.0
    }
}
