//! The reciprocal tests that give a keyframe its edges: its first search (the tracked edges —
//! parent and hand-over — and, in a full search, the candidates) and the re-estimation of its
//! edges after a depth update.

use super::super::KeyframeId;
use super::super::pose_graph::Constraint;
use super::super::search::reciprocal_test;
use super::candidates::Source;
use super::{Backend, ProcessReport};
use crate::Result;
use crate::geometry::Sim3;

/// The pairs of edges accepted by a keyframe's reciprocal tests, and the candidates that failed
/// with the initial pose each was tried from.
type Outcomes = (Vec<(Constraint, Constraint)>, Vec<(KeyframeId, Sim3)>);

impl Backend {
    /// Runs the constraint search of keyframe `id` (its tracked edges only unless
    /// `with_candidates`); returns whether edges were added.
    pub(super) fn search(
        &mut self,
        id: KeyframeId,
        with_candidates: bool,
        report: &mut ProcessReport,
    ) -> Result<bool> {
        let Some(pose) = self.graph.pose(id) else {
            return Ok(false);
        };
        let tests = self.tests_of(id, pose, with_candidates);
        let (accepted, failed) = self.run_tests(id, tests, report)?;
        // A tracked edge whose Sim(3) test failed falls back to the tracking estimate; a
        // trusted one is taken as it is.
        let fallbacks: Vec<_> = self.keyframes[&id]
            .tracked()
            .filter(|p| {
                self.keyframes.contains_key(&p.id)
                    && !accepted.iter().any(|(a, _)| a.to == p.id)
                    && !self.keyframes[&id].neighbours.contains(&p.id)
            })
            .cloned()
            .collect();
        let mut any = false;
        report.constraints_accepted += accepted.len();
        for (forward, backward) in accepted {
            if self.merge_fragments(&forward)? {
                report.fragments_merged += 1;
            }
            self.link(forward.from, forward.to);
            self.graph.add_edge(forward)?;
            self.graph.add_edge(backward)?;
            any = true;
        }
        for p in fallbacks {
            if !p.trusted {
                tracing::warn!(
                    keyframe = id,
                    tracked = p.id,
                    "Sim(3) test of a tracked edge failed; odometry edge"
                );
                report.fallback_parent_edges += 1;
            }
            self.link(id, p.id);
            self.graph.add_edge(Constraint {
                from: id,
                to: p.id,
                to_from_from: p.parent_from_keyframe,
                information: p.information,
            })?;
            any = true;
        }
        if let Some(entry) = self.keyframes.get_mut(&id) {
            if with_candidates {
                // Only this keyframe's own later search reads its failures, and a full search
                // is its last: a list kept for the whole session is dead weight (issue 37).
                entry.failed = Vec::new();
            } else {
                entry.failed.extend(failed);
            }
        }
        Ok(any)
    }

    /// The reciprocal tests keyframe `id` (at `pose`) takes: the candidates not tried before
    /// from about the same initial pose, at loop-closure strictness, then its tracked edges
    /// not yet in the graph, at parent strictness.
    fn tests_of(
        &self,
        id: KeyframeId,
        pose: Sim3,
        with_candidates: bool,
    ) -> Vec<(KeyframeId, Sim3, f64)> {
        let candidates = if with_candidates {
            self.candidates(id)
        } else {
            Vec::new()
        };
        let entry = &self.keyframes[&id];
        let mut tests: Vec<(KeyframeId, Sim3, f64)> = Vec::new();
        for (cid, source) in candidates {
            let Some(cpose) = self.graph.pose(cid) else {
                continue;
            };
            let initial = match source {
                Source::Pose => cpose.inverse() * pose,
                Source::Appearance => Sim3::identity(),
            };
            let tried_before = entry.failed.iter().any(|(f, init)| {
                *f == cid && (initial * init.inverse()).log().norm() < self.config.retry_min_change
            });
            if !tried_before {
                tests.push((cid, initial, self.config.loop_closure_strictness));
            }
        }
        for p in entry.tracked().filter(|p| {
            !p.trusted && self.keyframes.contains_key(&p.id) && !entry.neighbours.contains(&p.id)
        }) {
            // candidate_from_keyframe = parent_from_keyframe.
            tests.push((p.id, p.parent_from_keyframe, self.config.parent_strictness));
        }
        tests
    }

    /// Runs `tests` of keyframe `id`.
    fn run_tests(
        &mut self,
        id: KeyframeId,
        tests: Vec<(KeyframeId, Sim3, f64)>,
        report: &mut ProcessReport,
    ) -> Result<Outcomes> {
        let mut accepted = Vec::new();
        let mut failed = Vec::new();
        let this = self.resident.get(&self.keyframes[&id].kept)?;
        for (cid, initial, strictness) in tests {
            report.candidates_tested += 1;
            let candidate = self.resident.get(&self.keyframes[&cid].kept)?;
            let check = reciprocal_test(&self.tracker, &this, &candidate, &initial, strictness);
            tracing::debug!(
                keyframe = id,
                candidate = cid,
                consistency = check.consistency,
                failed_stage = ?check.failed_stage,
                "reciprocal Sim(3) test"
            );
            match check.constraints {
                Some(pair) => accepted.push(pair),
                None => failed.push((cid, initial)),
            }
        }
        Ok((accepted, failed))
    }

    /// Whether `a` and `b` are joined by a trusted tracked edge (either's).
    fn trusted_between(&self, a: KeyframeId, b: KeyframeId) -> bool {
        let trusts = |from: KeyframeId, to: KeyframeId| {
            self.keyframes
                .get(&from)
                .is_some_and(|e| e.tracked().any(|p| p.trusted && p.id == to))
        };
        trusts(a, b) || trusts(b, a)
    }

    /// Re-tests keyframe `id` against each neighbour (but those a trusted edge joins it to)
    /// from the current relative pose and replaces the pair of edges when accepted.
    pub(super) fn refresh_constraints(
        &mut self,
        id: KeyframeId,
        report: &mut ProcessReport,
    ) -> Result<bool> {
        let Some(entry) = self.keyframes.get(&id) else {
            return Ok(false);
        };
        let Some(pose) = self.graph.pose(id) else {
            return Ok(false);
        };
        let tracked: Vec<KeyframeId> = entry.tracked().map(|p| p.id).collect();
        let mut accepted = Vec::new();
        let this = self.resident.get(&entry.kept)?;
        let neighbours: Vec<KeyframeId> = entry
            .neighbours
            .iter()
            .copied()
            .filter(|&n| !self.trusted_between(id, n))
            .collect();
        for n in neighbours {
            let (Some(other), Some(npose)) = (self.keyframes.get(&n), self.graph.pose(n)) else {
                continue;
            };
            let strictness = if tracked.contains(&n) {
                self.config.parent_strictness
            } else {
                self.config.loop_closure_strictness
            };
            report.candidates_tested += 1;
            let initial = npose.inverse() * pose;
            let other = self.resident.get(&other.kept)?;
            let check = reciprocal_test(&self.tracker, &this, &other, &initial, strictness);
            if let Some(pair) = check.constraints {
                accepted.push(pair);
            }
        }
        let any = !accepted.is_empty();
        report.constraints_refreshed += accepted.len();
        for (forward, backward) in accepted {
            self.graph.remove_edges_between(forward.from, forward.to);
            self.graph.add_edge(forward)?;
            self.graph.add_edge(backward)?;
        }
        Ok(any)
    }
}
