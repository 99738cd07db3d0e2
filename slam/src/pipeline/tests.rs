//! Pipeline tests on a synthetic sequence with exact ground truth: they fail when tracking,
//! mapping or the pose graph regress (ATE bound), when the deterministic mode stops being
//! deterministic, or when bad input is not refused cleanly.

use std::sync::OnceLock;

use super::*;
use crate::Error;
use crate::dataset::synth::{Scene, SynthConfig, path_length, render_frame};
use crate::dataset::trajectory::StampedPose;
use crate::eval::{AlignMode, ate};

/// 200 frames (6.7 s) of the default orbit at 320×240: translation and rotation together.
pub(super) fn sequence() -> &'static (PinholeCamera, Vec<FrameInput>, Vec<StampedPose>) {
    static SEQ: OnceLock<(PinholeCamera, Vec<FrameInput>, Vec<StampedPose>)> = OnceLock::new();
    SEQ.get_or_init(|| {
        let config = SynthConfig {
            frames: 200,
            seed: 2,
            width: 320,
            height: 240,
            ..Default::default()
        };
        let camera = config.camera().expect("camera");
        let scene = Scene::generate(config.seed);
        let poses = config.poses();
        let mut frames = Vec::new();
        let mut gt = Vec::new();
        for (i, pose) in poses.iter().enumerate() {
            let timestamp = i as f64 / config.fps;
            let (rgb, depth) = render_frame(&scene, &camera, pose);
            frames.push(FrameInput {
                frame_id: None,
                timestamp,
                rgb,
                depth: Some(depth),
            });
            gt.push(StampedPose {
                timestamp,
                world_from_camera: *pose,
            });
        }
        (camera, frames, gt)
    })
}

pub(super) fn run(config: Config) -> (Pipeline, Vec<Event>) {
    let (camera, frames, _) = sequence();
    let mut pipeline = Pipeline::new(config, *camera, None).expect("pipeline");
    let mut events = Vec::new();
    for frame in frames {
        events.extend(pipeline.push(frame.clone()).expect("push"));
    }
    pipeline.finish().expect("finish");
    (pipeline, events)
}

/// What one run of [`deterministic`] over [`sequence`] gives. Three tests read it and it is
/// deterministic, so it runs once per test binary (a run costs about 24 s of CPU here; issue 36).
struct Baseline {
    trajectory: Vec<(f64, Sim3)>,
    keyframe_trajectory: Vec<(f64, Sim3)>,
    events: Vec<Event>,
    keyframes: usize,
    semidense_points: usize,
}

fn baseline() -> &'static Baseline {
    static BASELINE: OnceLock<Baseline> = OnceLock::new();
    BASELINE.get_or_init(|| {
        let (pipeline, events) = run(deterministic());
        Baseline {
            trajectory: pipeline.trajectory().expect("trajectory"),
            keyframe_trajectory: pipeline.keyframe_trajectory(),
            events,
            keyframes: pipeline.stats().keyframes,
            semidense_points: pipeline.semidense_points().expect("points").len(),
        }
    })
}

fn stamped(poses: &[(f64, Sim3)]) -> Vec<StampedPose> {
    crate::dataset::trajectory::stamped_se3(poses)
}

fn deterministic() -> Config {
    let mut config = Config::default();
    config.pipeline.deterministic = true;
    config.pipeline.init = DepthInit::Random;
    config
}

