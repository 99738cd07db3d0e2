//! The DSO-class odometry back end: a sliding window of keyframes whose poses, affine
//! brightness and point depths are estimated jointly, old keyframes leaving through
//! marginalisation (Engel, Koltun and Cremers, "Direct Sparse Odometry", TPAMI 2018;
//! `../shared/design-odometry.md` maps the method).
//!
//! Why: the LSD-style loop (track against a fixed map, update depths as if the pose were
//! exact, propagate) is coordinate descent along the rotation–translation ambiguity, so the
//! map's depth shape and then its scale drift (issue 35). In a joint window a wrong shape costs
//! residual in every keyframe that sees it, and the prior carries what old keyframes measured,
//! relative scale included, instead of fixing them.
//!
//! - [`residual`]: the 8-pixel photometric residual and its first-estimate Jacobians;
//! - [`energy`]: robust weights, outliers, normal equations with the depths kept apart;
//! - [`solve`]: Levenberg–Marquardt with the Schur complement, the step out of the gauge;
//! - [`prior`]: the marginalisation prior; [`gauge`]: the 7 unobservable directions;
//! - [`select`]: candidate points spread over the image by a region-adaptive threshold.

pub mod config;
pub mod energy;
pub mod gauge;
pub mod prior;
pub mod residual;
pub mod select;
pub mod solve;

use std::sync::Arc;

use nalgebra::Vector2;

pub use config::OdometryConfig;
pub use prior::MarginalisationPrior;
pub use residual::{FrameState, Linearisation, PATTERN};
pub use solve::SolveReport;

use crate::frame::Frame;
use crate::{Error, Result};

/// A keyframe of the window.
#[derive(Clone, Debug)]
pub struct WindowFrame {
    pub id: u64,
    pub frame: Arc<Frame>,
    pub state: FrameState,
    /// The state at which its Jacobians are evaluated: where it entered the window.
    pub first_estimate: FrameState,
}

/// An active point: one inverse depth in its host keyframe's camera.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowPoint {
    /// Id of the host keyframe.
    pub host: u64,
    /// Pixel in the host at the window's pyramid level.
    pub uv: Vector2<f64>,
    pub idepth: f64,
    /// Host intensities at the pattern pixels.
    pub intensity: [f64; PATTERN.len()],
}

/// The sliding window: keyframes, their active points and the marginalisation prior.
#[derive(Clone, Debug)]
pub struct SlidingWindow {
    config: OdometryConfig,
    frames: Vec<WindowFrame>,
    points: Vec<WindowPoint>,
    prior: MarginalisationPrior,
    linearisation: Linearisation,
}

