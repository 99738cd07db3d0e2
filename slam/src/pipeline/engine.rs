//! The one driver of the pipeline that every front end uses (`relfusion run`, a service
//! session): it maps from nothing, extends a saved map, or localises every frame in a saved
//! map that stays as it is, behind one interface — frames in, pipeline [`Event`]s out, the
//! final optimisation, and the results a run writes ([`Engine::trajectory_tum`], ...).
//!
//! A localised frame is reported as a pipeline pose event (`tracking` or `relocalized`, in the
//! map's frame; `lost`, at the identity, when the frame is not in the map), so a subscriber of
//! either kind of run reads one vocabulary.

use std::sync::Arc;

use super::{Config, Event, FrameInput, KeyframeMemory, KeyframePose, Pipeline, PoseEvent};
use super::{SemidenseSnapshot, Stats, TrackingState};
use crate::dense::DepthPrior;
use crate::error::Result;
use crate::geometry::{PinholeCamera, Sim3};
use crate::gpu::GpuContext;
use crate::map::{Localization, LocalizationState, Localizer, SavedMap};
use crate::spill::{Spill, SpillStore};

/// What a run starts from.
#[derive(Clone, Copy, Debug)]
pub enum Start<'a> {
    /// A new map.
    New,
    /// A saved map, extended: its keyframes join the pipeline, the back end and the fusion.
    Extend(&'a SavedMap),
    /// A saved map, left as it is: every frame is localised in it.
    Localize(&'a SavedMap),
}

/// The optimised keyframe poses and the events finishing produced.
pub type Finished = (Vec<KeyframePose>, Vec<Event>);

/// A mapping run's exported poses (timestamp, `world_from_camera`): every tracked frame's and
/// every keyframe's.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectories {
    pub frames: Vec<(f64, Sim3)>,
    pub keyframes: Vec<(f64, Sim3)>,
}

impl Trajectories {
    /// Both as TUM text, exactly as `relfusion run` writes them: the scale dropped (it acts on
    /// the map, not on the camera centre), values at full precision.
    pub fn tum(&self) -> (String, String) {
        let tum = |poses: &[(f64, Sim3)]| {
            crate::dataset::trajectory::format_tum_trajectory(
                &crate::dataset::trajectory::stamped_se3(poses),
            )
        };
        (tum(&self.frames), tum(&self.keyframes))
    }
}

/// A run of the pipeline or of a localiser.
#[derive(Debug)]
pub enum Engine {
    /// Mapping: tracking, mapping, pose graph, dense layer, fusion (from nothing, or on from a
    /// saved map).
    Map(Box<Pipeline>),
    /// Localising every frame in a saved map.
    Localize(Box<Localizing>),
}

/// A localiser's run.
#[derive(Debug)]
pub struct Localizing {
    localizer: Localizer,
    stats: Stats,
    /// The last frame's localisation (its score and reach, for a per-frame log).
    last: Option<Localization>,
}

impl Engine {
    /// A run from `start` for `camera` (a saved map must have been made with it), its kernels
    /// on `gpu` (`None`: the process's default context).
    pub fn start(
        config: &Config,
        camera: &PinholeCamera,
        prior: Option<Box<dyn DepthPrior>>,
        gpu: Option<Arc<GpuContext>>,
        start: Start<'_>,
    ) -> Result<Self> {
        match start {
            Start::New => Pipeline::with_gpu(config.clone(), *camera, prior, gpu)
                .map(|p| Engine::Map(Box::new(p))),
            Start::Extend(map) => Pipeline::extending(config.clone(), *camera, prior, gpu, map)
                .map(|p| Engine::Map(Box::new(p))),
            Start::Localize(map) => {
                let localizer =
                    Localizer::new(map, config.tracking.clone(), config.localize.clone())?;
                Ok(Engine::Localize(Box::new(Localizing {
                    localizer,
                    stats: Stats {
                        dense_mode: "off",
                        scale: super::scale_name(map.metric),
                        ..Stats::default()
                    },
                    last: None,
                })))
            }
        }
    }

    /// The mapping pipeline (`None` for a localiser).
    pub fn pipeline(&self) -> Option<&Pipeline> {
        match self {
            Engine::Map(pipeline) => Some(pipeline),
            Engine::Localize(_) => None,
        }
    }

    /// The mapping pipeline, to write its results (`None` for a localiser).
    pub fn pipeline_mut(&mut self) -> Option<&mut Pipeline> {
        match self {
            Engine::Map(pipeline) => Some(pipeline),
            Engine::Localize(_) => None,
        }
    }

