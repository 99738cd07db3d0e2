//! Tests of `fuser`.

use std::collections::BTreeMap;

use nalgebra::Vector3;

use super::*;
use crate::dense::DenseCompute;
use crate::eval::mesh::{score_surface, transform_vertices};
use crate::geometry::{PinholeCamera, SO3};
use crate::image::ImageF32;

/// A 96×72 view of a tilted wall with a spherical bump, in the keyframe's units.
fn wall_input(id: KeyframeId, config: &FusionConfig) -> FusionInput {
    let camera = PinholeCamera::new(70.0, 70.0, 47.5, 35.5, 96, 72).expect("camera");
    let (w, h) = (96, 72);
    let mut depth = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let ray = Vector3::new((x as f64 - 47.5) / 70.0, (y as f64 - 35.5) / 70.0, 1.0);
            // Plane z = 2 + 0.3·x (camera frame), plus a bump in the middle.
            let t = 2.0 / (ray.z - 0.3 * ray.x);
            let p = ray * t;
            let bump = 0.15 * (-(p.x * p.x + p.y * p.y) / 0.05).exp();
            *depth.at_mut(x, y) = (t * (1.0 - bump / p.z)) as f32;
        }
    }
    let colors: Vec<[u8; 3]> = (0..w * h).map(|i| [(i % 256) as u8, 90, 200]).collect();
    FusionInput::from_depth(id, id as f64, camera, &depth, Some(&colors), config).expect("input")
}

fn pose(yaw: f64, x: f64, scale: f64) -> Sim3 {
    Sim3::new(
        SO3::exp(&Vector3::new(0.0, yaw, 0.02)),
        Vector3::new(x, 0.05, -0.1),
        scale,
    )
}

fn config(compute: DenseCompute) -> FusionConfig {
    FusionConfig {
        compute,
        voxels_per_median_depth: 64.0,
        ..FusionConfig::default()
    }
}

/// Both meshes have every vertex within `tol` of the other's (same surface).
fn assert_same_surface(a: &Mesh, b: &Mesh, tol: f64) {
    let va = transform_vertices(a, &Sim3::identity());
    let vb = transform_vertices(b, &Sim3::identity());
    let s = score_surface(&va, &vb, tol);
    assert!(
        s.accuracy > 0.999 && s.completeness > 0.999,
        "{} vs {} vertices: {s:?}",
        va.len(),
        vb.len()
    );
}

#[test]
fn a_moved_keyframe_ends_up_as_if_fused_at_its_new_pose() {
    let config = config(DenseCompute::Cpu);
    let (p0, p1, p1_moved) = (
        pose(0.0, 0.0, 1.0),
        pose(0.2, 0.3, 1.0),
        pose(0.25, 0.4, 1.3),
    );
    let mut moved = Fuser::new(config.clone(), None).expect("fuser");
    moved
        .add_keyframe(wall_input(0, &config), p0)
        .expect("kf 0");
    moved
        .add_keyframe(wall_input(1, &config), p1)
        .expect("kf 1");
    let before = moved.mesh().expect("mesh");
    assert_eq!(
        moved.update_poses(&[(0, p0), (1, p1_moved)]).expect("move"),
        1
    );
    let after = moved.mesh().expect("mesh");

    let mut direct = Fuser::new(config.clone(), None).expect("fuser");
    direct
        .add_keyframe(wall_input(0, &config), p0)
        .expect("kf 0");
    direct
        .add_keyframe(wall_input(1, &config), p1_moved)
        .expect("kf 1");
    let expected = direct.mesh().expect("mesh");
    let voxel = f64::from(moved.voxel_size().expect("voxel"));
    assert_same_surface(&after, &expected, 1e-3 * voxel);
    assert_eq!(
        moved.stats().blocks,
        direct.stats().blocks,
        "emptied blocks are freed"
    );
    // And the move did change the surface.
    let s = score_surface(
        &transform_vertices(&before, &Sim3::identity()),
        &transform_vertices(&after, &Sim3::identity()),
        voxel,
    );
    assert!(s.accuracy < 0.9, "{s:?}");
}

