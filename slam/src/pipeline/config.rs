//! The one configuration of the pipeline: one nested section per component, each with the
//! paper's / LSD-SLAM's values as defaults. Config files only override (unknown keys are errors).

use serde::{Deserialize, Serialize};

use crate::dense::DenseConfig;
use crate::graph::BackendConfig;
use crate::mapping::MappingConfig;
use crate::tracking::TrackingConfig;
use crate::{Error, Result};

/// How the first keyframe's inverse depth is initialised.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthInit {
    /// From the depth prior (ONNX network), scale-normalised: the way past missing parallax on
    /// rotation-heavy starts (issue 3). Falls back to `Random` when no prior is loaded.
    #[default]
    Prior,
    /// LSD-SLAM's random initialisation (Engel et al. 2014 §3.1): needs translation early on.
    Random,
}

/// What estimates the frames' poses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Frontend {
    /// LSD-SLAM's loop: tracking against the current keyframe's semi-dense depth, which the
    /// tracked poses refine (Engel et al. 2014).
    #[default]
    Lsd,
    /// The DSO-class odometry (`crate::odometry`, issue 35): poses, affine brightness and
    /// point depths solved jointly over a window of keyframes; its keyframes become the
    /// pipeline's, and the semi-dense depth filter only follows its poses to give each
    /// keyframe the map the dense layer and the back end need. Not the default until it is
    /// at least as good on every sequence (docs/tuning.md).
    Dso,
}

