//! The back end: keyframe store, constraint search and pose-graph optimisation, run either
//! synchronously ([`Backend::process`], deterministic) or on its own thread behind a bounded
//! channel ([`super::BackendLink`]), so that it never blocks the frame path (LSD-SLAM runs the
//! same work in its `constraintSearchThread` and `optimizationThread`).
//!
//! Flow per keyframe: the pipeline sends it once its depth map is final (when the *next*
//! keyframe is created), with the tracking estimate of its pose relative to its parent. The
//! back end inserts a vertex at `world_from_parent · parent_from_keyframe` (using the parent's
//! *optimised* pose), searches constraints (the forced parent constraint, pose-proximity and
//! appearance candidates, each verified by the reciprocal test), adds every accepted pair of
//! edges and re-optimises the graph when edges were added. A later depth update of a keyframe
//! (DeepRelativeFusion's refined depth) re-estimates the constraints it takes part in.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::KeyframeId;
use super::config::BackendConfig;
use super::pose_graph::{Constraint, OptimizeReport, PoseGraph, ScalePrior};
use super::resident::Resident;
use super::search::{CompactKeyframe, Keyframe, KeyframeData, KeyframeMaps, Thumbnail};
use super::sim3_tracker::Sim3Tracker;
use crate::frame::Frame;
use nalgebra::Matrix6;

use crate::geometry::{Information7, Matrix7, Sim3};
use crate::mapping::{CompactDepth, DepthMap};
use crate::metric_scale::ScaleObservation;
use crate::{Error, Result};

mod candidates;
mod edges;
mod schedule;
pub use schedule::Budget;

/// The tracking estimate of a new keyframe relative to the keyframe it was tracked against.
#[derive(Clone, Debug, PartialEq)]
pub struct ParentEdge {
    pub id: KeyframeId,
    /// Maps the new keyframe's coordinates to the parent's (including the depth-scale change
    /// of the new keyframe's normalised map).
    pub parent_from_keyframe: Sim3,
    /// Information of a right perturbation of `parent_from_keyframe`, used as the parent edge
    /// only if the reciprocal Sim(3) test on the parent fails (LSD-SLAM's fallback odometry
    /// edge). It must be positive definite, including the scale entry.
    pub information: Information7,
    /// The front end's estimate is better than a Sim(3) alignment of the two depth maps
    /// could make it (a window's joint optimisation of poses and depths, `pipeline.frontend
    /// = "dso"`): it is the edge, neither tested nor re-estimated after depth updates.
    pub trusted: bool,
}

/// Scale information of an odometry edge built from SE(3) tracking, relative to the mean of its
/// translation informations: 0.02, the ratio in LSD-SLAM's hard-coded fallback edge
/// (`findConstraintsForNewKeyFrames`: 0.0228 against ≈ 1.08).
pub const SE3_EDGE_SCALE_INFORMATION_RATIO: f64 = 0.02;

impl ParentEdge {
    /// A parent edge from SE(3) tracking, whose 6×6 information (ρ, φ) says nothing about the
    /// scale: it is embedded in the (ρ, φ) block (a Sim(3) tangent with σ = 0 is the SE(3)
    /// one) and the scale gets [`SE3_EDGE_SCALE_INFORMATION_RATIO`] × the mean translation
    /// information.
    pub fn from_se3_information(
        id: KeyframeId,
        parent_from_keyframe: Sim3,
        information: &Matrix6<f64>,
    ) -> Self {
        let mut info = Matrix7::zeros();
        info.fixed_view_mut::<6, 6>(0, 0).copy_from(information);
        let mean_translation =
            (information[(0, 0)] + information[(1, 1)] + information[(2, 2)]) / 3.0;
        info[(6, 6)] = SE3_EDGE_SCALE_INFORMATION_RATIO * mean_translation.max(0.0);
        Self {
            id,
            parent_from_keyframe,
            information: info.into(),
            trusted: false,
        }
    }
}

