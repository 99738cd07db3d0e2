//! The constraint search's candidates for a new keyframe: close in pose (same fragment) and,
//! with `appearance_search`, similar in appearance and far in the graph (LSD-SLAM's
//! `findCandidates` and the close/far split of `findConstraintsForNewKeyFrames`).

use std::collections::{BTreeSet, HashMap, VecDeque};

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
        // Too many: drop the one best connected to the other candidates (ties: the farther,
        // then the larger id), as `findConstraintsForNewKeyFrames` does.
        while close.len() > self.config.max_loop_closure_candidates {
            let set: BTreeSet<KeyframeId> = close.iter().map(|c| c.0).collect();
            let connectivity = |k: KeyframeId| {
                self.keyframes[&k]
                    .neighbours
                    .iter()
                    .filter(|n| set.contains(n))
                    .count()
            };
            let worst = close
                .iter()
                .enumerate()
                .max_by(|(_, a), (_, b)| {
                    connectivity(a.0)
                        .cmp(&connectivity(b.0))
                        .then(a.1.total_cmp(&b.1))
                        .then(a.0.cmp(&b.0))
                })
                .map(|(i, _)| i);
            if let Some(i) = worst {
                close.remove(i);
            }
        }
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