impl SlidingWindow {
    /// An empty window.
    pub fn new(config: OdometryConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            config,
            frames: Vec::new(),
            points: Vec::new(),
            prior: MarginalisationPrior::default(),
            linearisation: Linearisation::FirstEstimate,
        })
    }

    /// The same window with Jacobians at the current state instead of the first estimates:
    /// only to measure what first-estimate Jacobians prevent.
    pub fn with_linearisation(mut self, linearisation: Linearisation) -> Self {
        self.linearisation = linearisation;
        self
    }

    pub fn config(&self) -> &OdometryConfig {
        &self.config
    }

    /// Keyframes, oldest first.
    pub fn frames(&self) -> &[WindowFrame] {
        &self.frames
    }

    pub fn points(&self) -> &[WindowPoint] {
        &self.points
    }

    pub fn prior(&self) -> &MarginalisationPrior {
        &self.prior
    }

    fn index_of(&self, id: u64) -> Option<usize> {
        self.frames.iter().position(|f| f.id == id)
    }

    /// Index in [`Self::frames`] of every point's host.
    fn hosts(&self) -> Vec<usize> {
        self.points
            .iter()
            .map(|p| {
                self.index_of(p.host)
                    .unwrap_or_else(|| unreachable!("hosts stay in the window"))
            })
            .collect()
    }

    /// Adds keyframe `id` at `state`, which also becomes its first estimate.
    pub fn add_frame(&mut self, id: u64, frame: Arc<Frame>, state: FrameState) -> Result<()> {
        if self.index_of(id).is_some() {
            return Err(Error::Config(format!(
                "keyframe {id} is already in the window"
            )));
        }
        if frame.pyramid.levels.len() <= self.config.level {
            return Err(Error::Shape(format!(
                "keyframe {id} has {} pyramid levels, the window works on level {}",
                frame.pyramid.levels.len(),
                self.config.level
            )));
        }
        self.frames.push(WindowFrame {
            id,
            frame,
            state,
            first_estimate: state,
        });
        self.prior.push_frame();
        Ok(())
    }

    /// Activates a point of keyframe `host` at pixel `uv` (window level) with inverse depth
    /// `idepth`; `false` when the host is not in the window, the depth is not positive or the
    /// pattern leaves the image.
    pub fn add_point(&mut self, host: u64, uv: Vector2<f64>, idepth: f64) -> bool {
        let Some(k) = self.index_of(host) else {
            return false;
        };
        if !(idepth.is_finite() && idepth > 0.0) {
            return false;
        }
        let level = self.frames[k].frame.level(self.config.level);
        let mut intensity = [0.0; PATTERN.len()];
        for (value, (ox, oy)) in intensity.iter_mut().zip(PATTERN) {
            match level.image.bilinear((uv.x + ox) as f32, (uv.y + oy) as f32) {
                Some(v) => *value = f64::from(v),
                None => return false,
            }
        }
        self.points.push(WindowPoint {
            host,
            uv,
            idepth,
            intensity,
        });
        true
    }

    /// Optimises every keyframe and point of the window jointly.
    pub fn optimize(&mut self) -> SolveReport {
        let hosts = self.hosts();
        solve::optimize(
            &self.config,
            &mut self.frames,
            &mut self.points,
            &hosts,
            &self.prior,
            self.linearisation,
        )
    }

    /// The window's normal equations at the current state with every depth eliminated:
    /// `(H, b)` over the keyframes' parameters (what the solver steps on, undamped).
    pub fn reduced_system(&self) -> (nalgebra::DMatrix<f64>, nalgebra::DVector<f64>) {
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        solve::normal_equations(
            &self.config,
            &self.frames,
            &states,
            &self.points,
            &self.hosts(),
            &self.prior,
            self.linearisation,
        )
        .reduced(0.0)
    }

    /// Marginalises keyframe `id`: its points' residuals (weighted by
    /// `marginalisation_weight`) and its affine prior go into the prior with their depths
    /// eliminated, then the keyframe itself is eliminated from the prior; residuals of other
    /// points in it are dropped (DSO, `FullSystemMarginalize.cpp`).
    pub fn marginalize_frame(&mut self, id: u64) -> Result<()> {
        let k = self
            .index_of(id)
            .ok_or_else(|| Error::Config(format!("keyframe {id} is not in the window")))?;
        let states: Vec<FrameState> = self.frames.iter().map(|f| f.state).collect();
        let views = solve::views(&self.config, &self.frames, &states);
        let mut eq = energy::NormalEquations::zeros(self.frames.len());
        for p in self.points.iter().filter(|p| p.host == id) {
            eq.add_point(&self.config, p, k, &views, self.linearisation);
        }
        let (mut h, mut g) = eq.reduced(0.0);
        h *= self.config.marginalisation_weight;
        g *= self.config.marginalisation_weight;
        // The keyframe's own affine prior goes with it (it would otherwise be lost).
        solve::add_affine_prior(&self.config, k, &states[k], &mut h, &mut g);
        let delta = solve::offsets(&self.frames, &states);
        self.prior.add_linearised(&h, &g, &delta);
        self.prior.remove_frame(k);
        self.frames.remove(k);
        self.points.retain(|p| p.host != id);
        Ok(())
    }
}

#[cfg(test)]
mod tests;
