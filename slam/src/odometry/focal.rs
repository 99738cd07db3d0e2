//! The focal length chosen at initialisation (issue 35, item 4): one initialiser per
//! candidate focal length, all on the same frames; once they have all handed over, the one
//! whose joint refinement fits the images best ([`Initialiser::score`]) starts the window, and
//! every later frame is taken with its focal length.
//!
//! Why: a wrong focal length bends every later estimate, and a camera's is often not known
//! (a phone streaming without intrinsics) or not right (7-Scenes' colour camera has only the
//! depth camera's nominal 585 px). Under a wrong one no first map fits the images of every
//! frame at once: on rendered sequences the energy per residual is least at the true focal
//! length, ±10 % cost 4-18 % more (docs/tuning.md, 2026-12-07). Each candidate needs its
//! own initialiser: refitting one initialiser's map under another focal length stays in the
//! basin the first one found. Not yet reliable: [0.9, 1, 1.1] chose the true focal length
//! in 76 % of rendered starts, and on real sequences the choice varies from start to start.

use std::sync::Arc;

use super::OdometryConfig;
use super::init::{Initialised, Initialiser};
use crate::frame::Frame;

/// Baseline, in mean depths of the first frame, every candidate must see before they are
/// compared (twice DSO's hand-over parallax of 1/60, about 2°): at the hand-over itself
/// (redkitchen 0-299: a true baseline of 0.004 mean depths) the maps are noise and so are
/// their scores, which chose 0.9 of a focal length that fits best at 1.0 later on.
const MIN_BASELINE: f64 = 1.0 / 30.0;
/// Frames the search waits after the first candidate handed over (2 s at 30 Hz). A camera
/// that has not moved [`MIN_BASELINE`] by then gives no evidence about its focal length:
/// the given one is kept.
const MAX_WAIT: usize = 60;

/// `frame` with its focal lengths (`fx`, `fy`) times `scale`; the same frame when it is 1.
pub fn with_focal(frame: &Arc<Frame>, scale: f64) -> Arc<Frame> {
    if scale == 1.0 {
        return frame.clone();
    }
    let mut camera = frame.camera;
    camera.fx *= scale;
    camera.fy *= scale;
    Arc::new(Frame {
        id: frame.id,
        input_id: frame.input_id,
        timestamp: frame.timestamp,
        camera,
        pyramid: frame.pyramid.clone(),
        rgb: frame.rgb.clone(),
        sensor_depth: frame.sensor_depth.clone(),
    })
}

#[derive(Debug)]
struct Candidate {
    /// Focal length relative to the given one.
    scale: f64,
    initialiser: Initialiser,
    /// Whether its initialiser has handed over (it goes on with every frame after).
    ready: bool,
}

/// Initialisers competing over the focal length.
#[derive(Debug)]
pub struct FocalSearch {
    candidates: Vec<Candidate>,
    /// Frames since the first candidate was ready.
    waited: usize,
}

/// What the search chose: the focal length relative to the given one, and its initialiser's
/// hand-over (first frame and poses with that focal length).
#[derive(Debug)]
pub struct Chosen {
    pub scale: f64,
    pub initialised: Initialised,
    /// Whether the candidates were compared (else the given focal length was kept).
    pub compared: bool,
    /// Every candidate's score: its energy per residual, or when the candidates were not
    /// compared, its distance from the given focal length.
    pub scores: Vec<(f64, f64)>,
}

impl FocalSearch {
    /// One initialiser from `first` per `config.focal_candidates` (the given focal length
    /// alone when there are none), each with about `points` points.
    pub fn new(config: &OdometryConfig, first: &Arc<Frame>, points: usize) -> Self {
        let scales = if config.focal_candidates.is_empty() {
            vec![1.0]
        } else {
            config.focal_candidates.clone()
        };
        Self {
            candidates: scales
                .into_iter()
                .map(|scale| Candidate {
                    scale,
                    initialiser: Initialiser::new(config, with_focal(first, scale), points),
                    ready: false,
                })
                .collect(),
            waited: 0,
        }
    }

    /// Gives `frame` to every candidate; `Some` once the search is over: at once with a
    /// single candidate (the initialiser alone), else when every candidate has handed over
    /// and sees [`MIN_BASELINE`], or [`MAX_WAIT`] frames after the first handed over.
    pub fn push(&mut self, frame: &Arc<Frame>) -> Option<Chosen> {
        for c in &mut self.candidates {
            c.ready |= c.initialiser.push(with_focal(frame, c.scale)).is_some();
        }
        if !self.candidates.iter().any(|c| c.ready) {
            return None;
        }
        self.waited += 1;
        let single = self.candidates.len() == 1;
        let far_enough = |c: &Candidate| c.ready && c.initialiser.baseline() >= MIN_BASELINE;
        let complete = self.candidates.iter().all(far_enough);
        if !single && !complete && self.waited <= MAX_WAIT {
            return None;
        }
        let scores: Vec<(f64, f64)> = self
            .candidates
            .iter()
            .map(|c| {
                let score = if !c.ready {
                    f64::INFINITY
                } else if single || !complete {
                    // Nothing to compare: the given focal length (or the ready one nearest it).
                    (c.scale - 1.0).abs()
                } else {
                    c.initialiser.score()
                };
                (c.scale, score)
            })
            .collect();
        let best = scores
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.1.total_cmp(&b.1.1))
            .map_or(0, |(i, _)| i);
        let winner = &self.candidates[best];
        Some(Chosen {
            scale: winner.scale,
            initialised: winner.initialiser.finish(),
            compared: complete && !single,
            scores,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::synth::{Motion, SynthConfig};
    use crate::odometry::system_tests::rendered_frames;

    /// The scale the search chooses on a rendered hand-held start whose frames carry
    /// `given` times the true focal length.
    fn chosen(given: f64) -> f64 {
        let frames = rendered_frames(&SynthConfig {
            width: 320,
            height: 240,
            seed: 1,
            frames: 60,
            motion: Motion::Handheld,
            ..SynthConfig::default()
        });
        let config = OdometryConfig {
            focal_candidates: vec![0.9, 1.0, 1.1],
            ..OdometryConfig::default()
        };
        let frames: Vec<_> = frames.iter().map(|f| with_focal(f, given)).collect();
        let mut search = FocalSearch::new(&config, &frames[0], 600);
        let done = frames[1..]
            .iter()
            .find_map(|f| search.push(f))
            .expect("a candidate handed over within 60 frames");
        assert!(done.compared, "not compared: {:?}", done.scores);
        done.scale
    }

    #[test]
    fn the_true_focal_length_fits_best() {
        assert_eq!(chosen(1.0), 1.0);
    }

    #[test]
    fn a_focal_length_given_ten_percent_short_is_corrected() {
        // 0.9 × 1.1 = 0.99 of the truth: the candidate nearest it.
        assert_eq!(chosen(0.9), 1.1);
    }
}
