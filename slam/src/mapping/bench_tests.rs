//! Timing of the per-frame mapping path on real data (observe → regularize → publish →
//! tracking reference), with a fingerprint of every intermediate result so that speed-ups can
//! be checked to leave the output bit-identical. Ignored by default (it measures, it does not
//! assert); run with
//! `cargo test -p relfusion-slam mapping_bench -- --ignored --nocapture`.

use std::sync::Arc;
use std::time::Instant;

use super::{DepthFilter, DepthMap, InverseDepth, MappingConfig};
use crate::frame::Frame;
use crate::tracking::TrackingReference;

/// FNV-1a over 32-bit words.
fn fnv(hash: &mut u64, word: u32) {
    for b in word.to_le_bytes() {
        *hash ^= u64::from(b);
        *hash = hash.wrapping_mul(0x100_0000_01b3);
    }
}

fn fingerprint_map(hash: &mut u64, map: &DepthMap) {
    for p in &map.pixels {
        match *p {
            InverseDepth::Unknown => fnv(hash, 1),
            InverseDepth::Discarded => fnv(hash, 2),
            InverseDepth::Estimate { idepth, var } => {
                fnv(hash, idepth.to_bits());
                fnv(hash, var.to_bits());
            }
        }
    }
}

fn fingerprint_reference(hash: &mut u64, r: &TrackingReference) {
    for l in 0..crate::frame::PYRAMID_LEVELS {
        let level = r.level(l);
        for i in 0..level.len() {
            for v in [
                level.x[i],
                level.y[i],
                level.z[i],
                level.intensity[i],
                level.idepth_var[i],
            ] {
                fnv(hash, v.to_bits());
            }
            fnv(hash, level.pixel[i]);
        }
    }
}

/// CPU time of the calling thread (Linux `schedstat`, ns → s); with one worker thread all of
/// the filter's work runs here, so this is immune to other processes' load.
fn thread_cpu_s() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .map_or(0.0, |ns| ns * 1e-9)
}

fn mean_ms(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64 * 1e3
}

#[test]
#[ignore = "benchmark: run explicitly with --ignored --nocapture"]
fn mapping_bench_per_frame_path() {
    let Some(seq) = crate::dataset::shared_sequence("7scenes_redkitchen_f0000-0299") else {
        return;
    };
    let n = 41;
    let frames: Vec<Arc<Frame>> = (0..n)
        .map(|i| Arc::new(crate::dataset::shared_frame(&seq, i)))
        .collect();
    let pose = |i: usize| seq.frames[i].world_from_camera.expect("ground truth");
    let threads: usize = std::env::var("RELFUSION_BENCH_THREADS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2);
    let config = MappingConfig {
        threads,
        ..MappingConfig::default()
    };
    let mut f = DepthFilter::new(frames[0].clone(), config).expect("filter");
    f.init_random(5);
    f.regularize();
    // Scene scale ≈ 1/mean inverse depth of the sensor (the random map has mean 1).
    let k = 0.5;
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    let (mut t_obs, mut t_reg, mut t_map, mut t_ref) = (vec![], vec![], vec![], vec![]);
    let mut cpu = [0.0f64; 4];
    let mut reference = TrackingReference::new(&frames[0], &f.depth_map()).expect("reference");
    for (i, frame) in frames.iter().enumerate().take(n - 1).skip(1) {
        let mut rel = pose(0).inverse() * pose(i);
        rel.translation *= k;
        let c0 = thread_cpu_s();
        let t0 = Instant::now();
        let stats = f.observe(frame, &rel).expect("observe");
        let t1 = Instant::now();
        let c1 = thread_cpu_s();
        f.regularize();
        let t2 = Instant::now();
        let c2 = thread_cpu_s();
        let map = f.depth_map();
        let t3 = Instant::now();
        let c3 = thread_cpu_s();
        reference.rebuild(&frames[0], &map).expect("reference");
        let t4 = Instant::now();
        let c4 = thread_cpu_s();
        for (k, (a, b)) in [(c0, c1), (c1, c2), (c2, c3), (c3, c4)]
            .into_iter()
            .enumerate()
        {
            cpu[k] += b - a;
        }
        assert_eq!(
            f.mean_idepth().map(f64::to_bits),
            map.mean_idepth().map(f64::to_bits),
            "DepthFilter::mean_idepth must equal the published map's"
        );
        t_obs.push((t1 - t0).as_secs_f64());
        t_reg.push((t2 - t1).as_secs_f64());
        t_map.push((t3 - t2).as_secs_f64());
        t_ref.push((t4 - t3).as_secs_f64());
        for v in [
            stats.created,
            stats.updated,
            stats.failed,
            stats.removed,
            stats.inconsistent,
            stats.skipped_epl,
            stats.skipped_recent,
        ] {
            fnv(&mut hash, v as u32);
        }
        fingerprint_map(&mut hash, &map);
        fingerprint_reference(&mut hash, &reference);
        let fresh = TrackingReference::new(&frames[0], &map).expect("reference");
        for l in 0..crate::frame::PYRAMID_LEVELS {
            assert_eq!(
                fresh.level(l),
                reference.level(l),
                "rebuild differs at level {l}"
            );
        }
    }
    let mut rel = pose(0).inverse() * pose(n - 1);
    rel.translation *= k;
    let t0 = Instant::now();
    let mut next = f
        .propagate_to(frames[n - 1].clone(), &rel.inverse())
        .expect("propagate");
    let t_prop = t0.elapsed().as_secs_f64();
    next.normalize_scale();
    fingerprint_map(&mut hash, &next.depth_map());
    eprintln!(
        "mapping bench ({threads} threads, {} frames): observe {:.2} ms, regularize {:.2} ms, \
         depth_map {:.2} ms, reference {:.2} ms, propagate {:.2} ms; estimates {}; \
         fingerprint {hash:016x}",
        t_obs.len(),
        mean_ms(&t_obs),
        mean_ms(&t_reg),
        mean_ms(&t_map),
        mean_ms(&t_ref),
        t_prop * 1e3,
        f.num_estimates(),
    );
    let frames_timed = t_obs.len() as f64;
    eprintln!(
        "  main-thread CPU per frame: observe {:.2} ms, regularize {:.2} ms, depth_map {:.2} ms, \
         reference {:.2} ms",
        cpu[0] / frames_timed * 1e3,
        cpu[1] / frames_timed * 1e3,
        cpu[2] / frames_timed * 1e3,
        cpu[3] / frames_timed * 1e3,
    );
}
