//! A small block-sparse Cholesky factorisation for the pose graph's normal equations.
//!
//! The Hessian of a keyframe pose graph has one 7×7 block per keyframe on the diagonal and one
//! per edge off it. In insertion (time) order a loop-closure edge fills in every block between
//! its end points, so a long session that keeps revisiting its start makes the factor dense:
//! 800 keyframes of a 50-keyframe loop took 20 s per solve, O(n³), and stalled the back end
//! (issue 37). The factorisation therefore eliminates in a fill-reducing order, greedy minimum
//! degree (Tinney and Walker 1967; George and Liu, "Computer Solution of Large Sparse Positive
//! Definite Systems", 1981), the ordering sparse solvers such as CHOLMOD and g2o use in its
//! approximate form. The factor's structure comes first from the elimination tree (the
//! symbolic factorisation, George and Liu ch. 5), so the numeric right-looking factorisation
//! `H = L·Lᵀ` fills a few contiguous arrays: a factor kept as one small tree node per block
//! (thousands of 4 kB allocations per solve, freed again) fragmented the heap of hour-long
//! sessions (issue 37). Exact, deterministic and fast enough for thousands of keyframes — no
//! external sparse solver (and its compile time) needed.

use std::collections::{BTreeSet, HashMap};

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
/// (row ≥ column) is stored, as a list of blocks with an index by position (two contiguous
/// arrays and a hash table, whatever the number of blocks).
#[derive(Clone, Debug, Default)]
pub struct BlockSparseSymmetric {
    n: usize,
    /// (row, column) of each stored block, row ≥ column, in insertion order.
    positions: Vec<(usize, usize)>,
    blocks: Vec<Matrix7>,
    /// Position → index into `positions` and `blocks`.
    index: HashMap<(usize, usize), usize>,
}

impl BlockSparseSymmetric {
    /// An all-zero matrix of `n` block rows and columns.
    pub fn new(n: usize) -> Self {
        Self {
            n,
            ..Self::default()
        }
    }

    /// Number of block rows.
    pub fn size(&self) -> usize {
        self.n
    }

    /// Blocks stored: the diagonal and the lower triangle's (each 7×7 doubles).
    pub fn stored_blocks(&self) -> usize {
        self.blocks.len()
    }

    /// Adds `block` to block (row, col) and, implicitly, its transpose to (col, row).
    pub fn add(&mut self, row: usize, col: usize, block: &Matrix7) {
        let (r, c, b) = if row >= col {
            (row, col, *block)
        } else {
            (col, row, block.transpose())
        };
        assert!(
            r < self.n,
            "block ({r}, {c}) outside a {0}×{0} matrix",
            self.n
        );
        let next = self.blocks.len();
        let at = *self.index.entry((r, c)).or_insert(next);
        if at == next {
            self.positions.push((r, c));
            self.blocks.push(b);
        } else {
            self.blocks[at] += b;
        }
    }

    /// Block (i, i).
    pub fn diagonal(&self, i: usize) -> Matrix7 {
        self.index
            .get(&(i, i))
            .map_or_else(Matrix7::zeros, |&at| self.blocks[at])
    }

    /// The stored lower blocks: (row, column, block).
    pub(super) fn entries(&self) -> impl Iterator<Item = (usize, usize, &Matrix7)> {
        self.positions
            .iter()
            .zip(&self.blocks)
            .map(|(&(r, c), b)| (r, c, b))
    }

