//! The window's photometric energy and its normal equations: robust weights, outliers, and
//! each point's depth block kept apart for the Schur complement.

use nalgebra::{DMatrix, DVector};

use super::WindowPoint;
use super::config::OdometryConfig;
use super::residual::{
    FRAME_PARAMS, FrameView, Linearisation, Linearised, Matrix8, PATTERN, PairGeometry, Vector8,
    linearise_in, residual_in,
};

/// Robust weight of a pattern pixel: DSO's gradient-dependent weight times Huber's.
fn weight(config: &OdometryConfig, lin: &Linearised) -> f64 {
    let c2 = config.gradient_weight_c * config.gradient_weight_c;
    let w_grad = c2 / (c2 + lin.grad2);
    let r = lin.residual.abs() * w_grad.sqrt();
    let huber = if r <= config.huber {
        1.0
    } else {
        config.huber / r
    };
    w_grad * huber
}

/// Huber energy of a residual `r` with width `d` (twice the usual ½ρ, as DSO sums it).
pub fn huber_energy(d: f64, r: f64) -> f64 {
    let r = r.abs();
    if r <= d { r * r } else { 2.0 * d * r - d * d }
}

/// What a point-target pair costs when it is an outlier or not visible: as much as a pattern
/// whose every pixel sits at the outlier threshold, so that pushing a point out of view or
/// into the outliers never lowers the energy.
pub fn outlier_energy(config: &OdometryConfig) -> f64 {
    PATTERN.len() as f64 * huber_energy(config.huber, config.outlier_threshold)
}

/// The linearised pattern of `point` in `target`, or `None` when a pixel is not visible or the
/// pattern is an outlier there (see [`outlier_tested`]).
pub fn pattern(
    config: &OdometryConfig,
    point: &WindowPoint,
    host: &FrameView<'_>,
    target: &FrameView<'_>,
    mode: Linearisation,
) -> Option<[Linearised; PATTERN.len()]> {
    let pair = PairGeometry::new(host, target, mode, &point.uv, point.idepth);
    outlier_tested(
        config,
        |k| {
            linearise_in(
                &pair,
                &point.uv,
                point.idepth,
                point.intensity[k],
                k,
                host,
                target,
            )
        },
        |lin| (lin.residual, lin.grad2),
    )
}

/// [`pattern`]'s residuals and squared gradients at the current state, without the
/// Jacobians (what an energy needs); `None` as for [`pattern`].
fn pattern_residuals(
    config: &OdometryConfig,
    point: &WindowPoint,
    host: &FrameView<'_>,
    target: &FrameView<'_>,
) -> Option<[(f64, f64); PATTERN.len()]> {
    let pair = PairGeometry::new(
        host,
        target,
        Linearisation::Current,
        &point.uv,
        point.idepth,
    );
    outlier_tested(
        config,
        |k| {
            residual_in(
                &pair,
                &point.uv,
                point.idepth,
                point.intensity[k],
                k,
                host,
                target,
            )
        },
        |&pixel| pixel,
    )
}

/// The pattern's pixels from `pixel` (`None` when one is not visible), or `None` when their
/// gradient-weighted energy (`residual(pixel)` gives residual and squared gradient) is above
/// `outlier_threshold²` per pixel. Gradient-weighted, as DSO tests it: on a strong edge a
/// sub-pixel error is a large residual, not an outlier.
#[inline]
fn outlier_tested<T: Copy>(
    config: &OdometryConfig,
    mut pixel: impl FnMut(usize) -> Option<T>,
    residual: impl Fn(&T) -> (f64, f64),
) -> Option<[T; PATTERN.len()]> {
    let c2 = config.gradient_weight_c * config.gradient_weight_c;
    let mut out = [None; PATTERN.len()];
    let mut energy = 0.0;
    for (k, slot) in out.iter_mut().enumerate() {
        let value = pixel(k)?;
        let (r, grad2) = residual(&value);
        energy += r * r * c2 / (c2 + grad2);
        *slot = Some(value);
    }
    let limit = config.outlier_threshold * config.outlier_threshold * PATTERN.len() as f64;
    if energy > limit {
        return None;
    }
    Some(out.map(|v| v.unwrap_or_else(|| unreachable!("every pattern pixel was filled"))))
}

/// The depth priors' energy of `points`.
pub fn depth_prior_energy(points: &[WindowPoint]) -> f64 {
    points
        .iter()
        .filter_map(|p| p.prior.map(|prior| prior.energy(p.idepth)))
        .sum()
}

