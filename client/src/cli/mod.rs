//! One module per subcommand: each exposes its clap `Args` (or subcommand enum) and `run`.

pub mod bench;
pub mod bench_accuracy;
pub mod bench_cluster;
pub mod bench_dense;
pub mod bench_densify;
pub mod bench_fusion;
pub mod bench_long;
pub mod bench_map;
pub mod bench_odometry;
pub mod bench_serve;
pub mod bench_slam;
pub mod bench_viewer;
pub mod connect;
pub mod depth_probe;
pub mod eval;
pub mod fetch;
pub mod gpu_info;
pub mod health;
pub mod localize;
pub mod maps;
pub mod prior;
pub mod rerun_out;
pub mod run;
pub mod stream;
pub mod synth;
pub mod upload;