/// Front-end orchestration settings. Its user settings are listed in
/// [`crate::pipeline::user_config`]; the rest is expert level.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineConfig {
    /// What estimates the poses. With `dso`, its settings are `odometry`; relocalisation and
    /// re-activation are LSD's and not used, and a lost odometry starts again in a new map
    /// fragment after `new_fragment_after_lost_s`.
    pub frontend: Frontend,
    /// First-keyframe depth initialisation.
    pub init: DepthInit,
    /// Variance given to prior-initialised inverse depths, in the normalised keyframe scale
    /// (mean inverse depth 1). Large enough that stereo observations override a wrong prior
    /// (PyDNet++ inverts depth ordering on ~1 frame in 6), small enough to track at once.
    pub prior_init_var: f32,
    /// Run the back end in step with the frames (deterministic, used by tests) instead of on its
    /// own thread.
    pub deterministic: bool,
    /// Map the current keyframe on its own thread (LSD-SLAM's mapping thread) unless
    /// `deterministic`: stereo and regularisation overlap with tracking; a mapping that falls
    /// behind maps its queued frames in one batch (`Stats::frames_batched`), and tracking
    /// waits only when `mapping_queue` frames are waiting. Live cameras turn it on (the server
    /// does for live sessions). Default false, as LSD-SLAM runs a dataset: every good frame is
    /// observed before the next one is tracked (docs/tuning.md, "Mapping thread").
    pub mapping_thread: bool,
    /// Tracked frames waiting for the mapping thread before tracking waits for it. Default 8
    /// (a quarter second at 30 Hz): enough to ride out a slow keyframe change, short enough
    /// that the depth tracking uses is never far behind. Frames are never dropped (issue 22).
    pub mapping_queue: usize,
    /// Row-band workers of the depth filter on the mapping thread (replaces `mapping.threads`
    /// there; 0 = all cores). Default 1: on a 2-core machine the other core stays with
    /// tracking (docs/tuning.md, "Mapping thread").
    pub mapping_thread_workers: usize,
    /// Seed of every random choice (random depth initialisation).
    pub seed: u64,
    /// How many recent keyframes relocalisation tries after tracking is lost.
    pub relocalisation_candidates: usize,
    /// Seconds (of frame time) tracking may stay lost, relocalisation failing on every frame,
    /// before a new map fragment is begun at the frame (ORB-SLAM3's Atlas starts a new map
    /// when it cannot relocalise; LSD-SLAM stays lost until the camera returns). The fragment is
    /// placed where the camera was last seen and merged into the map when the back end finds a
    /// constraint between them (`graph::Backend`). 0 = never. Default 2 s: long enough for
    /// relocalisation to find a camera that comes straight back (docs/tuning.md, "Map
    /// fragments").
    pub new_fragment_after_lost_s: f64,
    /// Start tracking from a constant-velocity prediction (the last inter-frame motion applied
    /// once more), falling back to the last pose when that fails. Default false, LSD-SLAM's
    /// behaviour (start from the last pose): it did not help overall (docs/tuning.md,
    /// "Constant velocity").
    pub constant_velocity: bool,
    /// Fill the holes of each new keyframe's propagated depth from the depth prior, aligned to
    /// the propagated estimates with eq. (3) (`DepthFilter::fill_from_prior`; at their median
    /// where the prior's depth order contradicts them), when a prior is loaded. Default true:
    /// under rotation the propagated map thins out keyframe after keyframe until tracking
    /// fails on a correct pose; the prior is the information the paper's dense layer adds
    /// (IROS 2021 §III).
    pub prior_fill: bool,
    /// Variance of prior-filled inverse depths (normalised scale). Default 0.1, the variance of
    /// the prior initialisation (`prior_init_var`): the aligned prior is about as reliable as
    /// the raw one, and stereo searches them within ±2σ.
    pub prior_fill_var: f32,
    /// Validity counter of prior-filled hypotheses. Default 5, LSD-SLAM's
    /// `VALIDITY_COUNTER_INITIAL_OBSERVE` (what one stereo match earns): a filled region
    /// survives regularisation (5×5 sum ≥ `val_sum_min_for_keep` = 24) but a few failed
    /// observations remove it.
    pub prior_fill_validity: i32,
    /// Fewest propagated estimates the eq. (3) fit needs before the prior is written into a
    /// keyframe. Default 1000 (0.3 % of a 640×480 image): fewer points cannot pin down the
    /// scale and shift of the whole prior.
    pub prior_fill_min_pixels: usize,
    /// The prior fills a new keyframe only when its propagated estimates cover at most this
    /// share of the usable (textured) pixels. Default 0.5: translating hand-held motion keeps
    /// ~80 % and filling the rest made things worse; under rotation coverage falls to
    /// 15–40 % before tracking runs out of points (docs/tuning.md, "Prior hole filling").
    pub prior_fill_max_coverage: f32,
    /// Old keyframes tried, nearest first, before a new keyframe is made: when the camera is
    /// back where one of them was, tracking against it is good and it would not need
    /// replacing, it becomes the current keyframe again instead (LSD-SLAM's
    /// `doKFReActivation`, `SlamSystem::changeKeyframe`). A camera that keeps revisiting a
    /// place then stops adding keyframes for it, so memory, the back end's searches and the
    /// final optimisation stop growing with the session's length (issue 37). 0 = never.
    /// Default 0: with 3 it saved 30 % of a looping path's keyframes, but the aggregate ATE
    /// was 1.7 % worse and the loop's 5-14 % (docs/tuning.md, "Keyframe re-activation");
    /// LSD-SLAM's own acceptance tests did not help (docs/tuning.md, "thirtieth stop").
    pub reactivation_candidates: usize,
}

impl PipelineConfig {
    /// Whether the current keyframe is mapped on its own thread: `mapping_thread`, except in
    /// deterministic mode, which always maps in step.
    pub fn maps_on_thread(&self) -> bool {
        self.mapping_thread && !self.deterministic
    }
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self {
            frontend: Frontend::Lsd,
            init: DepthInit::Prior,
            prior_init_var: 0.1,
            deterministic: false,
            mapping_thread: false,
            mapping_thread_workers: 1,
            mapping_queue: 8,
            seed: 0,
            relocalisation_candidates: 8,
            new_fragment_after_lost_s: 2.0,
            constant_velocity: false,
            prior_fill: true,
            prior_fill_var: 0.1,
            prior_fill_validity: 5,
            prior_fill_min_pixels: 1000,
            prior_fill_max_coverage: 0.5,
            reactivation_candidates: 0,
        }
    }
}

