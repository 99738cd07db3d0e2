//! Map round trip, refusals, and localisation on rendered views with exact poses.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use super::*;
use crate::dataset::synth::{Scene, SynthConfig, Trajectory, render_frame};
use crate::dataset::trajectory::{StampedPose, stamped_se3};
use crate::eval::{AlignMode, align, associate_poses};
use crate::geometry::SE3;
use crate::pipeline::{Config, DepthInit, FrameInput, Pipeline};
use crate::tracking::TrackingConfig;

const FPS: f64 = 30.0;

fn synth() -> SynthConfig {
    SynthConfig {
        frames: 150,
        seed: 2,
        width: 320,
        height: 240,
        ..Default::default()
    }
}

fn render(scene: &Scene, camera: &PinholeCamera, pose: &SE3, t: f64) -> FrameInput {
    let (rgb, _) = render_frame(scene, camera, pose);
    FrameInput {
        frame_id: None,
        timestamp: t,
        rgb,
        depth: None,
    }
}

/// A map of the first `frames` of the orbit (dense layer on when `dense`), with the ground truth
/// of its frames.
fn mapped(dense: bool, frames: usize) -> (SavedMap, Vec<StampedPose>) {
    let synth = synth();
    let camera = synth.camera().expect("camera");
    let scene = Scene::generate(synth.seed);
    let mut config = Config::default();
    config.pipeline.deterministic = true;
    config.pipeline.init = DepthInit::Random;
    config.dense.enabled = dense;
    let mut pipeline = Pipeline::new(config, camera, None).expect("pipeline");
    let mut gt = Vec::new();
    for (i, pose) in synth.poses().iter().enumerate().take(frames) {
        let t = i as f64 / FPS;
        pipeline
            .push(render(&scene, &camera, pose, t))
            .expect("push");
        gt.push(StampedPose {
            timestamp: t,
            world_from_camera: *pose,
        });
    }
    pipeline.finish().expect("finish");
    (pipeline.saved_map().expect("map"), gt)
}

