//! Datasets: the TUM RGB-D folder layout (from `relfusion-core`: reader and trajectory files)
//! and a synthetic textured-room renderer that writes the same layout with exact ground truth.

pub mod synth;

pub use relfusion_core::dataset::{
    DEPTH_SCALE, SequenceFolder, SequenceLimits, TumFrame, TumSequence, folder, preset,
    shared_data_dir, trajectory, tum,
};
pub use synth::{Motion, Scene, SynthConfig, SynthSummary, render_frame, render_sequence};

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
