//! Tests of `gpu_volume`.

use super::super::integrate::tests::{camera, random_maps, random_pose};
use super::super::integrate::{integrate_cpu, touched_blocks};
use super::*;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use std::time::Instant;

fn context() -> Arc<GpuContext> {
    crate::gpu::shared_context().unwrap_or_else(|e| panic!("no GPU context: {e}"))
}

/// Voxels whose update GPU and CPU may legitimately decide differently: the projection
/// within 1e-4 px of a pixel boundary, or the signed distance within 1e-5 of −truncation
/// (a rounding difference flips the test). Marks each pool entry of `blocks` that is so.
fn mark_ambiguous(
    view: &DepthView,
    p: &IntegrateParams,
    blocks: &[(BlockIndex, u32)],
    out: &mut [bool],
) {
    let m = &view.camera_from_world;
    let near_half = |c: f32| ((c + 0.5) - (c + 0.5).round()).abs() < 1e-4;
    for &(b, slot) in blocks {
        for i in 0..BLOCK_VOXELS {
            let v = b.voxel([i as i32 & 7, (i as i32 >> 3) & 7, i as i32 >> 6]);
            let pw = v.map(|c| c as f32 * p.voxel_size);
            let row = |r: &[f32; 4]| ((r[0] * pw[0] + r[1] * pw[1]) + r[2] * pw[2]) + r[3];
            let (x, y, z) = (row(&m[0]), row(&m[1]), row(&m[2]));
            if z.is_nan() || z <= 0.0 {
                continue;
            }
            let u = view.fx * (x / z) + view.cx;
            let vv = view.fy * (y / z) + view.cy;
            let (ur, vr) = ((u + 0.5).floor(), (vv + 0.5).floor());
            let mut ambiguous = near_half(u) || near_half(vv);
            if ur >= 0.0 && vr >= 0.0 && ur < view.width as f32 && vr < view.height as f32 {
                let d = view.depth[vr as usize * view.width as usize + ur as usize];
                let sdf = (d - z) * view.scale;
                ambiguous |= d > 0.0 && (sdf + p.truncation).abs() < 1e-5 * p.truncation.max(1.0);
            }
            out[slot as usize * BLOCK_VOXELS + i] |= ambiguous;
        }
    }
}

/// Compares every pool entry not marked ambiguous: tsdf and weight within 1e-5 (relative
/// to max(1, |value|)), colour channels within 1. Returns the number compared.
fn assert_pools_match(cpu: &CpuVoxels, gpu: &CpuVoxels, skip: &[bool], what: &str) -> usize {
    assert_eq!(cpu.tsdf.len(), gpu.tsdf.len(), "{what}: pool sizes");
    let close = |a: f32, b: f32| (a - b).abs() <= 1e-5 * a.abs().max(1.0);
    let mut compared = 0;
    for k in (0..cpu.tsdf.len()).filter(|&k| !skip[k]) {
        compared += 1;
        assert!(
            close(cpu.weight[k], gpu.weight[k]) && close(cpu.tsdf[k], gpu.tsdf[k]),
            "{what}: entry {k}: cpu (t {}, w {}) gpu (t {}, w {})",
            cpu.tsdf[k],
            cpu.weight[k],
            gpu.tsdf[k],
            gpu.weight[k]
        );
        let (a, b) = (
            super::super::block::unpack_rgb(cpu.color[k]),
            super::super::block::unpack_rgb(gpu.color[k]),
        );
        assert!(
            (0..3).all(|c| a[c].abs_diff(b[c]) <= 1),
            "{what}: entry {k}: colour {a:?} vs {b:?}"
        );
    }
    compared
}