#[test]
fn applying_every_delta_rebuilds_the_mesh() {
    let config = config(DenseCompute::Cpu);
    let mut fuser = Fuser::new(config.clone(), None).expect("fuser");
    let mut patched: BTreeMap<BlockIndex, BlockMesh> = BTreeMap::new();
    let mut revision = 0;
    let mut apply = |delta: MeshDelta| {
        assert_eq!(delta.revision, revision + 1);
        revision = delta.revision;
        for b in &delta.removed {
            assert!(
                patched.remove(b).is_some(),
                "removed block {b:?} was not there"
            );
        }
        for m in delta.changed {
            assert!(!m.is_empty());
            patched.insert(m.index, m);
        }
    };
    for (id, p) in [(0, pose(0.0, 0.0, 1.0)), (1, pose(0.3, 0.5, 1.1))] {
        fuser.add_keyframe(wall_input(id, &config), p).expect("add");
        apply(fuser.take_delta().expect("delta").expect("changed"));
    }
    assert!(
        fuser.take_delta().expect("delta").is_none(),
        "nothing changed since"
    );
    fuser
        .update_poses(&[(1, pose(0.6, 1.5, 1.1))])
        .expect("move");
    let delta = fuser.take_delta().expect("delta").expect("changed");
    assert!(
        !delta.removed.is_empty(),
        "moving a keyframe away empties blocks"
    );
    apply(delta);
    let current: BTreeMap<BlockIndex, BlockMesh> =
        fuser.block_meshes().map(|m| (m.index, m.clone())).collect();
    assert_eq!(patched, current);
    assert_eq!(fuser.stats().mesh_revision, revision);
}

#[test]
fn inputs_past_the_memory_budget_stay_where_they_were_fused() {
    let one = wall_input(0, &FusionConfig::default()).bytes() as f64;
    let config = FusionConfig {
        keyframe_memory_mb: 1.5 * one / (1024.0 * 1024.0),
        ..config(DenseCompute::Cpu)
    };
    let mut fuser = Fuser::new(config.clone(), None).expect("fuser");
    for id in 0..3 {
        fuser
            .add_keyframe(wall_input(id, &config), pose(0.1 * id as f64, 0.0, 1.0))
            .expect("add");
    }
    assert_eq!(
        fuser.stats().inputs_dropped,
        2,
        "only the newest input fits"
    );
    let moved: Vec<_> = (0..3)
        .map(|id| (id, pose(0.1 * id as f64, 1.0, 1.0)))
        .collect();
    assert_eq!(fuser.update_poses(&moved).expect("move"), 1);
    assert_eq!(fuser.stats().reintegrations, 1);
}