/// Most old keyframes one keyframe decision tracks against (each costs a tracking).
pub const MAX_REACTIVATION_CANDIDATES: usize = 16;

/// Every parameter of the SLAM pipeline.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub pipeline: PipelineConfig,
    pub tracking: TrackingConfig,
    pub mapping: MappingConfig,
    pub backend: BackendConfig,
    /// The dense layer (DeepRelativeFusion §III-B..E).
    pub dense: DenseConfig,
    /// TSDF fusion of the dense keyframes and meshing (§III-F).
    pub fusion: crate::fusion::FusionConfig,
    /// Localisation in a saved map (`relfusion run --map … --mode localize`; also how
    /// `--mode extend` finds its first frame in the map).
    pub localize: crate::map::LocalizeConfig,
    /// Extending a saved map (`relfusion run --map … --mode extend`).
    pub extend: super::ExtendConfig,
    /// The DSO-class odometry, when it is the front end (`pipeline.frontend = "dso"`).
    pub odometry: crate::odometry::OdometryConfig,
}

impl Config {
    /// Parses a TOML or JSON config (by extension; TOML otherwise); missing keys keep defaults.
    pub fn load(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let config: Config = if path.extension().is_some_and(|e| e == "json") {
            serde_json::from_str(&text)
                .map_err(|e| Error::Config(format!("{}: {e}", path.display())))?
        } else {
            toml::from_str(&text).map_err(|e| Error::Config(format!("{}: {e}", path.display())))?
        };
        config.validate()?;
        Ok(config)
    }

    /// Checks every section.
    pub fn validate(&self) -> Result<()> {
        if !(self.pipeline.prior_init_var.is_finite() && self.pipeline.prior_init_var > 0.0) {
            return Err(Error::Config("pipeline.prior_init_var must be > 0".into()));
        }
        if !(self.pipeline.prior_fill_var.is_finite() && self.pipeline.prior_fill_var > 0.0) {
            return Err(Error::Config("pipeline.prior_fill_var must be > 0".into()));
        }
        let fragment = self.pipeline.new_fragment_after_lost_s;
        if !(fragment.is_finite() && fragment >= 0.0) {
            return Err(Error::Config(
                "pipeline.new_fragment_after_lost_s must be ≥ 0".into(),
            ));
        }
        if !(1..=256).contains(&self.pipeline.mapping_queue) {
            return Err(Error::Config(
                "pipeline.mapping_queue must be in 1..=256 frames".into(),
            ));
        }
        if self.pipeline.reactivation_candidates > MAX_REACTIVATION_CANDIDATES {
            return Err(Error::Config(format!(
                "pipeline.reactivation_candidates must be at most {MAX_REACTIVATION_CANDIDATES}"
            )));
        }
        if self.pipeline.frontend == Frontend::Dso {
            self.odometry.validate()?;
            if !self.odometry.focal_candidates.is_empty() {
                return Err(Error::Config(
                    "odometry.focal_candidates: the pipeline takes the camera as given".into(),
                ));
            }
        }
        self.tracking.validate()?;
        self.localize.validate()?;
        self.mapping.validate()?;
        self.backend.validate()?;
        self.dense.validate()?;
        self.fusion.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_config_round_trips_and_rejects_unknown_keys() {
        let text = toml::to_string(&Config::default()).expect("serialise");
        let back: Config = toml::from_str(&text).expect("parse");
        assert_eq!(back, Config::default());
        assert!(toml::from_str::<Config>("[pipeline]\nseeed = 3\n").is_err());
        let partial: Config = toml::from_str("[pipeline]\nseed = 3\n").expect("partial");
        assert_eq!(partial.pipeline.seed, 3);
        assert_eq!(partial.tracking, TrackingConfig::default());
    }
}
