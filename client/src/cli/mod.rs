//! One module per subcommand: each exposes its clap `Args` (or subcommand enum) and `run`.

pub mod bench;
pub mod bench_slam;
pub mod eval;
pub mod gpu_info;
pub mod prior;
pub mod run;
pub mod synth;
