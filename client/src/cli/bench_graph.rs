//! `relfusion bench graph`: the pose graph of a session that keeps revisiting its start — what
//! a long session's back end optimises after every keyframe — at growing sizes: edges, size of
//! the Cholesky factor in the solver's minimum-degree order and in insertion order, time of one
//! full optimisation, and its error against the truth the edges were drawn from; the same for
//! a live pass over the whole graph, which solves by conjugate gradients beyond the live bound
//! (memory linear in the graph).

use std::time::Instant;

use nalgebra::Vector3;
use relfusion_slam::geometry::{Matrix7, Sim3, Vector7};
use relfusion_slam::graph::cholesky::BlockSparseSymmetric;
use relfusion_slam::graph::{BackendConfig, Constraint, PoseGraph};
use serde_json::json;

#[derive(Debug, clap::Args)]
pub struct GraphArgs {
    /// Keyframes of each graph, comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [250usize, 500, 1000, 2000])]
    pub keyframes: Vec<usize>,
    /// Keyframes per lap of the loop (the synthetic hand-held loop of `bench long` makes about
    /// 25 per 30 s lap at 640×480).
    #[arg(long, default_value_t = 25)]
    pub lap: usize,
    /// Earlier laps each keyframe is joined to at the same place (loop closures); 0: all.
    #[arg(long, default_value_t = 0)]
    pub loop_laps: usize,
    /// Noise of each measured edge, standard deviation per tangent coordinate.
    #[arg(long, default_value_t = 0.01)]
    pub noise: f64,
}

pub fn graph(args: &GraphArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.lap >= 4, "--lap must be at least 4");
    anyhow::ensure!(
        args.noise.is_finite() && args.noise >= 0.0,
        "--noise must be finite and non-negative"
    );
    let iterations = BackendConfig::default().max_optimization_iterations;
    for &n in &args.keyframes {
        anyhow::ensure!(n >= 2, "a graph needs at least 2 keyframes");
        let truth: Vec<Sim3> = (0..n).map(|i| place(i, args.lap)).collect();
        let mut noise = Noise(0x9E37_79B9_7F4A_7C15 ^ n as u64);
        let mut graph = PoseGraph::new(BackendConfig::default().pose_graph_huber);
        // Initial poses by chaining the noisy odometry edges: the drift loops correct.
        let mut edges = Vec::new();
        for i in 0..n {
            let chain = (1..=3).filter(|d| *d <= i).map(|d| i - d);
            let laps = i / args.lap;
            let closest = if args.loop_laps == 0 {
                laps
            } else {
                laps.min(args.loop_laps)
            };
            let loops = (1..=closest).map(|k| i - k * args.lap);
            for j in chain.chain(loops) {
                let exact = truth[j].inverse() * truth[i];
                let measured = exact * Sim3::exp(&noise.vector(args.noise));
                edges.push(Constraint {
                    from: i,
                    to: j,
                    to_from_from: measured,
                    information: (Matrix7::identity() / (args.noise * args.noise).max(1e-12))
                        .into(),
                });
            }
        }
        let mut pose = truth[0];
        graph.add_vertex(0, pose);
        for i in 1..n {
            let odometry = edges
                .iter()
                .find(|e| e.from == i && e.to == i - 1)
                .map(|e| e.to_from_from)
                .unwrap_or_else(Sim3::identity);
            pose = pose * odometry;
            graph.add_vertex(i, pose);
        }
        let mut structure = BlockSparseSymmetric::new(n);
        for e in &edges {
            structure.add(e.from, e.to, &Matrix7::identity());
        }
        for e in &edges {
            graph.add_edge(e.clone())?;
        }
        let insertion: Vec<usize> = (0..n).collect();
        let t = Instant::now();
        let order = structure.minimum_degree_order();
        let order_s = t.elapsed().as_secs_f64();
        let (sparse, dense) = (
            structure.factor_size(&order),
            structure.factor_size(&insertion),
        );
        let error_before = rms_position_error(&graph, &truth);
        // Every vertex is new: a live pass beyond the bound moves the whole graph.
        let mut live = graph.clone();
        let bound = BackendConfig::default().live_optimization_vertices;
        let t = Instant::now();
        let live_report = live.optimize_bounded(bound, iterations)?;
        let live_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let report = graph.optimize(iterations)?;
        let optimize_s = t.elapsed().as_secs_f64();
        println!(
            "{}",
            json!({
                "keyframes": n,
                "edges": edges.len(),
                "lap": args.lap,
                "matrix_blocks": structure.stored_blocks() + n,
                "factor_blocks": sparse.blocks,
                "factor_block_products": sparse.block_products,
                "insertion_order_blocks": dense.blocks,
                "insertion_order_block_products": dense.block_products,
                "ordering_s": order_s,
                "optimize_s": optimize_s,
                "iterations": report.iterations,
                "final_cost": report.final_cost,
                "rms_position_error_before_m": error_before,
                "rms_position_error_after_m": rms_position_error(&graph, &truth),
                "live_conjugate_gradients": live_report.iterative,
                "live_optimize_s": live_s,
                "live_iterations": live_report.iterations,
                "live_final_cost": live_report.final_cost,
                "live_rms_position_error_after_m": rms_position_error(&live, &truth),
            })
        );
    }
    Ok(())
}

/// Keyframe `i` on a circle of radius 1 m, `lap` keyframes per turn, looking outwards.
fn place(i: usize, lap: usize) -> Sim3 {
    let angle = std::f64::consts::TAU * (i % lap) as f64 / lap as f64;
    let mut xi = Vector7::zeros();
    xi[4] = angle;
    let rotation = Sim3::exp(&xi);
    Sim3 {
        translation: Vector3::new(angle.cos(), 0.0, angle.sin()),
        ..rotation
    }
}

fn rms_position_error(graph: &PoseGraph, truth: &[Sim3]) -> f64 {
    let squares: f64 = truth
        .iter()
        .enumerate()
        .filter_map(|(i, t)| Some((graph.pose(i)?.translation - t.translation).norm_squared()))
        .sum();
    (squares / truth.len() as f64).sqrt()
}

/// A small deterministic generator (xorshift64*) for the edge noise.
struct Noise(u64);

impl Noise {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in ±√3·σ per coordinate (standard deviation σ); scale noise a tenth of it.
    fn vector(&mut self, sigma: f64) -> Vector7 {
        let mut v = Vector7::from_fn(|_, _| 0.0);
        for k in 0..7 {
            v[k] = (2.0 * self.uniform() - 1.0) * 3f64.sqrt() * sigma;
        }
        v[6] *= 0.1;
        v
    }
}
