//! Surface accuracy and completeness of a fused mesh against ground-truth geometry — the
//! precision/recall pair of multi-view reconstruction benchmarks (Knapitsch et al., "Tanks and
//! Temples", SIGGRAPH 2017; Middlebury's accuracy/completeness, Seitz et al. CVPR 2006):
//! - **accuracy**: the fraction of mesh vertices with a reference point within the threshold
//!   (is what was built really there?);
//! - **completeness**: the fraction of reference points with a mesh vertex within the threshold
//!   (was everything that is there built?).
//!
//! Both use vertices, not triangle areas: fused meshes are near-uniformly sampled (one vertex
//! per voxel edge crossing), so vertex counts stand in for area, and vertex-to-point distances
//! keep the evaluation simple and fast. The reference comes from the dataset's depth maps at
//! ground-truth poses ([`ground_truth_points`]); the mesh is brought into that frame with the
//! Sim(3) alignment of the trajectory ([`transform_vertices`]).

use std::collections::HashMap;

use nalgebra::{Vector2, Vector3};
use serde::Serialize;

use super::Stats;
use crate::dataset::tum::TumSequence;
use crate::fusion::Mesh;
use crate::geometry::Sim3;
use crate::{Error, Result};

/// Vertex-to-reference distances are searched only out to this multiple of the threshold and
/// capped there: a stray vertex far from any surface counts as "far" without one outlier
/// dominating the mean, and the search stays local.
pub const DISTANCE_CAP: f64 = 5.0;

/// Integer cell coordinates of a uniform grid.
type Cell = [i64; 3];

/// A uniform hash grid over 3-D points for fixed-radius nearest-neighbour queries. With the
/// cell size equal to the usual query radius, a query visits at most 8 cells.
#[derive(Clone, Debug)]
pub struct PointGrid {
    cell: f64,
    cells: HashMap<Cell, Vec<Vector3<f64>>>,
    len: usize,
}

impl PointGrid {
    /// Buckets the finite points of `points` into cells of side `cell` (non-finite points are
    /// dropped: they are no distance from anything).
    ///
    /// # Panics
    /// If `cell` is not a positive finite number.
    pub fn new(points: &[Vector3<f64>], cell: f64) -> Self {
        assert!(
            cell.is_finite() && cell > 0.0,
            "grid cell size must be positive and finite, got {cell}"
        );
        let mut cells: HashMap<Cell, Vec<Vector3<f64>>> = HashMap::new();
        let mut len = 0;
        for p in points.iter().filter(|p| p.iter().all(|v| v.is_finite())) {
            cells.entry(cell_of(p, cell)).or_default().push(*p);
            len += 1;
        }
        Self { cell, cells, len }
    }

    /// Number of (finite) points in the grid.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The distance from `p` to its nearest grid point if that is at most `r`, else `None`.
    ///
    /// Cells are visited in rings of growing Chebyshev distance around `p`'s cell, clipped to
    /// the bounding box of the ball of radius `r`; after ring k every unvisited point is at
    /// least k cell sides away, so the search stops as soon as the best distance is within
    /// that.
    /// When the box holds more cells than the grid has occupied ones, scanning every point is
    /// cheaper and gives the same answer.
    pub fn nearest_within(&self, p: &Vector3<f64>, r: f64) -> Option<f64> {
        if r.is_nan() || r < 0.0 || !p.iter().all(|v| v.is_finite()) || self.is_empty() {
            return None;
        }
        let c = cell_of(p, self.cell);
        let lo = cell_of(&p.add_scalar(-r), self.cell);
        let hi = cell_of(&p.add_scalar(r), self.cell);
        let box_cells = (0..3).fold(1.0, |n, a| n * ((hi[a] - lo[a]) as f64 + 1.0));
        let best = if box_cells > self.cells.len() as f64 {
            nearest_squared(self.cells.values().flatten(), p)
        } else {
            let rings = (0..3).map(|a| (c[a] - lo[a]).max(hi[a] - c[a])).max();
            let mut best = f64::INFINITY;
            for k in 0..=rings.unwrap_or(0) {
                best = best.min(self.ring_nearest_squared(p, c, k, lo, hi));
                let reach = (k as f64) * self.cell;
                if best <= reach * reach {
                    break;
                }
            }
            best
        };
        (best <= r * r).then(|| best.sqrt())
    }

