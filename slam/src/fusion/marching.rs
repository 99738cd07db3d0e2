//! Marching cubes over voxel blocks (CPU reference of `marching_cubes.wgsl`).
//!
//! Cell `(x, y, z)` of a block (each in `0..8`, linear index `x + 8y + 64z`) has its corners at
//! the block's local voxels `(x + dx, y + dy, z + dz)`; a coordinate of 8 lives in one of the
//! seven upper neighbours ([`MeshJob::neighbours`]). A cell emits nothing when a corner lies in
//! a missing neighbour or has `weight <= min_weight`: the surface ends there instead of closing
//! on invented values, and the block gets its missing row of cells once the neighbour exists.
//!
//! Vertices: the vertex on a crossed edge is interpolated from the edge's *lower* endpoint
//! (`edge_vertex`), so the two blocks (or cells) that share an edge compute bit-identical
//! positions and the scene mesh welds on [`EdgeKey`]s without cracks.
//!
//! Both the CPU and the GPU path turn their per-cell triangles into the indexed
//! [`BlockMesh`] with one function, `assemble`, so the two outputs can differ only in the
//! rounding of the interpolated values.

use std::collections::HashMap;
use std::collections::hash_map::Entry;

use super::block::{BLOCK_SIDE, BlockIndex, MeshJob, unpack_rgb, voxel_linear};
use super::mc_table::{self, TABLE};
use super::mesh::{BlockMesh, EdgeKey, vertex_normals};
use super::voxels::CpuVoxels;

/// Parameters of mesh extraction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshParams {
    /// Voxel edge in world units (vertex positions are `voxel · voxel_size`).
    pub voxel_size: f32,
    /// A corner is observed when its weight is `> min_weight`; cells with an unobserved
    /// corner emit nothing.
    pub min_weight: f32,
}

/// Cells per block (one per voxel: the cell at voxel `v` spans `v … v + 1`).
pub const BLOCK_CELLS: usize = 512;

/// One triangle as a cell emits it, before vertices are shared; the common currency of the
/// CPU and GPU paths.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct CellTriangle {
    /// Linear cell index in the block (`x + 8y + 64z`).
    pub cell: u16,
    /// Index of the triangle within its cell's case.
    pub tri: u8,
    pub keys: [EdgeKey; 3],
    pub positions: [[f32; 3]; 3],
    pub colors: [[u8; 3]; 3],
}

/// Meshes every job's block (CPU reference): one [`BlockMesh`] per job, in job order, empty
/// ones included (a block that lost its surface must learn so).
///
/// Every slot a job names must lie inside the pool (jobs come from the block table that sized
/// it); an out-of-range slot panics.
pub fn extract_blocks(voxels: &CpuVoxels, jobs: &[MeshJob], p: &MeshParams) -> Vec<BlockMesh> {
    jobs.iter()
        .map(|job| assemble(job.index, &cell_triangles(voxels, job, p)))
        .collect()
}

/// Pool index of a job's cell corner at block-local `local` (each in `0..=8`), `None` when it
/// lies in a missing neighbour.
fn corner_index(job: &MeshJob, local: [i32; 3]) -> Option<usize> {
    let n = local
        .iter()
        .enumerate()
        .fold(0usize, |n, (k, &c)| n | usize::from(c >= BLOCK_SIDE) << k);
    let slot = if n == 0 {
        job.slot as i32
    } else {
        job.neighbours[n - 1]
    };
    let slot = usize::try_from(slot).ok()?;
    let [x, y, z] = local.map(|c| c % BLOCK_SIDE);
    Some(CpuVoxels::slot_range(slot as u32).start + voxel_linear(x, y, z))
}

/// The triangles of one job's cells, ordered by (cell, triangle in case).
pub(crate) fn cell_triangles(
    voxels: &CpuVoxels,
    job: &MeshJob,
    p: &MeshParams,
) -> Vec<CellTriangle> {
    let mut out = Vec::new();
    'cells: for cell in 0..BLOCK_CELLS {
        let c = [cell % 8, (cell / 8) % 8, cell / 64].map(|v| v as i32);
        let mut tsdf = [0f32; 8];
        let mut color = [0u32; 8];
        let mut case = 0u8;
        for corner in 0..8u8 {
            let o = mc_table::corner_offset(corner);
            let Some(i) = corner_index(job, [c[0] + o[0], c[1] + o[1], c[2] + o[2]]) else {
                continue 'cells;
            };
            // Written so that a NaN weight counts as unobserved.
            let observed = voxels.weight[i] > p.min_weight;
            if !observed {
                continue 'cells;
            }
            tsdf[corner as usize] = voxels.tsdf[i];
            color[corner as usize] = voxels.color[i];
            if voxels.tsdf[i] < 0.0 {
                case |= 1 << corner;
            }
        }
        let cell_voxel = job.index.voxel(c);
        for (k, edges) in TABLE.triangles(case).iter().enumerate() {
            let mut t = CellTriangle {
                cell: cell as u16,
                tri: k as u8,
                keys: edges.map(|e| mc_table::edge_key(cell_voxel, e)),
                positions: [[0.0; 3]; 3],
                colors: [[0; 3]; 3],
            };
            for (v, &e) in edges.iter().enumerate() {
                let (a, b) = mc_table::edge_corners(e);
                let (a, b) = (a as usize, b as usize);
                (t.positions[v], t.colors[v]) = edge_vertex(
                    &t.keys[v],
                    [tsdf[a], tsdf[b]],
                    [color[a], color[b]],
                    p.voxel_size,
                );
            }
            out.push(t);
        }
    }
    out
}

