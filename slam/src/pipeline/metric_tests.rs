//! The metric path (issue 39) on the synthetic orbit: a "prior" that is the true depth times
//! a known noise (per image and per pixel) anchors the map in metres; the same prior said to be
//! relative does not.

use std::collections::HashMap;
use std::hash::{DefaultHasher, Hash, Hasher};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::tests::sequence;
use super::*;
use crate::dense::{InverseDepth, ModelConfig};
use crate::eval::{AlignMode, AteResult, ate};
use crate::image::ImageF32;

/// Per-image scale error (uniform, ±) and per-pixel error (uniform, ±) of the noisy truth.
const IMAGE_NOISE: f64 = 0.08;
const PIXEL_NOISE: f64 = 0.15;

/// The rendered depth of each frame, recognised by its image, times the noise.
#[derive(Debug)]
struct NoisyTruth {
    depth: HashMap<u64, ImageF32>,
    config: ModelConfig,
    predictions: u64,
}

fn image_key(rgb: &::image::RgbImage) -> u64 {
    let mut h = DefaultHasher::new();
    rgb.as_raw().hash(&mut h);
    h.finish()
}

impl NoisyTruth {
    fn new(metric: bool) -> Self {
        let (_, frames, _) = sequence();
        let depth = frames
            .iter()
            .map(|f| (image_key(&f.rgb), f.depth.clone().expect("rendered depth")))
            .collect();
        let toml = format!(
            "name='noisy_truth'\ninput='x'\ninput_width=8\ninput_height=8\noutput='y'\n\
             output_kind='depth'\nmetric={metric}\n"
        );
        Self {
            depth,
            config: ModelConfig::from_toml(&toml).expect("config"),
            predictions: 0,
        }
    }
}

impl DepthPrior for NoisyTruth {
    fn predict(&mut self, rgb: &::image::RgbImage) -> crate::Result<InverseDepth> {
        let key = image_key(rgb);
        let depth = self.depth.get(&key).expect("a frame of the sequence");
        let mut rng = ChaCha8Rng::seed_from_u64(key ^ self.predictions);
        self.predictions += 1;
        let image = 1.0 + rng.random_range(-IMAGE_NOISE..IMAGE_NOISE);
        let data = depth
            .data
            .iter()
            .map(|&d| {
                let pixel = 1.0 + rng.random_range(-PIXEL_NOISE..PIXEL_NOISE);
                if d > 0.0 {
                    (1.0 / (f64::from(d) * image * pixel)) as f32
                } else {
                    0.0
                }
            })
            .collect();
        Ok(InverseDepth(ImageF32::from_vec(
            depth.width,
            depth.height,
            data,
        )?))
    }

    fn describe(&self) -> &ModelConfig {
        &self.config
    }
}

fn pipeline(metric: bool, config: Config) -> Pipeline {
    let (camera, _, _) = sequence();
    let prior: Box<dyn DepthPrior> = Box::new(NoisyTruth::new(metric));
    Pipeline::new(config, *camera, Some(prior)).expect("pipeline")
}

/// Runs the orbit through a pipeline with the metric noisy truth; returns the stats, the live
/// pose events of tracked frames, and the final trajectory's Sim(3) and SE(3) alignments.
fn metric_run(mut config: Config) -> (Stats, Vec<PoseEvent>, AteResult, AteResult) {
    let (_, frames, gt) = sequence();
    config.pipeline.deterministic = true;
    config.fusion.enabled = false;
    let frontend = config.pipeline.frontend;
    let mut pipeline = pipeline(true, config);
    let mut live = Vec::new();
    for frame in frames {
        for event in pipeline.push(frame.clone()).expect("push") {
            if let Event::Pose(pose) = event
                && pose.state == TrackingState::Tracking
            {
                live.push(pose);
            }
        }
    }
    pipeline.finish().expect("finish");
    let stats = pipeline.stats();
    let est = crate::dataset::trajectory::stamped_se3(&pipeline.trajectory().expect("trajectory"));
    let sim3 = ate(gt, &est, AlignMode::Sim3).expect("ate");
    let se3 = ate(gt, &est, AlignMode::Se3).expect("ate");
    eprintln!(
        "metric prior, {:?} front end: Sim(3) scale {:.4}, ATE Sim(3) {:.4} m, SE(3) {:.4} m, {} \
         keyframes",
        frontend, sim3.scale, sim3.rmse, se3.rmse, stats.keyframes
    );
    (stats.clone(), live, sim3, se3)
}