#[test]
fn gpu_integration_matches_cpu_on_random_inputs() {
    let ctx = context();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(29);
    for (round, &(w, h)) in [(64u32, 48u32), (37, 23), (64, 48)].iter().enumerate() {
        let cam = camera(w, h);
        let n = (w * h) as usize;
        let pose_a = random_pose(&mut rng);
        let pose_b = random_pose(&mut rng);
        let (da, wa, ca) = random_maps(n, 0.5..3.0, 0.2, &mut rng);
        let (db, wb, cb) = random_maps(n, 0.5..3.0, 0.2, &mut rng);
        let view_a = DepthView::new(&cam, &pose_a, &da, &wa, &ca).expect("view a");
        let view_b = DepthView::new(&cam, &pose_b, &db, &wb, &cb).expect("view b");
        let voxel_size = 0.04 * pose_a.scale as f32;
        let p = IntegrateParams {
            voxel_size,
            truncation: 4.0 * voxel_size,
            max_weight: if round == 1 { 1.5 } else { 128.0 },
        };
        let mut blocks = touched_blocks(&view_a, &p);
        blocks.extend(touched_blocks(&view_b, &p));
        // Blocks no view reaches, and far ones behind or beside the cameras.
        for _ in 0..50 {
            blocks.push(BlockIndex::new(
                rng.random_range(-300..300),
                rng.random_range(-300..300),
                rng.random_range(-300..300),
            ));
        }
        blocks.sort_unstable();
        blocks.dedup();
        // Random distinct slots in a pool with unused slots.
        let capacity = blocks.len() as u32 + 37;
        let mut slots: Vec<u32> = (0..capacity).collect();
        slots.shuffle(&mut rng);
        let listed: Vec<(BlockIndex, u32)> =
            blocks.iter().copied().zip(slots.iter().copied()).collect();

        let mut cpu = CpuVoxels::default();
        cpu.ensure_capacity(capacity);
        let mut gpu = GpuVoxels::new(Arc::clone(&ctx), capacity).expect("gpu pool");
        let mut skip = vec![false; capacity as usize * BLOCK_VOXELS];
        mark_ambiguous(&view_a, &p, &listed, &mut skip);
        mark_ambiguous(&view_b, &p, &listed, &mut skip);
        for (view, sign) in [(&view_a, 1.0), (&view_b, 1.0), (&view_a, -1.0)] {
            integrate_cpu(&mut cpu, &listed, view, &p, sign);
            gpu.integrate(&listed, view, &p, sign)
                .expect("gpu integrate");
        }
        let downloaded = gpu.download().expect("download");
        let compared = assert_pools_match(&cpu, &downloaded, &skip, &format!("round {round}"));
        let observed = cpu.weight.iter().filter(|&&w| w > 0.0).count();
        assert!(
            observed > 1000,
            "round {round}: only {observed} voxels observed"
        );
        eprintln!(
            "round {round}: {} blocks, {observed} observed voxels, {compared} compared, {} \
             skipped as boundary cases",
            listed.len(),
            skip.len() - compared
        );
        // Max weights agree too (the caller frees blocks whose weight fell to 0).
        let some: Vec<u32> = slots.iter().take(100).copied().collect();
        let (mg, mc) = (
            gpu.max_weights(&some).expect("max weights"),
            cpu.max_weights(&some),
        );
        for (g, c) in mg.iter().zip(&mc) {
            assert!((g - c).abs() <= 1e-5 * c.max(1.0), "max weight {g} vs {c}");
        }
    }
}

/// More blocks than 65535 workgroups of 64 reach (8191 blocks): the 2-D dispatch, with the
/// only surface-holding blocks at the end of the list.
#[test]
fn gpu_integration_uses_a_2d_dispatch_for_long_block_lists() {
    let ctx = context();
    let max = ctx.limits().max_compute_workgroups_per_dimension;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
    let cam = camera(32, 24);
    let pose = random_pose(&mut rng);
    let (d, w, c) = random_maps(32 * 24, 1.0..1.5, 0.1, &mut rng);
    let view = DepthView::new(&cam, &pose, &d, &w, &c).expect("view");
    let voxel_size = 0.05 * pose.scale as f32;
    let p = IntegrateParams {
        voxel_size,
        truncation: 3.0 * voxel_size,
        max_weight: 128.0,
    };
    let touched = touched_blocks(&view, &p);
    let filler = (u64::from(max) * u64::from(WORKGROUP) / BLOCK_VOXELS as u64) as usize + 10;
    // Filler blocks far away (never seen), then the touched ones.
    let mut listed: Vec<(BlockIndex, u32)> = (0..filler)
        .map(|k| (BlockIndex::new(1000 + k as i32, -1000, 1000), k as u32))
        .collect();
    listed.extend(
        touched
            .iter()
            .enumerate()
            .map(|(k, b)| (*b, (filler + k) as u32)),
    );
    let capacity = listed.len() as u32;
    assert!(dispatch_size(capacity as u64 * 8, max).expect("fits").1 > 1);
    let mut cpu = CpuVoxels::default();
    cpu.ensure_capacity(capacity);
    let mut gpu = GpuVoxels::new(Arc::clone(&ctx), capacity).expect("gpu pool");
    integrate_cpu(&mut cpu, &listed, &view, &p, 1.0);
    gpu.integrate(&listed, &view, &p, 1.0)
        .expect("gpu integrate");
    let mut skip = vec![false; capacity as usize * BLOCK_VOXELS];
    mark_ambiguous(&view, &p, &listed[filler..], &mut skip);
    let got = gpu.download().expect("download");
    assert_pools_match(&cpu, &got, &skip, "2-D dispatch");
    let tail = filler * BLOCK_VOXELS..;
    assert!(
        got.weight[tail].iter().any(|&w| w > 0.0),
        "the tail blocks were integrated"
    );
}

