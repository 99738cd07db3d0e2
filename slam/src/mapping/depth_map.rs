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

    /// Bytes of its pixels.
    pub fn heap_bytes(&self) -> usize {
        self.pixels.len() * std::mem::size_of::<InverseDepth>()
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

/// A [`DepthMap`] stored by its estimates (issue 37): one state byte per pixel and the values
/// of the estimates alone. A semi-dense keyframe estimates a fifth to a half of its pixels, so
/// this is 2-4 B per pixel instead of 12; [`CompactDepth::expand`] gives the map back
/// unchanged.
#[derive(Clone, Debug, PartialEq)]
pub struct CompactDepth {
    pub width: usize,
    pub height: usize,
    /// Per pixel: [`UNKNOWN`], [`DISCARDED`] or [`ESTIMATE`].
    states: Vec<u8>,
    /// `(idepth, var)` of the estimates, in pixel order.
    values: Vec<[f32; 2]>,
}

const UNKNOWN: u8 = 0;
const DISCARDED: u8 = 1;
const ESTIMATE: u8 = 2;

impl CompactDepth {
    /// The compact form of `map`.
    pub fn of(map: &DepthMap) -> Self {
        let mut values = Vec::with_capacity(map.num_estimates());
        let states = map
            .pixels
            .iter()
            .map(|p| match *p {
                InverseDepth::Unknown => UNKNOWN,
                InverseDepth::Discarded => DISCARDED,
                InverseDepth::Estimate { idepth, var } => {
                    values.push([idepth, var]);
                    ESTIMATE
                }
            })
            .collect();
        Self {
            width: map.width,
            height: map.height,
            states,
            values,
        }
    }

    /// The full map.
    pub fn expand(&self) -> DepthMap {
        let mut values = self.values.iter();
        let pixels = self
            .states
            .iter()
            .map(|&s| match s {
                ESTIMATE => match values.next() {
                    Some(&[idepth, var]) => InverseDepth::Estimate { idepth, var },
                    None => InverseDepth::Unknown,
                },
                DISCARDED => InverseDepth::Discarded,
                _ => InverseDepth::Unknown,
            })
            .collect();
        DepthMap {
            width: self.width,
            height: self.height,
            pixels,
        }
    }

    /// Number of pixels holding an estimate.
    pub fn num_estimates(&self) -> usize {
        self.values.len()
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.states.len()
    }

    /// Whether the map has no pixel.
    pub fn is_empty(&self) -> bool {
        self.states.is_empty()
    }

    /// [`DepthMap::mean_idepth`] of the full map (same order of summation, same value).
    pub fn mean_idepth(&self) -> Option<f64> {
        let n = self.values.len();
        let sum = self
            .values
            .iter()
            .fold(0.0f64, |s, [d, _]| s + f64::from(*d));
        (n > 0).then(|| sum / n as f64)
    }

    /// Bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.states.len() + 8 * self.values.len()
    }
}

impl crate::spill::Spillable for CompactDepth {
    fn encode(&self, out: &mut crate::spill::Writer) {
        out.u64(self.width as u64);
        out.u64(self.height as u64);
        out.bytes(&self.states);
        out.f32s(bytemuck::cast_slice(&self.values));
    }

    fn decode(input: &mut crate::spill::Reader<'_>) -> crate::Result<Self> {
        let (width, height) = (input.usize()?, input.usize()?);
        let states = input.bytes()?.to_vec();
        let flat = input.f32s()?;
        let values: Vec<[f32; 2]> = flat.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
        let estimates = states.iter().filter(|&&s| s == ESTIMATE).count();
        if width.checked_mul(height) != Some(states.len())
            || flat.len() != 2 * values.len()
            || values.len() != estimates
        {
            return Err(crate::Error::Spill(
                "a spilled depth map is inconsistent".into(),
            ));
        }
        Ok(Self {
            width,
            height,
            states,
            values,
        })
    }

    fn heap_bytes(&self) -> usize {
        CompactDepth::heap_bytes(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compact_depth_expands_to_the_same_map() {
        let mut map = DepthMap::unknown(40, 30);
        for (i, p) in map.pixels.iter_mut().enumerate() {
            *p = match i % 7 {
                0 | 3 => InverseDepth::Estimate {
                    idepth: 0.1 + i as f32 * 1e-3,
                    var: 1e-4 * (1 + i % 5) as f32,
                },
                5 => InverseDepth::Discarded,
                6 => InverseDepth::Estimate {
                    idepth: -0.5,
                    var: 2.0,
                },
                _ => InverseDepth::Unknown,
            };
        }
        let compact = CompactDepth::of(&map);
        assert_eq!(compact.expand(), map);
        assert_eq!(
            crate::spill::round_trip(&compact).expect("spilled"),
            compact
        );
        assert_eq!(compact.num_estimates(), map.num_estimates());
        assert_eq!(compact.mean_idepth(), map.mean_idepth());
        assert!(compact.heap_bytes() * 2 < map.heap_bytes());
        let empty = DepthMap::unknown(8, 6);
        assert_eq!(CompactDepth::of(&empty).expand(), empty);
        assert_eq!(CompactDepth::of(&empty).mean_idepth(), None);
    }
}