fn assert_metric(sim3: &AteResult, se3: &AteResult) {
    assert!(
        (sim3.scale - 1.0).abs() <= 0.02,
        "trajectory scale {} is not within 2 % of metric",
        sim3.scale
    );
    assert!(
        se3.rmse <= 1.5 * sim3.rmse + 0.005,
        "{} vs {}",
        se3.rmse,
        sim3.rmse
    );
}

#[test]
fn a_metric_prior_puts_the_trajectory_in_metres() {
    let (stats, _, sim3, se3) = metric_run(Config::default());
    assert_eq!(stats.scale, "metric");
    assert!(stats.keyframes_densified >= 3, "{stats:?}");
    assert_metric(&sim3, &se3);
}

/// With the odometry front end the first keyframe's scale comes from the prior too, so the
/// poses a client sees live are metric before the pose graph has seen a factor.
#[test]
fn a_metric_prior_puts_the_odometry_front_ends_trajectory_in_metres() {
    let mut config = Config::default();
    config.pipeline.frontend = Frontend::Dso;
    let (stats, live, sim3, se3) = metric_run(config);
    assert_eq!(stats.scale, "metric");
    assert_metric(&sim3, &se3);
    // The first 40 tracked frames as they were reported, against their ground truth.
    assert!(live.len() >= 40);
    let live_sim3 = live_alignment(&live[..40]);
    eprintln!(
        "live poses of the first 40 tracked frames: Sim(3) scale {:.4}",
        live_sim3.scale
    );
    // Without the prior's scale the live poses would be in the initialiser's unit (mean
    // inverse depth 1). Measured 1.095: the first keyframe's prior is off by up to 8 % per
    // image, and the window moves the scale a little before the pose graph's factors act.
    assert!(
        (live_sim3.scale - 1.0).abs() <= 0.2,
        "live scale {} is not metric",
        live_sim3.scale
    );
}

/// Sim(3) alignment of the poses as they were reported live (tracked frames) to the truth.
fn live_alignment(live: &[PoseEvent]) -> AteResult {
    let (_, _, gt) = sequence();
    let poses: Vec<(f64, Sim3)> = live
        .iter()
        .map(|p| (p.timestamp, p.world_from_camera))
        .collect();
    let poses = crate::dataset::trajectory::stamped_se3(&poses);
    ate(gt, &poses, AlignMode::Sim3).expect("ate")
}

#[test]
fn a_relative_prior_never_claims_metres() {
    assert_eq!(
        pipeline(false, Config::default()).stats().scale,
        "arbitrary"
    );
    let mut random_init = Config::default();
    random_init.pipeline.init = DepthInit::Random;
    let unanchored = pipeline(true, random_init).stats().scale;
    assert_eq!(
        unanchored, "arbitrary",
        "the first keyframe is not in metres"
    );
    let mut off = Config::default();
    off.backend.metric_scale.enabled = false;
    assert_eq!(pipeline(true, off).stats().scale, "arbitrary");
    assert_eq!(pipeline(true, Config::default()).stats().scale, "metric");
}