#[test]
fn gpu_pool_growth_preserves_contents_and_resets_clear_slots() {
    let ctx = context();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    let cam = camera(24, 18);
    let pose = random_pose(&mut rng);
    let (d, w, c) = random_maps(24 * 18, 1.0..1.5, 0.0, &mut rng);
    let view = DepthView::new(&cam, &pose, &d, &w, &c).expect("view");
    let voxel_size = 0.1 * pose.scale as f32;
    let p = IntegrateParams {
        voxel_size,
        truncation: 2.0 * voxel_size,
        max_weight: 128.0,
    };
    let touched = touched_blocks(&view, &p);
    let listed: Vec<(BlockIndex, u32)> = touched
        .iter()
        .enumerate()
        .map(|(k, b)| (*b, k as u32))
        .collect();
    let n = listed.len() as u32;
    let mut gpu = GpuVoxels::new(Arc::clone(&ctx), n).expect("gpu pool");
    assert_eq!(gpu.buffers().capacity, n);
    gpu.integrate(&listed, &view, &p, 1.0).expect("integrate");
    let before = gpu.download().expect("download");
    assert!(before.weight.iter().any(|&w| w > 0.0));

    gpu.ensure_capacity(n + 1).expect("grow");
    assert_eq!(gpu.buffers().capacity, 2 * n, "grows by doubling");
    assert!(gpu.bytes() >= 3 * u64::from(2 * n) * SLOT_BYTES);
    let after = gpu.download().expect("download");
    let old = before.tsdf.len();
    assert_eq!(after.tsdf[..old], before.tsdf[..]);
    assert_eq!(after.weight[..old], before.weight[..]);
    assert_eq!(after.color[..old], before.color[..]);
    assert!(after.weight[old..].iter().all(|&w| w == 0.0));
    assert!(after.tsdf[old..].iter().all(|&t| t == 0.0));
    assert!(after.color[old..].iter().all(|&c| c == 0));
    gpu.ensure_capacity(3).expect("no-op");
    assert_eq!(gpu.buffers().capacity, 2 * n);

    // Resets: a run of consecutive slots, a lone one, a duplicate, out of order.
    let resets = [3, 1, 2, n - 1, 2];
    gpu.reset_slots(&resets).expect("reset");
    let mut cpu = after.clone();
    cpu.reset_slots(&resets);
    assert_eq!(gpu.download().expect("download"), cpu);
    let all: Vec<u32> = (0..2 * n).collect();
    assert_eq!(gpu.max_weights(&all).expect("max"), cpu.max_weights(&all));

    // Beyond the capacity or the device: errors, not panics.
    assert!(matches!(gpu.reset_slots(&[2 * n]), Err(Error::Shape(_))));
    assert!(matches!(gpu.max_weights(&[2 * n]), Err(Error::Shape(_))));
    let bad = [(BlockIndex::new(0, 0, 0), 2 * n)];
    assert!(matches!(
        gpu.integrate(&bad, &view, &p, 1.0),
        Err(Error::Shape(_))
    ));
    assert!(matches!(gpu.ensure_capacity(u32::MAX), Err(Error::Gpu(_))));
    assert_eq!(gpu.buffers().capacity, 2 * n);
}

#[test]
fn dispatch_and_runs_helpers() {
    assert_eq!(dispatch_size(10, 65535), Some((10, 1)));
    assert_eq!(dispatch_size(65536, 65535), Some((65535, 2)));
    assert_eq!(dispatch_size(0, 65535), Some((0, 1)));
    assert_eq!(dispatch_size(65535u64 * 65535 + 1, 65535), None);
    assert_eq!(runs(&[1, 2, 3, 7, 9, 10]), vec![(1, 3), (7, 1), (9, 2)]);
    assert!(runs(&[]).is_empty());
}

