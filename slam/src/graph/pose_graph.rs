//! The keyframe pose graph on Sim(3) and its Levenberg–Marquardt optimisation (LSD-SLAM §3.5
//! "Map optimization", which uses g2o; DeepRelativeFusion keeps this back end).
//!
//! Vertices are `world_from_keyframe` similarities; an edge is a measured relative transform
//! `to_from_from` with its information matrix (from [`super::Sim3Tracker`]). With `i = to`,
//! `j = from` the residual is
//!
//! `r = log(T_ij⁻¹ · T_wi⁻¹ · T_wj) ∈ 𝔰𝔦𝔪(3)`,
//!
//! i.e. the measured relative pose is perturbed on the right to reach the estimated one,
//! matching the right-perturbation information of the tracker. With right increments
//! `T_wi ← T_wi·exp(δ_i)`, writing `E = T_wi⁻¹·T_wj` and `J_r⁻¹ = J_r⁻¹(r)`:
//!
//! - `∂r/∂δ_j = J_r⁻¹`  (since `Z⁻¹·E·exp(δ) = exp(r)·exp(δ)`),
//! - `∂r/∂δ_i = −J_r⁻¹·Ad(E⁻¹)`  (since `exp(−δ)·E = E·exp(−Ad(E⁻¹)·δ)`).
//!
//! The cost is `½ Σ ρ(rᵀ Ω r)` with g2o's Huber kernel ρ on the squared Mahalanobis norm. The
//! first vertex is held fixed (it fixes the 7-DoF gauge of a monocular map). The normal
//! equations are solved by the block-sparse Cholesky of [`super::cholesky`], those of a live
//! pass over a whole graph beyond the live bound by [`super::conjugate_gradients`].
//!
//! A vertex may also carry a unary [`ScalePrior`] (a metric depth prior's observation of its
//! scale, issue 39): `r = (ln s_i − ln m_i)/σ_i`. A right increment multiplies the scale by
//! `exp(δσ)`, so `∂r/∂δ = e_σᵀ/σ_i`, exactly. A fixed vertex with such a factor keeps only its
//! rotation and translation: the scale factors, not one keyframe, then fix the scale gauge.
//!
//! While scale factors are present, every edge's relative scale may be given an uncertainty
//! floor ([`PoseGraph::set_edge_scale_sigma`]): `Σ' = Σ + q²·e_σe_σᵀ`, i.e. (Sherman–Morrison)
//! `Ω' = Ω − q²·(Ωe_σ)(Ωe_σ)ᵀ / (1 + q²·Ω_σσ)`. A photometric Hessian claims a relative scale
//! to ~3·10⁻⁴ (information ~10⁷ on real video) while a monocular front end's scale drifts by
//! percents per keyframe; without the floor the factors (information 4–100) could not move it.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use serde::{Deserialize, Serialize};

use super::KeyframeId;
use super::cholesky::BlockSparseSymmetric;
use super::conjugate_gradients::CgStop;
use super::scope::{Changes, Whole, bounded_scope, pair};
use crate::geometry::{Information7, Matrix7, Sim3, Vector7};
use crate::{Error, Result};

/// A relative Sim(3) measurement between two keyframes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Constraint {
    pub from: KeyframeId,
    pub to: KeyframeId,
    /// Maps `from`-keyframe coordinates to `to`-keyframe coordinates.
    pub to_from_from: Sim3,
    /// Information (inverse covariance) of a right perturbation of `to_from_from`, tangent
    /// order (ρ, φ, σ); symmetric, so kept as its upper triangle.
    pub information: Information7,
}

/// A unary factor on one vertex's scale: `ln s ≈ log_scale` with standard deviation `sigma`,
/// under a Huber kernel of width `huber` (in units of σ).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScalePrior {
    pub log_scale: f64,
    pub sigma: f64,
    pub huber: f64,
}

impl ScalePrior {
    /// The normalised residual `(ln s − log_scale)/σ` at `pose`.
    fn residual(&self, pose: &Sim3) -> f64 {
        (pose.scale.ln() - self.log_scale) / self.sigma
    }
}