fn localisation_map() -> &'static (SavedMap, Vec<StampedPose>) {
    static MAP: OnceLock<(SavedMap, Vec<StampedPose>)> = OnceLock::new();
    MAP.get_or_init(|| mapped(false, synth().frames))
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("relfusion-map-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}

fn entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("read dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn map_round_trip_keeps_keyframes_depth_edges_and_poses() {
    let (map, _) = mapped(true, 60);
    assert!(
        map.keyframes.len() >= 3,
        "{} keyframes",
        map.keyframes.len()
    );
    assert!(map.keyframes.iter().any(|kf| kf.dense.is_some()));
    assert!(!map.edges.is_empty());
    let dir = temp_dir("round-trip");
    let path = dir.join("map");
    write_map(&path, &map).expect("write");
    let back = read_map(&path, Some(&map.camera)).expect("read");
    assert_eq!(back.camera, map.camera);
    assert_eq!(back.voxel_size, map.voxel_size);
    assert_eq!(back.keyframes.len(), map.keyframes.len());
    for (a, b) in map.keyframes.iter().zip(&back.keyframes) {
        assert_eq!(a.id, b.id);
        assert_eq!(a.timestamp.to_bits(), b.timestamp.to_bits());
        assert_eq!(a.world_from_keyframe, b.world_from_keyframe);
        assert_eq!(*a.depth, *b.depth, "keyframe {}", a.id);
        assert_eq!(a.dense, b.dense, "keyframe {}", a.id);
        assert_eq!(a.thumbnail, b.thumbnail);
        assert_eq!(a.image.rgb, b.image.rgb, "PNG is lossless");
        assert_eq!(
            a.image.rebuild().expect("frame").level(0).image,
            b.image.rebuild().expect("frame").level(0).image
        );
    }
    assert_eq!(back.edges.len(), map.edges.len());
    for (a, b) in map.edges.iter().zip(&back.edges) {
        assert_eq!(
            (a.from, a.to, a.to_from_from),
            (b.from, b.to, b.to_from_from)
        );
        assert_eq!(a.information, b.information);
    }
    assert_eq!(
        read_keyframe_poses(&path).expect("poses"),
        map.keyframes
            .iter()
            .map(|kf| (kf.timestamp, kf.world_from_keyframe))
            .collect::<Vec<_>>()
    );
    // Writing again replaces the map whole and leaves no temporary folder beside it.
    write_map(&path, &back).expect("rewrite");
    assert_eq!(entries(&dir), vec!["map".to_string()]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn map_refuses_another_version_another_camera_and_damaged_parts() {
    let (map, _) = localisation_map();
    let dir = temp_dir("refusals");
    let path = dir.join("map");
    write_map(&path, map).expect("write");

    let other = PinholeCamera::new(500.0, 500.0, 160.0, 120.0, 320, 240).expect("camera");
    let err = read_map(&path, Some(&other)).expect_err("another camera");
    assert!(
        matches!(err, Error::Map(_)) && err.to_string().contains("camera"),
        "{err}"
    );

    let manifest = path.join("manifest.json");
    let text = std::fs::read_to_string(&manifest).expect("manifest");
    let future = text.replacen(
        &format!("\"version\": {FORMAT_VERSION}"),
        "\"version\": 999",
        1,
    );
    assert_ne!(future, text);
    std::fs::write(&manifest, &future).expect("write");
    let err = read_map(&path, None).expect_err("another version");
    assert!(err.to_string().contains("version 999"), "{err}");
    std::fs::write(&manifest, &text).expect("restore");

    let npy = path.join("keyframes/000001/semidense_var.npy");
    std::fs::write(&npy, b"\x93NUMPY not really").expect("damage");
    assert!(read_map(&path, None).is_err());
    std::fs::remove_file(&npy).expect("remove");
    let err = read_map(&path, None).expect_err("missing part");
    assert!(err.to_string().contains("semidense_var.npy"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The map keyframes' Sim(3) to the ground truth: the only alignment the scores below use.
fn gt_from_map(map: &SavedMap, gt: &[StampedPose]) -> Sim3 {
    let keyframes: Vec<(f64, Sim3)> = map
        .keyframes
        .iter()
        .map(|kf| (kf.timestamp, kf.world_from_keyframe))
        .collect();
    let matched = associate_poses(gt, &stamped_se3(&keyframes), 1e-3).expect("matched");
    align(&matched, AlignMode::Sim3).expect("aligned")
}

#[test]
fn localizer_places_unseen_views_of_the_mapped_room_in_the_map_frame() {
    let (map, gt) = localisation_map();
    let synth = synth();
    let camera = synth.camera().expect("camera");
    let scene = Scene::generate(synth.seed);
    let trajectory = Trajectory::new(synth.motion, synth.seed);
    let gt_from_map = gt_from_map(map, gt);
    let mut localizer = Localizer::new(map, TrackingConfig::default(), LocalizeConfig::default())
        .expect("localizer");
    // Views between the mapped ones (half a frame later), started in the middle of the map.
    let mut errors = Vec::new();
    let times: Vec<f64> = (40..140).map(|i| (f64::from(i) + 0.5) / FPS).collect();
    for &t in &times {
        let truth = trajectory.world_from_camera(t);
        let input = render(&scene, &camera, &truth, t);
        let result = localizer.localize(t, input.rgb).expect("localize");
        if let Some(pose) = result.world_from_camera {
            errors.push((truth.translation - gt_from_map.act(&pose.translation)).norm());
        }
    }
    let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len().max(1) as f64).sqrt();
    let max = errors.iter().copied().fold(0.0, f64::max);
    eprintln!(
        "localised {} of {} views, rms {rms:.4} m, max {max:.4} m",
        errors.len(),
        times.len()
    );
    assert!(
        errors.len() * 10 >= times.len() * 9,
        "{} of {} views localised",
        errors.len(),
        times.len()
    );
    assert!(rms < 0.03 && max < 0.1, "rms {rms:.4} m, max {max:.4} m");
}

#[test]
fn localizer_gives_no_pose_in_a_room_it_never_mapped() {
    let (map, _) = localisation_map();
    let synth = synth();
    let camera = synth.camera().expect("camera");
    let other_room = Scene::generate(7);
    let trajectory = Trajectory::new(synth.motion, 7);
    let mut localizer = Localizer::new(map, TrackingConfig::default(), LocalizeConfig::default())
        .expect("localizer");
    for i in 0..40 {
        let t = f64::from(i) * 3.0 / FPS;
        let input = render(&other_room, &camera, &trajectory.world_from_camera(t), t);
        let result = localizer.localize(t, input.rgb).expect("localize");
        assert_eq!(
            result.state,
            LocalizationState::NotLocalized,
            "view {i}: {result:?}"
        );
        assert!(result.world_from_camera.is_none());
    }
}

#[test]
fn localizer_refuses_frames_of_another_size() {
    let (map, _) = localisation_map();
    let mut localizer = Localizer::new(map, TrackingConfig::default(), LocalizeConfig::default())
        .expect("localizer");
    let err = localizer
        .localize(0.0, ::image::RgbImage::new(64, 48))
        .expect_err("size");
    assert!(matches!(err, Error::Shape(_)), "{err}");
}

#[test]
fn an_extended_map_keeps_its_keyframes_and_maps_on_in_its_frame() {
    // The map covers the first 100 frames of the orbit; the second run starts inside it, half
    // a frame off the mapped views, and goes on 90 frames (a tenth of the orbit) beyond it.
    let (map, gt) = mapped(false, 100);
    let synth = synth();
    let camera = synth.camera().expect("camera");
    let scene = Scene::generate(synth.seed);
    let trajectory = Trajectory::new(synth.motion, synth.seed);
    let gt_from_map = gt_from_map(&map, &gt);
    let mut config = Config::default();
    config.pipeline.deterministic = true;
    let mut pipeline = Pipeline::extending(config, camera, None, None, &map).expect("extend");
    assert_eq!(pipeline.map_keyframes(), map.keyframes.len());
    // A view of another room first: not in the map, so lost, and no map of its own is begun.
    let other_room = Scene::generate(7);
    let events = pipeline
        .push(render(&other_room, &camera, &SE3::identity(), 0.0))
        .expect("push");
    let lost = events.iter().any(|e| {
        matches!(e, crate::pipeline::Event::Pose(p) if p.state == crate::pipeline::TrackingState::Lost)
    });
    assert!(lost, "{events:?}");
    assert_eq!(pipeline.stats().keyframes, map.keyframes.len());
    let mut truth = Vec::new();
    for i in 70..190 {
        let t = (f64::from(i) + 0.5) / FPS;
        let pose = trajectory.world_from_camera(t);
        pipeline
            .push(render(&scene, &camera, &pose, t))
            .expect("push");
        truth.push(StampedPose {
            timestamp: t,
            world_from_camera: pose,
        });
    }
    let poses = pipeline.finish().expect("finish");
    let n = map.keyframes.len();
    assert!(
        poses.len() >= n + 3,
        "{} keyframes, {n} from the map",
        poses.len()
    );
    for (kf, (id, pose)) in map.keyframes.iter().zip(&poses) {
        assert_eq!(kf.id, *id);
        let moved = (kf.world_from_keyframe.translation - pose.translation).norm();
        assert!(moved < 1e-9, "map keyframe {id} moved by {moved}");
    }
    // The new frames in the map's frame: where they see the mapped area (up to frame 100)
    // within the map's own accuracy under the map's alignment to the ground truth; beyond it,
    // the extension keeps the map's scale (its own alignment's scale within 10 % of the map's)
    // and its shape.
    let trajectory = pipeline.trajectory().expect("trajectory");
    let matched = associate_poses(&truth, &stamped_se3(&trajectory), 1e-3).expect("matched");
    let rms_under = |gt_from_est: &Sim3, until: f64| {
        let e: Vec<f64> = matched
            .gt
            .iter()
            .zip(&matched.est)
            .filter(|(g, _)| g.timestamp < until)
            .map(|(g, e)| {
                (g.world_from_camera.translation
                    - gt_from_est.act(&e.world_from_camera.translation))
                .norm()
            })
            .collect();
        (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt()
    };
    let own = align(&matched, AlignMode::Sim3).expect("own alignment");
    let (in_map, shape) = (
        rms_under(&gt_from_map, 100.0 / FPS),
        rms_under(&own, f64::INFINITY),
    );
    let scale = own.scale / gt_from_map.scale;
    eprintln!(
        "extended: {} keyframes ({n} from the map), {} of 120 frames tracked, rms {in_map:.4} m \
         in the mapped area, {shape:.4} m under its own alignment, scale {scale:.3} of the map's",
        poses.len(),
        matched.gt.len()
    );
    assert!(
        matched.gt.len() >= 110,
        "{} of 120 frames tracked",
        matched.gt.len()
    );
    assert!(in_map < 0.05, "rms {in_map:.4} m in the mapped area");
    assert!(shape < 0.05, "rms {shape:.4} m under its own alignment");
    assert!((0.9..1.1).contains(&scale), "scale {scale:.3} of the map's");
    // One merged map, which saves and loads like any other.
    let merged = pipeline.saved_map().expect("merged map");
    assert_eq!(merged.keyframes.len(), poses.len());
    assert!(merged.edges.len() > map.edges.len());
    assert!(
        pipeline
            .mesh()
            .expect("mesh")
            .is_some_and(|m| !m.is_empty())
    );
}