    /// The last frame's localisation (a localiser's; `None` before the first frame).
    pub fn last_localization(&self) -> Option<&Localization> {
        match self {
            Engine::Map(_) => None,
            Engine::Localize(run) => run.last.as_ref(),
        }
    }

    /// One frame; what happened, as pipeline events.
    pub fn push(&mut self, input: FrameInput) -> Result<Vec<Event>> {
        match self {
            Engine::Map(pipeline) => pipeline.push(input),
            Engine::Localize(run) => {
                let Localizing {
                    localizer,
                    stats,
                    last,
                } = &mut **run;
                let t0 = std::time::Instant::now();
                let result = localizer.localize(input.timestamp, input.rgb)?;
                stats.frames += 1;
                stats.tracking_s += t0.elapsed().as_secs_f64();
                let state = match result.state {
                    LocalizationState::Tracked => TrackingState::Tracking,
                    LocalizationState::Relocalized => TrackingState::Relocalized,
                    LocalizationState::NotLocalized => TrackingState::Lost,
                };
                if state == TrackingState::Lost {
                    stats.frames_lost += 1;
                }
                let event = Event::Pose(PoseEvent {
                    frame_id: input.frame_id.unwrap_or(stats.frames as u64 - 1),
                    timestamp: result.timestamp,
                    world_from_camera: result.world_from_camera.unwrap_or_else(Sim3::identity),
                    state,
                    keyframe_id: result.keyframe.unwrap_or(0),
                    is_keyframe: false,
                });
                *last = Some(result);
                Ok(vec![event])
            }
        }
    }

    /// What the pipeline's background threads finished since the last frame (nothing for a
    /// localiser, which has none).
    pub fn poll(&mut self) -> Result<Vec<Event>> {
        match self {
            Engine::Map(pipeline) => pipeline.poll(),
            Engine::Localize(_) => Ok(Vec::new()),
        }
    }

    /// The final optimisation and what it produced after the frames (the last dense
    /// keyframes, the mesh at the final poses); nothing to do for a localiser.
    pub fn finish(&mut self) -> Result<Finished> {
        match self {
            Engine::Map(pipeline) => {
                let poses = pipeline.finish()?;
                Ok((pipeline.with_frames(poses), pipeline.take_events()))
            }
            Engine::Localize(_) => Ok((Vec::new(), Vec::new())),
        }
    }

    pub fn stats(&self) -> &Stats {
        match self {
            Engine::Map(pipeline) => pipeline.stats(),
            Engine::Localize(run) => &run.stats,
        }
    }

    /// What a mapping run's keyframes hold in memory and in the store.
    pub fn keyframe_memory(&self) -> Option<KeyframeMemory> {
        self.pipeline().map(Pipeline::keyframe_memory)
    }

    /// The run's spilling (a mapping run's; `None` for a localiser).
    pub fn spill(&self) -> Option<&Spill> {
        self.pipeline().map(Pipeline::spill)
    }

    /// Old keyframes spill to `store` (a mapping run; a localiser's map stays as loaded).
    pub fn attach_spill(&self, store: Arc<dyn SpillStore>) -> Result<()> {
        match self.spill() {
            Some(spill) => spill.attach(store),
            None => Ok(()),
        }
    }

    /// The keyframes of the map an extending run started from (timestamp and pose, by id);
    /// none otherwise.
    pub fn map_keyframes(&self) -> Vec<(f64, Sim3)> {
        match self.pipeline() {
            Some(pipeline) => {
                let mut poses = pipeline.keyframe_trajectory();
                poses.truncate(pipeline.map_keyframes());
                poses
            }
            None => Vec::new(),
        }
    }

    /// A mapping run's trajectory and keyframe poses as TUM text ([`Trajectories::tum`]);
    /// `None` for a localiser, whose trajectory is the poses it reported.
    pub fn trajectories_tum(&self) -> Result<Option<(String, String)>> {
        Ok(self.trajectories()?.as_ref().map(Trajectories::tum))
    }

    /// The poses [`Engine::trajectories_tum`] writes, to format elsewhere; `None` for a
    /// localiser.
    pub fn trajectories(&self) -> Result<Option<Trajectories>> {
        let Some(pipeline) = self.pipeline() else {
            return Ok(None);
        };
        Ok(Some(Trajectories {
            frames: pipeline.trajectory()?,
            keyframes: pipeline.keyframe_trajectory(),
        }))
    }

    /// What a mapping run's semi-dense points are built from ([`SemidenseSnapshot::points`],
    /// on this thread or another); `None` for a localiser.
    pub fn semidense_snapshot(&self) -> Option<SemidenseSnapshot> {
        self.pipeline().map(Pipeline::semidense_snapshot)
    }
}