/// One keyframe pose of the graph.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Vertex {
    pub world_from_keyframe: Sim3,
    /// Held constant by the optimisation.
    pub fixed: bool,
}

/// What [`PoseGraph::optimize`] did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OptimizeReport {
    /// Robust cost `½ Σ ρ(rᵀΩr)` before and after (of the edges and factors that touch a moved
    /// vertex when the optimisation was bounded).
    pub initial_cost: f64,
    pub final_cost: f64,
    /// LM iterations run (accepted or not).
    pub iterations: usize,
    /// Vertices the optimisation could move: every free one, or a neighbourhood of what
    /// changed ([`PoseGraph::optimize_bounded`]).
    #[serde(default)]
    pub vertices: usize,
    /// Whether it was bounded to such a neighbourhood.
    #[serde(default)]
    pub bounded: bool,
    /// Whether its steps were solved by conjugate gradients (a whole live pass beyond the
    /// bound), not exactly.
    #[serde(default)]
    pub iterative: bool,
}

/// How an optimisation solves the damped normal equations of each step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Solver {
    /// Block Cholesky in a minimum-degree order: exact, its factor's fill grows with the loops.
    Cholesky,
    /// Preconditioned conjugate gradients to [`LIVE_CG`]: memory linear in the graph.
    Iterative,
}

/// Conjugate gradients of a whole live pass: 500 iterations at most, Ceres' default for its
/// iterative linear solvers, and a residual of 1e-4 relative — far below what moves a pose
/// visibly, and the final pass solves exactly anyway.
const LIVE_CG: CgStop = CgStop {
    max_iterations: 500,
    tolerance: 1e-4,
};

/// The residual `log(T_ij⁻¹ · T_wi⁻¹ · T_wj)` of a measurement `to_from_from = T_ij`
/// (`i = to`, `j = from`).
pub fn relative_residual(
    to_from_from: &Sim3,
    world_from_to: &Sim3,
    world_from_from: &Sim3,
) -> Vector7 {
    (to_from_from.inverse() * world_from_to.inverse() * *world_from_from).log()
}

/// The residual and its Jacobians with respect to right perturbations of `world_from_to`
/// (`∂r/∂δ_i`) and `world_from_from` (`∂r/∂δ_j`); see the module docs for the derivation.
pub fn relative_residual_jacobians(
    to_from_from: &Sim3,
    world_from_to: &Sim3,
    world_from_from: &Sim3,
) -> (Vector7, Matrix7, Matrix7) {
    let estimate = world_from_to.inverse() * *world_from_from;
    let r = (to_from_from.inverse() * estimate).log();
    let jr_inv = Sim3::right_jacobian_inverse(&r);
    let j_to = -jr_inv * estimate.inverse().adjoint();
    (r, j_to, jr_inv)
}

/// Sim(3) pose graph over keyframes.
#[derive(Clone, Debug, Default)]
pub struct PoseGraph {
    vertices: BTreeMap<KeyframeId, Vertex>,
    edges: Vec<Constraint>,
    /// Unary scale factors, by vertex.
    scale_priors: BTreeMap<KeyframeId, ScalePrior>,
    /// Huber width on `sqrt(rᵀΩr)`; `None` = plain least squares.
    huber: Option<f64>,
    /// Floor `q` of every edge's relative-scale standard deviation while scale factors are
    /// present (module docs).
    edge_scale_sigma: Option<f64>,
    /// What changed since the last optimisation (where a bounded one starts).
    changes: Changes,
    /// A loop closed outside a bounded pass's neighbourhood since the last whole optimisation:
    /// the whole graph owes a pass ([`PoseGraph::set_loop_pass_growth`]).
    whole_owed: Option<Whole>,
    /// Vertices at the last whole optimisation.
    vertices_at_whole: usize,
    /// See [`PoseGraph::set_loop_pass_growth`].
    loop_pass_growth: f64,
}