    /// The smallest squared distance from `p` to the points in the cells at Chebyshev
    /// distance exactly `k` from `c`, clipped to the box `lo..=hi` (∞ if none).
    fn ring_nearest_squared(&self, p: &Vector3<f64>, c: Cell, k: i64, lo: Cell, hi: Cell) -> f64 {
        let range = |a: usize| (c[a] - k).max(lo[a])..=(c[a] + k).min(hi[a]);
        let mut best = f64::INFINITY;
        for x in range(0) {
            for y in range(1) {
                let on_shell = (x - c[0]).abs() == k || (y - c[1]).abs() == k;
                for z in range(2).filter(|z| on_shell || (z - c[2]).abs() == k) {
                    if let Some(points) = self.cells.get(&[x, y, z]) {
                        best = best.min(nearest_squared(points, p));
                    }
                }
            }
        }
        best
    }
}

fn nearest_squared<'a>(
    points: impl IntoIterator<Item = &'a Vector3<f64>>,
    p: &Vector3<f64>,
) -> f64 {
    points
        .into_iter()
        .map(|q| (q - p).norm_squared())
        .fold(f64::INFINITY, f64::min)
}

fn cell_of(p: &Vector3<f64>, cell: f64) -> Cell {
    [0, 1, 2].map(|a| (p[a] / cell).floor() as i64)
}

/// Accuracy and completeness of a surface at one distance threshold (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MeshScores {
    /// Distance threshold, in the units of the inputs (metres for ground truth).
    pub threshold: f64,
    /// Fraction of mesh vertices with a reference point within `threshold` (precision).
    pub accuracy: f64,
    /// Fraction of reference points with a mesh vertex within `threshold` (recall).
    pub completeness: f64,
    /// Harmonic mean of accuracy and completeness (Tanks and Temples' F-score); 0 when both
    /// are 0.
    pub f_score: f64,
    /// Mean distance from a mesh vertex to its nearest reference point, each distance capped
    /// at `distance_cap`.
    pub mean_distance: f64,
    /// Median of the same capped distances.
    pub median_distance: f64,
    /// [`DISTANCE_CAP`] × `threshold`.
    pub distance_cap: f64,
    pub vertices: usize,
    pub reference_points: usize,
}

/// Scores `vertices` against `reference` at `threshold` (both point sets in one frame and
/// unit). Empty sets score 0 (nothing correct, nothing covered) with distances at the cap.
///
/// # Panics
/// If `threshold` is not a positive finite number.
pub fn score_surface(
    vertices: &[Vector3<f64>],
    reference: &[Vector3<f64>],
    threshold: f64,
) -> MeshScores {
    assert!(
        threshold.is_finite() && threshold > 0.0,
        "mesh threshold must be positive and finite, got {threshold}"
    );
    let cap = DISTANCE_CAP * threshold;
    let reference_grid = PointGrid::new(reference, threshold);
    let distances: Vec<f64> = vertices
        .iter()
        .map(|v| reference_grid.nearest_within(v, cap).unwrap_or(cap))
        .collect();
    let fraction = |hits: usize, of: usize| {
        if of == 0 {
            0.0
        } else {
            hits as f64 / of as f64
        }
    };
    let accuracy = fraction(
        distances.iter().filter(|&&d| d <= threshold).count(),
        vertices.len(),
    );
    let vertex_grid = PointGrid::new(vertices, threshold);
    let covered = reference
        .iter()
        .filter(|r| vertex_grid.nearest_within(r, threshold).is_some())
        .count();
    let completeness = fraction(covered, reference.len());
    let f_score = if accuracy + completeness > 0.0 {
        2.0 * accuracy * completeness / (accuracy + completeness)
    } else {
        0.0
    };
    // Distances are finite and capped, so the statistics exist whenever there is a vertex.
    let stats = Stats::from_errors(&distances).ok();
    MeshScores {
        threshold,
        accuracy,
        completeness,
        f_score,
        mean_distance: stats.map_or(cap, |s| s.mean),
        median_distance: stats.map_or(cap, |s| s.median),
        distance_cap: cap,
        vertices: vertices.len(),
        reference_points: reference.len(),
    }
}