/// A finalised keyframe handed to the back end.
#[derive(Clone, Debug)]
pub struct NewKeyframe {
    pub id: KeyframeId,
    /// Its frame and depth map, and their compact form when the caller keeps it (shared, and
    /// spilled once, instead of made again).
    pub maps: KeyframeMaps,
    /// The front end's estimate; used as the vertex's initial pose when there is no parent in
    /// the graph.
    pub world_from_keyframe: Sim3,
    pub parent: Option<ParentEdge>,
    /// The tracking estimate relative to the old keyframe that took over tracking from this
    /// one (the front end re-activated it, `pipeline.reactivation`): the frame that chose it
    /// was tracked against both. Tested and used like the parent edge; without it the chain of
    /// new keyframes would join the old one only through a constraint search.
    pub handover: Option<ParentEdge>,
    /// The descriptor of the same image when the caller has it: shared, so a keyframe keeps
    /// one copy (3 kB; issue 37). `None` computes it.
    pub thumbnail: Option<Thumbnail>,
}

/// What one [`Backend::process`] call did.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ProcessReport {
    /// Keyframes whose constraints were searched.
    pub keyframes_searched: usize,
    /// Reciprocal tests run (parent included).
    pub candidates_tested: usize,
    /// Pairs of edges accepted by the reciprocal test (parent included).
    pub constraints_accepted: usize,
    /// Parent edges added from the front end's estimate after a failed test.
    pub fallback_parent_edges: usize,
    /// Existing pairs of edges re-estimated after a depth update (and replaced).
    pub constraints_refreshed: usize,
    /// Fragments joined to an older one by a constraint found between them.
    pub fragments_merged: usize,
    /// Keyframes searched against their parent only, their full search deferred, because the
    /// back end was behind ([`Budget::Behind`]).
    pub searches_deferred: usize,
    /// Deferred searches and depth refreshes given up because more than
    /// [`BackendConfig::deferred_max`] were waiting (their keyframes stay candidates of later
    /// searches).
    pub searches_dropped: usize,
    /// The optimisation run, if any.
    pub optimize: Option<OptimizeReport>,
    /// The windowed bundle adjustment run, if any.
    #[serde(skip)]
    pub window: Option<crate::window::SolveReport>,
}

/// The back end's keyframes and what they hold ([`Backend::memory`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyframeMemory {
    pub keyframes: usize,
    /// Held in full (pyramid and alignment levels).
    pub resident: usize,
    /// Full forms rebuilt from compact ones so far.
    pub rebuilds: usize,
    /// Bytes of every keyframe's compact form held in memory (images and depth maps shared
    /// with the pipeline counted here in full).
    pub compact_bytes: usize,
    /// Keyframes whose compact form is spilled to the session's store.
    pub spilled: usize,
    /// Bytes the resident full forms add.
    pub resident_bytes: usize,
    /// Pose-graph edges between keyframes more than `resident_keyframes + held_keyframes`
    /// apart: loop closures and re-visits that reached past the working set (to keyframes
    /// that were spilled or compact when they were found).
    pub far_edges: usize,
    /// Full constraint searches deferred while the back end is behind (`schedule`).
    pub searches_deferred: usize,
    /// Deferred searches and refreshes given up so far.
    pub searches_given_up: usize,
    /// Pose-graph optimisations of the whole graph so far, and of a bounded neighbourhood
    /// (`BackendConfig::live_optimization_vertices`).
    #[serde(default)]
    pub optimizations_full: usize,
    #[serde(default)]
    pub optimizations_bounded: usize,
    /// Commands queued for the back end's thread and not yet handled (0 in step): a back end
    /// fallen behind holds their keyframes' compact forms and depth.
    #[serde(default)]
    pub commands_waiting: usize,
}

/// Graph bookkeeping of one keyframe.
#[derive(Clone, Debug)]
struct Entry {
    /// The keyframe between uses; its full form is in [`Backend::resident`] or rebuilt.
    kept: CompactKeyframe,
    /// Insertion index (LSD-SLAM's `idxInKeyframes`).
    order: usize,
    /// Boxed, as `handover`: every keyframe keeps its entry for the whole session, and inline
    /// the two took 2 × 472 B of it, though few keyframes have a hand-over (issue 37).
    parent: Option<Box<ParentEdge>>,
    /// See [`NewKeyframe::handover`].
    handover: Option<Box<ParentEdge>>,
    /// Keyframes joined to this one by an edge.
    neighbours: BTreeSet<KeyframeId>,
    /// Candidates whose test failed, with the initial relative pose tried.
    failed: Vec<(KeyframeId, Sim3)>,
    /// The fragment it belongs to: the id of the fragment's first keyframe. A keyframe without
    /// a parent starts a fragment (the session's first keyframe, or a new map begun after
    /// tracking was lost for good); a constraint between two fragments merges them.
    fragment: KeyframeId,
}

