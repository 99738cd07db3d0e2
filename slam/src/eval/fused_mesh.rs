//! Accuracy and completeness of a run's fused mesh (`relfusion eval mesh`, issue 5).
//!
//! The mesh is brought into the ground-truth frame by the Sim(3) alignment of the run's
//! keyframe trajectory (so its scale errors count) — positions *and* orientations, see
//! [`align_poses`] — and scored against the ground-truth
//! surface points the keyframes saw (their ground-truth depth back-projected at their
//! ground-truth poses). The threshold is `threshold_voxels` voxels, in metres through the same
//! alignment. The upper bound is the mesh the same fusion makes from ground-truth depth at
//! ground-truth poses, with the same voxel size in metres; our mesh is also scored against
//! that mesh's vertices.

use std::path::Path;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::mesh::{MeshScores, ground_truth_points, score_surface, transform_vertices};
use super::{AlignMode, DEFAULT_MAX_DT, Matched, associate_poses, ate_matched, umeyama};
use crate::dataset::TumSequence;
use crate::dataset::trajectory::read_tum_trajectory;
use crate::dense::store::DenseStore;
use crate::export::{read_mesh_ply, read_points_ply};
use crate::fusion::fuser::{Fuser, FusionStats};
use crate::fusion::input::{FusionInput, store_inputs};
use crate::fusion::{FusionConfig, Mesh};
use crate::geometry::{PinholeCamera, Sim3};
use crate::image::ImageF32;
use crate::{Error, Result};

/// Folder of a run's stored keyframes.
const KEYFRAMES_DIR: &str = "keyframes";

/// File of a run with the fusion's figures (voxel size, blocks, ...).
pub const MESH_STATS_FILE: &str = "mesh.json";

/// Largest timestamp gap between a keyframe and the dataset frame whose depth stands for it.
const FRAME_MAX_DT: f64 = 0.02;

/// Scores of one run's mesh.
#[derive(Clone, Debug, Serialize)]
pub struct MeshEvalReport {
    pub keyframes: usize,
    /// Metres per map unit (Sim(3) alignment of the keyframes).
    pub trajectory_scale: f64,
    pub keyframe_ate_rmse: f64,
    /// The run's voxel edge in map units and in metres.
    pub voxel_size: f64,
    pub voxel_size_m: f64,
    pub threshold_voxels: f64,
    pub threshold_m: f64,
    /// Our mesh against the ground-truth surface points.
    pub ours: MeshScores,
    /// The mesh fused from ground-truth depth and poses against the same points (upper bound).
    pub ground_truth_fusion: MeshScores,
    /// Our mesh against the ground-truth-depth mesh's vertices.
    pub ours_vs_ground_truth_mesh: MeshScores,
    /// The run's unfused dense points (`dense.ply`) against the ground-truth points: what the
    /// fusion starts from.
    pub dense_points: Option<MeshScores>,
}

/// What `relfusion run` writes next to the mesh.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct StatsFile {
    voxel_size: f64,
}

/// Writes `OUT/mesh.json` (the fusion's figures; `eval mesh` reads the voxel size there).
pub fn write_mesh_stats(run: &Path, stats: &FusionStats) -> Result<()> {
    let path = run.join(MESH_STATS_FILE);
    let text = serde_json::to_string_pretty(stats)
        .map_err(|e| Error::Eval(format!("serialising fusion stats: {e}")))?;
    std::fs::write(&path, text).map_err(|e| Error::io(&path, e))
}

/// Where the scored mesh comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshSource {
    /// The run's `mesh.ply` (voxel size from its `mesh.json`).
    RunMesh,
    /// The run's stored keyframes (`keyframes/`, optimised poses) fused again with the given
    /// `[fusion]` parameters: tunes the fusion without re-running the SLAM.
    Refuse,
}

/// Scores a run's mesh (see the module doc). `fusion` configures the ground-truth fusion (its
/// voxel size is replaced by the run's, in metres) and, with [`MeshSource::Refuse`], ours.
pub fn evaluate_fused_mesh(
    dataset: &Path,
    run: &Path,
    fusion: &FusionConfig,
    source: MeshSource,
    threshold_voxels: f64,
) -> Result<MeshEvalReport> {
    let seq = TumSequence::open(dataset, None)?;
    let gt = read_tum_trajectory(&dataset.join("groundtruth.txt"))?;
    let est = read_tum_trajectory(&run.join("keyframes.txt"))?;
    let matched = associate_poses(&gt, &est, DEFAULT_MAX_DT)?;
    let ate = ate_matched(&matched, AlignMode::Sim3)?;
    let alignment = align_poses(&matched, ate.scale)?;
    let (mesh, stats) = match source {
        MeshSource::RunMesh => {
            let path = run.join(MESH_STATS_FILE);
            let stats: StatsFile = serde_json::from_str(
                &std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?,
            )
            .map_err(|e| Error::Eval(format!("{}: {e}", path.display())))?;
            (read_mesh_ply(&run.join("mesh.ply"))?, stats)
        }
        MeshSource::Refuse => {
            let store = DenseStore::open(&run.join(KEYFRAMES_DIR))?;
            let mut fuser = Fuser::new(fusion.clone(), None)?;
            for (input, pose) in store_inputs(&store, fusion)? {
                fuser.add_keyframe(input, pose)?;
            }
            let mesh = fuser.mesh()?;
            let voxel_size = fuser.stats().voxel_size;
            (mesh, StatsFile { voxel_size })
        }
    };
    if mesh.is_empty() {
        return Err(Error::Eval(format!(
            "{}/mesh.ply has no triangles",
            run.display()
        )));
    }
    let frames: Vec<usize> = est
        .iter()
        .filter_map(|kf| nearest_frame(&seq, kf.timestamp))
        .collect();
    if frames.is_empty() {
        return Err(Error::Eval("no keyframe matches a dataset frame".into()));
    }
    let voxel_m = stats.voxel_size * alignment.scale;
    let threshold = threshold_voxels * voxel_m;
    let reference = ground_truth_points(&seq, &frames, 2, 10.0, voxel_m / 2.0)?;
    let ours = transform_vertices(&mesh, &alignment);
    let gt_mesh = fuse_ground_truth(&seq, &frames, fusion, voxel_m)?;
    let gt_vertices = transform_vertices(&gt_mesh, &Sim3::identity());
    let dense_points = match std::fs::exists(run.join("dense.ply")) {
        Ok(true) => {
            let points: Vec<_> = read_points_ply(&run.join("dense.ply"))?
                .iter()
                .map(|p| alignment.act(&Vector3::from(p.position.map(f64::from))))
                .collect();
            Some(score_surface(&points, &reference, threshold))
        }
        _ => None,
    };
    Ok(MeshEvalReport {
        keyframes: frames.len(),
        trajectory_scale: alignment.scale,
        keyframe_ate_rmse: ate.rmse,
        voxel_size: stats.voxel_size,
        voxel_size_m: voxel_m,
        threshold_voxels,
        threshold_m: threshold,
        ours: score_surface(&ours, &reference, threshold),
        ground_truth_fusion: score_surface(&gt_vertices, &reference, threshold),
        ours_vs_ground_truth_mesh: score_surface(&ours, &gt_vertices, threshold),
        dense_points,
    })
}