/// `ρ(e)` and `ρ'(e)` of g2o's Huber kernel on a squared error e.
fn huber(e: f64, delta: Option<f64>) -> (f64, f64) {
    match delta {
        Some(d) if e > d * d => {
            let s = e.sqrt();
            (2.0 * d * s - d * d, d / s)
        }
        _ => (e, 1.0),
    }
}

impl PoseGraph {
    /// An empty graph; `huber` is the robust-kernel width (see
    /// [`super::BackendConfig::pose_graph_huber`]).
    pub fn new(huber: Option<f64>) -> Self {
        Self {
            vertices: BTreeMap::new(),
            edges: Vec::new(),
            scale_priors: BTreeMap::new(),
            huber,
            edge_scale_sigma: None,
            changes: Changes::default(),
            whole_owed: None,
            vertices_at_whole: 0,
            loop_pass_growth: 0.0,
        }
    }

    /// A live pass whose new edge closes a loop beyond its neighbourhood moves the whole graph
    /// only once the graph has `growth` × its size at the last whole optimisation in new
    /// vertices; until then it moves the neighbourhood (the loop's edges pulling it towards
    /// the old keyframes, held where they are) and the whole pass is owed. A whole pass costs
    /// time linear in the graph, so their share of the back end's time stays constant as a
    /// session grows instead of growing with it (docs/tuning.md, issue 37). 0 (the default)
    /// moves the whole graph at once; `growth` must be finite and ≥ 0.
    pub fn set_loop_pass_growth(&mut self, growth: f64) -> Result<()> {
        if !(growth.is_finite() && growth >= 0.0) {
            return Err(Error::Backend(format!(
                "pose graph: loop pass growth must be finite and ≥ 0, got {growth}"
            )));
        }
        self.loop_pass_growth = growth;
        Ok(())
    }

    /// Sets the floor `q` of every edge's relative-scale standard deviation (natural log), in
    /// force while any vertex has a scale factor; `None` (the default) keeps the measured
    /// information. `q` must be positive and finite.
    pub fn set_edge_scale_sigma(&mut self, q: Option<f64>) -> Result<()> {
        if let Some(q) = q
            && !(q.is_finite() && q > 0.0)
        {
            return Err(Error::Backend(format!(
                "pose graph: edge scale σ must be positive and finite, got {q}"
            )));
        }
        self.edge_scale_sigma = q;
        Ok(())
    }

    /// The information an edge enters the optimisation with: its own, or with the
    /// relative-scale floor added to its covariance (module docs).
    fn information(&self, e: &Constraint) -> Matrix7 {
        match self.edge_scale_sigma {
            Some(q) if !self.scale_priors.is_empty() => {
                let information = e.information.matrix();
                let column = information.column(6).into_owned();
                let q2 = q * q;
                information - column * column.transpose() * (q2 / (1.0 + q2 * column[6]))
            }
            _ => e.information.matrix(),
        }
    }

    /// Adds (or re-poses) a vertex. The first vertex ever added is fixed.
    pub fn add_vertex(&mut self, id: KeyframeId, world_from_keyframe: Sim3) {
        let fixed = self.vertices.is_empty();
        if !self.vertices.contains_key(&id) {
            self.changes.added.insert(id);
        }
        self.changes.touched.insert(id);
        self.vertices
            .entry(id)
            .and_modify(|v| v.world_from_keyframe = world_from_keyframe)
            .or_insert(Vertex {
                world_from_keyframe,
                fixed,
            });
    }

    /// Holds a vertex constant (or releases it).
    pub fn set_fixed(&mut self, id: KeyframeId, fixed: bool) -> Result<()> {
        let v = self.vertices.get_mut(&id).ok_or_else(|| unknown(id))?;
        v.fixed = fixed;
        Ok(())
    }

