//! A session's fused mesh as its subscribers have it (every `MeshUpdate` applied), in bounded
//! memory (issue 37, item 3). Past `fusion.resident_blocks` blocks, the chunks of 4×4×4
//! blocks changed least recently go to the session's store with their meshes, as the fuser's
//! voxels do (`relfusion_slam::fusion::chunks`). A chunk comes back when a delta touches it;
//! the downloads, results and map snapshots walk the surface a slab of chunks at a time
//! (`fusion::weld`, `session::snapshot`). Spilling changes where the mesh lives, never the
//! mesh.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

use relfusion_slam::fusion::chunks::{ChunkData, ChunkIndex, Surface};
use relfusion_slam::fusion::{BlockIndex, BlockMesh, MeshDelta};
use relfusion_slam::spill::{Spill, Stored};

/// The session's fused mesh, block by block (what `MeshUpdate`s describe).
#[derive(Debug, Default)]
pub(crate) struct MeshState {
    blocks: BTreeMap<BlockIndex, BlockMesh>,
    spilled: BTreeMap<ChunkIndex, SpilledChunk>,
    /// The revision at which each chunk in memory last changed.
    changed: HashMap<ChunkIndex, u64>,
    pub revision: u64,
    pub block_size: f32,
    /// The session's spilling and the blocks to keep in memory (none: everything stays).
    bound: Option<(Spill, usize)>,
}

/// [`MeshState::snapshot`].
#[derive(Debug)]
pub(super) struct MeshSnapshot {
    resident: BTreeMap<BlockIndex, BlockMesh>,
    spilled: Vec<(ChunkIndex, Arc<Stored<ChunkData>>)>,
}

impl MeshSnapshot {
    pub(super) fn surface(&self) -> Surface<'_> {
        Surface::new(&self.resident, self.spilled.iter().cloned())
    }
}

#[derive(Debug)]
struct SpilledChunk {
    stored: Arc<Stored<ChunkData>>,
    blocks: usize,
    triangles: u64,
    changed: u64,
}

impl MeshState {
    /// From now on, past `resident_blocks` blocks, chunks spill through `spill`.
    pub(super) fn bound(&mut self, spill: Spill, resident_blocks: usize) {
        self.bound = Some((spill, resident_blocks.max(1)));
    }

    /// Replaces the changed blocks and drops the removed ones (their chunks come back from
    /// the store first), then spills what is past the bound.
    pub(super) fn apply(&mut self, delta: &MeshDelta) {
        let touched: BTreeSet<ChunkIndex> = delta
            .removed
            .iter()
            .chain(delta.changed.iter().map(|m| &m.index))
            .map(ChunkIndex::of)
            .collect();
        for c in &touched {
            self.load(c);
        }
        for b in &delta.removed {
            self.blocks.remove(b);
        }
        for m in &delta.changed {
            self.blocks.insert(m.index, m.clone());
        }
        for c in touched {
            self.changed.insert(c, delta.revision);
        }
        self.revision = delta.revision;
        self.block_size = delta.block_size;
        self.evict();
    }

    pub(super) fn is_empty(&self) -> bool {
        self.blocks.is_empty() && self.spilled.is_empty()
    }

    pub(super) fn triangles(&self) -> u64 {
        let resident: u64 = self
            .blocks
            .values()
            .map(|m| m.triangle_count() as u64)
            .sum();
        resident + self.spilled.values().map(|s| s.triangles).sum::<u64>()
    }

    /// Blocks in memory and in the store.
    pub(super) fn block_counts(&self) -> (usize, usize) {
        (
            self.blocks.len(),
            self.spilled.values().map(|s| s.blocks).sum(),
        )
    }

    /// The whole surface as it stands, to weld or encode a slab at a time once the session's
    /// lock is released: a copy of the blocks in memory (at most the bound) and handles to
    /// the spilled chunks (which stay in the store while a handle lives).
    pub(super) fn snapshot(&self) -> MeshSnapshot {
        MeshSnapshot {
            resident: self.blocks.clone(),
            spilled: self
                .spilled
                .iter()
                .map(|(c, s)| (*c, Arc::clone(&s.stored)))
                .collect(),
        }
    }

    /// Brings chunk `c` back from the store, if it is there.
    fn load(&mut self, c: &ChunkIndex) {
        let Some(s) = self.spilled.remove(c) else {
            return;
        };
        match s.stored.get() {
            Ok(data) => {
                for m in &data.meshes {
                    self.blocks.insert(m.index, m.clone());
                }
                self.changed.insert(*c, s.changed);
            }
            // The store lost what it acknowledged: the subscribers still have these blocks,
            // the session's own copy goes on without them.
            Err(e) => tracing::error!(chunk = ?c, error = %e, "mesh chunk lost from the store"),
        }
    }

