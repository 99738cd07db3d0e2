//! Which vertices a live pose-graph optimisation moves ([`PoseGraph::optimize_bounded`]).
//!
//! A full optimisation of an hour-long session's graph (4200 keyframes, 19 000 edges) holds a
//! Cholesky factor that grows faster than the graph, and it runs after every pass that adds
//! an edge: the back end's memory and time per pass then grow with the session (issue 37,
//! docs/tuning.md). New constraints mostly correct their own neighbourhood, so a live pass
//! moves only the vertices nearest, by graph edges, to what changed since the last
//! optimisation, holding the rest where they are — ORB-SLAM's local optimisation around a new
//! keyframe, on the pose graph. Two cases still move everything: the graph is small enough
//! (every short sequence: the results are those of a full optimisation), and a new edge
//! closes a loop that the neighbourhood does not contain (its two ends are joined only
//! through vertices outside it, or not at all). A loop's correction must then spread along
//! the whole loop, as LSD-SLAM's and ORB-SLAM's full loop-closure optimisations do; such a
//! pass may wait until the graph has grown by a fraction of itself
//! ([`super::PoseGraph::set_loop_pass_growth`]), the neighbourhood moving meanwhile. The
//! session's final pass optimises the whole graph in any case.
//!
//! [`PoseGraph::optimize_bounded`]: super::PoseGraph::optimize_bounded

use std::collections::{BTreeSet, HashMap, HashSet, VecDeque};

use super::KeyframeId;
use super::pose_graph::Constraint;

/// What changed since the last optimisation: where a bounded optimisation starts.
#[derive(Clone, Debug, Default)]
pub(super) struct Changes {
    /// Vertices added or re-posed, given or losing a scale factor, and both ends of every
    /// edge added or removed.
    pub touched: BTreeSet<KeyframeId>,
    /// Vertices added.
    pub added: BTreeSet<KeyframeId>,
    /// Edges added, as (from, to), in order.
    pub edges: Vec<(KeyframeId, KeyframeId)>,
    /// The keyframe pairs ([`pair`]) of edges removed.
    pub removed: BTreeSet<(KeyframeId, KeyframeId)>,
}

impl Changes {
    pub fn clear(&mut self) {
        *self = Self::default();
    }
}

/// Why a bounded optimisation moved the whole graph (logged at debug level: which of them
/// keeps a long session's live passes whole is what bounds their memory).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Whole {
    /// The graph has at most the bound's free vertices.
    Small,
    /// Nothing changed since the last optimisation.
    Untouched,
    /// More vertices changed than the bound.
    ManyTouched,
    /// The new edge (from, to) closes a loop outside the neighbourhood or joins two fragments.
    Loop(KeyframeId, KeyframeId),
    /// The new edge (from, to) has an end that the bound left outside the neighbourhood.
    CutOff(KeyframeId, KeyframeId),
}

/// A bounded optimisation's neighbourhood.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Scope {
    /// The free vertices it moves, in id order.
    pub moved: Vec<KeyframeId>,
    /// Why the whole graph should move as well: a new edge closes a loop outside the
    /// neighbourhood ([`Whole::Loop`], [`Whole::CutOff`]).
    pub closes: Option<Whole>,
}

/// The free vertices a bounded optimisation moves: breadth-first over the edges from the
/// touched vertices until `max_vertices` free ones are reached, and whether a new edge closes
/// a loop outside them. Why only the whole graph can move: it has at most `max_vertices` free
/// vertices, nothing was touched, or more than that were (module docs).
pub(super) fn bounded_scope(
    ids: &[KeyframeId],
    free: &BTreeSet<KeyframeId>,
    edges: &[Constraint],
    changes: &Changes,
    max_vertices: usize,
) -> Result<Scope, Whole> {
    if free.len() <= max_vertices {
        return Err(Whole::Small);
    }
    if changes.touched.is_empty() {
        return Err(Whole::Untouched);
    }
    let index: HashMap<KeyframeId, usize> = ids.iter().enumerate().map(|(i, &k)| (k, i)).collect();
    let mut adjacent = vec![Vec::new(); ids.len()];
    for e in edges {
        let (Some(&a), Some(&b)) = (index.get(&e.from), index.get(&e.to)) else {
            continue;
        };
        adjacent[a].push(b);
        adjacent[b].push(a);
    }
    let mut inside = vec![false; ids.len()];
    let mut queue = VecDeque::new();
    let mut moved = 0;
    for id in &changes.touched {
        let Some(&i) = index.get(id) else { continue };
        inside[i] = true;
        queue.push_back(i);
        moved += usize::from(free.contains(id));
    }
    if moved > max_vertices {
        return Err(Whole::ManyTouched);
    }
    'search: while let Some(i) = queue.pop_front() {
        for &j in &adjacent[i] {
            if inside[j] {
                continue;
            }
            if free.contains(&ids[j]) {
                if moved == max_vertices {
                    break 'search;
                }
                moved += 1;
            }
            inside[j] = true;
            queue.push_back(j);
        }
    }
    let closes = new_edge_leaves_the_scope(ids, &index, &inside, edges, changes).err();
    let moved = (ids.iter().zip(&inside))
        .filter(|&(k, &i)| i && free.contains(k))
        .map(|(&k, _)| k)
        .collect();
    Ok(Scope { moved, closes })
}