    /// The dense matrix (tests and small debugging).
    pub fn to_dense(&self) -> DMatrix<f64> {
        let n = self.size() * 7;
        let mut m = DMatrix::zeros(n, n);
        for (r, c, b) in self.entries() {
            m.view_mut((7 * r, 7 * c), (7, 7)).copy_from(b);
            if r != c {
                m.view_mut((7 * c, 7 * r), (7, 7)).copy_from(&b.transpose());
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
        let position = inverse_permutation(order)?;
        let mut factor = Factor::symbolic(self, &position);
        factor.factorise(self, &position)?;
        let rhs: Vec<Vector7> = order.iter().map(|&old| b[old]).collect();
        let y = factor.solve(rhs)?;
        Some((0..n).map(|old| y[position[old]]).collect())
    }

    /// The elimination order of greedy minimum degree on the block graph: repeatedly the
    /// vertex with the fewest neighbours (ties: the lowest index, so it is deterministic),
    /// whose neighbours then become a clique (the fill its elimination creates). It costs a
    /// small part of the numeric factorisation on 7×7 blocks.
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
    /// indices): its memory and its work. Empty when `order` is not a permutation.
    pub fn factor_size(&self, order: &[usize]) -> FactorSize {
        let Some(position) = inverse_permutation(order).filter(|p| p.len() == self.n) else {
            return FactorSize::default();
        };
        let factor = Factor::symbolic(self, &position);
        let mut size = FactorSize::default();
        for k in 0..self.n {
            let below = factor.start[k + 1] - factor.start[k];
            size.blocks += 1 + below;
            size.block_products += below * (below + 1) / 2;
        }
        size
    }

    /// The off-diagonal structure as sorted adjacency lists.
    fn block_graph(&self) -> Vec<Vec<usize>> {
        let mut neighbours = vec![Vec::new(); self.size()];
        for (r, c, _) in self.entries().filter(|(r, c, _)| r != c) {
            neighbours[r].push(c);
            neighbours[c].push(r);
        }
        for adjacent in &mut neighbours {
            adjacent.sort_unstable();
            adjacent.dedup();
        }
        neighbours
    }
}

/// `position[old] = new` for a permutation `order[new] = old`; `None` when `order` is not one.
fn inverse_permutation(order: &[usize]) -> Option<Vec<usize>> {
    let mut position = vec![usize::MAX; order.len()];
    for (new, &old) in order.iter().enumerate() {
        let slot = position.get_mut(old)?;
        if *slot != usize::MAX {
            return None;
        }
        *slot = new;
    }
    Some(position)
}

/// Eliminates vertex `v` from the block graph: its neighbours become a clique (the fill its
/// elimination creates) and lose `v`. Returns those neighbours.
fn eliminate(neighbours: &mut [Vec<usize>], v: usize) -> Vec<usize> {
    let adjacent = std::mem::take(&mut neighbours[v]);
    for &a in &adjacent {
        let list = &mut neighbours[a];
        list.retain(|&o| o != v);
        list.extend(adjacent.iter().copied().filter(|&o| o != a));
        list.sort_unstable();
        list.dedup();
    }
    adjacent
}

/// The block Cholesky factor `L` in the elimination order: its diagonal blocks and, per
/// column `k`, the rows below the diagonal (`rows[start[k]..start[k + 1]]`, increasing) with
/// their blocks — all in contiguous arrays sized by the symbolic factorisation.
struct Factor {
    diagonal: Vec<Matrix7>,
    start: Vec<usize>,
    rows: Vec<usize>,
    below: Vec<Matrix7>,
}

impl Factor {
    /// The structure of `L` for `h` permuted by `position` (old index → new): column `k` holds
    /// the rows of `h`'s column `k` below the diagonal and those of its children in the
    /// elimination tree (the columns whose first row below the diagonal is `k`).
    fn symbolic(h: &BlockSparseSymmetric, position: &[usize]) -> Self {
        let n = h.size();
        // The lower pattern of the permuted matrix, column by column (counting sort).
        let lower = |(r, c, _): (usize, usize, &Matrix7)| {
            let (pr, pc) = (position[r], position[c]);
            (pr != pc).then(|| (pr.max(pc), pr.min(pc)))
        };
        let mut a_start = vec![0usize; n + 1];
        for (_, c) in h.entries().filter_map(lower) {
            a_start[c + 1] += 1;
        }
        for k in 0..n {
            a_start[k + 1] += a_start[k];
        }
        let mut a_rows = vec![0usize; a_start[n]];
        let mut fill = a_start.clone();
        for (r, c) in h.entries().filter_map(lower) {
            a_rows[fill[c]] = r;
            fill[c] += 1;
        }
        // Children of each column in the elimination tree, as linked lists.
        const NONE: usize = usize::MAX;
        let (mut first_child, mut next_sibling) = (vec![NONE; n], vec![NONE; n]);
        let mut start = Vec::with_capacity(n + 1);
        start.push(0);
        let mut rows = Vec::with_capacity(a_rows.len());
        let mut column = Vec::new();
        for k in 0..n {
            column.clear();
            column.extend_from_slice(&a_rows[a_start[k]..a_start[k + 1]]);
            let mut child = first_child[k];
            while child != NONE {
                column.extend(
                    rows[start[child]..start[child + 1]]
                        .iter()
                        .filter(|&&r| r != k),
                );
                child = next_sibling[child];
            }
            column.sort_unstable();
            column.dedup();
            if let Some(&parent) = column.first() {
                next_sibling[k] = first_child[parent];
                first_child[parent] = k;
            }
            rows.extend_from_slice(&column);
            start.push(rows.len());
        }
        Self {
            diagonal: Vec::new(),
            below: Vec::new(),
            start,
            rows,
        }
    }

    /// The index of block (row, col) of `L` below the diagonal.
    fn find(&self, row: usize, col: usize) -> Option<usize> {
        let (from, to) = (self.start[col], self.start[col + 1]);
        self.rows[from..to]
            .binary_search(&row)
            .ok()
            .map(|i| from + i)
    }

    /// The numeric right-looking factorisation of `h` permuted by `position`; `None` when it
    /// is not positive definite.
    fn factorise(&mut self, h: &BlockSparseSymmetric, position: &[usize]) -> Option<()> {
        let n = h.size();
        self.diagonal = vec![Matrix7::zeros(); n];
        self.below = vec![Matrix7::zeros(); self.rows.len()];
        for (r, c, block) in h.entries() {
            let (pr, pc) = (position[r], position[c]);
            if pr == pc {
                self.diagonal[pr] += block;
            } else if pr > pc {
                let at = self.find(pr, pc)?;
                self.below[at] = *block;
            } else {
                let at = self.find(pc, pr)?;
                self.below[at] = block.transpose();
            }
        }
        for k in 0..n {
            let l_kk = Cholesky::new(self.diagonal[k])?.l();
            let (from, to) = (self.start[k], self.start[k + 1]);
            // L_ik = A_ik · L_kk⁻ᵀ  ⇔  L_kk · L_ikᵀ = A_ikᵀ.
            for a_ik in &mut self.below[from..to] {
                let x = l_kk.solve_lower_triangular(&a_ik.transpose())?;
                if x.iter().any(|v| !v.is_finite()) {
                    return None;
                }
                *a_ik = x.transpose();
            }
            self.diagonal[k] = l_kk;
            // Schur complement update of the trailing matrix. The rows of column k below j
            // are a subset of column j's rows (the elimination tree's fill), so one forward
            // walk through column j finds every target block.
            for a in from..to {
                let (j, l_jk) = (self.rows[a], self.below[a]);
                self.diagonal[j] -= l_jk * l_jk.transpose();
                let (mut target, end) = (self.start[j], self.start[j + 1]);
                for b in a + 1..to {
                    let (i, l_ik) = (self.rows[b], self.below[b]);
                    while target < end && self.rows[target] < i {
                        target += 1;
                    }
                    if target == end || self.rows[target] != i {
                        return None;
                    }
                    self.below[target] -= l_ik * l_jk.transpose();
                }
            }
        }
        Some(())
    }

    /// Forward then back substitution with the factor: `L·Lᵀ·x = b`.
    fn solve(&self, mut x: Vec<Vector7>) -> Option<Vec<Vector7>> {
        let n = self.diagonal.len();
        for k in 0..n {
            let yk = self.diagonal[k].solve_lower_triangular(&x[k])?;
            x[k] = yk;
            for a in self.start[k]..self.start[k + 1] {
                x[self.rows[a]] -= self.below[a] * yk;
            }
        }
        for k in (0..n).rev() {
            let mut rhs = x[k];
            for a in self.start[k]..self.start[k + 1] {
                rhs -= self.below[a].transpose() * x[self.rows[a]];
            }
            x[k] = self.diagonal[k].transpose().solve_upper_triangular(&rhs)?;
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

    /// The symbolic factorisation (elimination tree) must give the structure the elimination
    /// game gives, and the factor must solve exactly, for any graph and any order.
    #[test]
    fn symbolic_structure_matches_the_elimination_game_in_random_orders() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for trial in 0..20 {
            let n = rng.random_range(2..40);
            let mut h = BlockSparseSymmetric::new(n);
            for i in 0..n {
                h.add(i, i, &(Matrix7::identity() * 30.0 * n as f64));
            }
            for _ in 0..rng.random_range(0..3 * n) {
                let (i, j) = (rng.random_range(0..n), rng.random_range(0..n));
                if i != j {
                    h.add(i, j, &(random_block(&mut rng) * 0.3));
                }
            }
            let mut order: Vec<usize> = (0..n).collect();
            for i in (1..n).rev() {
                order.swap(i, rng.random_range(0..=i));
            }
            let mut neighbours = h.block_graph();
            let mut game = FactorSize::default();
            for &v in &order {
                let below = eliminate(&mut neighbours, v).len();
                game.blocks += 1 + below;
                game.block_products += below * (below + 1) / 2;
            }
            assert_eq!(h.factor_size(&order), game, "trial {trial}, n {n}");
            let b: Vec<Vector7> = (0..n)
                .map(|_| Vector7::from_fn(|_, _| rng.random_range(-1.0..1.0)))
                .collect();
            let x = h.solve_ordered(&b, &order).expect("diagonally dominant");
            let residual = h.to_dense() * flatten(&x) - flatten(&b);
            assert!(residual.norm() < 1e-9 * flatten(&b).norm(), "trial {trial}");
        }
        let h = BlockSparseSymmetric::new(3);
        assert_eq!(
            h.factor_size(&[0, 0, 1]),
            FactorSize::default(),
            "not a permutation"
        );
        assert!(
            h.solve_ordered(&[Vector7::zeros(); 3], &[0, 1, 1])
                .is_none()
        );
    }

    #[test]
    fn block_cholesky_rejects_indefinite_matrices() {
        let mut h = BlockSparseSymmetric::new(2);
        h.add(0, 0, &Matrix7::identity());
        h.add(1, 1, &(-Matrix7::identity()));
        assert!(h.solve(&[Vector7::zeros(), Vector7::zeros()]).is_none());
    }
}