impl Entry {
    /// The edges the front end measured by tracking: the parent's, then the hand-over's.
    fn tracked(&self) -> impl Iterator<Item = &ParentEdge> {
        self.parent.iter().chain(&self.handover).map(|p| &**p)
    }
}

/// The back end (see the module docs).
#[derive(Debug)]
pub struct Backend {
    config: BackendConfig,
    tracker: Sim3Tracker,
    graph: PoseGraph,
    keyframes: BTreeMap<KeyframeId, Entry>,
    /// The most recently used keyframes in full.
    resident: Resident,
    pending: Vec<KeyframeId>,
    /// Keyframes whose depth changed: their existing constraints are re-estimated.
    refresh: Vec<KeyframeId>,
    /// Keyframes searched only against their parent while the back end was behind, oldest
    /// first: their full search follows when it catches up ([`Budget`]).
    deferred: std::collections::VecDeque<KeyframeId>,
    /// Deferred searches and refreshes given up so far.
    searches_given_up: usize,
    /// Optimisations run so far: of the whole graph, of a bounded neighbourhood.
    optimizations: [usize; 2],
    /// The window's edge of each consecutive pair `(newer, older)` it optimised, as in the
    /// graph (replaced by the next window over the same pair).
    window_edges: HashMap<(KeyframeId, KeyframeId), Constraint>,
    /// A scale factor changed since the last optimisation.
    scale_observed: bool,
}