/// Metres each camera axis contributes to [`align_poses`]: a point this far along each axis
/// of every camera, about the depth at which a room is seen.
const ORIENTATION_LEVER_M: f64 = 1.0;

/// The Sim(3) `gt_from_est` that best maps the estimated keyframes onto the ground truth,
/// positions and orientations alike: each pose contributes its centre and a point
/// [`ORIENTATION_LEVER_M`] along each of its axes (`position_scale` — the positions-only fit —
/// converts that lever into map units). The trajectory ATE aligns positions only (as evo
/// does); for a map that is not enough: on a short or nearly straight path the positions
/// leave the rotation about the path poorly determined (4.5° off on the 300-frame synthetic
/// orbit, which moves a wall 2 m away by 16 cm), while the cameras' orientations pin it down.
pub fn align_poses(matched: &Matched, position_scale: f64) -> Result<Sim3> {
    let lever = ORIENTATION_LEVER_M / position_scale;
    let (mut est, mut gt) = (Vec::new(), Vec::new());
    for (e, g) in matched.est.iter().zip(&matched.gt) {
        let (e, g) = (&e.world_from_camera, &g.world_from_camera);
        est.push(e.translation);
        gt.push(g.translation);
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            est.push(e.translation + e.rotation.act(&(axis * lever)));
            gt.push(g.translation + g.rotation.act(&(axis * ORIENTATION_LEVER_M)));
        }
    }
    umeyama(&est, &gt, true)
}

/// The dataset frame nearest to `timestamp` (within [`FRAME_MAX_DT`]).
fn nearest_frame(seq: &TumSequence, timestamp: f64) -> Option<usize> {
    seq.frames
        .iter()
        .enumerate()
        .map(|(i, f)| (i, (f.timestamp - timestamp).abs()))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .filter(|&(_, dt)| dt <= FRAME_MAX_DT)
        .map(|(i, _)| i)
}

/// Fuses the ground-truth depth of `frames` at their ground-truth poses with voxel edge
/// `voxel_m` metres, at the dense layer's working resolution (every other pixel of a 640×480
/// sequence), so that it differs from the pipeline's mesh only by its depth and poses.
pub fn fuse_ground_truth(
    seq: &TumSequence,
    frames: &[usize],
    fusion: &FusionConfig,
    voxel_m: f64,
) -> Result<Mesh> {
    if seq.camera.distortion.is_some() {
        return Err(Error::Eval(
            "ground-truth fusion needs an undistorted sequence (its depth is sampled on the \
             image grid)"
                .into(),
        ));
    }
    let config = FusionConfig {
        voxel_size: Some(voxel_m),
        ..fusion.clone()
    };
    let mut fuser = Fuser::new(config.clone(), None)?;
    let c = &seq.camera;
    let step = (c.width as usize / 320).max(1);
    let (w, h) = (c.width as usize / step, c.height as usize / step);
    let s = step as f64;
    let camera = PinholeCamera::new(c.fx / s, c.fy / s, c.cx / s, c.cy / s, w as u32, h as u32)?;
    for &i in frames {
        let (Some(pose), Some(depth)) = (seq.frames[i].world_from_camera, seq.load_depth(i)?)
        else {
            continue;
        };
        let rgb = seq.load_rgb(i)?;
        let mut d = Vec::with_capacity(w * h);
        let mut colors = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                d.push(depth.at(x * step, y * step));
                colors.push(rgb.get_pixel((x * step) as u32, (y * step) as u32).0);
            }
        }
        let input = FusionInput::from_depth(
            i,
            seq.frames[i].timestamp,
            camera,
            &ImageF32::from_vec(w, h, d)?,
            Some(&colors),
            &config,
        )?;
        fuser.add_keyframe(input, Sim3::from_se3(&pose, 1.0))?;
    }
    fuser.mesh()
}
