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
use crate::eval::{AlignMode, ate};
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

#[test]
fn a_metric_prior_puts_the_trajectory_in_metres() {
    let (_, frames, gt) = sequence();
    let mut config = Config::default();
    config.pipeline.deterministic = true;
    config.fusion.enabled = false;
    let mut pipeline = pipeline(true, config);
    for frame in frames {
        pipeline.push(frame.clone()).expect("push");
    }
    pipeline.finish().expect("finish");
    let stats = pipeline.stats();
    assert_eq!(stats.scale, "metric");
    assert!(stats.keyframes_densified >= 3, "{stats:?}");
    let est = crate::dataset::trajectory::stamped_se3(&pipeline.trajectory().expect("trajectory"));
    let sim3 = ate(gt, &est, AlignMode::Sim3).expect("ate");
    let se3 = ate(gt, &est, AlignMode::Se3).expect("ate");
    eprintln!(
        "metric prior: Sim(3) scale {:.4}, ATE Sim(3) {:.4} m, SE(3) {:.4} m, {} keyframes",
        sim3.scale, sim3.rmse, se3.rmse, stats.keyframes
    );
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