impl Backend {
    /// An empty back end (validates `config`).
    pub fn new(config: BackendConfig) -> Result<Self> {
        config.validate()?;
        let mut graph = PoseGraph::new(config.pose_graph_huber);
        let metric = &config.metric_scale;
        graph.set_edge_scale_sigma(metric.enabled.then_some(metric.edge_scale_sigma))?;
        graph.set_loop_pass_growth(config.loop_pass_growth)?;
        Ok(Self {
            tracker: Sim3Tracker::new(config.clone()),
            graph,
            resident: Resident::new(config.resident_keyframes),
            config,
            keyframes: BTreeMap::new(),
            pending: Vec::new(),
            refresh: Vec::new(),
            deferred: std::collections::VecDeque::new(),
            searches_given_up: 0,
            optimizations: [0; 2],
            window_edges: HashMap::new(),
            scale_observed: false,
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &BackendConfig {
        &self.config
    }

    /// Inserts a keyframe as a vertex; its constraints are searched by the next
    /// [`Backend::process`]. Fails for a duplicate id or a depth map of the wrong size.
    pub fn add_keyframe(&mut self, new: NewKeyframe) -> Result<()> {
        if self.keyframes.contains_key(&new.id) {
            return Err(Error::Backend(format!("keyframe {} added twice", new.id)));
        }
        let finest = self.config.finest_level();
        let (frame, depth, data) = new.maps.resolve()?;
        let mut keyframe = Keyframe::from_level(new.id, frame, depth, finest)?;
        if let Some(thumbnail) = new.thumbnail {
            keyframe.thumbnail = thumbnail;
        }
        let kept = keyframe.compact_sharing(data);
        let parent = new.parent.as_ref().and_then(|p| {
            Some((
                self.graph.pose(p.id)?,
                self.keyframes.get(&p.id)?.fragment,
                p,
            ))
        });
        let (initial, fragment) = match parent {
            Some((world_from_parent, fragment, p)) => {
                (world_from_parent * p.parent_from_keyframe, fragment)
            }
            None => (new.world_from_keyframe, new.id),
        };
        self.graph.add_vertex(new.id, initial);
        if fragment == new.id {
            // A fragment's first keyframe fixes its gauge until it is merged into another.
            self.graph.set_fixed(new.id, true)?;
        }
        let order = self.keyframes.len();
        self.keyframes.insert(
            new.id,
            Entry {
                kept,
                order,
                parent: new.parent.map(Box::new),
                handover: new.handover.map(Box::new),
                neighbours: BTreeSet::new(),
                failed: Vec::new(),
                fragment,
            },
        );
        self.pending.push(new.id);
        self.resident.insert(keyframe);
        self.spill_old();
        Ok(())
    }

    /// Inserts a keyframe of a saved map (`crate::map`) at its saved pose: no constraint
    /// search (its edges come with the map, [`Backend::add_map_edge`]); `fixed` holds the pose
    /// constant in every later optimisation; `data` is its image and `depth` in compact form
    /// when the caller keeps them.
    pub fn add_map_keyframe(
        &mut self,
        id: KeyframeId,
        frame: Arc<Frame>,
        depth: Arc<DepthMap>,
        data: Option<KeyframeData>,
        world_from_keyframe: Sim3,
        fixed: bool,
    ) -> Result<()> {
        if self.keyframes.contains_key(&id) {
            return Err(Error::Backend(format!("keyframe {id} added twice")));
        }
        let keyframe = Keyframe::from_level(id, frame, depth, self.config.finest_level())?;
        let kept = keyframe.compact_sharing(data);
        self.graph.add_vertex(id, world_from_keyframe);
        self.graph.set_fixed(id, fixed || self.graph.len() == 1)?;
        let order = self.keyframes.len();
        // A saved map is one fragment: the one of its first keyframe.
        let fragment = self
            .keyframes
            .values()
            .map(|e| e.fragment)
            .min()
            .unwrap_or(id);
        self.keyframes.insert(
            id,
            Entry {
                kept,
                order,
                parent: None,
                handover: None,
                neighbours: BTreeSet::new(),
                failed: Vec::new(),
                fragment,
            },
        );
        self.resident.insert(keyframe);
        self.spill_old();
        Ok(())
    }

    /// Spills the compact data of keyframes older than the newest `resident_keyframes +
    /// held_keyframes` to the session's store (`crate::spill`; nothing happens without one).
    fn spill_old(&self) {
        let keep = self.config.resident_keyframes + self.config.held_keyframes;
        let old = self.keyframes.len().saturating_sub(keep);
        for entry in self.keyframes.values().filter(|e| e.order < old) {
            entry.kept.data.spill();
        }
    }

    /// Adds an edge of a saved map between two of its keyframes (both already inserted).
    pub fn add_map_edge(&mut self, edge: Constraint) -> Result<()> {
        self.link(edge.from, edge.to);
        self.graph.add_edge(edge)
    }

    /// Puts a saved map's scale factor on its keyframe `id` (already inserted) back into the
    /// graph (ignored when `metric_scale.enabled` is off, as [`Backend::observe_scale`]); the
    /// next [`Backend::process`] optimises.
    pub fn add_map_scale_prior(&mut self, id: KeyframeId, prior: ScalePrior) -> Result<()> {
        if !self.config.metric_scale.enabled {
            return Ok(());
        }
        self.graph.set_scale_prior(id, Some(prior))?;
        self.scale_observed = true;
        Ok(())
    }

    /// Replaces the depth map of keyframe `id` — e.g. DeepRelativeFusion's two-view consistent
    /// densified depth (§III "Pose-graph refinement": "we update the Sim(3) constraints in the
    /// pose-graph to refine the keyframe poses") — and schedules the re-estimation of every
    /// constraint it takes part in by the next [`Backend::process`]: each pair of edges with a
    /// neighbour is re-tested from the current relative pose and replaced when the reciprocal
    /// test accepts it (kept otherwise). A keyframe still pending simply uses the new depth.
    pub fn update_keyframe_depth(&mut self, id: KeyframeId, depth: Arc<DepthMap>) -> Result<()> {
        let entry = self
            .keyframes
            .get_mut(&id)
            .ok_or_else(|| Error::Backend(format!("depth update for unknown keyframe {id}")))?;
        let frame = Arc::clone(&self.resident.get(&entry.kept)?.frame);
        let mut keyframe = Keyframe::from_level(id, frame, depth, self.config.finest_level())?;
        // The same image: its descriptor stays the one copy the pipeline's record shares
        // (a second one per keyframe was 3 kB of a long session's growth; issue 37).
        keyframe.thumbnail = entry.kept.thumbnail.clone();
        let data = entry
            .kept
            .data
            .with_depth(CompactDepth::of(&keyframe.depth));
        entry.kept = keyframe.compact_sharing(Some(data));
        self.resident.insert(keyframe);
        entry.failed.clear();
        if !self.pending.contains(&id) && !self.refresh.contains(&id) {
            self.refresh.push(id);
        }
        self.spill_old();
        Ok(())
    }

    /// A metric prior observed keyframe `id`'s scale: it becomes (or replaces) the vertex's
    /// unary scale factor ([`super::config::MetricScaleConfig::factor`]; ignored when too few
    /// pixels voted or `metric_scale.enabled` is off), and the next [`Backend::process`]
    /// optimises.
    pub fn observe_scale(&mut self, id: KeyframeId, obs: &ScaleObservation) -> Result<()> {
        let config = &self.config.metric_scale;
        if !config.enabled {
            return Ok(());
        }
        let Some(factor) = config.factor(obs) else {
            return Ok(());
        };
        self.graph.set_scale_prior(id, Some(factor))?;
        self.scale_observed = true;
        Ok(())
    }

    /// Runs the windowed bundle adjustment over the latest keyframes (from their graph poses)
    /// and puts its relative Sim(3) of each consecutive pair into the graph, replacing the
    /// previous window's edge of that pair. The edge's information is
    /// [`crate::window::WindowConfig::edge_weight`] times that of the pair's strongest Sim(3)
    /// edge. Returns whether edges changed.
    pub(super) fn run_window(&mut self, report: &mut ProcessReport) -> Result<bool> {
        let config = &self.config.window;
        // Only the newest keyframe's fragment: poses of another are in another frame.
        let Some(newest) = self.keyframes.values().max_by_key(|e| e.order) else {
            return Ok(false);
        };
        let fragment = newest.fragment;
        let mut ids: Vec<(usize, KeyframeId)> = self
            .keyframes
            .iter()
            .filter(|(_, e)| e.fragment == fragment)
            .map(|(id, e)| (e.order, *id))
            .collect();
        ids.sort_unstable();
        let ids: Vec<KeyframeId> = ids
            .iter()
            .rev()
            .take(config.keyframes)
            .rev()
            .map(|(_, id)| *id)
            .collect();
        if ids.len() < config.keyframes {
            return Ok(false);
        }
        let mut full = Vec::with_capacity(ids.len());
        for &id in &ids {
            let Some(pose) = self.graph.pose(id) else {
                return Ok(false);
            };
            full.push((self.resident.get(&self.keyframes[&id].kept)?, pose));
        }
        let members: Vec<_> = full
            .iter()
            .map(|(kf, pose)| crate::window::WindowKeyframe {
                id: kf.id,
                frame: &kf.frame,
                depth: &kf.depth,
                world_from_keyframe: *pose,
            })
            .collect();
        let Some(result) = crate::window::optimize_window(config, &members) else {
            return Ok(false);
        };
        report.window = Some(result.report);
        tracing::debug!(
            keyframes = ?ids,
            points = result.points,
            initial_cost = result.report.initial_cost,
            final_cost = result.report.final_cost,
            iterations = result.report.iterations,
            scale_change = ?result
                .poses
                .iter()
                .map(|(id, p)| self.graph.pose(*id).map_or(1.0, |g| p.scale / g.scale))
                .collect::<Vec<_>>(),
            "window bundle adjustment"
        );
        let mut changed = false;
        for pair in result.poses.windows(2) {
            let ((older, world_from_older), (newer, world_from_newer)) = (pair[0], pair[1]);
            let strongest = self
                .graph
                .edges()
                .iter()
                .filter(|e| e.from == newer && e.to == older)
                .filter(|e| self.window_edges.get(&(newer, older)) != Some(e))
                .max_by(|a, b| a.information.trace().total_cmp(&b.information.trace()))
                .map(|e| e.information);
            let Some(information) = strongest else {
                continue;
            };
            let edge = Constraint {
                from: newer,
                to: older,
                to_from_from: world_from_older.inverse() * world_from_newer,
                information: information.scaled(config.edge_weight),
            };
            if let Some(old) = self.window_edges.remove(&(newer, older)) {
                self.graph.remove_edge(&old);
            }
            self.graph.add_edge(edge.clone())?;
            self.window_edges.insert((newer, older), edge);
            changed = true;
        }
        Ok(changed)
    }

    /// Processes pending keyframes, then optimises the graph regardless of new edges (the final
    /// optimisation of a session, or [`BackendCommand::Optimize`]).
    pub fn optimize_full(&mut self) -> Result<OptimizeReport> {
        let report = self.process()?;
        match report.optimize {
            Some(r) => Ok(r),
            None => self.optimize_within(Budget::All),
        }
    }

    /// The current `world_from_keyframe` of every keyframe.
    pub fn poses(&self) -> HashMap<KeyframeId, Sim3> {
        self.graph.poses()
    }

    /// The pose graph (vertices and edges).
    pub fn graph(&self) -> &PoseGraph {
        &self.graph
    }

    /// All edges in insertion order.
    pub fn constraints(&self) -> &[Constraint] {
        self.graph.edges()
    }

    /// The edges keyframe `id` takes part in (either end), in insertion order; their
    /// informations give the pose uncertainty DeepRelativeFusion propagates into the dense
    /// depth's variance (§III "Pose-graph refinement", `Σ_ξ`).
    pub fn constraints_of(&self, id: KeyframeId) -> impl Iterator<Item = &Constraint> + '_ {
        self.graph
            .edges()
            .iter()
            .filter(move |c| c.from == id || c.to == id)
    }

    /// What the back end's keyframes hold (issue 37).
    pub fn memory(&self) -> KeyframeMemory {
        KeyframeMemory {
            keyframes: self.keyframes.len(),
            resident: self.resident.len(),
            rebuilds: self.resident.rebuilds(),
            compact_bytes: self.keyframes.values().map(|e| e.kept.heap_bytes()).sum(),
            spilled: self
                .keyframes
                .values()
                .filter(|e| !e.kept.data.is_held())
                .count(),
            resident_bytes: self.resident.heap_bytes(),
            far_edges: {
                let window = self.config.resident_keyframes + self.config.held_keyframes;
                let graph = self.graph();
                graph
                    .edges()
                    .iter()
                    .filter(|e| e.from.abs_diff(e.to) > window)
                    .count()
            },
            searches_deferred: self.deferred.len(),
            searches_given_up: self.searches_given_up,
            optimizations_full: self.optimizations[0],
            optimizations_bounded: self.optimizations[1],
            commands_waiting: 0,
        }
    }

    /// Keyframes whose constraint search has not run yet.
    pub fn pending(&self) -> &[KeyframeId] {
        &self.pending
    }

    /// When `edge` joins two fragments, moves the younger one (the larger first id) into the
    /// older one's frame by the similarity the edge implies and releases its gauge: from then
    /// on the optimisation treats them as one map. Returns whether it merged.
    fn merge_fragments(&mut self, edge: &Constraint) -> Result<bool> {
        let fragment = |id: KeyframeId| self.keyframes.get(&id).map(|e| e.fragment);
        let (Some(from), Some(to)) = (fragment(edge.from), fragment(edge.to)) else {
            return Ok(false);
        };
        if from == to {
            return Ok(false);
        }
        let (Some(world_from_a), Some(world_from_b)) =
            (self.graph.pose(edge.from), self.graph.pose(edge.to))
        else {
            return Ok(false);
        };
        // Maps the `from` fragment's frame into the `to` fragment's.
        let to_world_from_from_world = world_from_b * edge.to_from_from * world_from_a.inverse();
        let (keep, moved, transform) = if to < from {
            (to, from, to_world_from_from_world)
        } else {
            (from, to, to_world_from_from_world.inverse())
        };
        let members: Vec<KeyframeId> = self
            .keyframes
            .iter()
            .filter(|(_, e)| e.fragment == moved)
            .map(|(id, _)| *id)
            .collect();
        for id in members {
            if let Some(pose) = self.graph.pose(id) {
                self.graph.add_vertex(id, transform * pose);
            }
            if let Some(e) = self.keyframes.get_mut(&id) {
                e.fragment = keep;
            }
        }
        self.graph.set_fixed(moved, false)?;
        tracing::info!(kept = keep, merged = moved, "map fragments merged");
        Ok(true)
    }

    /// The fragment of every keyframe (the id of its fragment's first keyframe).
    pub fn fragments(&self) -> HashMap<KeyframeId, KeyframeId> {
        self.keyframes
            .iter()
            .map(|(id, e)| (*id, e.fragment))
            .collect()
    }

    fn link(&mut self, a: KeyframeId, b: KeyframeId) {
        if let Some(e) = self.keyframes.get_mut(&a) {
            e.neighbours.insert(b);
        }
        if let Some(e) = self.keyframes.get_mut(&b) {
            e.neighbours.insert(a);
        }
    }
}
