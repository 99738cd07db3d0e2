//! The constraint search's candidates for a new keyframe: close in pose (same fragment) and,
//! with `appearance_search`, similar in appearance and far in the graph (LSD-SLAM's
//! `findCandidates` and the close/far split of `findConstraintsForNewKeyFrames`).

use std::cmp::Ordering;
use std::collections::{BTreeSet, BinaryHeap, HashMap, VecDeque};

use super::super::KeyframeId;
use super::super::search::pose_proximity;
use super::{Backend, Entry};

/// Where a candidate comes from (decides its initial relative pose).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Source {
    /// Close in pose: start from the graph's relative pose.
    Pose,
    /// Proposed by appearance: poses may have drifted apart, start from the identity as
    /// LSD-SLAM does for its FAB-MAP candidates.
    Appearance,
}

impl Backend {
    /// Graph distances (edges) from `start` over the current neighbour sets.
    pub(super) fn graph_distances(&self, start: KeyframeId) -> HashMap<KeyframeId, usize> {
        let mut dist = HashMap::from([(start, 0)]);
        let mut queue = VecDeque::from([start]);
        while let Some(k) = queue.pop_front() {
            let d = dist[&k];
            for &n in self
                .keyframes
                .get(&k)
                .map(|e| &e.neighbours)
                .into_iter()
                .flatten()
            {
                if let std::collections::hash_map::Entry::Vacant(v) = dist.entry(n) {
                    v.insert(d + 1);
                    queue.push_back(n);
                }
            }
        }
        dist
    }

    /// Candidates for keyframe `id`, in test order (LSD-SLAM's `findCandidates` plus the
    /// close/far split of `findConstraintsForNewKeyFrames`).
    pub(super) fn candidates(&self, id: KeyframeId) -> Vec<(KeyframeId, Source)> {
        let Some(entry) = self.keyframes.get(&id) else {
            return Vec::new();
        };
        let Some(pose) = self.graph.pose(id) else {
            return Vec::new();
        };
        let parent = entry.parent.as_ref().map(|p| p.id);
        let eligible = |cid: KeyframeId, c: &Entry| {
            cid != id
                && entry.tracked().all(|p| p.id != cid)
                && !entry.neighbours.contains(&cid)
                && c.order >= self.config.skip_initial_keyframes
                && c.kept.estimates > 0
        };
        // Poses of another fragment are in another frame: only appearance proposes those.
        let mut close: Vec<(KeyframeId, f64)> = self
            .keyframes
            .iter()
            .filter(|(cid, c)| eligible(**cid, c) && c.fragment == entry.fragment)
            .filter_map(|(&cid, c)| {
                let cpose = self.graph.pose(cid)?;
                pose_proximity(&self.config, &entry.kept, &pose, &c.kept, &cpose)
                    .map(|d2| (cid, d2))
            })
            .collect();
        drop_best_connected(&mut close, self.config.max_loop_closure_candidates, |k| {
            &self.keyframes[&k].neighbours
        });
        let mut out: Vec<(KeyframeId, Source)> =
            close.iter().map(|&(c, _)| (c, Source::Pose)).collect();

        if self.config.appearance_search {
            let distances = self.graph_distances(parent.unwrap_or(id));
            let mut far: Vec<(KeyframeId, f64)> = self
                .keyframes
                .iter()
                .filter(|(cid, c)| eligible(**cid, c) && !close.iter().any(|x| x.0 == **cid))
                .filter(|(cid, _)| {
                    distances
                        .get(cid)
                        .is_none_or(|&d| d >= self.config.min_far_graph_distance)
                })
                .map(|(&cid, c)| (cid, entry.kept.thumbnail.score(&c.kept.thumbnail)))
                .filter(|&(_, s)| s >= self.config.appearance_min_score)
                .collect();
            far.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
            far.truncate(self.config.max_far_candidates);
            out.extend(far.into_iter().map(|(c, _)| (c, Source::Appearance)));
        }
        out
    }
}

