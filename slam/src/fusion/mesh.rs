//! Triangle meshes of the fused surface: one [`BlockMesh`] per voxel block (what marching cubes
//! emits and what a `MeshUpdate` carries) and the welded whole-scene [`Mesh`] (what the PLY and
//! GLB exports write).

use std::collections::{BTreeMap, HashMap};

use super::block::BlockIndex;

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
        let p = |i: u32| positions[i as usize].map(f64::from);
        let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        for &i in t {
            for k in 0..3 {
                acc[i as usize][k] += n[k];
            }
        }
    }
    acc.into_iter()
        .map(|n| {
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
        })
        .collect()
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
    /// are taken in index order, so the result does not depend on the map's iteration order.
    pub fn from_blocks<'a>(blocks: impl IntoIterator<Item = &'a BlockMesh>) -> Self {
        let sorted: BTreeMap<BlockIndex, &BlockMesh> =
            blocks.into_iter().map(|b| (b.index, b)).collect();
        let mut mesh = Mesh::default();
        let mut welded: HashMap<EdgeKey, u32> = HashMap::new();
        for block in sorted.values() {
            let remap: Vec<u32> = (0..block.positions.len())
                .map(|v| {
                    *welded.entry(block.edge_keys[v]).or_insert_with(|| {
                        mesh.positions.push(block.positions[v]);
                        mesh.colors.push(block.colors[v]);
                        (mesh.positions.len() - 1) as u32
                    })
                })
                .collect();
            mesh.indices
                .extend(block.indices.iter().map(|&i| remap[i as usize]));
        }
        mesh.normals = vertex_normals(&mesh.positions, &mesh.indices);
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
