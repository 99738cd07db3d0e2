//! Triangle meshes of the fused surface: one [`BlockMesh`] per voxel block (what marching cubes
//! emits and what a `MeshUpdate` carries) and the welded whole-scene [`Mesh`] (what the PLY and
//! GLB exports write).

use super::block::BlockIndex;
use super::weld::{SortedBlocks, WeldSink};
use crate::Result;

/// The grid edge a marching-cubes vertex lies on: its lower endpoint (global voxel
/// coordinates) and its axis (0 = x, 1 = y, 2 = z). Two blocks that share a face compute the
/// same key for a vertex on it, which is how the whole-scene mesh is welded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct EdgeKey {
    pub voxel: [i32; 3],
    pub axis: u8,
}

/// The triangles of one block, indexed (one vertex per distinct edge key), in world
/// coordinates. Triangles are wound counter-clockwise seen from free space (positive SDF), so
/// face normals point out of the surface towards the cameras that saw it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BlockMesh {
    pub index: BlockIndex,
    pub positions: Vec<[f32; 3]>,
    /// Unit vertex normals ([`vertex_normals`] over this block's triangles).
    pub normals: Vec<[f32; 3]>,
    pub colors: Vec<[u8; 3]>,
    /// Three vertex indices per triangle.
    pub indices: Vec<u32>,
    /// One per vertex.
    pub edge_keys: Vec<EdgeKey>,
}

impl BlockMesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }
}

/// Area-weighted vertex normals (the cross product of two triangle edges is the face normal
/// times twice its area, so summing them weights each face by its area). Vertices without a
/// non-degenerate face get `[0, 0, 1]`.
pub fn vertex_normals(positions: &[[f32; 3]], indices: &[u32]) -> Vec<[f32; 3]> {
    let mut acc = vec![[0f64; 3]; positions.len()];
    for t in indices.chunks_exact(3) {
        let p = |i: u32| positions[i as usize];
        let n = face_normal(p(t[0]), p(t[1]), p(t[2]));
        for &i in t {
            for k in 0..3 {
                acc[i as usize][k] += n[k];
            }
        }
    }
    acc.into_iter().map(unit_normal).collect()
}

/// A triangle's normal times twice its area, in f64 (summed per vertex by
/// [`vertex_normals`] and the streaming weld alike, so both give the same bits).
pub(super) fn face_normal(a: [f32; 3], b: [f32; 3], c: [f32; 3]) -> [f64; 3] {
    let (a, b, c) = (a.map(f64::from), b.map(f64::from), c.map(f64::from));
    let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ]
}

/// A summed normal made unit length (`[0, 0, 1]` for a zero sum).
pub(super) fn unit_normal(n: [f64; 3]) -> [f32; 3] {
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 {
        [
            (n[0] / len) as f32,
            (n[1] / len) as f32,
            (n[2] / len) as f32,
        ]
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// The whole fused surface, welded across blocks, with vertex normals and colours.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub colors: Vec<[u8; 3]>,
    pub indices: Vec<u32>,
}

impl Mesh {
    /// Welds block meshes into one: vertices with the same [`EdgeKey`] become one, and normals
    /// are recomputed over the welded triangles (so there are no seams at block faces). Blocks
    /// are taken in index order, so the result does not depend on the map's iteration order
    /// ([`super::weld`], whose streaming weld gives the same mesh a slab at a time).
    pub fn from_blocks<'a>(blocks: impl IntoIterator<Item = &'a BlockMesh>) -> Self {
        let mut mesh = Mesh::default();
        super::weld::weld_in_memory(&mut SortedBlocks::new(blocks), &mut mesh)
            .expect("sorted blocks weld, and a mesh in memory takes every record");
        mesh
    }

    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }
}

/// A mesh in memory takes the weld's records as they come.
impl WeldSink for Mesh {
    fn vertex(&mut self, position: [f32; 3], normal: [f32; 3], color: [u8; 3]) -> Result<()> {
        self.positions.push(position);
        self.normals.push(normal);
        self.colors.push(color);
        Ok(())
    }

    fn triangle(&mut self, vertices: [u32; 3]) -> Result<()> {
        self.indices.extend(vertices);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad_block(index: BlockIndex, x0: i32) -> BlockMesh {
        // Two triangles of a unit square in the z = 0 plane spanning x0..x0+1, keyed by x.
        let key = |x: i32, y: i32| EdgeKey {
            voxel: [x, y, 0],
            axis: 2,
        };
        let positions = vec![
            [x0 as f32, 0.0, 0.0],
            [x0 as f32 + 1.0, 0.0, 0.0],
            [x0 as f32 + 1.0, 1.0, 0.0],
            [x0 as f32, 1.0, 0.0],
        ];
        let indices = vec![0, 1, 2, 0, 2, 3];
        BlockMesh {
            index,
            normals: vertex_normals(&positions, &indices),
            positions,
            colors: vec![[10, 20, 30]; 4],
            indices,
            edge_keys: vec![key(x0, 0), key(x0 + 1, 0), key(x0 + 1, 1), key(x0, 1)],
        }
    }

    #[test]
    fn blocks_weld_on_shared_edge_keys() {
        let a = quad_block(BlockIndex::new(0, 0, 0), 0);
        let b = quad_block(BlockIndex::new(1, 0, 0), 1);
        let mesh = Mesh::from_blocks([&b, &a]);
        assert_eq!(
            mesh.vertex_count(),
            6,
            "the shared edge's two vertices are welded"
        );
        assert_eq!(mesh.triangle_count(), 4);
        for n in &mesh.normals {
            assert!(
                (n[2] - 1.0).abs() < 1e-6,
                "counter-clockwise in xy faces +z: {n:?}"
            );
        }
    }
}