/// The reference surface of a sequence: each listed frame's ground-truth depth map (metres)
/// back-projected at its ground-truth pose, every `stride`-th pixel along both axes, depths in
/// (0, `max_depth`], then thinned to one point per occupied cube of side `spacing` — the
/// sample nearest the cube's centre, so the points are real depth samples (no averaging across
/// corners) at a near-uniform density that does not depend on how often a surface was seen.
/// Frames without a ground-truth pose or depth map are skipped. Pixels are undistorted with
/// the sequence camera's lens model before back-projection.
pub fn ground_truth_points(
    seq: &TumSequence,
    frames: &[usize],
    stride: usize,
    max_depth: f64,
    spacing: f64,
) -> Result<Vec<Vector3<f64>>> {
    if stride == 0 {
        return Err(Error::Eval("pixel stride must be at least 1".into()));
    }
    if !(spacing.is_finite() && spacing > 0.0) {
        return Err(Error::Eval(format!(
            "point spacing must be positive, got {spacing}"
        )));
    }
    let camera = &seq.camera;
    let mut points: Vec<Vector3<f64>> = Vec::new();
    let mut occupied: HashMap<Cell, usize> = HashMap::new();
    let centre_offset = |p: &Vector3<f64>, c: &Cell| {
        (p - Vector3::new(c[0] as f64 + 0.5, c[1] as f64 + 0.5, c[2] as f64 + 0.5) * spacing)
            .norm_squared()
    };
    for &i in frames {
        let frame = seq.frames.get(i).ok_or_else(|| {
            Error::Eval(format!(
                "frame {i} out of range ({} frames)",
                seq.frames.len()
            ))
        })?;
        let Some(world_from_camera) = frame.world_from_camera else {
            continue;
        };
        let Some(depth) = seq.load_depth(i)? else {
            continue;
        };
        for y in (0..depth.height).step_by(stride) {
            for x in (0..depth.width).step_by(stride) {
                let d = f64::from(depth.at(x, y));
                if !(d > 0.0 && d <= max_depth) {
                    continue;
                }
                let ray = camera.undistort_normalized(
                    &camera.pixel_to_normalized(&Vector2::new(x as f64, y as f64)),
                );
                let p = world_from_camera.act(&Vector3::new(ray.x * d, ray.y * d, d));
                let c = cell_of(&p, spacing);
                match occupied.get(&c) {
                    Some(&j) if centre_offset(&points[j], &c) <= centre_offset(&p, &c) => {}
                    Some(&j) => points[j] = p,
                    None => {
                        occupied.insert(c, points.len());
                        points.push(p);
                    }
                }
            }
        }
    }
    Ok(points)
}

