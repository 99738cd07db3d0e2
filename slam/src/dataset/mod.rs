//! Datasets: the TUM RGB-D folder layout (reader and trajectory files) and a synthetic
//! textured-room renderer that writes the same layout with exact ground truth.
//!
//! Both sides share one on-disk convention (Sturm et al., "A Benchmark for the Evaluation of
//! RGB-D SLAM Systems", IROS 2012): `rgb.txt` / `depth.txt` list `timestamp path` lines,
//! depth is a 16-bit PNG holding metres × 5000 (0 = no measurement), and `groundtruth.txt`
//! holds `t tx ty tz qx qy qz qw` camera-to-world poses (`world_from_camera`).
//! `calibration.txt` (`fx fy cx cy [k1 k2 p1 p2 k3]`) is this project's addition for
//! sequences that are not one of the three Freiburg cameras.

pub mod folder;
pub mod synth;
pub mod trajectory;
pub mod tum;

pub use folder::SequenceFolder;
pub use synth::{Motion, Scene, SynthConfig, SynthSummary, render_frame, render_sequence};
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

/// For tests on real data: the shared sequence `name` (e.g. `7scenes_redkitchen_f0000-0299`),
/// or `None`, with the reason printed, when the data folder is absent.
#[cfg(test)]
pub(crate) fn shared_sequence(name: &str) -> Option<TumSequence> {
    let dir = shared_data_dir().join("sequences").join(name);
    if !dir.is_dir() {
        eprintln!("skipping: {} not found (set RELFUSION_DATA)", dir.display());
        return None;
    }
    Some(TumSequence::open(&dir, None).expect("shared sequence loads"))
}

/// For tests on real data: frame `i` of `seq` as a [`crate::frame::Frame`] (id `i`). Only for
/// sequences whose camera has no distortion (7-Scenes); distorted ones go through the pipeline.
#[cfg(test)]
pub(crate) fn shared_frame(seq: &TumSequence, i: usize) -> crate::frame::Frame {
    let gray = seq.load_gray(i).expect("image");
    crate::frame::Frame::new(i as u64, seq.frames[i].timestamp, seq.camera, &gray, None)
        .expect("frame")
}

/// TUM depth PNGs store metres × 5000 (TUM RGB-D file formats page).
pub const DEPTH_SCALE: f64 = 5000.0;