/// One 320×240 view of a tilted plane, GPU against CPU (prints the times; dev profile).
#[test]
fn gpu_integration_of_a_working_resolution_view() {
    let ctx = context();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let (w, h) = (320u32, 240u32);
    let cam = camera(w, h);
    let pose = random_pose(&mut rng);
    let n = (w * h) as usize;
    let (mut d, wt, c) = random_maps(n, 1.0..2.0, 0.05, &mut rng);
    for (i, x) in d.iter_mut().enumerate() {
        if *x > 0.0 {
            *x = 1.5 + 0.002 * ((i % w as usize) as f32 - 160.0);
        }
    }
    let view = DepthView::new(&cam, &pose, &d, &wt, &c).expect("view");
    // 128 voxels across the median depth, truncation 4 voxels (the defaults).
    let voxel_size = 1.5 * pose.scale as f32 / 128.0;
    let p = IntegrateParams {
        voxel_size,
        truncation: 4.0 * voxel_size,
        max_weight: 128.0,
    };
    let start = Instant::now();
    let touched = touched_blocks(&view, &p);
    let t_touched = start.elapsed();
    let listed: Vec<(BlockIndex, u32)> = touched
        .iter()
        .enumerate()
        .map(|(k, b)| (*b, k as u32))
        .collect();
    let cap = listed.len() as u32;
    let mut cpu = CpuVoxels::default();
    cpu.ensure_capacity(cap);
    let start = Instant::now();
    integrate_cpu(&mut cpu, &listed, &view, &p, 1.0);
    let t_cpu = start.elapsed();
    let mut gpu = GpuVoxels::new(Arc::clone(&ctx), cap).expect("gpu pool");
    // Warm-up (first dispatch allocates the input buffers and compiles on some drivers).
    gpu.integrate(&listed, &view, &p, 1.0)
        .expect("gpu integrate");
    ctx.wait().expect("wait");
    gpu.reset_slots(&(0..cap).collect::<Vec<_>>())
        .expect("reset");
    ctx.wait().expect("wait");
    let start = Instant::now();
    gpu.integrate(&listed, &view, &p, 1.0)
        .expect("gpu integrate");
    ctx.wait().expect("wait");
    let t_gpu = start.elapsed();
    let mut skip = vec![false; cap as usize * BLOCK_VOXELS];
    mark_ambiguous(&view, &p, &listed, &mut skip);
    assert_pools_match(&cpu, &gpu.download().expect("download"), &skip, "320x240");
    eprintln!(
        "320x240 view, {} blocks ({} voxels) on {}: touched_blocks {:.1} ms, CPU integrate \
         {:.1} ms, GPU integrate (upload + kernel) {:.1} ms",
        listed.len(),
        listed.len() * BLOCK_VOXELS,
        ctx.adapter_info().name,
        t_touched.as_secs_f64() * 1e3,
        t_cpu.as_secs_f64() * 1e3,
        t_gpu.as_secs_f64() * 1e3
    );
}

/// The slot copies a spilled chunk leaves and comes back through (`fusion::chunks`): random
/// voxels written into random slots of the GPU pool and of the CPU pool read back the same,
/// in any slot order, with runs of consecutive slots copied at once.
#[test]
fn gpu_slot_copies_match_cpu_on_random_slots() {
    let ctx = context();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(37);
    let capacity = 40u32;
    let mut gpu = GpuVoxels::new(ctx, capacity).expect("pool");
    let mut cpu = CpuVoxels::default();
    cpu.ensure_capacity(capacity);
    let mut slots: Vec<u32> = (0..capacity).collect();
    slots.shuffle(&mut rng);
    // 24 random slots, then a run of consecutive ones.
    slots.retain(|s| !(30..33).contains(s));
    slots.truncate(24);
    slots.extend(30..33);
    let n = slots.len() * BLOCK_VOXELS;
    let data = CpuVoxels {
        tsdf: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
        weight: (0..n).map(|_| rng.random_range(0.0..128.0)).collect(),
        color: (0..n).map(|_| rng.random::<u32>() & 0xff_ffff).collect(),
    };
    gpu.write_slots(&slots, &data).expect("write");
    cpu.write_slots(&slots, &data);
    let mut order = slots.clone();
    order.shuffle(&mut rng);
    let (g, c) = (
        gpu.read_slots(&order).expect("read"),
        cpu.read_slots(&order),
    );
    assert_eq!(g, c);
    assert_eq!(gpu.read_slots(&slots).expect("read"), data, "bit-identical");
    assert_eq!(gpu.download().expect("download"), cpu);
    assert!(
        gpu.write_slots(&slots[..2], &data).is_err(),
        "size mismatch"
    );
    assert!(gpu.read_slots(&[capacity]).is_err(), "slot beyond the pool");
}