/// Position and colour of the vertex on grid edge `key` whose lower / upper endpoint have
/// signed distances `t[0]`, `t[1]` (opposite signs) and packed colours `c`: the contract's
/// `s = t0 / (t0 − t1)`, `p = pa + s (pb − pa)`, colour lerp rounded half away from zero.
/// The kernel does the same f32 operations in the same order.
fn edge_vertex(key: &EdgeKey, t: [f32; 2], c: [u32; 2], voxel_size: f32) -> ([f32; 3], [u8; 3]) {
    let s = t[0] / (t[0] - t[1]);
    let mut upper = key.voxel;
    upper[key.axis as usize] += 1;
    let pa = key.voxel.map(|v| v as f32 * voxel_size);
    let pb = upper.map(|v| v as f32 * voxel_size);
    let position = [0, 1, 2].map(|k| pa[k] + s * (pb[k] - pa[k]));
    let (ca, cb) = (unpack_rgb(c[0]), unpack_rgb(c[1]));
    let color = [0, 1, 2].map(|k| {
        let (a, b) = (f32::from(ca[k]), f32::from(cb[k]));
        (a + s * (b - a)).round() as u8
    });
    (position, color)
}

/// The indexed mesh of block `index` from its cells' triangles, which must be ordered by
/// (cell, triangle in case): vertices are deduplicated by edge key and numbered in order of
/// first use (taking the first occurrence's position and colour), normals are
/// [`vertex_normals`].
pub(crate) fn assemble(index: BlockIndex, triangles: &[CellTriangle]) -> BlockMesh {
    let mut mesh = BlockMesh {
        index,
        ..BlockMesh::default()
    };
    // A closed surface has about half as many vertices as triangles, an open patch up to three
    // times as many: reserved for one per triangle, then trimmed, since the block keeps its
    // mesh (docs/tuning.md, issue 37, heaptrack).
    let mut vertex_of: HashMap<EdgeKey, u32> = HashMap::with_capacity(triangles.len());
    mesh.indices.reserve_exact(3 * triangles.len());
    mesh.positions.reserve(triangles.len());
    mesh.colors.reserve(triangles.len());
    mesh.edge_keys.reserve(triangles.len());
    for t in triangles {
        for v in 0..3 {
            let i = match vertex_of.entry(t.keys[v]) {
                Entry::Occupied(e) => *e.get(),
                Entry::Vacant(e) => {
                    mesh.positions.push(t.positions[v]);
                    mesh.colors.push(t.colors[v]);
                    mesh.edge_keys.push(t.keys[v]);
                    *e.insert((mesh.positions.len() - 1) as u32)
                }
            };
            mesh.indices.push(i);
        }
    }
    mesh.positions.shrink_to_fit();
    mesh.colors.shrink_to_fit();
    mesh.edge_keys.shrink_to_fit();
    mesh.normals = vertex_normals(&mesh.positions, &mesh.indices);
    mesh
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::fusion::block::{BLOCK_VOXELS, BlockTable, pack_rgb};
    use crate::fusion::mesh::Mesh;
    use std::collections::HashSet;

    /// A sphere's TSDF written into every voxel of the blocks `-4..=3` per axis (weight 1).
    pub(crate) struct SphereScene {
        pub voxels: CpuVoxels,
        pub jobs: Vec<MeshJob>,
        pub params: MeshParams,
        pub centre: [f64; 3],
        pub radius: f64,
    }

    pub(crate) fn sphere_scene() -> SphereScene {
        let voxel_size = 0.05f32;
        let h = f64::from(voxel_size);
        let block = 8.0 * h;
        let radius = 2.3 * block;
        // Off-grid so that no corner lands exactly on the surface.
        let centre = [0.37 * block, -0.21 * block, 0.13 * block];
        let truncation = 4.0 * h;
        let mut table = BlockTable::new(512);
        let mut blocks = Vec::new();
        for z in -4..4 {
            for y in -4..4 {
                for x in -4..4 {
                    let b = BlockIndex::new(x, y, z);
                    table.get_or_alloc(b).expect("512 blocks fit");
                    blocks.push(b);
                }
            }
        }
        let mut voxels = CpuVoxels::default();
        voxels.ensure_capacity(table.high_water());
        for &b in &blocks {
            let base = CpuVoxels::slot_range(table.get(&b).expect("allocated")).start;
            for i in 0..BLOCK_VOXELS {
                let local = [i % 8, (i / 8) % 8, i / 64].map(|c| c as i32);
                let v = b.voxel(local);
                let p = v.map(|c| f64::from(c) * h);
                let d = ((p[0] - centre[0]).powi(2)
                    + (p[1] - centre[1]).powi(2)
                    + (p[2] - centre[2]).powi(2))
                .sqrt();
                voxels.tsdf[base + i] = ((d - radius) / truncation).clamp(-1.0, 1.0) as f32;
                voxels.weight[base + i] = 1.0;
                let c = v.map(|c| (c * 37).rem_euclid(256) as u8);
                voxels.color[base + i] = pack_rgb(c);
            }
        }
        let jobs = blocks
            .iter()
            .map(|&b| table.mesh_job(b).expect("allocated"))
            .collect();
        SphereScene {
            voxels,
            jobs,
            params: MeshParams {
                voxel_size,
                min_weight: 0.0,
            },
            centre,
            radius,
        }
    }

    fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    }

    #[test]
    fn sphere_mesh_is_watertight_outward_and_on_the_sphere() {
        let s = sphere_scene();
        let blocks = extract_blocks(&s.voxels, &s.jobs, &s.params);
        assert_eq!(blocks.len(), s.jobs.len());
        for (b, j) in blocks.iter().zip(&s.jobs) {
            assert_eq!(b.index, j.index);
            assert_eq!(b.normals.len(), b.positions.len());
            assert_eq!(b.colors.len(), b.positions.len());
            assert_eq!(b.edge_keys.len(), b.positions.len());
        }
        let mesh = Mesh::from_blocks(&blocks);
        assert!(mesh.triangle_count() > 1000, "{}", mesh.triangle_count());

        // Closed and consistently oriented: each directed edge once, with its reverse.
        let directed: Vec<(u32, u32)> = mesh
            .indices
            .chunks_exact(3)
            .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
            .collect();
        let set: HashSet<(u32, u32)> = directed.iter().copied().collect();
        assert_eq!(set.len(), directed.len(), "a directed edge is used twice");
        for &(a, b) in &directed {
            assert!(set.contains(&(b, a)), "edge {a}-{b} is on the boundary");
        }
        // A sphere: Euler characteristic V − E + F = 2.
        let (v, e, f) = (
            mesh.vertex_count() as i64,
            directed.len() as i64 / 2,
            mesh.triangle_count() as i64,
        );
        assert_eq!(v - e + f, 2, "V {v} E {e} F {f}");

        let p = |i: u32| mesh.positions[i as usize].map(f64::from);
        for t in mesh.indices.chunks_exact(3) {
            let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
            let (e1, e2) = (sub(b, a), sub(c, a));
            let n = [
                e1[1] * e2[2] - e1[2] * e2[1],
                e1[2] * e2[0] - e1[0] * e2[2],
                e1[0] * e2[1] - e1[1] * e2[0],
            ];
            let centroid = [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0);
            let out = sub(centroid, s.centre);
            assert!(
                n[0] * out[0] + n[1] * out[1] + n[2] * out[2] > 0.0,
                "triangle {t:?} faces inwards"
            );
        }
        // Linear interpolation of f(p) = |p − c| − r along an edge of length h, whose points
        // are at least r − h from the centre (both endpoints are within h of the surface),
        // misses the root by at most h² max f'' / 8 with f'' ≤ 1/(r − h); f is the exact
        // distance to the sphere. Plus f32 rounding of coordinates of magnitude ~1.
        let h = f64::from(s.params.voxel_size);
        let bound = h * h / (8.0 * (s.radius - h)) + 1e-4 * h;
        let mut worst = 0f64;
        for q in &mesh.positions {
            let d = sub(q.map(f64::from), s.centre);
            let err = ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() - s.radius).abs();
            worst = worst.max(err);
        }
        assert!(
            worst <= bound,
            "vertex {worst} off the sphere (bound {bound})"
        );
        for (q, n) in mesh.positions.iter().zip(&mesh.normals) {
            let d = sub(q.map(f64::from), s.centre);
            let cos = (d[0] * f64::from(n[0]) + d[1] * f64::from(n[1]) + d[2] * f64::from(n[2]))
                / s.radius;
            assert!(cos > 0.9, "vertex normal {n:?} at {q:?}");
        }
    }

    /// Cells reaching into a missing neighbour, or with a corner at `weight <= min_weight`,
    /// emit nothing; every other crossed cell emits.
    #[test]
    fn cells_with_missing_or_unobserved_corners_emit_nothing() {
        let mut table = BlockTable::new(4);
        let home = BlockIndex::new(0, 0, 0);
        // Only the +x neighbour exists.
        for b in [home, BlockIndex::new(1, 0, 0)] {
            table.get_or_alloc(b).expect("fits");
        }
        let mut voxels = CpuVoxels::default();
        voxels.ensure_capacity(table.high_water());
        for (b, slot) in table.iter() {
            let base = CpuVoxels::slot_range(slot).start;
            for i in 0..BLOCK_VOXELS {
                let v = b.voxel([i % 8, (i / 8) % 8, i / 64].map(|c| c as i32));
                let f = v[0] as f32 + 0.5 * v[1] as f32 + 0.25 * v[2] as f32 - 8.3;
                voxels.tsdf[base + i] = (f / 4.0).clamp(-1.0, 1.0);
                voxels.weight[base + i] = 2.0;
                voxels.color[base + i] = pack_rgb([10, 20, 30]);
            }
        }
        let home_base = CpuVoxels::slot_range(table.get(&home).expect("home")).start;
        let low = [3, 2, 1];
        voxels.weight[home_base + voxel_linear(low[0], low[1], low[2])] = 0.5;
        let job = table.mesh_job(home).expect("home");
        let p = MeshParams {
            voxel_size: 0.1,
            min_weight: 0.5,
        };
        let emitted: HashSet<u16> = cell_triangles(&voxels, &job, &p)
            .iter()
            .map(|t| t.cell)
            .collect();
        let f = |v: [i32; 3]| v[0] as f32 + 0.5 * v[1] as f32 + 0.25 * v[2] as f32 - 8.3;
        let mut expected = HashSet::new();
        for cell in 0..BLOCK_CELLS as u16 {
            let c = [cell % 8, (cell / 8) % 8, cell / 64].map(i32::from);
            let corners: Vec<[i32; 3]> = (0..8u8)
                .map(|k| {
                    let o = mc_table::corner_offset(k);
                    [c[0] + o[0], c[1] + o[1], c[2] + o[2]]
                })
                .collect();
            let reaches_missing = c[1] == 7 || c[2] == 7;
            let touches_low = corners.contains(&low);
            let crossed =
                corners.iter().any(|&v| f(v) < 0.0) && corners.iter().any(|&v| f(v) >= 0.0);
            if crossed && !reaches_missing && !touches_low {
                expected.insert(cell);
            }
        }
        assert!(expected.len() > 20, "{}", expected.len());
        assert!(
            expected.iter().any(|c| c % 8 == 7),
            "x = 7 cells use the +x neighbour"
        );
        assert_eq!(emitted, expected);

        // Without the neighbour the x = 7 cells go quiet too.
        let mut alone = job;
        alone.neighbours = [-1; 7];
        let emitted: HashSet<u16> = cell_triangles(&voxels, &alone, &p)
            .iter()
            .map(|t| t.cell)
            .collect();
        let expected: HashSet<u16> = expected.into_iter().filter(|c| c % 8 != 7).collect();
        assert_eq!(emitted, expected);
    }

    #[test]
    fn block_meshes_share_vertices_in_order_of_first_use() {
        let s = sphere_scene();
        let job = s
            .jobs
            .iter()
            .find(|j| j.index == BlockIndex::new(2, 0, 0))
            .expect("job");
        let tris = cell_triangles(&s.voxels, job, &s.params);
        assert!(!tris.is_empty());
        assert!(
            tris.windows(2)
                .all(|w| (w[0].cell, w[0].tri) < (w[1].cell, w[1].tri))
        );
        let mesh = assemble(job.index, &tris);
        assert_eq!(mesh.triangle_count(), tris.len());
        let distinct: HashSet<EdgeKey> = tris.iter().flat_map(|t| t.keys).collect();
        assert_eq!(mesh.positions.len(), distinct.len());
        // First use order: the highest index seen so far grows by at most one.
        let mut next = 0;
        for &i in &mesh.indices {
            assert!(i <= next);
            if i == next {
                next += 1;
            }
        }
        for (t, tri) in mesh.indices.chunks_exact(3).zip(&tris) {
            for (&i, (key, position)) in t.iter().zip(tri.keys.iter().zip(&tri.positions)) {
                assert_eq!(&mesh.edge_keys[i as usize], key);
                assert_eq!(&mesh.positions[i as usize], position);
            }
        }
    }
}
