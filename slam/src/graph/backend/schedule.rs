//! How much of its queued work the back end does in one pass ([`Budget`]).
//!
//! A keyframe's full constraint search and a depth refresh each run several reciprocal Sim(3)
//! tests, some against keyframes read back from the session's store. On a loaded machine the
//! back end then takes longer per keyframe than the front end takes to make one, falls behind
//! without bound, fills its queue and stalls the frame path: a 640×480 session of 20 minutes
//! on 2 cores had 520 keyframes in its pipeline and 267 in its back end, and took no frames
//! for minutes (docs/tuning.md, "Long sessions, issue 37"). LSD-SLAM's constraint-search
//! thread simply lags; here a pass that finds the back end behind (several new keyframes
//! queued at once) gives the newest keyframes their full search, links the older ones to
//! their parent only and defers their full search and their depth refreshes until a pass
//! finds it caught up. A caught-up pass then takes only a few of each, oldest first: running
//! every waiting refresh at once made single passes of 90 s and queue spikes of 185 commands
//! in an hour's session (docs/tuning.md, "thirty-seventh stop"). The final pass of a session
//! does everything, so loop closures are found late, not missed; in step (deterministic runs)
//! every pass is a caught-up one.

use super::super::KeyframeId;
use super::{Backend, ProcessReport};
use crate::Result;
use crate::graph::OptimizeReport;

/// How much a [`Backend::process_within`] pass does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Budget {
    /// Everything queued and deferred (the final pass; [`Backend::process`]).
    All,
    /// Caught up: every new keyframe in full, then up to `n` depth refreshes and up to `n`
    /// deferred searches, oldest first.
    CaughtUp(usize),
    /// Behind: full searches for the `n` newest keyframes, the parent test for the others;
    /// depth refreshes wait.
    Behind(usize),
}

impl Budget {
    /// The budget of a pass that finds `new_keyframes` queued: behind when more than
    /// `catch_up` arrived since the last pass.
    pub fn for_pass(new_keyframes: usize, catch_up: usize) -> Self {
        if new_keyframes > catch_up {
            Self::Behind(catch_up)
        } else {
            Self::CaughtUp(catch_up)
        }
    }
}

/// The stages of a pass, timed for the debug log: what a loaded back end spends its time on.
#[derive(Clone, Copy)]
enum Stage {
    New,
    Refresh,
    CatchUp,
    Optimize,
    Window,
}

/// Milliseconds per [`Stage`] of one pass.
struct StageClock {
    last: std::time::Instant,
    ms: [u64; 5],
}

impl Default for StageClock {
    fn default() -> Self {
        Self {
            last: std::time::Instant::now(),
            ms: [0; 5],
        }
    }
}

impl StageClock {
    /// Ends `stage`: the time since the previous lap is its.
    fn lap(&mut self, stage: Stage) {
        let now = std::time::Instant::now();
        self.ms[stage as usize] = (now - self.last).as_millis() as u64;
        self.last = now;
    }
}

impl Backend {
    /// Searches constraints for every pending keyframe (in arrival order), re-estimates those of
    /// keyframes whose depth was updated, and optimises the graph when edges or scale factors
    /// changed. Deterministic: same inputs, same outputs.
    pub fn process(&mut self) -> Result<ProcessReport> {
        self.process_within(Budget::All)
    }

    /// [`Backend::process`] within `budget` (module docs).
    pub fn process_within(&mut self, budget: Budget) -> Result<ProcessReport> {
        let mut report = ProcessReport::default();
        let mut added = false;
        let mut clock = StageClock::default();
        let pending = std::mem::take(&mut self.pending);
        let searched = !pending.is_empty();
        let full_from = match budget {
            Budget::Behind(n) => pending.len().saturating_sub(n),
            _ => 0,
        };
        for (i, id) in pending.into_iter().enumerate() {
            report.keyframes_searched += 1;
            let full = i >= full_from;
            added |= self.search(id, full, &mut report)?;
            if !full {
                self.deferred.push_back(id);
                report.searches_deferred += 1;
            }
        }
        clock.lap(Stage::New);
        let catch_up = match budget {
            Budget::All => usize::MAX,
            Budget::CaughtUp(n) => n,
            Budget::Behind(_) => 0,
        };
        let refreshes: Vec<_> = (self.refresh)
            .drain(..catch_up.min(self.refresh.len()))
            .collect();
        for id in refreshes {
            added |= self.refresh_constraints(id, &mut report)?;
        }
        clock.lap(Stage::Refresh);
        for _ in 0..catch_up {
            let Some(id) = self.deferred.pop_front() else {
                break;
            };
            report.keyframes_searched += 1;
            added |= self.search(id, true, &mut report)?;
        }
        clock.lap(Stage::CatchUp);
        let max = self.config.deferred_max;
        let (old_searches, old_refreshes) = (
            self.deferred.len().saturating_sub(max),
            self.refresh.len().saturating_sub(max),
        );
        self.deferred.drain(..old_searches);
        self.refresh.drain(..old_refreshes);
        report.searches_dropped += old_searches + old_refreshes;
        self.searches_given_up += report.searches_dropped;
        if report.searches_dropped > 0 {
            tracing::warn!(
                dropped = report.searches_dropped,
                "back end far behind: deferred constraint searches given up"
            );
        }
        added |= std::mem::take(&mut self.scale_observed);
        if added {
            report.optimize = Some(self.optimize_within(budget)?);
        }
        clock.lap(Stage::Optimize);
        if searched && self.config.window.enabled && self.run_window(&mut report)? {
            report.optimize = Some(self.optimize_within(budget)?);
        }
        clock.lap(Stage::Window);
        tracing::debug!(
            ?budget,
            keyframes = self.keyframes.len(),
            searched = report.keyframes_searched,
            tests = report.candidates_tested,
            ms = ?clock.ms,
            "back-end pass (ms: new, refresh, catch-up, optimise, window)"
        );
        Ok(report)
    }

    /// The whole graph in the final pass, a bounded neighbourhood of what changed in a live
    /// one ([`crate::graph::PoseGraph::optimize_bounded`]).
    pub(super) fn optimize_within(&mut self, budget: Budget) -> Result<OptimizeReport> {
        let iterations = self.config.max_optimization_iterations;
        let report = match budget {
            Budget::All => self.graph.optimize(iterations)?,
            _ => {
                (self.graph).optimize_bounded(self.config.live_optimization_vertices, iterations)?
            }
        };
        self.optimizations[usize::from(report.bounded)] += 1;
        Ok(report)
    }

    /// Keyframes whose full constraint search waits for the back end to catch up.
    pub fn deferred(&self) -> impl Iterator<Item = KeyframeId> + '_ {
        self.deferred.iter().copied()
    }

    /// Keyframes whose constraints wait to be re-tested with their updated depth, oldest first.
    pub fn refreshes(&self) -> impl Iterator<Item = KeyframeId> + '_ {
        self.refresh.iter().copied()
    }
}
