//! Welding block meshes into one indexed surface a block at a time (issue 37, item 3): the
//! final mesh of a long session is written block by block, its spilled chunks read back a
//! slab at a time, without the whole surface in memory.
//!
//! Why it can stream: a vertex is keyed by its grid edge ([`EdgeKey`], lower endpoint `v`),
//! and marching cubes emits an edge only from the cells of the block holding `v` and of its
//! lower neighbours (cells reach one voxel into the upper neighbours). So an edge with
//! `v.x` in block slab `K` is met only in the slabs `K − 1` and `K`. Fed in ascending block
//! order, once slab `S` starts every vertex of a slab below `S` has all its triangles: its
//! normal is final, it is handed on and its key forgotten. What is held is two slabs of
//! vertices. Vertices are numbered in order of first occurrence and handed on in that order,
//! so the result is the same, bit for bit, as welding everything at once.

use std::collections::{HashMap, VecDeque};

use super::block::{BLOCK_SIDE, BlockIndex};
use super::mesh::{BlockMesh, EdgeKey, face_normal, unit_normal};
use crate::{Error, Result};

/// Where welded vertices (with their final normals) and triangles go, each in index order.
pub trait WeldSink {
    fn vertex(&mut self, position: [f32; 3], normal: [f32; 3], color: [u8; 3]) -> Result<()>;
    fn triangle(&mut self, vertices: [u32; 3]) -> Result<()>;
}

/// Block meshes in ascending [`BlockIndex`] order, handed out in runs: what a source holds at
/// once (everything, for a surface in memory; a slab of chunks read back from the store, for
/// a fuser with spilled chunks). A source can be walked more than once (an encoder that
/// writes counts before records makes several passes).
pub trait BlockSource {
    fn runs(&mut self, each: &mut dyn FnMut(&[&BlockMesh]) -> Result<()>) -> Result<()>;
}

/// Block meshes held in memory, sorted once.
#[derive(Debug)]
pub struct SortedBlocks<'a>(Vec<&'a BlockMesh>);

impl<'a> SortedBlocks<'a> {
    /// `blocks` in index order; of two with one index, the later is kept (as a map would).
    pub fn new(blocks: impl IntoIterator<Item = &'a BlockMesh>) -> Self {
        let mut v: Vec<&BlockMesh> = blocks.into_iter().collect();
        v.reverse();
        v.sort_by_key(|b| b.index);
        v.dedup_by_key(|b| b.index);
        Self(v)
    }
}

impl BlockSource for SortedBlocks<'_> {
    fn runs(&mut self, each: &mut dyn FnMut(&[&BlockMesh]) -> Result<()>) -> Result<()> {
        each(&self.0)
    }
}

/// What a weld produced.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WeldCounts {
    pub vertices: u32,
    pub triangles: u64,
}

/// Welds every block of `source` into `sink` a slab at a time (see the module docs). Blocks
/// must come in ascending order and key their vertices as marching cubes does (an edge within
/// the block's cells), or the weld stops with [`Error::Shape`].
pub fn weld(source: &mut dyn BlockSource, sink: &mut dyn WeldSink) -> Result<WeldCounts> {
    weld_with(source, sink, true)
}

/// [`weld`] holding every vertex until the end: the same result for marching cubes' blocks,
/// and welds any blocks (a mesh in memory, [`super::Mesh::from_blocks`]).
pub fn weld_in_memory(source: &mut dyn BlockSource, sink: &mut dyn WeldSink) -> Result<WeldCounts> {
    weld_with(source, sink, false)
}

fn weld_with(
    source: &mut dyn BlockSource,
    sink: &mut dyn WeldSink,
    streaming: bool,
) -> Result<WeldCounts> {
    let mut welder = Welder::new(sink, streaming);
    source.runs(&mut |blocks| blocks.iter().try_for_each(|b| welder.add(b)))?;
    welder.finish()
}

/// A vertex whose triangles may not all have been seen yet.
struct Pending {
    key: EdgeKey,
    /// Block slab of the key's lower endpoint: final once a block of a higher slab comes.
    slab: i32,
    position: [f32; 3],
    color: [u8; 3],
    /// Sum of the area-weighted normals of its triangles so far.
    normal: [f64; 3],
}