    /// Past the bound, moves the chunks changed least recently to the store until a quarter
    /// of the bound is free (so a session exploring new ground spills every few updates, not
    /// at each). A store that refuses stops it, and the blocks stay.
    fn evict(&mut self) {
        let Some((spill, limit)) = &self.bound else {
            return;
        };
        if self.blocks.len() <= *limit || !spill.enabled() {
            return;
        }
        let target = limit - limit / 4;
        let mut by_chunk: BTreeMap<ChunkIndex, Vec<BlockIndex>> = BTreeMap::new();
        for b in self.blocks.keys() {
            by_chunk.entry(ChunkIndex::of(b)).or_default().push(*b);
        }
        let mut order: Vec<(u64, ChunkIndex)> = by_chunk
            .keys()
            .map(|c| (self.changed.get(c).copied().unwrap_or(0), *c))
            .collect();
        order.sort_unstable();
        for (changed, c) in order {
            // What the latest update touched is where the camera works: it stays.
            if self.blocks.len() <= target || changed == self.revision {
                break;
            }
            let meshes: Vec<BlockMesh> = by_chunk[&c]
                .iter()
                .filter_map(|b| self.blocks.remove(b))
                .collect();
            let triangles = meshes.iter().map(|m| m.triangle_count() as u64).sum();
            let blocks = meshes.len();
            let stored = Stored::new(
                spill,
                Arc::new(ChunkData {
                    meshes,
                    ..ChunkData::default()
                }),
            );
            if let Err(e) = stored.spill() {
                tracing::warn!(error = %e, "mesh chunks stay in memory");
                if let Some(data) = stored.held() {
                    for m in &data.meshes {
                        self.blocks.insert(m.index, m.clone());
                    }
                }
                return;
            }
            self.changed.remove(&c);
            self.spilled.insert(
                c,
                SpilledChunk {
                    stored,
                    blocks,
                    triangles,
                    changed,
                },
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use relfusion_slam::export::{mesh_glb_bytes, mesh_ply_bytes, mesh_ply_bytes_from};
    use relfusion_slam::fusion::weld::BlockSource;
    use relfusion_slam::fusion::{EdgeKey, Mesh};

    /// A flat block mesh of block `b` on the shared grid (so neighbours weld), its height
    /// and colour set by `v`.
    fn block(b: BlockIndex, v: u8) -> BlockMesh {
        let mut m = BlockMesh {
            index: b,
            ..BlockMesh::default()
        };
        let (x0, y0) = (b.x * 8, b.y * 8);
        for (dx, dy) in [(0, 0), (8, 0), (8, 8), (0, 8)] {
            m.positions
                .push([(x0 + dx) as f32, (y0 + dy) as f32, f32::from(v)]);
            m.normals.push([0.0, 0.0, 1.0]);
            m.colors.push([v, 2 * v, 3]);
            m.edge_keys.push(EdgeKey {
                voxel: [x0 + dx, y0 + dy, b.z * 8],
                axis: 2,
            });
        }
        m.indices = vec![0, 1, 2, 0, 2, 3];
        m
    }

    fn delta(revision: u64, changed: Vec<BlockMesh>, removed: Vec<BlockIndex>) -> MeshDelta {
        MeshDelta {
            revision,
            block_size: 0.08,
            changed,
            removed,
        }
    }

    /// A camera sweeping along x over a 24×4 strip of blocks (6 chunks), one column per
    /// update, then back over the start, changing and removing blocks there.
    fn updates() -> Vec<MeshDelta> {
        let mut out = Vec::new();
        for x in 0..24 {
            let column = (0..4).map(|y| block(BlockIndex::new(x, y, 0), 1)).collect();
            out.push(delta(x as u64 + 1, column, vec![]));
        }
        out.push(delta(
            25,
            vec![
                block(BlockIndex::new(0, 1, 0), 9),
                block(BlockIndex::new(1, 1, 0), 9),
            ],
            vec![BlockIndex::new(0, 0, 0)],
        ));
        out
    }

    #[test]
    fn spilled_mesh_chunks_change_where_the_mesh_lives_never_the_mesh() {
        let dir = std::env::temp_dir().join(format!("relfusion-mesh-state-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let spill = Spill::default();
        spill
            .attach(Arc::new(
                relfusion_slam::spill::FolderStore::new(&dir).expect("dir"),
            ))
            .expect("attach");
        let mut bounded = MeshState::default();
        bounded.bound(spill.clone(), 20);
        let mut kept = MeshState::default();
        let mut most_resident = 0;
        for d in updates() {
            bounded.apply(&d);
            kept.apply(&d);
            most_resident = most_resident.max(bounded.block_counts().0);
        }
        let (resident, spilled) = bounded.block_counts();
        assert!(spilled > 0, "chunks went to the store");
        // The bound, overshot by at most the chunk the latest update touched.
        assert!(most_resident <= 20 + 16, "{most_resident} blocks held");
        assert_eq!(resident + spilled, kept.block_counts().0);
        assert_eq!(bounded.triangles(), kept.triangles());
        // The revisit brought the first chunk back and changed it.
        let all = |m: &MeshState| {
            let mut out = Vec::new();
            m.snapshot()
                .surface()
                .runs(&mut |blocks| {
                    out.extend(blocks.iter().map(|b| (*b).clone()));
                    Ok(())
                })
                .expect("read back");
            out
        };
        assert_eq!(all(&bounded), all(&kept));
        let whole = Mesh::from_blocks(kept.blocks.values());
        let snapshot = bounded.snapshot();
        let streamed = mesh_ply_bytes_from(&mut snapshot.surface()).expect("ply");
        assert!(streamed == mesh_ply_bytes(&whole), "the same PLY bytes");
        let glb =
            relfusion_slam::export::mesh_glb_bytes_from(&mut snapshot.surface()).expect("glb");
        assert!(glb == mesh_glb_bytes(&whole), "the same GLB bytes");
        let files = || std::fs::read_dir(&dir).map_or(0, |d| d.count());
        assert_eq!(
            files(),
            bounded.spilled.len(),
            "one object per spilled chunk"
        );
        drop(bounded);
        assert!(files() > 0, "a snapshot keeps what it reads");
        drop(snapshot);
        assert_eq!(files(), 0, "a dropped mesh leaves nothing in the store");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn without_a_bound_or_a_store_everything_stays() {
        let mut unbounded = MeshState::default();
        let mut no_store = MeshState::default();
        no_store.bound(Spill::default(), 4);
        for d in updates() {
            unbounded.apply(&d);
            no_store.apply(&d);
        }
        assert_eq!(unbounded.block_counts(), (95, 0));
        assert_eq!(no_store.block_counts(), (95, 0));
    }
}
