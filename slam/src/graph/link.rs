//! The back end as a background [`Service`] ([`BackendLink`]): in step with the frames
//! (deterministic runs) or on its own thread, where it processes the commands that queued up
//! while it worked as one batch, within a [`Budget`] that the batch's new keyframes set (so
//! a back end that fell behind catches up instead of stalling the frame path), and publishes
//! the optimised poses after each.

use std::collections::HashMap;
use std::sync::{Arc, RwLock};

use super::KeyframeId;
use super::backend::{Backend, Budget, KeyframeMemory, NewKeyframe};
use super::config::BackendConfig;
use crate::Result;
use crate::background::{Link, Priority, Service, WorkerSpec};
use crate::geometry::Sim3;
use crate::mapping::CompactDepth;

/// What the back end is asked to do.
#[derive(Debug)]
pub enum BackendCommand {
    AddKeyframe(Box<NewKeyframe>),
    /// Replace a keyframe's depth map and re-estimate the constraints it takes part in
    /// ([`Backend::update_keyframe_depth`]). The map waits in the queue in its compact form
    /// (a quarter of the full one for semi-dense depth; expanded unchanged).
    UpdateDepth {
        id: KeyframeId,
        depth: CompactDepth,
    },
    /// A metric prior's observation of a keyframe's scale ([`Backend::observe_scale`]).
    ObserveScale {
        id: KeyframeId,
        observation: crate::metric_scale::ScaleObservation,
    },
    /// Process pending keyframes, then optimise the whole graph even without new edges.
    Optimize,
    /// Nothing new: a pass that takes deferred searches. A camera that re-activates old
    /// keyframes sends no new ones, and without this the back end would get no pass to catch
    /// up in until the session ends.
    CatchUp,
}

/// The latest optimised poses, published after every batch.
type Published = Arc<RwLock<HashMap<KeyframeId, Sim3>>>;

/// The back end with its published poses.
#[derive(Debug)]
pub struct BackendService {
    backend: Backend,
    published: Published,
    /// Its memory figures after the latest batch, readable while it runs on its thread.
    memory: Arc<std::sync::Mutex<KeyframeMemory>>,
}

impl Service for BackendService {
    type Job = BackendCommand;
    type Reply = ();
    const BATCH: bool = true;

    /// Applies the batch (every command is tried: one rejected keyframe does not hold up the
    /// others), then processes, or optimises fully when asked, and publishes the poses.
    fn handle(&mut self, commands: Vec<BackendCommand>, _: &mut dyn FnMut(())) -> Result<()> {
        let mut first_error = None;
        let mut optimize = false;
        let new_keyframes = commands
            .iter()
            .filter(|c| matches!(c, BackendCommand::AddKeyframe(_)))
            .count();
        let (batch, started) = (commands.len(), std::time::Instant::now());
        for command in commands {
            let applied = match command {
                BackendCommand::AddKeyframe(k) => self.backend.add_keyframe(*k),
                BackendCommand::UpdateDepth { id, depth } => self
                    .backend
                    .update_keyframe_depth(id, Arc::new(depth.expand())),
                BackendCommand::ObserveScale { id, observation } => {
                    self.backend.observe_scale(id, &observation)
                }
                BackendCommand::Optimize => {
                    optimize = true;
                    Ok(())
                }
                BackendCommand::CatchUp => Ok(()),
            };
            if let Err(e) = applied {
                tracing::error!(error = %e, "back end");
                first_error.get_or_insert(e);
            }
        }
        tracing::debug!(
            batch,
            new_keyframes,
            apply_ms = started.elapsed().as_millis() as u64,
            "back-end batch applied"
        );
        let processed = if optimize {
            self.backend.optimize_full().map(|_| ())
        } else {
            let budget = Budget::for_pass(new_keyframes, self.backend.config().catch_up_searches);
            self.backend.process_within(budget).map(|_| ())
        };
        if let Ok(mut poses) = self.published.write() {
            *poses = self.backend.poses();
        }
        if let Ok(mut memory) = self.memory.lock() {
            *memory = self.backend.memory();
        }
        match first_error {
            Some(e) => Err(e),
            None => processed,
        }
    }
}

/// The session's back end, in step or on its thread.
#[derive(Debug)]
pub struct BackendLink {
    link: Link<BackendService>,
    published: Published,
    memory: Arc<std::sync::Mutex<KeyframeMemory>>,
}

impl BackendLink {
    /// A back end with `config`, on its own thread when `threaded` (commands then wait only
    /// while [`BackendConfig::channel_capacity`] are queued).
    pub fn new(config: BackendConfig, threaded: bool) -> Result<Self> {
        Self::with_backend(Backend::new(config)?, threaded)
    }

    /// [`BackendLink::new`] around a back end that already holds keyframes (a loaded map).
    pub fn with_backend(backend: Backend, threaded: bool) -> Result<Self> {
        let spec = WorkerSpec {
            name: "backend",
            priority: Priority::Graph,
            queue: backend.config().channel_capacity,
        };
        let published = Published::default();
        let memory = Arc::new(std::sync::Mutex::new(backend.memory()));
        let service = BackendService {
            backend,
            published: published.clone(),
            memory: memory.clone(),
        };
        Ok(Self {
            link: Link::new(threaded, spec, move || Ok(service))?,
            published,
            memory,
        })
    }

    /// Queues a command (in step: runs it now; its error is the caller's). On a thread the
    /// error is logged and kept as [`BackendLink::last_error`].
    pub fn send(&mut self, command: BackendCommand) -> Result<()> {
        self.link.send(command)
    }

    /// Convenience for `send(AddKeyframe(..))`.
    pub fn add_keyframe(&mut self, keyframe: NewKeyframe) -> Result<()> {
        self.send(BackendCommand::AddKeyframe(Box::new(keyframe)))
    }

    /// The latest optimised poses (never waits for an optimisation).
    pub fn poses(&self) -> HashMap<KeyframeId, Sim3> {
        self.published.read().map(|p| p.clone()).unwrap_or_default()
    }

    /// The back end's memory figures: current when it is at hand, as of its latest batch
    /// while it runs on its thread.
    pub fn memory(&self) -> KeyframeMemory {
        match self.backend() {
            Some(backend) => backend.memory(),
            None => KeyframeMemory {
                commands_waiting: self.link.worker().map_or(0, |w| w.waiting() as usize),
                ..self.memory.lock().map(|m| *m).unwrap_or_default()
            },
        }
    }

    /// Commands handled so far on the thread (in step: 0).
    pub fn handled_commands(&self) -> u64 {
        self.link.worker().map_or(0, |w| w.handled())
    }

    /// The last error the thread met (e.g. a rejected keyframe), if any.
    pub fn last_error(&self) -> Option<String> {
        self.link.worker().and_then(|w| w.last_error())
    }

    /// Ends the session: processes what is queued, runs the final full optimisation, stops
    /// the thread and returns the final poses (also [`BackendLink::poses`] from then on).
    pub fn finish(&mut self) -> Result<HashMap<KeyframeId, Sim3>> {
        self.send(BackendCommand::Optimize)?;
        self.link.finish()?;
        Ok(self.poses())
    }

    /// The back end itself once it is at hand (in step, or after [`BackendLink::finish`]).
    pub fn backend(&self) -> Option<&Backend> {
        self.link.service().map(|s| &s.backend)
    }
}