/// A map made with a metric prior says so and keeps its keyframes' scale factors through the
/// disk; an extension maps on in its metres (whatever the prior) and keeps its factors, and a
/// map of arbitrary scale is never called metric (issue 39).
#[test]
fn a_metric_map_keeps_its_metres_through_the_disk_and_an_extension() {
    let (camera, frames, gt) = sequence();
    let mut config = Config::default();
    config.pipeline.deterministic = true;
    config.fusion.enabled = false;
    let mut mapping = pipeline(true, config.clone());
    for frame in &frames[..120] {
        mapping.push(frame.clone()).expect("push");
    }
    mapping.finish().expect("finish");
    let map = mapping.saved_map().expect("map");
    let priors = map
        .keyframes
        .iter()
        .filter(|k| k.scale_prior.is_some())
        .count();
    assert!(map.metric);
    assert!(priors >= 2, "{priors} of {} keyframes", map.keyframes.len());

    // Through the disk, and as a version-1 reader of the same map would have written it.
    let dir = std::env::temp_dir().join(format!("relfusion-metric-map-{}", std::process::id()));
    crate::map::write_map(&dir, &map).expect("write");
    let read = crate::map::read_map(&dir, Some(camera)).expect("read");
    assert!(read.metric);
    let factors = |m: &crate::map::SavedMap| -> Vec<_> {
        m.keyframes.iter().map(|k| k.scale_prior).collect()
    };
    assert_eq!(factors(&read), factors(&map));
    let manifest = dir.join("manifest.json");
    let mut v1: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&manifest).expect("manifest")).expect("json");
    v1["version"] = 1.into();
    v1.as_object_mut().expect("object").remove("metric");
    for kf in v1["keyframes"].as_array_mut().expect("keyframes") {
        kf.as_object_mut().expect("object").remove("scale_prior");
    }
    std::fs::write(&manifest, serde_json::to_vec(&v1).expect("json")).expect("write");
    let old = crate::map::read_map(&dir, Some(camera)).expect("a version-1 map");
    assert!(!old.metric && factors(&old).iter().all(Option::is_none));
    let _ = std::fs::remove_dir_all(&dir);

    // A relative prior extends a metric map in the map's metres; a metric prior never calls a
    // map of arbitrary scale metric.
    let relative = Box::new(NoisyTruth::new(false));
    let p =
        Pipeline::extending(config.clone(), *camera, Some(relative), None, &map).expect("extend");
    assert_eq!((p.stats().scale, p.metric), ("metric", false));
    // The map's factors enter the pose graph only where its keyframes may move.
    let in_graph = |p: &Pipeline| {
        p.backend
            .backend()
            .expect("in step")
            .graph()
            .scale_priors()
            .len()
    };
    assert_eq!(in_graph(&p), 0, "fixed map keyframes keep their scale");
    let mut free = config.clone();
    free.extend.fix_map = false;
    let p = Pipeline::extending(free, *camera, None, None, &map).expect("extend");
    assert_eq!(in_graph(&p), priors);
    let metric = Box::new(NoisyTruth::new(true));
    let p = Pipeline::extending(config.clone(), *camera, Some(metric), None, &old).expect("extend");
    assert_eq!((p.stats().scale, p.metric), ("arbitrary", false));

    // A metric prior extends it in metres: the map's factors kept, new keyframes anchored by
    // the map alone.
    let metric = Box::new(NoisyTruth::new(true));
    let mut extension =
        Pipeline::extending(config, *camera, Some(metric), None, &read).expect("extend");
    for frame in &frames[90..] {
        extension.push(frame.clone()).expect("push");
    }
    extension.finish().expect("finish");
    assert_eq!(extension.stats().scale, "metric");
    let merged = extension.saved_map().expect("merged map");
    let n = map.keyframes.len();
    assert!(merged.metric && merged.keyframes.len() > n + 1);
    assert_eq!(factors(&merged)[..n], factors(&map)[..]);
    assert!(factors(&merged)[n..].iter().all(Option::is_none));
    let est = crate::dataset::trajectory::stamped_se3(&extension.trajectory().expect("poses"));
    let sim3 = ate(&gt[90..], &est, AlignMode::Sim3).expect("ate");
    eprintln!(
        "extended metric map: {} new keyframes, Sim(3) scale {:.4}, ATE {:.4} m",
        merged.keyframes.len() - n,
        sim3.scale,
        sim3.rmse
    );
    // Measured 0.995 (with the new keyframes anchored to the prior as well: 0.980).
    assert!(
        (sim3.scale - 1.0).abs() <= 0.02,
        "the extension's scale {} is not within 2 % of metric",
        sim3.scale
    );
}