#[test]
fn pipeline_tracks_every_synthetic_frame_within_the_ate_bound() {
    let (_, frames, gt) = sequence();
    let run = baseline();
    let path = path_length(&gt.iter().map(|p| p.world_from_camera).collect::<Vec<_>>());
    let poses: Vec<&PoseEvent> = run
        .events
        .iter()
        .filter_map(|e| {
            if let Event::Pose(p) = e {
                Some(p)
            } else {
                None
            }
        })
        .collect();
    assert_eq!(poses.len(), frames.len(), "one pose event per frame");
    assert!(
        poses.iter().all(|p| p.state != TrackingState::Lost),
        "no frame may be lost"
    );
    assert!(run.keyframes >= 3, "the orbit needs several keyframes");

    let traj = ate(gt, &stamped(&run.trajectory), AlignMode::Sim3).expect("ate");
    let kfs = ate(gt, &stamped(&run.keyframe_trajectory), AlignMode::Sim3).expect("ate");
    println!(
        "synthetic: path {path:.3} m, {} keyframes, ATE frames {:.4} m, keyframes {:.4} m",
        run.keyframes, traj.rmse, kfs.rmse
    );
    assert_eq!(traj.matched, frames.len());
    // Regression bounds, not the goal: at 320×240 this sequence measures 1.8% (frames) and
    // 1.9% (keyframes) of the path, and 2.6% / 2.9% when the first five keyframes may not be
    // linked (`backend.skip_initial_keyframes` = 5, LSD-SLAM's choice). Issue 3's goal of
    // 0.5% is met at 640×480 on seeds 0 and 1 (0.16%, 0.12%), not on seed 2 (0.65%).
    assert!(
        kfs.rmse <= 0.025 * path,
        "keyframe ATE {} > 2.5% of {path} m",
        kfs.rmse
    );
    assert!(
        traj.rmse <= 0.025 * path,
        "frame ATE {} > 2.5% of {path} m",
        traj.rmse
    );
    assert!(run.semidense_points > 0);
}

/// The paper's Table III baseline "*": refining the pose graph with the sensor depth must
/// reach every keyframe and beat the refinement with the estimated depth.
#[test]
fn ground_truth_depth_refinement_refines_every_keyframe_and_lowers_the_ate() {
    let (_, _, gt) = sequence();
    let keyframe_ate = |keyframes: &[(f64, Sim3)]| {
        ate(gt, &stamped(keyframes), AlignMode::Sim3)
            .expect("ate")
            .rmse
    };
    let estimated = keyframe_ate(&baseline().keyframe_trajectory);
    let mut config = deterministic();
    config.dense.two_view.ground_truth_depth = true;
    let (sensor, _) = run(config);
    let sensor_ate = keyframe_ate(&sensor.keyframe_trajectory());
    let stats = sensor.stats();
    println!(
        "synthetic keyframe ATE: estimated-depth refinement {estimated:.4} m, sensor-depth \
         {sensor_ate:.4} m ({} of {} keyframes refined)",
        stats.depth_refinements, stats.keyframes_densified
    );
    assert_eq!(stats.depth_refinements, stats.keyframes_densified);
    assert!(stats.keyframes_densified >= 3);
    assert!(sensor_ate < 0.25 * estimated);
}