/// Fails with the first new edge that joins two parts of the scope that each hold an older
/// vertex and that no older edge inside the scope joins: the loop it closes runs outside the scope, or it joins
/// two fragments. Union–find over the scope's older joins, then the new ones in order (a new
/// keyframe's first edge joins it to the map and is no loop). An edge between keyframes that
/// were already joined, or whose edge it replaces (a re-estimate after a depth update, the
/// window's edge of a consecutive pair), joins nothing new.
fn new_edge_leaves_the_scope(
    ids: &[KeyframeId],
    index: &HashMap<KeyframeId, usize>,
    inside: &[bool],
    edges: &[Constraint],
    changes: &Changes,
) -> Result<(), Whole> {
    let mut parts = Parts::new(ids.len());
    for (i, id) in ids.iter().enumerate() {
        parts.has_older[i] = inside[i] && !changes.added.contains(id);
    }
    let mut added: HashMap<(KeyframeId, KeyframeId), usize> = HashMap::new();
    for &(a, b) in &changes.edges {
        *added.entry(pair(a, b)).or_default() += 1;
    }
    let mut present: HashMap<(KeyframeId, KeyframeId), usize> = HashMap::new();
    for e in edges
        .iter()
        .filter(|e| added.contains_key(&pair(e.from, e.to)))
    {
        *present.entry(pair(e.from, e.to)).or_default() += 1;
    }
    // Pairs whose every edge is new and that had none removed since the last optimisation.
    let joins: HashSet<(KeyframeId, KeyframeId)> = (added.iter())
        .filter(|&(p, n)| present.get(p) == Some(n) && !changes.removed.contains(p))
        .map(|(&p, _)| p)
        .collect();
    let ends = |from: KeyframeId, to: KeyframeId| {
        let (a, b) = (*index.get(&from)?, *index.get(&to)?);
        (inside[a] && inside[b]).then_some((a, b))
    };
    for e in edges
        .iter()
        .filter(|e| !joins.contains(&pair(e.from, e.to)))
    {
        if let Some((a, b)) = ends(e.from, e.to) {
            parts.join(a, b);
        }
    }
    for &(from, to) in changes
        .edges
        .iter()
        .filter(|&&(a, b)| joins.contains(&pair(a, b)))
    {
        let Some((a, b)) = ends(from, to) else {
            // An end outside the scope: only a graph whose touched vertices were cut off by the
            // bound; move everything.
            return Err(Whole::CutOff(from, to));
        };
        let (ra, rb) = (parts.root(a), parts.root(b));
        if ra != rb && parts.has_older[ra] && parts.has_older[rb] {
            return Err(Whole::Loop(from, to));
        }
        parts.join(a, b);
    }
    Ok(())
}

/// The unordered pair of an edge's keyframes.
pub(super) fn pair(a: KeyframeId, b: KeyframeId) -> (KeyframeId, KeyframeId) {
    (a.min(b), a.max(b))
}

/// Union–find with path halving; a root knows whether its part holds an older vertex.
struct Parts {
    parent: Vec<usize>,
    has_older: Vec<bool>,
}

impl Parts {
    fn new(n: usize) -> Self {
        Self {
            parent: (0..n).collect(),
            has_older: vec![false; n],
        }
    }

    fn root(&mut self, mut i: usize) -> usize {
        while self.parent[i] != i {
            self.parent[i] = self.parent[self.parent[i]];
            i = self.parent[i];
        }
        i
    }

    fn join(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.root(a), self.root(b));
        if ra != rb {
            self.parent[rb] = ra;
            self.has_older[ra] |= self.has_older[rb];
        }
    }
}