    /// Adds a measurement; both keyframes must be vertices and the information finite.
    pub fn add_edge(&mut self, constraint: Constraint) -> Result<()> {
        for id in [constraint.from, constraint.to] {
            if !self.vertices.contains_key(&id) {
                return Err(unknown(id));
            }
        }
        if constraint.from == constraint.to || !constraint.information.is_finite() {
            return Err(Error::Backend(format!(
                "pose graph: edge {} -> {} is a self-loop or has non-finite information",
                constraint.from, constraint.to
            )));
        }
        if self.edges.len() == self.edges.capacity() {
            // By a quarter, not double: the edges stay for the whole session, and a doubled
            // vector is up to half slack (15 MB of 31 at 2242 keyframes; issue 37).
            self.edges.reserve_exact((self.edges.len() / 4).max(64));
        }
        self.changes
            .touched
            .extend([constraint.from, constraint.to]);
        self.changes.edges.push((constraint.from, constraint.to));
        self.edges.push(constraint);
        Ok(())
    }

    /// Sets (or, with `None`, removes) the unary scale factor of vertex `id`; `sigma` and
    /// `huber` must be positive and finite.
    pub fn set_scale_prior(&mut self, id: KeyframeId, prior: Option<ScalePrior>) -> Result<()> {
        if !self.vertices.contains_key(&id) {
            return Err(unknown(id));
        }
        self.changes.touched.insert(id);
        match prior {
            Some(p) => {
                let positive = |v: f64| v.is_finite() && v > 0.0;
                if !(p.log_scale.is_finite() && positive(p.sigma) && positive(p.huber)) {
                    return Err(Error::Backend(format!(
                        "pose graph: scale prior of keyframe {id} is not finite and positive: {p:?}"
                    )));
                }
                self.scale_priors.insert(id, p);
            }
            None => {
                self.scale_priors.remove(&id);
            }
        }
        Ok(())
    }

    /// The unary scale factors, by vertex.
    pub fn scale_priors(&self) -> &BTreeMap<KeyframeId, ScalePrior> {
        &self.scale_priors
    }

    /// Removes the first edge equal to `edge`; returns whether there was one.
    pub fn remove_edge(&mut self, edge: &Constraint) -> bool {
        match self.edges.iter().position(|e| e == edge) {
            Some(i) => {
                self.changes.touched.extend([edge.from, edge.to]);
                self.changes.removed.insert(pair(edge.from, edge.to));
                self.edges.remove(i);
                true
            }
            None => false,
        }
    }

    /// Removes every edge between `a` and `b` (both directions); returns how many.
    pub fn remove_edges_between(&mut self, a: KeyframeId, b: KeyframeId) -> usize {
        let before = self.edges.len();
        self.edges
            .retain(|e| !((e.from == a && e.to == b) || (e.from == b && e.to == a)));
        let removed = before - self.edges.len();
        if removed > 0 {
            self.changes.touched.extend([a, b]);
            self.changes.removed.insert(pair(a, b));
        }
        removed
    }

    /// The vertex of `id`.
    pub fn vertex(&self, id: KeyframeId) -> Option<&Vertex> {
        self.vertices.get(&id)
    }

    /// `world_from_keyframe` of `id`.
    pub fn pose(&self, id: KeyframeId) -> Option<Sim3> {
        self.vertices.get(&id).map(|v| v.world_from_keyframe)
    }

    /// All poses.
    pub fn poses(&self) -> HashMap<KeyframeId, Sim3> {
        self.vertices
            .iter()
            .map(|(&k, v)| (k, v.world_from_keyframe))
            .collect()
    }

