//! A 7×7 information matrix stored as its upper triangle.
//!
//! A long session keeps every pose-graph edge for its whole length (about 12 edges a keyframe,
//! 70 keyframes a minute at 30 fps), and a `Matrix7` is 392 B of each 472 B edge. The
//! information of a Sim(3) edge is symmetric, so its 28 upper entries say everything: 224 B,
//! exact for every symmetric matrix (issue 37). One that is symmetric only up to rounding (an
//! SE(3) tracking's `Adᵀ·H·Ad`) becomes its upper triangle's mirror.

use super::sim3::Matrix7;
use serde::{Deserialize, Serialize};

/// Entries of the upper triangle, row by row.
const ENTRIES: usize = 28;

/// A symmetric 7×7 matrix (tangent order ρ, φ, σ): the upper triangle, row by row.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Information7 {
    upper: [f64; ENTRIES],
}

/// Index of `(row, col)`, `row ≤ col`, in the row-by-row upper triangle.
const fn index(row: usize, col: usize) -> usize {
    row * 7 - row * (row + 1) / 2 + col
}

impl Information7 {
    /// The symmetric matrix whose upper triangle (diagonal included) is `m`'s; its lower
    /// triangle is not read.
    pub fn from_upper(m: &Matrix7) -> Self {
        let mut upper = [0.0; ENTRIES];
        for row in 0..7 {
            for col in row..7 {
                upper[index(row, col)] = m[(row, col)];
            }
        }
        Self { upper }
    }

    /// The full matrix.
    pub fn matrix(&self) -> Matrix7 {
        Matrix7::from_fn(|r, c| self.upper[index(r.min(c), r.max(c))])
    }

    /// Entry `(row, col)` (either order).
    pub fn at(&self, row: usize, col: usize) -> f64 {
        self.upper[index(row.min(col), row.max(col))]
    }

    /// Sum of the diagonal.
    pub fn trace(&self) -> f64 {
        (0..7).map(|i| self.upper[index(i, i)]).sum()
    }

    /// Every entry finite.
    pub fn is_finite(&self) -> bool {
        self.upper.iter().all(|v| v.is_finite())
    }

    /// The matrix times `factor`.
    pub fn scaled(&self, factor: f64) -> Self {
        Self {
            upper: self.upper.map(|v| v * factor),
        }
    }
}

impl From<Matrix7> for Information7 {
    fn from(m: Matrix7) -> Self {
        Self::from_upper(&m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_symmetric_matrix_comes_back_exactly_and_the_lower_triangle_is_not_read() {
        let mut m = Matrix7::from_fn(|r, c| ((r * 7 + c) as f64).sin() * 1e3 + 0.1);
        m = m + m.transpose();
        let packed = Information7::from(m);
        assert_eq!(packed.matrix(), m);
        assert_eq!(packed.trace(), m.trace());
        for r in 0..7 {
            for c in 0..7 {
                assert_eq!(packed.at(r, c), m[(r, c)]);
            }
        }
        let mut skewed = m;
        skewed[(5, 2)] = 7.0;
        assert_eq!(Information7::from(skewed), packed);
        assert_eq!(packed.scaled(2.0).matrix(), m * 2.0);
        assert!(packed.is_finite());
        skewed[(2, 5)] = f64::NAN;
        assert!(!Information7::from(skewed).is_finite());
        assert_eq!(std::mem::size_of::<Information7>(), 224);
    }
}