/// The mesh's vertices in the reference frame: `world_from_map` applied to each position
/// (for a monocular map, the Sim(3) alignment of its trajectory to the ground truth).
pub fn transform_vertices(mesh: &Mesh, world_from_map: &Sim3) -> Vec<Vector3<f64>> {
    mesh.positions
        .iter()
        .map(|p| world_from_map.act(&Vector3::new(p[0].into(), p[1].into(), p[2].into())))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{Scene, SynthConfig, render_sequence};
    use crate::geometry::SO3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Points on the plane z = `z` over x ∈ [x0, x1], y ∈ [0, 1] at `step`.
    fn plane(x0: f64, x1: f64, z: f64, step: f64) -> Vec<Vector3<f64>> {
        let nx = ((x1 - x0) / step).round() as usize;
        let ny = (1.0 / step).round() as usize;
        (0..=nx)
            .flat_map(|i| {
                (0..=ny).map(move |j| Vector3::new(x0 + i as f64 * step, j as f64 * step, z))
            })
            .collect()
    }

    #[test]
    fn plane_scores_match_coverage() {
        let reference = plane(0.0, 1.0, 0.0, 0.01);
        // The mesh samples the plane on a different grid (offset and coarser).
        let mesh = plane(0.003, 0.993, 0.0, 0.015);
        let s = score_surface(&mesh, &reference, 0.02);
        assert_eq!(s.accuracy, 1.0);
        assert!(s.completeness > 0.99, "{s:?}");
        assert!(s.mean_distance < 0.01 && s.median_distance < 0.01, "{s:?}");
        assert_eq!(
            (s.vertices, s.reference_points),
            (mesh.len(), reference.len())
        );

        let shifted: Vec<_> = mesh
            .iter()
            .map(|p| p + Vector3::new(0.0, 0.0, 0.05))
            .collect();
        let s = score_surface(&shifted, &reference, 0.02);
        assert_eq!((s.accuracy, s.completeness, s.f_score), (0.0, 0.0, 0.0));
        // Straight down plus at most half the reference spacing diagonally in the plane.
        assert!((0.05..0.0505).contains(&s.median_distance), "{s:?}");
        let far: Vec<_> = mesh
            .iter()
            .map(|p| p + Vector3::new(0.0, 0.0, 1.0))
            .collect();
        let s = score_surface(&far, &reference, 0.02);
        assert_eq!(s.median_distance, s.distance_cap);
        assert!((s.mean_distance - s.distance_cap).abs() < 1e-12, "{s:?}");

        let half = plane(0.0, 0.5, 0.0, 0.01);
        let s = score_surface(&half, &reference, 0.02);
        assert_eq!(s.accuracy, 1.0);
        assert!((s.completeness - 0.5).abs() < 0.03, "{s:?}");
        assert!((s.f_score - 2.0 * s.completeness / (1.0 + s.completeness)).abs() < 1e-12);

        let empty = score_surface(&[], &reference, 0.02);
        assert_eq!((empty.accuracy, empty.completeness), (0.0, 0.0));
        assert_eq!(empty.mean_distance, empty.distance_cap);
    }

    #[test]
    fn point_grid_matches_brute_force() {
        fn random_point(rng: &mut ChaCha8Rng) -> Vector3<f64> {
            Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0))
        }
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let points: Vec<Vector3<f64>> = (0..2000).map(|_| random_point(&mut rng)).collect();
        for cell in [0.02, 0.1, 0.5] {
            let grid = PointGrid::new(&points, cell);
            assert_eq!(grid.len(), points.len());
            for r in [0.0, 0.01, cell, 2.5 * cell, 10.0] {
                for _ in 0..300 {
                    let q = random_point(&mut rng) * 1.2;
                    let brute = points
                        .iter()
                        .map(|p| (p - q).norm_squared())
                        .fold(f64::INFINITY, f64::min);
                    let expected = (brute <= r * r).then(|| brute.sqrt());
                    assert_eq!(grid.nearest_within(&q, r), expected, "cell {cell} r {r}");
                }
            }
        }
        let on_point = points[3];
        assert_eq!(
            PointGrid::new(&points, 0.1).nearest_within(&on_point, 0.0),
            Some(0.0)
        );
        let empty = PointGrid::new(&[], 0.1);
        assert_eq!(empty.nearest_within(&Vector3::zeros(), 1.0), None);
    }

    #[test]
    fn transform_vertices_applies_the_similarity() {
        let mesh = Mesh {
            positions: vec![[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]],
            ..Mesh::default()
        };
        let quarter = SO3::exp(&Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2));
        let t = Sim3::new(quarter, Vector3::new(1.0, 1.0, 1.0), 2.0);
        let v = transform_vertices(&mesh, &t);
        assert!((v[0] - Vector3::new(1.0, 3.0, 1.0)).norm() < 1e-12, "{v:?}");
        assert!(
            (v[1] - Vector3::new(-3.0, 1.0, 1.0)).norm() < 1e-12,
            "{v:?}"
        );
    }

    #[test]
    fn ground_truth_points_lie_on_the_scene() {
        let dir = std::env::temp_dir().join(format!("relfusion-meshgt-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let config = SynthConfig {
            frames: 2,
            seed: 3,
            width: 160,
            height: 120,
            ..SynthConfig::default()
        };
        render_sequence(&config, &dir).expect("render");
        let seq = TumSequence::open(&dir, None).expect("open");
        let scene = Scene::generate(config.seed);
        let spacing = 0.05;
        let points = ground_truth_points(&seq, &[0, 1], 2, 10.0, spacing).expect("points");
        assert!(points.len() > 100, "{} points", points.len());
        for p in &points {
            // Depth PNGs quantise to 0.2 mm; a real surface sample sits on a wall or block.
            assert!(!scene.is_free(p, 1e-3), "{p:?} is not on a surface");
            assert!(
                (0..3).all(|a| p[a] > scene.room_min[a] - 1e-3 && p[a] < scene.room_max[a] + 1e-3),
                "{p:?} is outside the room"
            );
        }
        let mut cells: Vec<Cell> = points.iter().map(|p| cell_of(p, spacing)).collect();
        cells.sort_unstable();
        cells.dedup();
        assert_eq!(cells.len(), points.len(), "one point per cell");
        let near = ground_truth_points(&seq, &[0], 2, 1.0, spacing).expect("points");
        assert!(near.len() < points.len());
        assert!(ground_truth_points(&seq, &[0], 0, 10.0, spacing).is_err());
        assert!(ground_truth_points(&seq, &[5], 1, 10.0, spacing).is_err());
        std::fs::remove_dir_all(&dir).expect("clean up");
    }
}