    /// Vertex ids in increasing order.
    pub fn ids(&self) -> impl Iterator<Item = KeyframeId> + '_ {
        self.vertices.keys().copied()
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.vertices.len()
    }

    /// Whether the graph has no vertex.
    pub fn is_empty(&self) -> bool {
        self.vertices.is_empty()
    }

    /// All edges in insertion order.
    pub fn edges(&self) -> &[Constraint] {
        &self.edges
    }

    /// The robust cost `½ Σ ρ(rᵀΩr)` at the current poses.
    pub fn cost(&self) -> f64 {
        self.cost_with(&|id| self.pose(id), None)
    }

    /// Every edge, or those at `scope` (indices into the edges, in order).
    fn edges_in<'a>(
        &'a self,
        scope: Option<&'a [usize]>,
    ) -> Box<dyn Iterator<Item = &'a Constraint> + 'a> {
        match scope {
            None => Box::new(self.edges.iter()),
            Some(at) => Box::new(at.iter().map(|&i| &self.edges[i])),
        }
    }

    /// The cost of every edge and factor (`scope` `None`), or of the edges at `scope` and the
    /// factors of `moved` vertices.
    fn cost_with(
        &self,
        pose: &dyn Fn(KeyframeId) -> Option<Sim3>,
        scope: Option<(&[usize], &HashMap<KeyframeId, usize>)>,
    ) -> f64 {
        let edges: f64 = self
            .edges_in(scope.map(|s| s.0))
            .filter_map(|e| {
                let (wi, wj) = (pose(e.to)?, pose(e.from)?);
                let r = relative_residual(&e.to_from_from, &wi, &wj);
                Some(0.5 * huber(r.dot(&(self.information(e) * r)), self.huber).0)
            })
            .sum();
        let scales: f64 = self
            .scale_priors
            .iter()
            .filter(|(id, _)| scope.is_none_or(|(_, moved)| moved.contains_key(id)))
            .filter_map(|(&id, p)| {
                let r = p.residual(&pose(id)?);
                Some(0.5 * huber(r * r, Some(p.huber)).0)
            })
            .sum();
        edges + scales
    }

    /// Levenberg–Marquardt with Marquardt's diagonal damping (`H + λ·diag(H)`), at most
    /// `max_iterations` linearisations; stops early when the cost no longer decreases by more
    /// than 1e-12 relative. Fails only when the graph has no free vertex to move (returns the
    /// unchanged cost then) — it never leaves the poses worse than they were.
    pub fn optimize(&mut self, max_iterations: usize) -> Result<OptimizeReport> {
        let free = self.free_vertices();
        self.changes.clear();
        self.optimize_vertices(free, None, max_iterations, Solver::Cholesky)
    }

    /// [`PoseGraph::optimize`] of at most `max_vertices` vertices, those nearest by edges to
    /// what changed since the last optimisation, the others held where they are; the whole
    /// graph when it is no larger or a new edge closes a loop outside that neighbourhood
    /// ([`super::scope`]; possibly later, [`PoseGraph::set_loop_pass_growth`]), by conjugate
    /// gradients when it is larger. For live passes: memory per pass stays linear in the
    /// graph, time bounded or linear per solver iteration, as the session grows.
    pub fn optimize_bounded(
        &mut self,
        max_vertices: usize,
        max_iterations: usize,
    ) -> Result<OptimizeReport> {
        let free = self.free_vertices();
        let ids: Vec<KeyframeId> = self.vertices.keys().copied().collect();
        let free_set: BTreeSet<KeyframeId> = free.iter().copied().collect();
        let scope = bounded_scope(&ids, &free_set, &self.edges, &self.changes, max_vertices);
        self.changes.clear();
        let scope = match scope {
            Ok(scope) => scope,
            Err(why) => return self.optimize_whole(free, why, max_iterations),
        };
        if let Some(why) = scope.closes {
            self.whole_owed.get_or_insert(why);
        }
        if let Some(owed) = self.whole_owed {
            let due = self.vertices_at_whole as f64 * (1.0 + self.loop_pass_growth);
            if self.vertices.len() as f64 >= due {
                return self.optimize_whole(free, owed, max_iterations);
            }
            tracing::debug!(
                ?owed,
                "a loop's whole pose-graph pass waits for the graph to grow"
            );
        }
        let moved = scope.moved;
        let inside: BTreeSet<KeyframeId> = moved.iter().copied().collect();
        let edges: Vec<usize> = (self.edges.iter().enumerate())
            .filter(|(_, e)| inside.contains(&e.from) || inside.contains(&e.to))
            .map(|(i, _)| i)
            .collect();
        self.optimize_vertices(moved, Some(edges), max_iterations, Solver::Cholesky)
    }

    /// A live pass over the whole graph, for `why`.
    fn optimize_whole(
        &mut self,
        free: Vec<KeyframeId>,
        why: Whole,
        max_iterations: usize,
    ) -> Result<OptimizeReport> {
        if tracing::enabled!(tracing::Level::DEBUG) {
            let chi2 = match why {
                Whole::Loop(a, b) | Whole::CutOff(a, b) => self.edge_chi2(a, b),
                _ => None,
            };
            tracing::debug!(?why, ?chi2, "live pose-graph pass moves the whole graph");
        }
        // Past the bound a whole live pass must not allocate a factor that grows faster than
        // the graph (`super::conjugate_gradients`).
        let solver = match why {
            Whole::Small => Solver::Cholesky,
            _ => Solver::Iterative,
        };
        self.optimize_vertices(free, None, max_iterations, solver)
    }

    /// The largest `rᵀΩr` of the edges from `from` to `to` at the current poses, with the
    /// information the optimisation weighs them by.
    fn edge_chi2(&self, from: KeyframeId, to: KeyframeId) -> Option<f64> {
        (self.edges.iter())
            .filter(|e| e.from == from && e.to == to)
            .filter_map(|e| {
                let r = relative_residual(&e.to_from_from, &self.pose(e.to)?, &self.pose(e.from)?);
                Some(r.dot(&(self.information(e) * r)))
            })
            .reduce(f64::max)
    }

    /// The vertices an optimisation may move, in id order. A fixed vertex with a scale factor
    /// still has its scale free: the factors, not the first keyframe's single observation,
    /// set the scale gauge.
    fn free_vertices(&self) -> Vec<KeyframeId> {
        (self.vertices.iter())
            .filter(|(k, v)| !v.fixed || self.scale_priors.contains_key(k))
            .map(|(&k, _)| k)
            .collect()
    }

    /// Levenberg–Marquardt over the `free` vertices and the edges at `scope` (every edge when
    /// `None`), its steps solved by `solver`.
    fn optimize_vertices(
        &mut self,
        free: Vec<KeyframeId>,
        scope: Option<Vec<usize>>,
        max_iterations: usize,
        solver: Solver,
    ) -> Result<OptimizeReport> {
        let pinned: Vec<bool> = free
            .iter()
            .map(|k| self.vertices.get(k).is_some_and(|v| v.fixed))
            .collect();
        let index: HashMap<KeyframeId, usize> =
            free.iter().enumerate().map(|(i, &k)| (k, i)).collect();
        if scope.is_none() {
            self.whole_owed = None;
            self.vertices_at_whole = self.vertices.len();
        }
        let scoped = scope.as_deref().map(|at| (at, &index));
        let initial_cost = self.cost_with(&|id| self.pose(id), scoped);
        let mut report = OptimizeReport {
            initial_cost,
            final_cost: initial_cost,
            iterations: 0,
            vertices: free.len(),
            bounded: scope.is_some(),
            iterative: solver == Solver::Iterative,
        };
        if free.is_empty() || (self.edges.is_empty() && self.scale_priors.is_empty()) {
            return Ok(report);
        }
        let mut cost = initial_cost;
        let mut lambda = 1e-4;
        // The elimination order follows the edges alone: the same in every iteration.
        let mut order: Option<Vec<usize>> = None;
        for _ in 0..max_iterations {
            report.iterations += 1;
            let (h, g) = self.normal_equations(&index, free.len(), scope.as_deref());
            if matches!(solver, Solver::Cholesky) && order.is_none() {
                order = Some(h.minimum_degree_order());
            }
            let mut improved = false;
            while lambda < 1e12 {
                let mut damped = h.clone();
                for (i, &pin) in pinned.iter().enumerate() {
                    let d = h.diagonal(i);
                    let mut add = Matrix7::zeros();
                    for k in 0..7 {
                        add[(k, k)] = lambda * d[(k, k)].max(1e-12) + 1e-12;
                        // A scale-only vertex's rotation and translation are held by a
                        // stiffness that dwarfs every other term (and zeroed below).
                        if pin && k < 6 {
                            add[(k, k)] += 1e12 * (d[(k, k)].abs() + 1.0);
                        }
                    }
                    damped.add(i, i, &add);
                }
                let rhs: Vec<Vector7> = g.iter().map(|v| -v).collect();
                let step = match &order {
                    Some(order) => damped.solve_ordered(&rhs, order),
                    None => damped.solve_cg(&rhs, LIVE_CG).map(|(x, _)| x),
                };
                let Some(mut step) = step else {
                    lambda *= 10.0;
                    continue;
                };
                for (d, _) in step.iter_mut().zip(&pinned).filter(|(_, p)| **p) {
                    d.fixed_rows_mut::<6>(0).fill(0.0);
                }
                let candidate: HashMap<KeyframeId, Sim3> = free
                    .iter()
                    .zip(&step)
                    .filter_map(|(&k, d)| Some((k, self.pose(k)? * Sim3::exp(d))))
                    .collect();
                let new_cost = self.cost_with(
                    &|id| candidate.get(&id).copied().or_else(|| self.pose(id)),
                    scoped,
                );
                if new_cost.is_finite() && new_cost < cost {
                    for (k, p) in candidate {
                        if let Some(v) = self.vertices.get_mut(&k) {
                            v.world_from_keyframe = p;
                        }
                    }
                    let relative = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
                    cost = new_cost;
                    lambda = (lambda / 3.0).max(1e-12);
                    improved = relative > 1e-12;
                    break;
                }
                lambda *= 4.0;
            }
            if !improved {
                break;
            }
        }
        report.final_cost = cost;
        Ok(report)
    }

    /// `H = Σ Jᵀ ρ' Ω J`, `g = Σ Jᵀ ρ' Ω r` over the free vertices (IRLS form of the Huber cost),
    /// the edges at `scope` (every one when `None`) and unary scale factors.
    fn normal_equations(
        &self,
        index: &HashMap<KeyframeId, usize>,
        n: usize,
        scope: Option<&[usize]>,
    ) -> (BlockSparseSymmetric, Vec<Vector7>) {
        let mut h = BlockSparseSymmetric::new(n);
        let mut g = vec![Vector7::zeros(); n];
        for e in self.edges_in(scope) {
            let (Some(wi), Some(wj)) = (self.pose(e.to), self.pose(e.from)) else {
                continue;
            };
            let (r, j_to, j_from) = relative_residual_jacobians(&e.to_from_from, &wi, &wj);
            let information = self.information(e);
            let weight = huber(r.dot(&(information * r)), self.huber).1;
            let omega = information * weight;
            let blocks = [
                (index.get(&e.to).copied(), j_to),
                (index.get(&e.from).copied(), j_from),
            ];
            for &(a, ja) in &blocks {
                let Some(a) = a else { continue };
                g[a] += ja.transpose() * (omega * r);
                for &(b, jb) in &blocks {
                    let Some(b) = b else { continue };
                    if a >= b {
                        h.add(a, b, &(ja.transpose() * omega * jb));
                    }
                }
            }
        }
        for (id, p) in &self.scale_priors {
            let (Some(&a), Some(pose)) = (index.get(id), self.pose(*id)) else {
                continue;
            };
            let r = p.residual(&pose);
            let weight = huber(r * r, Some(p.huber)).1;
            let mut block = Matrix7::zeros();
            block[(6, 6)] = weight / (p.sigma * p.sigma);
            h.add(a, a, &block);
            g[a][6] += weight * r / p.sigma;
        }
        (h, g)
    }
}

fn unknown(id: KeyframeId) -> Error {
    Error::Backend(format!("pose graph: keyframe {id} is not a vertex"))
}
