//! The semi-dense inverse-depth map of a keyframe, as tracking and the dense layer consume it.
//!
//! The depth filter (`mapping::filter`) keeps richer per-pixel state (raw and regularised
//! estimates, validity counters, blacklisting); this is its published snapshot: one
//! [`InverseDepth`] per full-resolution pixel, in the keyframe's own scale.

/// What is known about the inverse depth of one pixel (state in the type, after vors).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum InverseDepth {
    /// Never estimated (low gradient, or not yet observed).
    #[default]
    Unknown,
    /// Estimated once but rejected as an outlier.
    Discarded,
    /// A Gaussian estimate: inverse depth `idepth` (> 0) with variance `var`.
    Estimate { idepth: f32, var: f32 },
}

impl InverseDepth {
    /// `(idepth, var)` when this pixel holds an estimate.
    #[inline]
    pub fn estimate(self) -> Option<(f32, f32)> {
        match self {
            InverseDepth::Estimate { idepth, var } => Some((idepth, var)),
            _ => None,
        }
    }
}

/// A full-resolution map of [`InverseDepth`], row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<InverseDepth>,
}

impl DepthMap {
    /// A map with every pixel [`InverseDepth::Unknown`].
    pub fn unknown(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            pixels: vec![InverseDepth::Unknown; width * height],
        }
    }

    /// The pixel at column `x`, row `y`.
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> InverseDepth {
        self.pixels[y * self.width + x]
    }

    /// Number of pixels holding an estimate.
    pub fn num_estimates(&self) -> usize {
        self.pixels
            .iter()
            .filter(|p| p.estimate().is_some())
            .count()
    }

    /// Mean inverse depth over the estimates (LSD-SLAM normalises each new keyframe's map so
    /// that this is 1, which fixes the monocular scale gauge); `None` without estimates.
    pub fn mean_idepth(&self) -> Option<f64> {
        let (sum, n) = self
            .pixels
            .iter()
            .filter_map(|p| p.estimate())
            .fold((0.0f64, 0usize), |(s, n), (d, _)| (s + f64::from(d), n + 1));
        (n > 0).then(|| sum / n as f64)
    }
}
