//! A small block-sparse Cholesky factorisation for the pose graph's normal equations.
//!
//! The Hessian of a keyframe pose graph has one 7×7 block per keyframe on the diagonal and one
//! per edge off it. Keyframes arrive in time order and most edges join neighbours in time, so
//! the natural (insertion) order already has a narrow profile; loop-closure edges add fill-in
//! between their end points only. A right-looking block factorisation `H = L·Lᵀ` in that order,
//! with the lower blocks of each column in a `BTreeMap` (fill-in is created on demand), is
//! exact, deterministic and fast enough for thousands of keyframes — no external sparse solver
//! (and its compile time) needed.

use std::collections::BTreeMap;

use nalgebra::{Cholesky, DMatrix, DVector};

use crate::geometry::{Matrix7, Vector7};

/// A symmetric positive-definite matrix of `n × n` blocks of size 7; only the lower triangle
/// (row ≥ column) is stored.
#[derive(Clone, Debug, Default)]
pub struct BlockSparseSymmetric {
    /// `columns[c]` maps a row index r ≥ c to the block (r, c).
    columns: Vec<BTreeMap<usize, Matrix7>>,
}

impl BlockSparseSymmetric {
    /// An all-zero matrix of `n` block rows and columns.
    pub fn new(n: usize) -> Self {
        Self {
            columns: vec![BTreeMap::new(); n],
        }
    }

    /// Number of block rows.
    pub fn size(&self) -> usize {
        self.columns.len()
    }

    /// Adds `block` to block (row, col) and, implicitly, its transpose to (col, row).
    pub fn add(&mut self, row: usize, col: usize, block: &Matrix7) {
        let (r, c, b) = if row >= col {
            (row, col, *block)
        } else {
            (col, row, block.transpose())
        };
        *self.columns[c].entry(r).or_insert_with(Matrix7::zeros) += b;
    }

    /// Block (i, i).
    pub fn diagonal(&self, i: usize) -> Matrix7 {
        self.columns[i]
            .get(&i)
            .copied()
            .unwrap_or_else(Matrix7::zeros)
    }

    /// The dense matrix (tests and small debugging).
    pub fn to_dense(&self) -> DMatrix<f64> {
        let n = self.size() * 7;
        let mut m = DMatrix::zeros(n, n);
        for (c, col) in self.columns.iter().enumerate() {
            for (&r, b) in col {
                m.view_mut((7 * r, 7 * c), (7, 7)).copy_from(b);
                if r != c {
                    m.view_mut((7 * c, 7 * r), (7, 7)).copy_from(&b.transpose());
                }
            }
        }
        m
    }

    /// Solves `H·x = b` by block Cholesky; `None` when H is not positive definite.
    pub fn solve(&self, b: &[Vector7]) -> Option<Vec<Vector7>> {
        let n = self.size();
        if b.len() != n {
            return None;
        }
        // Right-looking factorisation: columns become the blocks of L.
        let mut l = self.columns.clone();
        for k in 0..n {
            let diag = l[k].get(&k).copied().unwrap_or_else(Matrix7::zeros);
            let chol = Cholesky::new(diag)?;
            let l_kk = chol.l();
            // L_ik = A_ik · L_kk⁻ᵀ  ⇔  L_kk · L_ikᵀ = A_ikᵀ.
            let below: Vec<(usize, Matrix7)> = l[k]
                .range(k + 1..)
                .map(|(&i, a_ik)| {
                    let x = l_kk
                        .solve_lower_triangular(&a_ik.transpose())
                        .unwrap_or_else(|| Matrix7::repeat(f64::NAN));
                    (i, x.transpose())
                })
                .collect();
            if below.iter().any(|(_, m)| m.iter().any(|v| !v.is_finite())) {
                return None;
            }
            l[k].insert(k, l_kk);
            // Schur complement update of the trailing matrix, creating fill-in.
            for (a, (j, l_jk)) in below.iter().enumerate() {
                for (i, l_ik) in &below[a..] {
                    *l[*j].entry(*i).or_insert_with(Matrix7::zeros) -= l_ik * l_jk.transpose();
                }
            }
            for (i, m) in below {
                l[k].insert(i, m);
            }
        }
        // Forward substitution L·y = b (column-oriented).
        let mut y: Vec<Vector7> = b.to_vec();
        for k in 0..n {
            let l_kk = l[k].get(&k)?;
            let yk = l_kk.solve_lower_triangular(&y[k])?;
            y[k] = yk;
            for (&i, l_ik) in l[k].range(k + 1..) {
                y[i] -= l_ik * yk;
            }
        }
        // Back substitution Lᵀ·x = y.
        let mut x = y;
        for k in (0..n).rev() {
            let mut rhs = x[k];
            for (&i, l_ik) in l[k].range(k + 1..) {
                rhs -= l_ik.transpose() * x[i];
            }
            let l_kk = l[k].get(&k)?;
            x[k] = l_kk.transpose().solve_upper_triangular(&rhs)?;
        }
        x.iter()
            .all(|v| v.iter().all(|e| e.is_finite()))
            .then_some(x)
    }
}

/// Flattens block vectors (tests).
pub fn flatten(v: &[Vector7]) -> DVector<f64> {
    DVector::from_iterator(v.len() * 7, v.iter().flat_map(|b| b.iter().copied()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_block(rng: &mut ChaCha8Rng) -> Matrix7 {
        Matrix7::from_fn(|_, _| rng.random_range(-1.0..1.0))
    }

    #[test]
    fn block_cholesky_matches_dense_solve_with_loop_fill_in() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let n = 12;
        let mut h = BlockSparseSymmetric::new(n);
        // A chain plus two loop edges (fill-in between 1..9 and 3..11).
        let mut edges: Vec<(usize, usize)> = (0..n - 1).map(|i| (i, i + 1)).collect();
        edges.extend([(1, 9), (3, 11)]);
        for &(i, j) in &edges {
            let a = random_block(&mut rng);
            let b = random_block(&mut rng);
            // Jᵀ J of a residual r = A·x_i + B·x_j.
            h.add(i, i, &(a.transpose() * a));
            h.add(j, j, &(b.transpose() * b));
            h.add(j, i, &(b.transpose() * a));
        }
        h.add(0, 0, &(Matrix7::identity() * 1e-3));
        let b: Vec<Vector7> = (0..n)
            .map(|_| Vector7::from_fn(|_, _| rng.random_range(-1.0..1.0)))
            .collect();
        let x = h.solve(&b).expect("positive definite");
        let dense = h.to_dense();
        let x_dense = dense
            .clone()
            .cholesky()
            .expect("dense SPD")
            .solve(&flatten(&b));
        let err = (flatten(&x) - &x_dense).norm() / x_dense.norm();
        assert!(err < 1e-9, "relative difference {err}");
        assert!((dense * flatten(&x) - flatten(&b)).norm() < 1e-8);
    }

    #[test]
    fn block_cholesky_rejects_indefinite_matrices() {
        let mut h = BlockSparseSymmetric::new(2);
        h.add(0, 0, &Matrix7::identity());
        h.add(1, 1, &(-Matrix7::identity()));
        assert!(h.solve(&[Vector7::zeros(), Vector7::zeros()]).is_none());
    }
}
