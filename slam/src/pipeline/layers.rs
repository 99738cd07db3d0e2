//! The dense layer and the fusion seen from the pipeline: finished keyframes go in, dense
//! keyframes and mesh deltas come back (in step, or polled from their threads) and become
//! events; a dense keyframe's two-view consistent depth refines the back end (§III-E) and the
//! keyframe is fused at its current pose.

use std::sync::Arc;

use super::Pipeline;
use super::events::Event;
use crate::Result;
use crate::dense::DenseKeyframe;
use crate::dense::layer::{DenseJob, DenseOutput};
use crate::fusion::MeshDelta;
use crate::fusion::worker::{FusionJob, FusionLink, FusionReply};
use crate::geometry::Sim3;
use crate::graph::{BackendCommand, KeyframeId};
use crate::mapping::CompactDepth;
use crate::spill::Stored;

impl Pipeline {
    /// Hands a finished keyframe to the dense layer (handled at once in step; dropped and
    /// counted when its queue is full).
    pub(super) fn densify(&mut self, mut job: DenseJob) -> Result<()> {
        if self.dense.is_none() {
            return Ok(());
        }
        job.poses = self.keyframe_poses();
        let id = job.keyframe_id;
        if let Some(dense) = &mut self.dense
            && !dense.submit(job)?
        {
            tracing::warn!(keyframe = id, "dense layer busy: keyframe not densified");
            self.stats.keyframes_not_densified += 1;
        }
        self.poll_dense()
    }

    /// Collects the dense layer's finished keyframes.
    pub(super) fn poll_dense(&mut self) -> Result<()> {
        let replies = match &mut self.dense {
            Some(dense) => dense.poll(),
            None => return Ok(()),
        };
        self.apply_dense(replies)
    }

    /// Records dense results, sends their two-view consistent depth to the back end (§III-E)
    /// and, with a metric prior, their observed scale, and queues their events. A keyframe the
    /// layer failed on is logged and counted: the semi-dense SLAM goes on without it.
    pub(super) fn apply_dense(
        &mut self,
        replies: Vec<(KeyframeId, Result<DenseOutput>)>,
    ) -> Result<()> {
        for (id, reply) in replies {
            let output = match reply {
                Ok(output) => output,
                Err(e) => {
                    tracing::warn!(keyframe = id, error = %e, "dense layer failed on a keyframe");
                    self.stats.keyframes_not_densified += 1;
                    continue;
                }
            };
            if let (true, Some(observation)) = (self.metric, output.scale) {
                self.backend
                    .send(BackendCommand::ObserveScale { id, observation })?;
            }
            if let Some(depth) = output.refined_depth {
                self.stats.depth_refinements += 1;
                self.backend.send(BackendCommand::UpdateDepth {
                    id,
                    depth: CompactDepth::of(&depth),
                })?;
            }
            let kf = output.keyframe;
            self.stats.keyframes_densified += 1;
            self.pending_events.push(Event::KeyframeDensified {
                keyframe_id: id,
                frame_id: self.keyframes[id].frame_id,
                timestamp: kf.timestamp,
                mode: kf.mode,
                keyframe: kf.clone(),
            });
            self.dense_keyframes
                .insert(id, Stored::new(&self.spill, kf.clone()));
            self.fuse(kf)?;
        }
        Ok(())
    }

    /// Hands a densified keyframe to the fusion with the current keyframe poses (which
    /// re-integrate keyframes the pose graph moved).
    fn fuse(&mut self, keyframe: Arc<DenseKeyframe>) -> Result<()> {
        if self.fusion.is_none() {
            return Ok(());
        }
        let id = keyframe.keyframe_id;
        let job = FusionJob {
            rgb: self.keyframes[id].data.image.get()?.rgb.clone(),
            pose: self.current_pose(id),
            keyframe,
        };
        let poses = self.keyframe_poses();
        if let Some(fusion) = &mut self.fusion {
            fusion.post_poses(poses);
            if !fusion.submit(job)? {
                tracing::warn!(keyframe = id, "fusion busy: keyframe not fused");
                self.stats.keyframes_not_fused += 1;
            }
        }
        self.poll_fusion();
        Ok(())
    }

    /// Collects the fusion's mesh deltas.
    pub(super) fn poll_fusion(&mut self) {
        if let Some(fusion) = &mut self.fusion {
            let replies = fusion.poll();
            self.apply_fusion(replies);
        }
    }

    /// Turns fusion replies into `MeshUpdated` events; a keyframe the fusion failed on is
    /// logged and counted (the mesh goes on without it).
    fn apply_fusion(&mut self, replies: Vec<FusionReply>) {
        for (had_keyframe, reply) in replies {
            match reply {
                Ok(delta) => {
                    self.stats.keyframes_fused += usize::from(had_keyframe);
                    if let Some(delta) = delta {
                        self.push_mesh_event(delta);
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, "fusion failed");
                    self.stats.keyframes_not_fused += usize::from(had_keyframe);
                }
            }
        }
    }

    fn push_mesh_event(&mut self, delta: MeshDelta) {
        self.stats.mesh_revision = delta.revision;
        self.pending_events.push(Event::MeshUpdated {
            revision: delta.revision,
            delta: Arc::new(delta),
        });
    }

    /// Re-integrates at the final poses and meshes; the fuser stays for [`Pipeline::mesh`].
    /// Keyframes of fragments left apart are taken out of the mesh, which then shows what the
    /// other exports show (the main fragment): their poses are only a guess.
    pub(super) fn finish_fusion(&mut self, poses: &[(KeyframeId, Sim3)]) -> Result<()> {
        let exported = self.exported();
        let Some(fusion) = &mut self.fusion else {
            return Ok(());
        };
        fusion.post_poses(poses.to_vec());
        let replies = fusion.finish()?;
        self.apply_fusion(replies);
        let apart = exported.iter().enumerate().filter(|(_, e)| !**e);
        if let Some(fuser) = self.fusion.as_mut().and_then(FusionLink::fuser) {
            let mut removed = false;
            for (id, _) in apart {
                fuser.remove_keyframe(id)?;
                removed = true;
            }
            if removed && let Some(delta) = fuser.take_delta()? {
                self.push_mesh_event(delta);
            }
        }
        Ok(())
    }
}