#[test]
fn inputs_past_the_budget_spill_and_still_move() {
    let one = wall_input(0, &FusionConfig::default()).bytes() as f64;
    let tight = FusionConfig {
        keyframe_memory_mb: 1.5 * one / (1024.0 * 1024.0),
        ..config(DenseCompute::Cpu)
    };
    let dir = std::env::temp_dir().join(format!("relfusion-fuser-spill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let spill = Spill::default();
    spill
        .attach(Arc::new(crate::spill::FolderStore::new(&dir).expect("dir")))
        .expect("attach");
    let mut spilled = Fuser::new(tight.clone(), None)
        .expect("fuser")
        .with_spill(spill.clone());
    let mut held = Fuser::new(config(DenseCompute::Cpu), None).expect("fuser");
    for fuser in [&mut spilled, &mut held] {
        for id in 0..3 {
            fuser
                .add_keyframe(wall_input(id, &tight), pose(0.1 * id as f64, 0.0, 1.0))
                .expect("add");
        }
    }
    let s = spilled.stats();
    assert_eq!((s.inputs_spilled, s.inputs_dropped), (2, 0));
    assert_eq!(spill.figures().spilled, 2);
    let moved: Vec<_> = (0..3)
        .map(|id| (id, pose(0.1 * id as f64, 1.0, 1.0)))
        .collect();
    assert_eq!(spilled.update_poses(&moved).expect("move"), 3);
    assert_eq!(held.update_poses(&moved).expect("move"), 3);
    assert_eq!(
        spill.figures().loads,
        2,
        "the spilled inputs were read back"
    );
    let (a, b) = (spilled.mesh().expect("mesh"), held.mesh().expect("mesh"));
    assert_eq!(
        a.positions, b.positions,
        "spilling changes where inputs live, not the mesh"
    );
    // Removing a keyframe whose input is spilled takes it out of the volume too.
    spilled.remove_keyframe(0).expect("remove");
    held.remove_keyframe(0).expect("remove");
    assert_eq!(
        spilled.mesh().expect("mesh").positions,
        held.mesh().expect("mesh").positions
    );
    let files = || std::fs::read_dir(&dir).expect("dir").count();
    assert_eq!(files(), 1, "keyframe 0's input left the store with it");
    drop(spilled);
    assert_eq!(files(), 0, "a finished fusion empties its spill");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn small_moves_are_not_reintegrated_and_scale_changes_are() {
    let config = config(DenseCompute::Cpu);
    let mut fuser = Fuser::new(config.clone(), None).expect("fuser");
    fuser
        .add_keyframe(wall_input(0, &config), pose(0.0, 0.0, 1.0))
        .expect("add");
    let voxel = f64::from(fuser.voxel_size().expect("voxel"));
    assert_eq!(
        fuser
            .update_poses(&[(0, pose(0.0, 0.2 * voxel, 1.0))])
            .expect("tiny"),
        0
    );
    assert_eq!(
        fuser
            .update_poses(&[(0, pose(0.0, 0.0, 1.05))])
            .expect("scale"),
        1
    );
}

#[test]
fn gpu_and_cpu_fusion_make_the_same_mesh() {
    let Ok(ctx) = crate::gpu::shared_context() else {
        eprintln!("SKIP: no GPU adapter (not even lavapipe)");
        return;
    };
    let mut meshes = Vec::new();
    for compute in [DenseCompute::Gpu, DenseCompute::Cpu] {
        let config = config(compute);
        let mut fuser = Fuser::new(config.clone(), Some(ctx.clone())).expect("fuser");
        assert_eq!(
            fuser.stats().compute,
            if compute == DenseCompute::Gpu {
                "gpu"
            } else {
                "cpu"
            }
        );
        fuser
            .add_keyframe(wall_input(0, &config), pose(0.0, 0.0, 1.0))
            .expect("kf 0");
        fuser
            .add_keyframe(wall_input(1, &config), pose(0.2, 0.3, 1.0))
            .expect("kf 1");
        fuser
            .update_poses(&[(1, pose(0.25, 0.4, 1.2))])
            .expect("move");
        meshes.push((
            fuser.mesh().expect("mesh"),
            fuser.voxel_size().expect("voxel"),
        ));
    }
    let tol = 1e-3 * f64::from(meshes[0].1);
    assert!(meshes[0].0.triangle_count() > 1000);
    assert_same_surface(&meshes[0].0, &meshes[1].0, tol);
}

/// Issue 37, item 3: with a store attached and `resident_blocks` 1, every chunk of blocks but
/// those the newest keyframe touched leaves the pool after each step, and comes back for a
/// revisit, a moved keyframe, a removed one and for meshing its neighbours. The deltas and the
/// mesh are those of a pool that keeps everything, to the bit, on the CPU and on the GPU.
#[test]
fn spilled_chunks_change_where_the_volume_lives_never_the_mesh() {
    let ctx = crate::gpu::shared_context().ok();
    for compute in [DenseCompute::Cpu, DenseCompute::Gpu] {
        if compute == DenseCompute::Gpu && ctx.is_none() {
            eprintln!("SKIP: no GPU adapter (not even lavapipe)");
            continue;
        }
        let dir = std::env::temp_dir().join(format!(
            "relfusion-chunk-spill-{}-{compute:?}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        let spill = Spill::default();
        spill
            .attach(Arc::new(crate::spill::FolderStore::new(&dir).expect("dir")))
            .expect("attach");
        let forced = FusionConfig {
            resident_blocks: 1,
            ..config(compute)
        };
        let mut spilled = Fuser::new(forced, ctx.clone())
            .expect("fuser")
            .with_spill(spill.clone());
        let mut kept = Fuser::new(config(compute), ctx.clone()).expect("fuser");
        let run = |fuser: &mut Fuser| {
            let cfg = config(compute);
            let mut deltas = Vec::new();
            // Three places two walls apart, then back to the first (a revisit).
            for (id, x) in [(0, 0.0), (1, 3.0), (2, 6.0), (3, 0.2)] {
                fuser
                    .add_keyframe(wall_input(id, &cfg), pose(0.05 * id as f64, x, 1.0))
                    .expect("add");
                deltas.push(fuser.take_delta().expect("delta"));
            }
            // A loop closure moves the first two; the third is taken out again.
            fuser
                .update_poses(&[(0, pose(0.02, 0.3, 1.1)), (1, pose(0.1, 3.2, 0.9))])
                .expect("move");
            deltas.push(fuser.take_delta().expect("delta"));
            fuser.remove_keyframe(2).expect("remove");
            deltas.push(fuser.take_delta().expect("delta"));
            (deltas, fuser.mesh().expect("mesh"))
        };
        let (spilled_deltas, a) = run(&mut spilled);
        let (kept_deltas, b) = run(&mut kept);
        assert!(a.triangle_count() > 1000);
        assert_eq!(spilled_deltas, kept_deltas, "{compute:?}");
        assert_eq!(
            (&a.positions, &a.colors, &a.indices),
            (&b.positions, &b.colors, &b.indices),
            "{compute:?}"
        );
        // The exports written a slab at a time from the store are the in-memory mesh's bytes.
        let out = dir.with_extension("export");
        std::fs::create_dir_all(&out).expect("export dir");
        let ply = out.join("mesh.ply");
        let glb = out.join("mesh.glb");
        {
            let mut surface = spilled.surface().expect("surface");
            let counts = crate::export::write_mesh_ply_from(&ply, &mut surface).expect("ply");
            crate::export::write_mesh_glb_from(&glb, &mut surface).expect("glb");
            assert_eq!(counts.triangles as usize, a.triangle_count());
        }
        let read = |p: &std::path::Path| std::fs::read(p).expect("read");
        assert!(read(&ply) == crate::export::mesh_ply_bytes(&a), "PLY");
        assert!(read(&glb) == crate::export::mesh_glb_bytes(&a), "GLB");
        std::fs::remove_dir_all(&out).ok();
        let s = spilled.stats();
        println!("{compute:?}: {s:?}");
        assert!(s.chunks_spilled > 0 && s.blocks_spilled > 0, "{s:?}");
        assert!(
            s.chunk_loads > 0,
            "the revisit and the moves load chunks: {s:?}"
        );
        assert!(s.blocks < kept.stats().blocks, "{s:?}");
        assert_eq!((s.blocks_refused, kept.stats().blocks_spilled), (0, 0));
        assert_eq!(s.triangles, kept.stats().triangles, "spilled meshes count");
        let files = || std::fs::read_dir(&dir).expect("dir").count();
        assert_eq!(files(), s.chunks_spilled, "one object per spilled chunk");
        drop(spilled);
        assert_eq!(files(), 0, "a finished fusion empties its spill");
        std::fs::remove_dir_all(&dir).ok();
    }
}
