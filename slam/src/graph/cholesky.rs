//! A small block-sparse Cholesky factorisation for the pose graph's normal equations.
//!
//! The Hessian of a keyframe pose graph has one 7×7 block per keyframe on the diagonal and one
//! per edge off it. In insertion (time) order a loop-closure edge fills in every block between
//! its end points, so a long session that keeps revisiting its start makes the factor dense:
//! 800 keyframes of a 50-keyframe loop took 20 s per solve, O(n³), and stalled the back end
//! (issue 37). The factorisation therefore eliminates in a fill-reducing order, greedy minimum
//! degree (Tinney and Walker 1967; George and Liu, "Computer Solution of Large Sparse Positive
//! Definite Systems", 1981), the ordering sparse solvers such as CHOLMOD and g2o use in its
//! approximate form. A right-looking block factorisation `H = L·Lᵀ` in that order, with the
//! lower blocks of each column in a `BTreeMap` (fill-in is created on demand), is exact,
//! deterministic and fast enough for thousands of keyframes — no external sparse solver (and
//! its compile time) needed.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{Cholesky, DMatrix, DVector};

use crate::geometry::{Matrix7, Vector7};

/// The size of a block Cholesky factor ([`BlockSparseSymmetric::factor_size`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FactorSize {
    /// 7×7 blocks of L, diagonal included.
    pub blocks: usize,
    /// 7×7 block products of the Schur complement updates (the work of factorising).
    pub block_products: usize,
}

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

    /// Solves `H·x = b` by block Cholesky in a minimum-degree order; `None` when H is not
    /// positive definite.
    pub fn solve(&self, b: &[Vector7]) -> Option<Vec<Vector7>> {
        self.solve_ordered(b, &self.minimum_degree_order())
    }

    /// [`BlockSparseSymmetric::solve`] eliminating in `order` (a permutation of the block
    /// indices), e.g. one minimum-degree order reused for every matrix of the same structure.
    pub fn solve_ordered(&self, b: &[Vector7], order: &[usize]) -> Option<Vec<Vector7>> {
        let n = self.size();
        if b.len() != n || order.len() != n {
            return None;
        }
        // position[old] = new index.
        let mut position = vec![0; n];
        for (new, &old) in order.iter().enumerate() {
            position[old] = new;
        }
        let mut permuted = Self::new(n);
        for (c, column) in self.columns.iter().enumerate() {
            for (&r, block) in column {
                permuted.add(position[r], position[c], block);
            }
        }
        let rhs: Vec<Vector7> = order.iter().map(|&old| b[old]).collect();
        let y = permuted.solve_in_order(&rhs)?;
        Some((0..n).map(|old| y[position[old]]).collect())
    }

    /// The elimination order of greedy minimum degree on the block graph: repeatedly the
    /// vertex with the fewest neighbours (ties: the lowest index, so it is deterministic),
    /// whose neighbours then become a clique (the fill its elimination creates). It costs the
    /// symbolic factorisation, a small part of the numeric one on 7×7 blocks.
    pub fn minimum_degree_order(&self) -> Vec<usize> {
        let mut neighbours = self.block_graph();
        let mut queue: BTreeSet<(usize, usize)> = neighbours
            .iter()
            .enumerate()
            .map(|(v, adjacent)| (adjacent.len(), v))
            .collect();
        let mut order = Vec::with_capacity(self.size());
        while let Some((_, v)) = queue.pop_first() {
            order.push(v);
            for &a in &neighbours[v] {
                queue.remove(&(neighbours[a].len(), a));
            }
            for a in eliminate(&mut neighbours, v) {
                queue.insert((neighbours[a].len(), a));
            }
        }
        order
    }

    /// The size of the Cholesky factor when eliminating in `order` (a permutation of the block
    /// indices): its memory and its work.
    pub fn factor_size(&self, order: &[usize]) -> FactorSize {
        let mut neighbours = self.block_graph();
        let mut size = FactorSize::default();
        for &v in order {
            let below = eliminate(&mut neighbours, v).len();
            size.blocks += 1 + below;
            size.block_products += below * (below + 1) / 2;
        }
        size
    }

    /// The off-diagonal structure as adjacency sets.
    fn block_graph(&self) -> Vec<BTreeSet<usize>> {
        let mut neighbours = vec![BTreeSet::new(); self.size()];
        for (c, column) in self.columns.iter().enumerate() {
            for &r in column.keys().filter(|&&r| r != c) {
                neighbours[r].insert(c);
                neighbours[c].insert(r);
            }
        }
        neighbours
    }

    /// Block Cholesky in the matrix's own order.
    fn solve_in_order(&self, b: &[Vector7]) -> Option<Vec<Vector7>> {
        let n = self.size();
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

/// Eliminates vertex `v` from the block graph: its neighbours become a clique (the fill its
/// elimination creates) and lose `v`. Returns those neighbours.
fn eliminate(neighbours: &mut [BTreeSet<usize>], v: usize) -> BTreeSet<usize> {
    let adjacent = std::mem::take(&mut neighbours[v]);
    for &a in &adjacent {
        neighbours[a].remove(&v);
        neighbours[a].extend(adjacent.iter().copied().filter(|&o| o != a));
    }
    adjacent
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

    /// The block structure of a session that keeps revisiting its start: a chain of `n`
    /// keyframes (edges to the 3 previous ones) on a loop of `lap` keyframes, each also joined
    /// to the same place in every earlier lap.
    fn looping_session(n: usize, lap: usize) -> BlockSparseSymmetric {
        let mut h = BlockSparseSymmetric::new(n);
        for i in 0..n {
            h.add(i, i, &(Matrix7::identity() * 8.0));
            let chain = (1..=3).filter(|d| *d <= i).map(|d| i - d);
            let loops = (1..=i / lap).map(|k| i - k * lap);
            for j in chain.chain(loops) {
                h.add(i, j, &(Matrix7::identity() * -0.1));
            }
        }
        h
    }

    #[test]
    fn minimum_degree_keeps_a_looping_session_sparse_and_solves_it_exactly() {
        let h = looping_session(600, 50);
        let insertion: Vec<usize> = (0..600).collect();
        let order = h.minimum_degree_order();
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, insertion, "a permutation");
        let (dense, sparse) = (h.factor_size(&insertion), h.factor_size(&order));
        // Insertion order fills nearly the whole lower triangle (600·601/2 = 180 300 blocks)
        // and costs ~n³/6 block products.
        assert!(dense.blocks > 150_000, "insertion order: {dense:?}");
        assert!(
            sparse.blocks * 4 < dense.blocks && sparse.block_products * 10 < dense.block_products,
            "minimum degree {sparse:?} vs insertion {dense:?}"
        );
        let b: Vec<Vector7> = (0..600)
            .map(|i| Vector7::from_fn(|r, _| ((i * 7 + r) as f64).sin()))
            .collect();
        let x = h.solve(&b).expect("diagonally dominant");
        let residual = h.to_dense() * flatten(&x) - flatten(&b);
        assert!(residual.norm() < 1e-9 * flatten(&b).norm());
    }

    #[test]
    fn block_cholesky_rejects_indefinite_matrices() {
        let mut h = BlockSparseSymmetric::new(2);
        h.add(0, 0, &Matrix7::identity());
        h.add(1, 1, &(-Matrix7::identity()));
        assert!(h.solve(&[Vector7::zeros(), Vector7::zeros()]).is_none());
    }
}
