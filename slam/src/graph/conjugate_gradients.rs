//! Preconditioned conjugate gradients on the pose graph's normal equations: the solver of the
//! live passes that move a long session's whole graph (issue 37).
//!
//! The block Cholesky of [`super::cholesky`] is exact, but its factor grows faster than the
//! graph: a session that keeps revisiting one room joins every lap to the others, and minimum
//! degree cannot keep the fill of thousands of keyframes with their loop edges small. Every
//! live pass that moves the whole graph allocated and freed that factor again, the transient
//! that grew the heap of the hour-long sessions (docs/tuning.md, thirty-fourth stop).
//! Conjugate gradients need the matrix and four vectors: memory linear in the graph, for any
//! structure. The block-Jacobi preconditioner (each keyframe's 7×7 diagonal block inverted)
//! takes out the different units of rotation, translation and scale and the stiff hold of
//! scale-only vertices; it is the usual preconditioner of iterative pose-graph and bundle
//! adjustment solvers (Agarwal et al., "Bundle Adjustment in the Large", ECCV 2010).
//! Inside Levenberg–Marquardt an inexact step does no harm: one that does not lower the cost
//! is rejected and damped like a Cholesky step would be.

use nalgebra::Cholesky;

use super::cholesky::BlockSparseSymmetric;
use crate::geometry::{Matrix7, Vector7};

/// When conjugate gradients stop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CgStop {
    /// Most iterations (one matrix–vector product each).
    pub max_iterations: usize,
    /// The relative residual `‖b − H·x‖ / ‖b‖` that ends the solve.
    pub tolerance: f64,
}

impl BlockSparseSymmetric {
    /// `y = H·x` from the stored lower triangle (each block off the diagonal acts twice).
    pub fn multiply_into(&self, x: &[Vector7], y: &mut [Vector7]) {
        y.iter_mut().for_each(|v| v.fill(0.0));
        for (r, c, b) in self.entries() {
            y[r] += b * x[c];
            if r != c {
                y[c] += b.tr_mul(&x[r]);
            }
        }
    }

