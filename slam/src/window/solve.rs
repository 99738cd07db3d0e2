//! Levenberg–Marquardt on the window's normal equations, with the inverse depths eliminated
//! by the Schur complement (each point's depth block is a scalar, so the reduced system is only
//! `8 × free keyframes` wide — DSO's `EnergyFunctional::solveSystemF`).

use nalgebra::{DMatrix, DVector};

use super::config::WindowConfig;
use super::residual::{
    KF_PARAMS, Linearised, PATTERN, Point, Vector8, View, apply_step, linearise,
};

/// Robust weight of a pattern pixel: DSO's gradient-dependent weight times Huber's.
fn weight(config: &WindowConfig, lin: &Linearised) -> f64 {
    let c2 = config.gradient_weight_c * config.gradient_weight_c;
    let w_grad = c2 / (c2 + lin.grad2);
    let r = lin.residual * w_grad.sqrt();
    let huber = if r.abs() <= config.huber {
        1.0
    } else {
        config.huber / r.abs()
    };
    w_grad * huber
}

/// The linearised pattern of `point` in view `t`, or `None` when a pixel is not visible or the
/// pattern is an outlier there (energy above the threshold).
fn pattern(
    config: &WindowConfig,
    point: &Point,
    views: &[View<'_>],
    t: usize,
) -> Option<[Linearised; PATTERN.len()]> {
    let mut out = [None; PATTERN.len()];
    let mut energy = 0.0;
    for (k, slot) in out.iter_mut().enumerate() {
        let lin = linearise(point, k, &views[point.host], &views[t])?;
        energy += lin.residual * lin.residual;
        *slot = Some(lin);
    }
    let limit = config.outlier_threshold * config.outlier_threshold * PATTERN.len() as f64;
    if energy > limit {
        return None;
    }
    Some(out.map(|l| l.unwrap_or_else(|| unreachable!("every pattern pixel was filled"))))
}

/// Robust cost of the window, the number of pattern residuals in it, and the number of
/// point-target pairs that were visible but outliers.
pub fn cost(config: &WindowConfig, points: &[Point], views: &[View<'_>]) -> (f64, usize, usize) {
    let mut total = 0.0;
    let mut n = 0;
    let mut outliers = 0;
    for p in points {
        for t in 0..views.len() {
            if t == p.host {
                continue;
            }
            match pattern(config, p, views, t) {
                Some(lins) => {
                    for lin in &lins {
                        let c2 = config.gradient_weight_c * config.gradient_weight_c;
                        let r2 = lin.residual * lin.residual * c2 / (c2 + lin.grad2);
                        let d = config.huber;
                        total += if r2 <= d * d {
                            r2
                        } else {
                            2.0 * d * r2.sqrt() - d * d
                        };
                        n += 1;
                    }
                }
                // An outlier or invisible pattern costs the outlier energy, so that moving a
                // point out of view is never a way to lower the cost.
                None => {
                    total += config.outlier_threshold * config.outlier_threshold;
                    outliers += visible(p, views, t) as usize;
                }
            }
        }
    }
    (total, n, outliers)
}

/// Whether every pattern pixel of `point` lands in view `t`.
fn visible(point: &Point, views: &[View<'_>], t: usize) -> bool {
    (0..PATTERN.len()).all(|k| linearise(point, k, &views[point.host], &views[t]).is_some())
}

/// DSO's cut-off doubling (`CoarseTracker::trackNewestCoarse`): while more than 60 % of the
/// visible point-target pairs are outliers, the start is too far off for the threshold, so it
/// is doubled (at most four times) rather than letting the outliers decide.
fn adapt_threshold(config: &WindowConfig, points: &[Point], views: &[View<'_>]) -> WindowConfig {
    let mut config = config.clone();
    for _ in 0..4 {
        let (_, inliers, outliers) = cost(&config, points, views);
        let inlier_pairs = inliers / PATTERN.len();
        if (outliers as f64) <= 0.6 * (outliers + inlier_pairs).max(1) as f64 {
            break;
        }
        config.outlier_threshold *= 2.0;
    }
    config
}

/// One point's contribution: its depth block, gradient and coupling with each keyframe.
struct PointSystem {
    h_dd: f64,
    b_d: f64,
    /// (keyframe index, H_kd column).
    coupling: Vec<(usize, Vector8)>,
}

/// The normal equations of the current state: the camera block `H_cc`, `b_c`, and per point.
fn normal_equations(
    config: &WindowConfig,
    points: &[Point],
    views: &[View<'_>],
) -> (DMatrix<f64>, DVector<f64>, Vec<PointSystem>) {
    let n = views.len() * KF_PARAMS;
    let mut h = DMatrix::<f64>::zeros(n, n);
    let mut b = DVector::<f64>::zeros(n);
    let mut systems = Vec::with_capacity(points.len());
    for p in points {
        let mut sys = PointSystem {
            h_dd: 0.0,
            b_d: 0.0,
            coupling: Vec::new(),
        };
        let mut host_col = Vector8::zeros();
        for t in 0..views.len() {
            if t == p.host {
                continue;
            }
            let Some(lins) = pattern(config, p, views, t) else {
                continue;
            };
            let mut target_col = Vector8::zeros();
            for lin in &lins {
                let w = weight(config, lin);
                let (jh, jt, jd, r) = (&lin.d_host, &lin.d_target, lin.d_idepth, lin.residual);
                let (oh, ot) = (p.host * KF_PARAMS, t * KF_PARAMS);
                let hh = w * jh * jh.transpose();
                let ht = w * jh * jt.transpose();
                let tt = w * jt * jt.transpose();
                let mut add = |r0: usize, c0: usize, m: &nalgebra::SMatrix<f64, 8, 8>| {
                    let mut view = h.view_mut((r0, c0), (KF_PARAMS, KF_PARAMS));
                    view += m;
                };
                add(oh, oh, &hh);
                add(oh, ot, &ht);
                add(ot, oh, &ht.transpose());
                add(ot, ot, &tt);
                let mut bh = b.rows_mut(oh, KF_PARAMS);
                bh += w * r * jh;
                let mut bt = b.rows_mut(ot, KF_PARAMS);
                bt += w * r * jt;
                sys.h_dd += w * jd * jd;
                sys.b_d += w * jd * r;
                host_col += w * jd * jh;
                target_col += w * jd * jt;
            }
            sys.coupling.push((t, target_col));
        }
        sys.coupling.push((p.host, host_col));
        systems.push(sys);
    }
    (h, b, systems)
}

/// The information `H_ρρ` of each point's inverse depth at the current state (how well the
/// window measures it; 0 for a point seen nowhere).
pub fn depth_information(config: &WindowConfig, points: &[Point], views: &[View<'_>]) -> Vec<f64> {
    points
        .iter()
        .map(|p| {
            (0..views.len())
                .filter(|&t| t != p.host)
                .filter_map(|t| pattern(config, p, views, t))
                .flat_map(|lins| lins.into_iter())
                .map(|lin| weight(config, &lin) * lin.d_idepth * lin.d_idepth)
                .sum()
        })
        .collect()
}

/// What [`optimize`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SolveReport {
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: usize,
    pub residuals: usize,
}

/// The normal equations of the free keyframes (`fixed..fixed + nfree`) with the depths
/// eliminated by the Schur complement, and LM damping `lambda` on every diagonal.
fn reduced_system(
    h: &DMatrix<f64>,
    b: &DVector<f64>,
    systems: &[PointSystem],
    (fixed, nfree): (usize, usize),
    lambda: f64,
) -> (DMatrix<f64>, DVector<f64>) {
    let off = fixed * KF_PARAMS;
    let m = nfree * KF_PARAMS;
    let mut hr = h.view((off, off), (m, m)).into_owned();
    let mut br = b.rows(off, m).into_owned();
    for i in 0..m {
        hr[(i, i)] *= 1.0 + lambda;
        hr[(i, i)] += 1e-9;
    }
    for sys in systems {
        let hdd = sys.h_dd * (1.0 + lambda);
        if hdd <= 1e-12 {
            continue;
        }
        let free: Vec<&(usize, Vector8)> =
            sys.coupling.iter().filter(|(k, _)| *k >= fixed).collect();
        for (k, ck) in &free {
            let ok = (k - fixed) * KF_PARAMS;
            let mut bk = br.rows_mut(ok, KF_PARAMS);
            bk -= ck * (sys.b_d / hdd);
            for (l, cl) in &free {
                let ol = (l - fixed) * KF_PARAMS;
                let mut block = hr.view_mut((ok, ol), (KF_PARAMS, KF_PARAMS));
                block -= ck * cl.transpose() / hdd;
            }
        }
    }
    (hr, br)
}

/// Each point's inverse-depth step from the keyframes' steps (back substitution), applied to
/// `points`.
fn back_substitute(
    points: &mut [Point],
    systems: &[PointSystem],
    step_of: &dyn Fn(usize) -> Vector8,
    lambda: f64,
) {
    for (p, sys) in points.iter_mut().zip(systems) {
        let hdd = sys.h_dd * (1.0 + lambda);
        if hdd <= 1e-12 {
            continue;
        }
        let coupled: f64 = sys.coupling.iter().map(|(k, c)| c.dot(&step_of(*k))).sum();
        let step = -(sys.b_d + coupled) / hdd;
        // Keep the inverse depth positive: at most halve or double it per step.
        p.idepth = (p.idepth + step).clamp(0.5 * p.idepth, 2.0 * p.idepth);
    }
}

/// Minimises the window's photometric cost over the poses and affine brightness of the views
/// `fixed..` and the inverse depths of `points`. `views` and `points` are updated in place.
pub fn optimize(
    config: &WindowConfig,
    points: &mut [Point],
    views: &mut [View<'_>],
    fixed: usize,
) -> SolveReport {
    let config = &adapt_threshold(config, points, views);
    let (mut current, residuals, _) = cost(config, points, views);
    let mut report = SolveReport {
        initial_cost: current,
        final_cost: current,
        iterations: 0,
        residuals,
    };
    let nfree = views.len().saturating_sub(fixed);
    if nfree == 0 || points.is_empty() {
        return report;
    }
    let mut lambda = 1e-4;
    for _ in 0..config.iterations {
        report.iterations += 1;
        let (h, b, systems) = normal_equations(config, points, views);
        let mut accepted = false;
        for _ in 0..6 {
            let (hr, br) = reduced_system(&h, &b, &systems, (fixed, nfree), lambda);
            let Some(chol) = hr.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let dc = chol.solve(&(-br));
            let step_of = |k: usize| -> Vector8 {
                if k < fixed {
                    Vector8::zeros()
                } else {
                    dc.fixed_rows::<KF_PARAMS>((k - fixed) * KF_PARAMS)
                        .into_owned()
                }
            };
            let mut trial_views = views.to_vec();
            for (k, v) in trial_views.iter_mut().enumerate() {
                let (pose, affine) = apply_step(v, &step_of(k));
                v.world_from_camera = pose;
                v.affine = affine;
            }
            let mut trial_points = points.to_vec();
            back_substitute(&mut trial_points, &systems, &step_of, lambda);
            let (trial, _, _) = cost(config, &trial_points, &trial_views);
            if trial < current {
                views.copy_from_slice(&trial_views);
                points.clone_from_slice(&trial_points);
                let gain = (current - trial) / current.max(1e-12);
                current = trial;
                lambda = (lambda * 0.5).max(1e-6);
                accepted = true;
                if gain < 1e-4 {
                    report.final_cost = current;
                    return report;
                }
                break;
            }
            lambda *= 10.0;
        }
        if !accepted {
            break;
        }
    }
    report.final_cost = current;
    report
}
