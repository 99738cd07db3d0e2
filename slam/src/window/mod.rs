//! Windowed photometric bundle adjustment of the most recent keyframes (DSO: Engel, Koltun and
//! Cremers, "Direct Sparse Odometry", TPAMI 2018, §2-3), run by the back end beside the
//! pose graph.
//!
//! Why: LSD-SLAM hands the map's scale from keyframe to keyframe (depth propagation, then a
//! pairwise Sim(3) alignment), so a small bias per keyframe compounds (docs/tuning.md, "Scale
//! drift"). Here the poses of the last [`WindowConfig::keyframes`] keyframes, their affine
//! brightness and the inverse depths of well-spread semi-dense points hosted in them are
//! optimised jointly against the photometric residuals of every point in every other keyframe
//! of the window; the oldest [`WindowConfig::fixed_keyframes`] are held fixed and carry the
//! gauge — scale included — from the windows before. The result enters the Sim(3) pose graph as
//! one edge per consecutive pair, whose scale is each keyframe's depth map measured against the
//! window's jointly estimated depths.
//!
//! - [`residual`]: point selection, residuals and their analytic Jacobians;
//! - [`solve`]: Levenberg–Marquardt with the depths eliminated by the Schur complement.

pub mod config;
pub mod residual;
pub mod solve;

pub use config::WindowConfig;
pub use residual::{Point, View};
pub use solve::SolveReport;

use crate::frame::Frame;
use crate::geometry::{SE3, Sim3};
use crate::graph::KeyframeId;
use crate::mapping::DepthMap;

/// A keyframe handed to the window.
#[derive(Clone, Copy, Debug)]
pub struct WindowKeyframe<'a> {
    pub id: KeyframeId,
    pub frame: &'a Frame,
    /// Semi-dense inverse depth in the keyframe's own units.
    pub depth: &'a DepthMap,
    pub world_from_keyframe: Sim3,
}

/// The window's estimate.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowResult {
    /// `world_from_keyframe` of every keyframe of the window (oldest first), the scale being
    /// that of its depth map against the window's depths.
    pub poses: Vec<(KeyframeId, Sim3)>,
    pub points: usize,
    pub report: SolveReport,
}

/// Fewest points a keyframe must host for its scale to be measured (otherwise it keeps the
/// pose graph's).
pub const MIN_POINTS_FOR_SCALE: usize = 20;

/// Runs the window over `keyframes` (oldest first); `None` when there are too few keyframes
/// or points to optimise.
pub fn optimize_window(
    config: &WindowConfig,
    keyframes: &[WindowKeyframe<'_>],
) -> Option<WindowResult> {
    if keyframes.len() <= config.fixed_keyframes {
        return None;
    }
    let levels = keyframes
        .iter()
        .map(|k| k.frame.pyramid.levels.len())
        .min()?;
    let finest = config.level.min(levels - 1);
    let coarsest = (finest + 1).min(levels - 1);
    // Coarse to fine: one level up first widens the basin for the pose graph's start; each
    // level selects its own points, with the hosts' scales as the level before left them.
    let mut poses: Vec<(SE3, f64)> = keyframes
        .iter()
        .map(|k| k.world_from_keyframe.to_se3_and_scale())
        .collect();
    let mut report = SolveReport::default();
    let mut total_points = 0;
    for level in (finest..=coarsest).rev() {
        let mut views: Vec<View<'_>> = keyframes
            .iter()
            .zip(&poses)
            .map(|(k, (pose, _))| View {
                level: k.frame.level(level),
                camera: k.frame.camera_at(level),
                world_from_camera: *pose,
                affine: (0.0, 0.0),
            })
            .collect();
        let mut points = Vec::new();
        for (i, k) in keyframes.iter().enumerate() {
            points.extend(residual::select_points(
                i,
                &views[i],
                k.depth,
                level,
                poses[i].1,
                config.points_per_keyframe,
            ));
        }
        if points.is_empty() {
            return None;
        }
        let level_report = solve::optimize(config, &mut points, &mut views, config.fixed_keyframes);
        if level == coarsest {
            report.initial_cost = level_report.initial_cost;
        }
        report.final_cost = level_report.final_cost;
        report.iterations += level_report.iterations;
        report.residuals = level_report.residuals;
        total_points = points.len();
        let information = solve::depth_information(config, &points, &views);
        for (i, pose) in poses.iter_mut().enumerate() {
            pose.0 = views[i].world_from_camera;
            if let Some(scale) = host_scale(&points, &information, i) {
                pose.1 = scale;
            }
        }
    }
    let poses = keyframes
        .iter()
        .zip(&poses)
        .map(|(k, (pose, scale))| (k.id, Sim3::from_se3(pose, *scale)))
        .collect();
    Some(WindowResult {
        poses,
        points: total_points,
        report,
    })
}

/// The scale of host `i`'s depth map against the window: the median of its points' keyframe
/// over world inverse depths, each point weighted by the information of its depth (a point the
/// window hardly sees says nothing about the scale); `None` with fewer than
/// [`MIN_POINTS_FOR_SCALE`] measured points.
fn host_scale(points: &[Point], information: &[f64], i: usize) -> Option<f64> {
    let mut ratios: Vec<(f64, f64)> = points
        .iter()
        .zip(information)
        .filter(|(p, info)| p.host == i && **info > 0.0)
        .map(|(p, info)| (p.idepth_keyframe / p.idepth, *info))
        .filter(|(r, _)| r.is_finite() && *r > 0.0)
        .collect();
    if ratios.len() < MIN_POINTS_FOR_SCALE {
        return None;
    }
    ratios.sort_by(|a, b| a.0.total_cmp(&b.0));
    let half = 0.5 * ratios.iter().map(|r| r.1).sum::<f64>();
    let mut acc = 0.0;
    ratios
        .iter()
        .find(|(_, w)| {
            acc += w;
            acc >= half
        })
        .map(|r| r.0)
}

#[cfg(test)]
mod tests;