struct Welder<'s> {
    sink: &'s mut dyn WeldSink,
    /// Keys of the pending vertices, to their indices.
    keys: HashMap<EdgeKey, u32>,
    pending: VecDeque<Pending>,
    /// Index of `pending[0]`.
    first_pending: u32,
    counts: WeldCounts,
    last: Option<BlockIndex>,
    /// Hand vertices on a slab at a time (else all at the end).
    streaming: bool,
}

impl<'s> Welder<'s> {
    fn new(sink: &'s mut dyn WeldSink, streaming: bool) -> Self {
        Self {
            streaming,
            sink,
            keys: HashMap::new(),
            pending: VecDeque::new(),
            first_pending: 0,
            counts: WeldCounts::default(),
            last: None,
        }
    }

    fn add(&mut self, block: &BlockMesh) -> Result<()> {
        if self.last.is_some_and(|l| l >= block.index) {
            return Err(Error::Shape(format!(
                "weld: block {:?} after {:?} (blocks must come in ascending order, once each)",
                block.index, self.last
            )));
        }
        if self.streaming && self.last.is_none_or(|l| l.x != block.index.x) {
            self.hand_on(block.index.x)?;
        }
        self.last = Some(block.index);
        let mut remap = Vec::with_capacity(block.positions.len());
        for v in 0..block.positions.len() {
            let key = block.edge_keys[v];
            let index = match self.keys.get(&key) {
                Some(&i) => i,
                None => {
                    let slab = key.voxel[0].div_euclid(BLOCK_SIDE);
                    if self.streaming && slab != block.index.x && slab != block.index.x + 1 {
                        // Welding a block at a time rests on this (see the module docs).
                        return Err(Error::Shape(format!(
                            "weld: block {:?} has a vertex on edge {key:?}, outside its cells",
                            block.index
                        )));
                    }
                    let i = self.counts.vertices;
                    self.counts.vertices += 1;
                    self.keys.insert(key, i);
                    self.pending.push_back(Pending {
                        key,
                        slab,
                        position: block.positions[v],
                        color: block.colors[v],
                        normal: [0.0; 3],
                    });
                    i
                }
            };
            remap.push(index);
        }
        for t in block.indices.chunks_exact(3) {
            let t = [
                remap[t[0] as usize],
                remap[t[1] as usize],
                remap[t[2] as usize],
            ];
            let at = |i: u32| (i - self.first_pending) as usize;
            let p = |i: u32| self.pending[at(i)].position;
            let n = face_normal(p(t[0]), p(t[1]), p(t[2]));
            for i in t {
                let acc = &mut self.pending[at(i)].normal;
                for k in 0..3 {
                    acc[k] += n[k];
                }
            }
            self.sink.triangle(t)?;
            self.counts.triangles += 1;
        }
        Ok(())
    }

    /// Hands on, in index order, the vertices that no block of slab `slab` or above can
    /// touch.
    fn hand_on(&mut self, slab: i32) -> Result<()> {
        while self.pending.front().is_some_and(|p| p.slab < slab) {
            let p = self.pending.pop_front().expect("checked");
            self.keys.remove(&p.key);
            self.first_pending += 1;
            self.sink
                .vertex(p.position, unit_normal(p.normal), p.color)?;
        }
        Ok(())
    }

    fn finish(mut self) -> Result<WeldCounts> {
        self.hand_on(i32::MAX)?;
        Ok(self.counts)
    }
}

/// A sink that only counts, and bounds the positions (GLB's `POSITION` accessor needs them
/// before the data).
#[derive(Clone, Copy, Debug)]
pub struct Bounds {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Default for Bounds {
    fn default() -> Self {
        Self {
            min: [f32::INFINITY; 3],
            max: [f32::NEG_INFINITY; 3],
        }
    }
}

impl Bounds {
    pub fn add(&mut self, p: [f32; 3]) {
        for (k, v) in p.into_iter().enumerate() {
            self.min[k] = self.min[k].min(v);
            self.max[k] = self.max[k].max(v);
        }
    }
}

impl WeldSink for Bounds {
    fn vertex(&mut self, position: [f32; 3], _: [f32; 3], _: [u8; 3]) -> Result<()> {
        self.add(position);
        Ok(())
    }