/// Photometric energy of the window and the number of pattern residuals in it.
/// `hosts[i]` is the index in `views` of point `i`'s host.
pub fn photometric_energy(
    config: &OdometryConfig,
    points: &[WindowPoint],
    hosts: &[usize],
    views: &[FrameView<'_>],
) -> (f64, usize) {
    let c2 = config.gradient_weight_c * config.gradient_weight_c;
    let mut total = 0.0;
    let mut n = 0;
    for (p, &h) in points.iter().zip(hosts) {
        for (t, target) in views.iter().enumerate() {
            if t == h {
                continue;
            }
            match pattern_residuals(config, p, &views[h], target) {
                Some(pixels) => {
                    for (residual, grad2) in pixels {
                        total += huber_energy(config.huber, residual * (c2 / (c2 + grad2)).sqrt());
                        n += 1;
                    }
                }
                None => total += outlier_energy(config),
            }
        }
    }
    (total, n)
}

/// One point's part of the normal equations: its depth block, its depth gradient and its
/// coupling `H_kρ` with each keyframe `k` it touches.
#[derive(Clone, Debug, Default)]
pub struct PointSystem {
    pub h_dd: f64,
    pub b_d: f64,
    pub coupling: Vec<(usize, Vector8)>,
    /// Targets in which the point was an inlier.
    pub inlier_targets: usize,
}

/// The keyframes' Hessian and gradient (`8·n`), and every point's [`PointSystem`].
#[derive(Clone, Debug)]
pub struct NormalEquations {
    pub h: DMatrix<f64>,
    pub b: DVector<f64>,
    pub points: Vec<PointSystem>,
    pub residuals: usize,
}

impl NormalEquations {
    /// Zero equations for `frames` keyframes.
    pub fn zeros(frames: usize) -> Self {
        let n = frames * FRAME_PARAMS;
        Self {
            h: DMatrix::zeros(n, n),
            b: DVector::zeros(n),
            points: Vec::new(),
            residuals: 0,
        }
    }

    /// Adds the residuals of `point` (hosted in `views[host]`) in every other keyframe.
    pub fn add_point(
        &mut self,
        config: &OdometryConfig,
        point: &WindowPoint,
        host: usize,
        views: &[FrameView<'_>],
        mode: Linearisation,
    ) {
        let mut sys = PointSystem::default();
        let mut host_col = Vector8::zeros();
        let oh = host * FRAME_PARAMS;
        for (t, target) in views.iter().enumerate() {
            if t == host {
                continue;
            }
            let Some(lins) = pattern(config, point, &views[host], target, mode) else {
                continue;
            };
            let ot = t * FRAME_PARAMS;
            let mut target_col = Vector8::zeros();
            for lin in &lins {
                let w = weight(config, lin);
                let (jh, jt, jd, r) = (&lin.d_host, &lin.d_target, lin.d_idepth, lin.residual);
                let ht = w * jh * jt.transpose();
                let mut add = |r0: usize, c0: usize, m: &Matrix8| {
                    let mut view = self.h.view_mut((r0, c0), (FRAME_PARAMS, FRAME_PARAMS));
                    view += m;
                };
                add(oh, oh, &(w * jh * jh.transpose()));
                add(oh, ot, &ht);
                add(ot, oh, &ht.transpose());
                add(ot, ot, &(w * jt * jt.transpose()));
                let mut bh = self.b.rows_mut(oh, FRAME_PARAMS);
                bh += w * r * jh;
                let mut bt = self.b.rows_mut(ot, FRAME_PARAMS);
                bt += w * r * jt;
                sys.h_dd += w * jd * jd;
                sys.b_d += w * jd * r;
                host_col += w * jd * jh;
                target_col += w * jd * jt;
                self.residuals += 1;
            }
            sys.inlier_targets += 1;
            sys.coupling.push((t, target_col));
        }
        if let Some(prior) = point.prior {
            let w = prior.weight_at(point.idepth);
            sys.h_dd += w;
            sys.b_d += w * (point.idepth - prior.idepth);
        }
        sys.coupling.push((host, host_col));
        self.points.push(sys);
    }

    /// The equations of every point of the window.
    pub fn build(
        config: &OdometryConfig,
        points: &[WindowPoint],
        hosts: &[usize],
        views: &[FrameView<'_>],
        mode: Linearisation,
    ) -> Self {
        let mut eq = Self::zeros(views.len());
        for (p, &h) in points.iter().zip(hosts) {
            eq.add_point(config, p, h, views, mode);
        }
        eq
    }

    /// The keyframes' system with every depth eliminated (Schur complement; each depth block
    /// is a scalar), each depth's diagonal damped by `1 + lambda` first.
    pub fn reduced(&self, lambda: f64) -> (DMatrix<f64>, DVector<f64>) {
        let mut h = self.h.clone();
        let mut b = self.b.clone();
        for sys in &self.points {
            let hdd = sys.h_dd * (1.0 + lambda);
            if hdd <= 1e-12 {
                continue;
            }
            for (k, ck) in &sys.coupling {
                let ok = k * FRAME_PARAMS;
                let mut bk = b.rows_mut(ok, FRAME_PARAMS);
                bk -= ck * (sys.b_d / hdd);
                for (l, cl) in &sys.coupling {
                    let ol = l * FRAME_PARAMS;
                    let mut block = h.view_mut((ok, ol), (FRAME_PARAMS, FRAME_PARAMS));
                    block -= ck * cl.transpose() / hdd;
                }
            }
        }
        (h, b)
    }
}

/// The step of each point's inverse depth given the keyframes' step (back-substitution).
pub fn depth_step(sys: &PointSystem, lambda: f64, frame_step: &DVector<f64>) -> Option<f64> {
    let hdd = sys.h_dd * (1.0 + lambda);
    if hdd <= 1e-12 {
        return None;
    }
    let coupled: f64 = sys
        .coupling
        .iter()
        .map(|(k, c)| c.dot(&frame_step.fixed_rows::<FRAME_PARAMS>(k * FRAME_PARAMS)))
        .sum();
    Some(-(sys.b_d + coupled) / hdd)
}