    /// Solves `H·x = b` by conjugate gradients with a block-Jacobi preconditioner, from
    /// `x = 0`, until `stop`; returns `x` and the iterations it took. `None` when a diagonal
    /// block or a search direction shows that H is not positive definite, or `b` does not fit.
    pub fn solve_cg(&self, b: &[Vector7], stop: CgStop) -> Option<(Vec<Vector7>, usize)> {
        let n = self.size();
        if b.len() != n {
            return None;
        }
        let inverses: Vec<Matrix7> = (0..n)
            .map(|i| Cholesky::new(self.diagonal(i)).map(|c| c.inverse()))
            .collect::<Option<_>>()?;
        let dot =
            |u: &[Vector7], v: &[Vector7]| u.iter().zip(v).map(|(a, b)| a.dot(b)).sum::<f64>();
        let mut x = vec![Vector7::zeros(); n];
        let b_norm = dot(b, b).sqrt();
        if !b_norm.is_finite() {
            return None;
        }
        if b_norm == 0.0 {
            return Some((x, 0));
        }
        let mut r = b.to_vec();
        let mut z: Vec<Vector7> = inverses.iter().zip(&r).map(|(m, v)| m * v).collect();
        let mut p = z.clone();
        let mut hp = vec![Vector7::zeros(); n];
        let mut rz = dot(&r, &z);
        for iteration in 1..=stop.max_iterations {
            self.multiply_into(&p, &mut hp);
            let curvature = dot(&p, &hp);
            if !(curvature > 0.0 && curvature.is_finite()) {
                return None;
            }
            let alpha = rz / curvature;
            for ((xi, ri), (pi, hpi)) in x.iter_mut().zip(&mut r).zip(p.iter().zip(&hp)) {
                *xi += alpha * pi;
                *ri -= alpha * hpi;
            }
            if dot(&r, &r).sqrt() <= stop.tolerance * b_norm {
                return Some((x, iteration));
            }
            for ((zi, m), ri) in z.iter_mut().zip(&inverses).zip(&r) {
                *zi = m * ri;
            }
            let rz_next = dot(&r, &z);
            let beta = rz_next / rz;
            rz = rz_next;
            for (pi, zi) in p.iter_mut().zip(&z) {
                *pi = zi + beta * *pi;
            }
        }
        Some((x, stop.max_iterations))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::cholesky::flatten;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A random SPD matrix with the structure of a session that revisits its start: a chain
    /// with edges to the 3 previous keyframes, each joined to the same place of every earlier
    /// lap; blocks `JᵀJ` of random residuals, units far apart per coordinate.
    fn looping_graph(rng: &mut ChaCha8Rng, n: usize, lap: usize) -> BlockSparseSymmetric {
        let units = Matrix7::from_diagonal(&Vector7::from_column_slice(&[
            1.0, 1.0, 1.0, 30.0, 30.0, 30.0, 0.1,
        ]));
        let mut h = BlockSparseSymmetric::new(n);
        for i in 1..n {
            let chain = (1..=3).filter(|d| *d <= i).map(|d| i - d);
            let loops = (1..=i / lap).map(|k| i - k * lap);
            for j in chain.chain(loops) {
                let a = Matrix7::from_fn(|_, _| rng.random_range(-1.0..1.0)) * units;
                let b = Matrix7::from_fn(|_, _| rng.random_range(-1.0..1.0)) * units;
                h.add(i, i, &(a.transpose() * a));
                h.add(j, j, &(b.transpose() * b));
                h.add(i, j, &(a.transpose() * b));
            }
        }
        h.add(0, 0, &(Matrix7::identity() * 1e-2));
        h
    }

    #[test]
    fn conjugate_gradients_match_cholesky_on_random_looping_graphs() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for (n, lap) in [(40, 10), (150, 25)] {
            let h = looping_graph(&mut rng, n, lap);
            let b: Vec<Vector7> = (0..n)
                .map(|_| Vector7::from_fn(|_, _| rng.random_range(-1.0..1.0)))
                .collect();
            let exact = h.solve(&b).expect("positive definite");
            let stop = CgStop {
                max_iterations: 20 * 7 * n,
                tolerance: 1e-12,
            };
            let (x, iterations) = h.solve_cg(&b, stop).expect("positive definite");
            let err = (flatten(&x) - flatten(&exact)).norm() / flatten(&exact).norm();
            assert!(err < 1e-6, "n {n}: relative error {err} after {iterations}");
            let mut hx = vec![Vector7::zeros(); n];
            h.multiply_into(&x, &mut hx);
            let dense = h.to_dense() * flatten(&x);
            assert!((flatten(&hx) - &dense).norm() < 1e-9 * dense.norm());
        }
    }

    #[test]
    fn conjugate_gradients_stop_at_the_tolerance_and_reject_indefinite_matrices() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let h = looping_graph(&mut rng, 60, 15);
        let b: Vec<Vector7> = (0..60).map(|i| Vector7::from_element(i as f64)).collect();
        let stop = |tolerance| CgStop {
            max_iterations: 10_000,
            tolerance,
        };
        let (_, loose) = h.solve_cg(&b, stop(1e-2)).expect("solves");
        let (x, tight) = h.solve_cg(&b, stop(1e-10)).expect("solves");
        assert!(loose < tight, "{loose} vs {tight} iterations");
        let mut hx = vec![Vector7::zeros(); 60];
        h.multiply_into(&x, &mut hx);
        let residual = (flatten(&hx) - flatten(&b)).norm() / flatten(&b).norm();
        assert!(residual <= 1e-10, "{residual}");
        let mut indefinite = BlockSparseSymmetric::new(2);
        indefinite.add(0, 0, &Matrix7::identity());
        indefinite.add(1, 1, &Matrix7::identity());
        indefinite.add(1, 0, &(Matrix7::identity() * 2.0));
        // Along (1, −1) the curvature is negative.
        let across = vec![Vector7::from_element(1.0), Vector7::from_element(-1.0)];
        assert!(indefinite.solve_cg(&across, stop(1e-10)).is_none());
        assert!(h.solve_cg(&across, stop(1e-10)).is_none(), "wrong length");
    }
}
