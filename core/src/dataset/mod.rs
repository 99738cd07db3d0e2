//! The TUM RGB-D folder layout: its reader, calibration and trajectory files.
//!
//! One on-disk convention (Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM
//! Systems", IROS 2012): `rgb.txt` / `depth.txt` list `timestamp path` lines, depth is a 16-bit
//! PNG holding metres × 5000 (0 = no measurement), and `groundtruth.txt` holds
//! `t tx ty tz qx qy qz qw` camera-to-world poses (`world_from_camera`). `calibration.txt`
//! (`fx fy cx cy [k1 k2 p1 p2 k3]`) is this project's addition for sequences that are not one
//! of the three Freiburg cameras.

pub mod folder;
pub mod trajectory;
pub mod tum;

pub use folder::SequenceFolder;
pub use tum::{SequenceLimits, TumFrame, TumSequence, preset};

/// The shared real-data folder (sequences, models): `$RELFUSION_DATA`, else `../shared/data`
/// beside the checkout. Data are never copied into the repository.
pub fn shared_data_dir() -> std::path::PathBuf {
    std::env::var_os("RELFUSION_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data"))
        })
}

/// TUM depth PNGs store metres × 5000 (TUM RGB-D file formats page).
pub const DEPTH_SCALE: f64 = 5000.0;
