//! Datasets: the TUM RGB-D folder layout (reader and trajectory files) and a synthetic
//! textured-room renderer that writes the same layout with exact ground truth.
//!
//! Both sides share one on-disk convention (Sturm et al., "A Benchmark for the Evaluation of
//! RGB-D SLAM Systems", IROS 2012): `rgb.txt` / `depth.txt` list `timestamp path` lines,
//! depth is a 16-bit PNG holding metres × 5000 (0 = no measurement), and `groundtruth.txt`
//! holds `t tx ty tz qx qy qz qw` camera-to-world poses (`world_from_camera`).
//! `calibration.txt` (`fx fy cx cy [k1 k2 p1 p2 k3]`) is this project's addition for
//! sequences that are not one of the three Freiburg cameras.

pub mod synth;
pub mod trajectory;
pub mod tum;

pub use synth::{Motion, Scene, SynthConfig, SynthSummary, render_frame, render_sequence};
pub use tum::{TumFrame, TumSequence, preset};

/// TUM depth PNGs store metres × 5000 (TUM RGB-D file formats page).
pub const DEPTH_SCALE: f64 = 5000.0;
