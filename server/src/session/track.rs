//! What a session has produced so far, as its subscribers have it: the poses reported (the
//! live trajectory), the keyframes with their latest poses, and the fused mesh with every
//! `MeshUpdate` applied. The result files served from it are [`super::results`].

use std::collections::BTreeMap;

use relfusion_slam::frame_log::{FrameLog, LogRecord};
use relfusion_slam::geometry::Sim3;
use relfusion_slam::spill::{Reader, Writer};

use super::mesh_state::MeshState;

/// The poses reported so far (the live trajectory, before the final optimisation).
#[derive(Debug, Default)]
pub(crate) struct Track {
    /// Every processed frame; full chunks spill with the session (`frame_log`).
    pub(super) frames: FrameLog<Reported>,
    /// Keyframe id → (timestamp, latest pose).
    pub(super) keyframes: BTreeMap<u64, (f64, Sim3)>,
    /// The fused mesh as the subscribers have it: every delta applied (bounded in memory once
    /// the session spills).
    pub(super) mesh: MeshState,
}

/// One processed frame: timestamp, pose at tracking time, lost.
#[derive(Clone, Copy, Debug)]
pub(super) struct Reported {
    pub timestamp: f64,
    pub pose: Sim3,
    pub lost: bool,
}

impl LogRecord for Reported {
    fn encode(&self, out: &mut Writer) {
        out.f64(self.timestamp);
        out.sim3(&self.pose);
        out.u8(u8::from(self.lost));
    }

    fn decode(input: &mut Reader<'_>) -> relfusion_slam::Result<Self> {
        Ok(Self {
            timestamp: input.f64()?,
            pose: input.sim3()?,
            lost: input.u8()? != 0,
        })
    }
}