/// Too many close candidates: drops the one best connected to the others (ties: the farther,
/// then the larger id) until `max` remain, as `findConstraintsForNewKeyFrames` does. A path
/// that keeps revisiting a place has ever more keyframes close to it, so the counts are kept
/// and decremented rather than recounted after each drop: O(n·deg·log n), not O(n²·deg) per
/// search (the recount was a growing share of a long session's back end; issue 37).
fn drop_best_connected<'a>(
    close: &mut Vec<(KeyframeId, f64)>,
    max: usize,
    neighbours: impl Fn(KeyframeId) -> &'a BTreeSet<KeyframeId>,
) {
    if close.len() <= max {
        return;
    }
    let index: HashMap<KeyframeId, usize> =
        close.iter().enumerate().map(|(i, c)| (c.0, i)).collect();
    let mut counts: Vec<usize> = close
        .iter()
        .map(|c| {
            neighbours(c.0)
                .iter()
                .filter(|n| index.contains_key(n))
                .count()
        })
        .collect();
    let mut heap: BinaryHeap<Connected> = (close.iter().zip(&counts))
        .map(|(c, &count)| Connected::new(count, *c))
        .collect();
    let mut dropped = vec![false; close.len()];
    let mut left = close.len();
    while left > max {
        let Some(top) = heap.pop() else { break };
        let i = index[&top.id];
        // Counts only fall: an entry with another count is stale, its newer one is queued.
        if dropped[i] || counts[i] != top.count {
            continue;
        }
        dropped[i] = true;
        left -= 1;
        // Neighbour sets are symmetric (`Backend::link`).
        for n in neighbours(top.id) {
            if let Some(&j) = index.get(n).filter(|&&j| !dropped[j]) {
                counts[j] -= 1;
                heap.push(Connected::new(counts[j], close[j]));
            }
        }
    }
    let mut keep = dropped.iter().map(|d| !d);
    close.retain(|_| keep.next().unwrap_or(true));
}

/// A close candidate ordered for [`drop_best_connected`]: connections, distance, id.
#[derive(Clone, Copy, Debug)]
struct Connected {
    count: usize,
    d2: f64,
    id: KeyframeId,
}

impl Connected {
    fn new(count: usize, (id, d2): (KeyframeId, f64)) -> Self {
        Self { count, d2, id }
    }
}

impl Ord for Connected {
    fn cmp(&self, other: &Self) -> Ordering {
        (self.count.cmp(&other.count))
            .then(self.d2.total_cmp(&other.d2))
            .then(self.id.cmp(&other.id))
    }
}

impl PartialOrd for Connected {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl PartialEq for Connected {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Connected {}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The recount after every drop, as the search did before (the reference).
    fn recount(close: &mut Vec<(KeyframeId, f64)>, max: usize, graph: &[BTreeSet<KeyframeId>]) {
        while close.len() > max {
            let set: BTreeSet<KeyframeId> = close.iter().map(|c| c.0).collect();
            let connectivity = |k: KeyframeId| graph[k].iter().filter(|n| set.contains(n)).count();
            let worst = (close.iter().enumerate())
                .max_by(|(_, a), (_, b)| {
                    (connectivity(a.0).cmp(&connectivity(b.0)))
                        .then(a.1.total_cmp(&b.1))
                        .then(a.0.cmp(&b.0))
                })
                .map(|(i, _)| i);
            if let Some(i) = worst {
                close.remove(i);
            }
        }
    }

    #[test]
    fn dropping_by_kept_counts_matches_the_recount() {
        let mut rng = ChaCha8Rng::seed_from_u64(37);
        for trial in 0..200 {
            let n = rng.random_range(1..80);
            let mut graph = vec![BTreeSet::new(); n];
            for _ in 0..rng.random_range(0..4 * n) {
                let (a, b) = (rng.random_range(0..n), rng.random_range(0..n));
                if a != b {
                    graph[a].insert(b);
                    graph[b].insert(a);
                }
            }
            // Few distinct distances, so that ties on count and distance are common.
            let mut close: Vec<(KeyframeId, f64)> = Vec::new();
            for k in 0..n {
                if rng.random_bool(0.7) {
                    close.push((k, f64::from(rng.random_range(0..4u8))));
                }
            }
            let max = rng.random_range(0..12);
            let mut expected = close.clone();
            recount(&mut expected, max, &graph);
            drop_best_connected(&mut close, max, |k| &graph[k]);
            assert_eq!(close, expected, "trial {trial}");
        }
    }
}