    fn triangle(&mut self, _: [u32; 3]) -> Result<()> {
        Ok(())
    }
}

/// One welding pass of `source` that hands each vertex to `each` (an encoder's pass over one
/// vertex section).
pub fn each_vertex(
    source: &mut dyn BlockSource,
    each: impl FnMut([f32; 3], [f32; 3], [u8; 3]) -> Result<()>,
) -> Result<WeldCounts> {
    weld(
        source,
        &mut Records {
            vertex: each,
            triangle: |_| Ok(()),
        },
    )
}

/// One welding pass of `source` that hands each triangle to `each`.
pub fn each_triangle(
    source: &mut dyn BlockSource,
    each: impl FnMut([u32; 3]) -> Result<()>,
) -> Result<WeldCounts> {
    weld(
        source,
        &mut Records {
            vertex: |_, _, _| Ok(()),
            triangle: each,
        },
    )
}

/// A sink that hands vertices and triangles to two closures.
struct Records<V, T> {
    vertex: V,
    triangle: T,
}

impl<V, T> WeldSink for Records<V, T>
where
    V: FnMut([f32; 3], [f32; 3], [u8; 3]) -> Result<()>,
    T: FnMut([u32; 3]) -> Result<()>,
{
    fn vertex(&mut self, position: [f32; 3], normal: [f32; 3], color: [u8; 3]) -> Result<()> {
        (self.vertex)(position, normal, color)
    }

    fn triangle(&mut self, vertices: [u32; 3]) -> Result<()> {
        (self.triangle)(vertices)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fusion::Mesh;
    use crate::fusion::mesh::vertex_normals;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// A surface of random blocks: a heightfield over x and y, meshed per block with keys on
    /// the shared grid so neighbouring blocks weld (the way marching cubes keys them).
    fn random_blocks(seed: u64, side: i32) -> Vec<BlockMesh> {
        let mut rng = StdRng::seed_from_u64(seed);
        let height: Vec<f32> = (0..(side * 8 + 1).pow(2))
            .map(|_| rng.random_range(-0.4f32..0.4))
            .collect();
        let h = |x: i32, y: i32| height[(y * (side * 8 + 1) + x) as usize];
        let mut blocks = Vec::new();
        for bx in 0..side {
            for by in 0..side {
                if rng.random_bool(0.15) {
                    continue; // holes: slabs and rows with gaps
                }
                let mut m = BlockMesh {
                    index: BlockIndex::new(bx, by, 0),
                    ..BlockMesh::default()
                };
                let mut local: HashMap<EdgeKey, u32> = HashMap::new();
                let mut vertex = |m: &mut BlockMesh, x: i32, y: i32| {
                    let key = EdgeKey {
                        voxel: [x, y, 0],
                        axis: 2,
                    };
                    *local.entry(key).or_insert_with(|| {
                        m.positions.push([x as f32, y as f32, h(x, y)]);
                        m.colors.push([x as u8, y as u8, 7]);
                        m.edge_keys.push(key);
                        (m.positions.len() - 1) as u32
                    })
                };
                for x in bx * 8..bx * 8 + 8 {
                    for y in by * 8..by * 8 + 8 {
                        let q = [
                            vertex(&mut m, x, y),
                            vertex(&mut m, x + 1, y),
                            vertex(&mut m, x + 1, y + 1),
                            vertex(&mut m, x, y + 1),
                        ];
                        m.indices.extend([q[0], q[1], q[2], q[0], q[2], q[3]]);
                    }
                }
                m.normals = vertex_normals(&m.positions, &m.indices);
                blocks.push(m);
            }
        }
        blocks
    }

    /// The reference: every block welded at once in one map, normals over the whole mesh.
    fn weld_at_once(blocks: &[BlockMesh]) -> Mesh {
        let mut sorted: Vec<&BlockMesh> = blocks.iter().collect();
        sorted.sort_by_key(|b| b.index);
        let mut mesh = Mesh::default();
        let mut welded: HashMap<EdgeKey, u32> = HashMap::new();
        for b in sorted {
            let remap: Vec<u32> = (0..b.positions.len())
                .map(|v| {
                    *welded.entry(b.edge_keys[v]).or_insert_with(|| {
                        mesh.positions.push(b.positions[v]);
                        mesh.colors.push(b.colors[v]);
                        (mesh.positions.len() - 1) as u32
                    })
                })
                .collect();
            mesh.indices
                .extend(b.indices.iter().map(|&i| remap[i as usize]));
        }
        mesh.normals = vertex_normals(&mesh.positions, &mesh.indices);
        mesh
    }

    /// A source that hands blocks out one x-slab per run, the way a fuser reads its spilled
    /// chunks back.
    struct BySlab(Vec<BlockMesh>);

    impl BlockSource for BySlab {
        fn runs(&mut self, each: &mut dyn FnMut(&[&BlockMesh]) -> Result<()>) -> Result<()> {
            let mut sorted: Vec<&BlockMesh> = self.0.iter().collect();
            sorted.sort_by_key(|b| b.index);
            for slab in sorted.chunk_by(|a, b| a.index.x == b.index.x) {
                each(slab)?;
            }
            Ok(())
        }
    }

    #[test]
    fn streamed_weld_equals_welding_everything_at_once() {
        for seed in 0..4 {
            let blocks = random_blocks(seed, 5);
            let expected = weld_at_once(&blocks);
            assert!(expected.vertex_count() > 100);
            let mut got = Mesh::default();
            let counts = weld(&mut BySlab(blocks.clone()), &mut got).expect("weld");
            assert_eq!(got, expected, "seed {seed}");
            assert_eq!(counts.vertices as usize, expected.vertex_count());
            assert_eq!(counts.triangles as usize, expected.triangle_count());
            assert_eq!(Mesh::from_blocks(blocks.iter()), expected);
        }
    }

    #[test]
    fn vertices_are_handed_on_before_the_end() {
        // A sink that checks how many vertices are still pending when each comes.
        struct Early(u32);
        impl WeldSink for Early {
            fn vertex(&mut self, _: [f32; 3], _: [f32; 3], _: [u8; 3]) -> Result<()> {
                self.0 += 1;
                Ok(())
            }
            fn triangle(&mut self, _: [u32; 3]) -> Result<()> {
                Ok(())
            }
        }
        let blocks = random_blocks(9, 6);
        let mut slabs = BySlab(blocks);
        let mut sink = Early(0);
        let mut welder = Welder::new(&mut sink, true);
        let mut most_pending = 0;
        slabs
            .runs(&mut |run| {
                for b in run {
                    welder.add(b)?;
                }
                most_pending = most_pending.max(welder.pending.len());
                Ok(())
            })
            .expect("weld");
        let total = welder.finish().expect("finish").vertices as usize;
        // Two slabs of six at most are held, never the whole surface.
        assert!(
            most_pending * 2 < total,
            "{most_pending} pending of {total}"
        );
    }

    #[test]
    fn blocks_out_of_order_or_off_their_cells_are_refused() {
        let blocks = random_blocks(1, 2);
        let mut mesh = Mesh::default();
        let mut backwards = SortedBlocks(blocks.iter().rev().collect());
        assert!(weld(&mut backwards, &mut mesh).is_err());
        // A vertex two slabs away cannot be welded a slab at a time; in memory it can.
        let mut far = blocks[0].clone();
        far.edge_keys[0].voxel[0] += 3 * BLOCK_SIDE;
        let e = weld(&mut SortedBlocks::new([&far]), &mut Mesh::default()).expect_err("far");
        assert!(e.to_string().contains("outside its cells"), "{e}");
        weld_in_memory(&mut SortedBlocks::new([&far]), &mut Mesh::default()).expect("in memory");
    }
}