/// Issue 37: keyframes that leave the working set keep a compact form and are rebuilt when
/// used again; older ones spill to the session's store and are read back. Rebuilding on every
/// use (`resident_keyframes` 0) with every finished keyframe spilled (`held_keyframes` 0), and
/// every TSDF chunk the newest keyframe did not touch spilled (`resident_blocks` 1), must
/// give the same trajectory, keyframes, semi-dense points, dense depth and mesh as holding
/// every keyframe in full, while holding far less. The run holding everything is also the
/// determinism check: an independent run of [`baseline`]'s config with other storage limits,
/// it must give the same trajectory bit for bit (one run fewer per `make test`, issue 36).
#[test]
fn compact_and_spilled_keyframes_change_where_data_lives_never_results() {
    let spill_dir = std::env::temp_dir().join(format!("relfusion-spill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&spill_dir);
    let run_with = |resident: usize, spill: bool| {
        let mut config = deterministic();
        config.backend.resident_keyframes = resident;
        config.backend.held_keyframes = 0;
        if spill {
            // Every fusion input but the newest spills too (read back when its keyframe moves),
            // and every chunk of TSDF blocks the newest keyframe did not touch.
            config.fusion.keyframe_memory_mb = 1e-3;
            config.fusion.resident_blocks = 1;
        }
        let (camera, frames, _) = sequence();
        let mut pipeline = Pipeline::new(config, *camera, None).expect("pipeline");
        if spill {
            let store = crate::spill::FolderStore::new(&spill_dir).expect("spill folder");
            pipeline.spill().attach(Arc::new(store)).expect("attach");
            // The frame records spill a few at a time (an hour's session, 4096 at a time).
            pipeline.frames = crate::frame_log::FrameLog::with_chunk(pipeline.spill(), 7);
        }
        for frame in frames {
            pipeline.push(frame.clone()).expect("push");
        }
        pipeline.finish().expect("finish");
        let mesh = pipeline.mesh().expect("mesh").expect("a fused mesh");
        (pipeline, mesh)
    };
    let (all, all_mesh) = run_with(64, false);
    assert_eq!(baseline().trajectory, all.trajectory().expect("trajectory"));
    assert_eq!(baseline().keyframe_trajectory, all.keyframe_trajectory());
    let (none, none_mesh) = run_with(0, true);
    assert_eq!(
        all.trajectory().expect("trajectory"),
        none.trajectory().expect("trajectory")
    );
    // Only the newest chunk of frame records stays in memory; the trajectory read the rest back.
    assert!(none.frames.len() > 7, "{:?}", none.frames);
    assert_eq!(
        none.frames.held_bytes(),
        7 * std::mem::size_of::<super::keyframes::FrameRecord>()
    );
    assert_eq!(all.keyframe_trajectory(), none.keyframe_trajectory());
    assert_eq!(
        all.semidense_points().expect("points"),
        none.semidense_points().expect("points")
    );
    let dense = |p: &Pipeline| {
        p.dense_keyframes()
            .expect("dense keyframes")
            .into_iter()
            .map(|(k, pose)| (k.idepth.data.clone(), pose))
            .collect::<Vec<_>>()
    };
    assert_eq!(dense(&all), dense(&none));
    assert_eq!(all_mesh.positions, none_mesh.positions);
    assert_eq!(all_mesh.colors, none_mesh.colors);

    let (a, n) = (all.keyframe_memory(), none.keyframe_memory());
    println!("all resident: {a:?}\nnone resident, spilled: {n:?}");
    assert!(a.keyframes >= 5, "the orbit makes several keyframes");
    assert_eq!((a.resident, a.spilled), (a.keyframes, 0));
    assert_eq!(n.resident, 0);
    let (ab, nb) = (a.backend.expect("in step"), n.backend.expect("in step"));
    assert_eq!((ab.resident, ab.rebuilds), (ab.keyframes, 0));
    assert_eq!(nb.resident, 0);
    assert!(
        nb.rebuilds > 0,
        "constraint searches rebuild compact keyframes"
    );
    // Every finished keyframe is spilled (the current one was finished by `finish`) and
    // nothing of them stays in memory; constraint searches read them back.
    assert_eq!((n.spilled, nb.spilled), (n.keyframes, nb.keyframes));
    assert_eq!((n.compact_bytes, nb.compact_bytes), (0, 0));
    assert!(n.spill.spilled >= 2 * n.keyframes && n.spill.loads > 0);
    // Dense maps spill with their keyframes, fusion inputs past the budget too.
    assert!(
        n.dense_spilled > 0 && n.dense_bytes < a.dense_bytes,
        "{n:?}"
    );
    let fusion = none.fusion_stats().expect("in step");
    assert!(
        fusion.inputs_spilled > 0 && fusion.inputs_dropped == 0,
        "{fusion:?}"
    );
    assert!(
        fusion.chunks_spilled > 0 && fusion.chunk_loads > 0 && fusion.blocks_refused == 0,
        "{fusion:?}"
    );
    let kept = all.fusion_stats().expect("in step");
    assert_eq!((kept.inputs_spilled, kept.chunks_spilled), (0, 0));
    // Superseded values (a depth map refined after it was spilled) left the store.
    let files = std::fs::read_dir(&spill_dir).expect("spill folder").count();
    assert!(
        files >= 2 * n.keyframes && files <= n.spill.spilled,
        "{files} objects for {} keyframes, {} spilled",
        n.keyframes,
        n.spill.spilled
    );
    // The map written keyframe by keyframe from spilled data is the map held in memory.
    let (held_map, streamed_map) = (spill_dir.join("map-held"), spill_dir.join("map-streamed"));
    crate::map::write_map(&held_map, &all.saved_map().expect("map")).expect("write");
    none.write_map(&streamed_map).expect("write streamed");
    fn map_files(dir: &std::path::Path, root: &std::path::Path, out: &mut Vec<(String, Vec<u8>)>) {
        let mut entries: Vec<_> = std::fs::read_dir(dir)
            .expect("map folder")
            .map(|e| e.expect("entry").path())
            .collect();
        entries.sort();
        for path in entries {
            if path.is_dir() {
                map_files(&path, root, out);
            } else {
                let name = path
                    .strip_prefix(root)
                    .expect("inside")
                    .display()
                    .to_string();
                out.push((name, std::fs::read(&path).expect("read")));
            }
        }
    }
    let (mut held_files, mut streamed_files) = (Vec::new(), Vec::new());
    map_files(&held_map, &held_map, &mut held_files);
    map_files(&streamed_map, &streamed_map, &mut streamed_files);
    assert!(held_files.len() > 2 * n.keyframes);
    assert!(held_files == streamed_files, "the two maps differ");
    // A full keyframe (pyramid, tracking reference, alignment levels) costs several times
    // its compact form.
    let full = (a.resident_bytes + ab.resident_bytes) / a.keyframes;
    let compact = a.compact_bytes / a.keyframes;
    assert!(full > 3 * compact, "full {full} B, compact {compact} B");
    std::fs::remove_dir_all(&spill_dir).ok();
}

#[test]
fn threaded_back_end_tracks_the_sequence_too() {
    let (_, frames, gt) = sequence();
    let mut config = deterministic();
    config.pipeline.deterministic = false;
    let (pipeline, _) = run(config);
    assert_eq!(pipeline.stats().frames_lost, 0);
    let traj = ate(
        gt,
        &stamped(&pipeline.trajectory().expect("trajectory")),
        AlignMode::Sim3,
    )
    .expect("ate");
    assert_eq!(traj.matched, frames.len());
    let path = path_length(&gt.iter().map(|p| p.world_from_camera).collect::<Vec<_>>());
    assert!(
        traj.rmse <= 0.05 * path,
        "threaded ATE {} > 5% of {path} m",
        traj.rmse
    );
}

/// Live use: frames arrive at the sequence's 30 fps and the mapping runs on its own thread,
/// keyframes made there while tracking goes on. Every frame still gets exactly one pose,
/// every keyframe one keyframe event, the back end's moves arrive as `KeyframePoses`, every
/// event names the caller's own frame id (keyframes made from frames pushed earlier
/// included), and the trajectory stays within the threaded bound.
#[test]
fn mapping_thread_tracks_a_live_stream() {
    let (camera, frames, gt) = sequence();
    let mut config = deterministic();
    config.pipeline.deterministic = false;
    config.pipeline.mapping_thread = true;
    let mut pipeline = Pipeline::new(config, *camera, None).expect("pipeline");
    let mut events = Vec::new();
    let t0 = std::time::Instant::now();
    // A client's ids: neither the pipeline's count nor contiguous.
    let client_id = |i: usize| 1000 + 3 * i as u64;
    let sent: Vec<u64> = (0..frames.len()).map(client_id).collect();
    for (i, frame) in frames.iter().enumerate() {
        let due = t0 + std::time::Duration::from_secs_f64(frame.timestamp);
        std::thread::sleep(due.saturating_duration_since(std::time::Instant::now()));
        let frame = FrameInput {
            frame_id: Some(client_id(i)),
            ..frame.clone()
        };
        events.extend(pipeline.push(frame).expect("push"));
    }
    pipeline.finish().expect("finish");
    events.extend(pipeline.take_events());
    let stats = pipeline.stats().clone();
    let frame_ids: Vec<u64> = events
        .iter()
        .filter_map(|e| match e {
            Event::Pose(p) => Some(p.frame_id),
            _ => None,
        })
        .collect();
    assert_eq!(
        frame_ids, sent,
        "one pose event per frame, with its id, in order"
    );
    for e in &events {
        let ids: Vec<Option<u64>> = match e {
            Event::Keyframe(k) => vec![Some(k.frame_id)],
            Event::KeyframePoses { poses } => poses.iter().map(|p| p.frame_id).collect(),
            Event::KeyframeDensified { frame_id, .. } => vec![*frame_id],
            _ => Vec::new(),
        };
        for id in ids {
            assert!(
                id.is_some_and(|id| sent.contains(&id)),
                "{id:?} is not a sent frame's id"
            );
        }
    }
    let keyframe_events = events
        .iter()
        .filter(|e| matches!(e, Event::Keyframe(_)))
        .count();
    assert_eq!(keyframe_events, stats.keyframes, "one event per keyframe");
    assert!(stats.keyframes >= 3, "{stats:?}");
    // The back end's thread publishes its optimised poses while the stream runs: live
    // subscribers re-anchor on them as deterministic ones do.
    let moved = events
        .iter()
        .filter_map(|e| match e {
            Event::KeyframePoses { poses } => Some(poses.len()),
            _ => None,
        })
        .collect::<Vec<_>>();
    assert!(
        moved.iter().any(|&n| n >= 2),
        "no KeyframePoses event in live mode: {moved:?}"
    );
    assert_eq!(stats.frames_lost, 0, "{stats:?}");
    let traj = ate(
        gt,
        &stamped(&pipeline.trajectory().expect("trajectory")),
        AlignMode::Sim3,
    )
    .expect("ate");
    assert_eq!(traj.matched, frames.len(), "every frame has a pose");
    let path = path_length(&gt.iter().map(|p| p.world_from_camera).collect::<Vec<_>>());
    println!(
        "mapping thread at 30 fps: {} of {} frames not mapped, {} keyframes, ATE {:.4} m",
        stats.frames_batched,
        frames.len(),
        stats.keyframes,
        traj.rmse
    );
    assert!(
        traj.rmse <= 0.05 * path,
        "ATE {} > 5% of {path} m",
        traj.rmse
    );
}

#[test]
fn a_frame_of_the_wrong_size_is_refused_and_nothing_is_lost() {
    let (camera, frames, _) = sequence();
    let mut config = deterministic();
    config.dense.two_view.ground_truth_depth = true;
    let mut pipeline = Pipeline::new(config, *camera, None).expect("pipeline");
    pipeline.push(frames[0].clone()).expect("first frame");
    let wrong = FrameInput {
        frame_id: None,
        timestamp: 0.5,
        rgb: ::image::RgbImage::new(100, 80),
        depth: None,
    };
    assert!(matches!(pipeline.push(wrong), Err(Error::Shape(_))));
    // A depth image that does not match its colour image is refused the same way.
    let wrong_depth = FrameInput {
        depth: Some(ImageF32::filled(100, 80, 1.0)),
        ..frames[1].clone()
    };
    assert!(matches!(pipeline.push(wrong_depth), Err(Error::Shape(_))));
    let events = pipeline.push(frames[1].clone()).expect("next frame");
    assert!(
        events
            .iter()
            .any(|e| matches!(e, Event::Pose(p) if p.state == TrackingState::Tracking))
    );
    assert_eq!(
        pipeline.stats().frames,
        2,
        "the refused frame is not counted"
    );
}

#[test]
fn invalid_config_is_refused() {
    let (camera, _, _) = sequence();
    let mut config = Config::default();
    config.pipeline.prior_init_var = -1.0;
    assert!(Pipeline::new(config, *camera, None).is_err());
    // The sensor-depth baseline refines through the dense layer: asking for it without one
    // would silently do nothing.
    let mut config = Config::default();
    config.dense.enabled = false;
    config.dense.two_view.ground_truth_depth = true;
    assert!(matches!(
        Pipeline::new(config, *camera, None),
        Err(Error::Config(m)) if m.contains("ground_truth_depth")
    ));
}

/// Issue 22's scale-drift goal on a long hand-held path: the 60-frame windowed scale of a
/// 1000-frame `loop` sequence (ideal camera, 320×240, no model) must stay within 1.1 (largest
/// over smallest window scale). Not met yet: 1.24 here, 1.7 on a clean 700-frame `handheld`
/// path (docs/tuning.md, "Scale drift, issue 22"), so it is ignored in the suite; run it with
/// `--ignored`.
#[test]
#[ignore = "issue 22 goal not met: scale drift 1.24 on this path (docs/tuning.md)"]
fn pipeline_scale_drift_over_a_1000_frame_loop_stays_within_1_1() {
    let config = SynthConfig {
        frames: 1000,
        seed: 11,
        motion: crate::dataset::Motion::Loop,
        width: 320,
        height: 240,
        supersample: 1,
        ..Default::default()
    };
    let camera = config.camera().expect("camera");
    let scene = Scene::generate(config.seed);
    let mut pipeline = Pipeline::new(Config::default(), camera, None).expect("pipeline");
    let mut gt = Vec::new();
    for (i, pose) in config.poses().iter().enumerate() {
        let timestamp = i as f64 / config.fps;
        let (rgb, _) = crate::dataset::synth::render_frame_with(&scene, &camera, pose, 1);
        pipeline
            .push(FrameInput {
                frame_id: None,
                timestamp,
                rgb,
                depth: None,
            })
            .expect("push");
        gt.push(StampedPose {
            timestamp,
            world_from_camera: *pose,
        });
    }
    pipeline.finish().expect("finish");
    let matched = crate::eval::associate_poses(
        &gt,
        &stamped(&pipeline.trajectory().expect("trajectory")),
        crate::eval::DEFAULT_MAX_DT,
    )
    .expect("matched");
    assert_eq!(matched.len(), 1000, "every frame has a pose");
    let drift = crate::eval::scale_drift(&matched, 60)
        .expect("drift")
        .drift
        .expect("windows with a scale");
    assert!(drift <= 1.1, "scale drift {drift} over 1000 frames");
}

/// A camera that is covered for 1 s and uncovered elsewhere (a third of the orbit on) loses
/// tracking for good: relocalisation against the recent keyframes cannot find it. With
/// `new_fragment_after_lost_s` it begins a new fragment 2 s after it was lost, maps on there,
/// and the fragment is merged into the map when the orbit brings the camera back to the start;
/// without, every frame until then is lost.
fn covered_and_moved(config: Config, resumed_until: usize) -> (Pipeline, Vec<StampedPose>) {
    let (camera, shown) = covered_frames();
    let mut pipeline = Pipeline::new(config, *camera, None).expect("pipeline");
    let mut gt = Vec::new();
    for (frame, pose) in &shown[..90 + 30 + (resumed_until - 180)] {
        pipeline.push(frame.clone()).expect("push");
        if let Some(pose) = pose {
            gt.push(StampedPose {
                timestamp: frame.timestamp,
                world_from_camera: *pose,
            });
        }
    }
    pipeline.finish().expect("finish");
    (pipeline, gt)
}

type CoveredFrames = (PinholeCamera, Vec<(FrameInput, Option<SE3>)>);

/// The frames [`covered_and_moved`] shows, each with its pose on the orbit (none while the
/// lens is covered): orbit frames 0-89, 30 frames of something else in front of the lens,
/// orbit frames 180-329. Rendered once per test binary (three runs read them).
fn covered_frames() -> &'static CoveredFrames {
    static FRAMES: OnceLock<CoveredFrames> = OnceLock::new();
    FRAMES.get_or_init(|| {
        let synth = SynthConfig {
            frames: 330,
            seed: 2,
            width: 320,
            height: 240,
            ..Default::default()
        };
        let camera = synth.camera().expect("camera");
        let (scene, covered) = (Scene::generate(synth.seed), Scene::generate(7));
        let poses = synth.poses();
        let shown = (0..90)
            .map(|i| (&scene, i))
            .chain((0..30).map(|i| (&covered, i)))
            .chain((180..330).map(|i| (&scene, i)));
        let frames = shown
            .enumerate()
            .map(|(k, (s, i))| {
                let (rgb, _) = render_frame(s, &camera, &poses[i]);
                let frame = FrameInput {
                    frame_id: None,
                    timestamp: k as f64 / synth.fps,
                    rgb,
                    depth: None,
                };
                (frame, std::ptr::eq(s, &scene).then_some(poses[i]))
            })
            .collect();
        (camera, frames)
    })
}

#[test]
fn a_camera_lost_for_good_starts_a_fragment_that_is_merged_when_it_returns() {
    let (pipeline, gt) = covered_and_moved(deterministic(), 330);
    let stats = pipeline.stats().clone();
    let trajectory = pipeline.trajectory().expect("trajectory");
    let result = ate(&gt, &stamped(&trajectory), AlignMode::Sim3).expect("ate");
    eprintln!(
        "with fragments: {} fragment(s), {} left apart, {} of {} frames with a pose, ATE {:.4}",
        stats.fragments,
        stats.fragments_apart,
        result.matched,
        gt.len(),
        result.rmse
    );
    assert_eq!(stats.fragments, 1, "{stats:?}");
    assert_eq!(
        stats.fragments_apart, 0,
        "the fragment was merged: {stats:?}"
    );
    assert!(
        result.matched >= gt.len() - 70,
        "{} of {}",
        result.matched,
        gt.len()
    );
    assert!(
        result.rmse < 0.05,
        "ATE {} over both fragments",
        result.rmse
    );

    let mut without = deterministic();
    without.pipeline.new_fragment_after_lost_s = 0.0;
    let (pipeline, _) = covered_and_moved(without, 330);
    let lost = pipeline.trajectory().expect("trajectory").len();
    eprintln!("without fragments: {lost} frames with a pose");
    assert_eq!(pipeline.stats().fragments, 0);
    assert!(lost < result.matched, "{lost} vs {}", result.matched);
}

#[test]
fn a_fragment_never_merged_is_left_out_of_every_export_and_the_mesh() {
    // The camera does not come back: the fragment (frames 180-239) stays apart.
    let (mut pipeline, gt) = covered_and_moved(deterministic(), 240);
    let stats = pipeline.stats().clone();
    assert_eq!(
        (stats.fragments, stats.fragments_apart),
        (1, 1),
        "{stats:?}"
    );
    let exported = pipeline.exported();
    let kept: Vec<KeyframeId> = (0..exported.len()).filter(|&id| exported[id]).collect();
    assert!(
        kept.len() < exported.len(),
        "a fragment apart is not exported"
    );
    // The exports hold the main fragment only: the frames before the lens was covered.
    let trajectory = pipeline.trajectory().expect("trajectory");
    assert!(!trajectory.is_empty());
    assert!(
        trajectory.iter().all(|(t, _)| *t < 90.0 / 30.0),
        "only frames of the main fragment"
    );
    assert_eq!(pipeline.keyframe_trajectory().len(), kept.len());
    let result = ate(&gt, &stamped(&trajectory), AlignMode::Sim3).expect("ate");
    assert!(
        result.rmse < 0.05,
        "ATE {} of the main fragment",
        result.rmse
    );
    let map = pipeline.saved_map().expect("map");
    assert_eq!(map.keyframes.len(), kept.len());
    assert!(
        map.edges
            .iter()
            .all(|e| e.from < kept.len() && e.to < kept.len())
    );
    // The mesh shows the main fragment only.
    let fused: Vec<KeyframeId> = pipeline
        .fusion
        .as_mut()
        .and_then(crate::fusion::worker::FusionLink::fuser)
        .expect("fuser")
        .fused_poses()
        .into_iter()
        .map(|(id, _)| id)
        .collect();
    assert!(!fused.is_empty());
    assert!(
        fused.iter().all(|id| exported[*id]),
        "fused {fused:?}, exported {kept:?}"
    );
}
