//! `--rerun FILE.rrd` of `relfusion stream` and `relfusion run`: what each sees (the service's
//! updates, the local pipeline's events) written through [`relfusion_client::recording`].
//! Without the cargo feature `rerun` the flag answers with how to get it.

use std::path::Path;

#[cfg(feature = "rerun")]
pub use with_rerun::{RunRecorder, StreamRecorder};
#[cfg(not(feature = "rerun"))]
pub use without_rerun::{RunRecorder, StreamRecorder};

#[cfg(feature = "rerun")]
mod with_rerun {
    use std::path::{Path, PathBuf};

    use anyhow::Context as _;
    use relfusion_client::recording::{
        DepthRef, MeshBlockRef, Pose, Recording, RecordingCounts, RecordingError,
    };
    use relfusion_sdk::dataset_stream::StreamEvent;
    use relfusion_slam::dataset::TumSequence;
    use relfusion_slam::pipeline::{Event, TrackingState};

    /// The recording of a stream; the first failure is kept and reported at the end (the
    /// stream itself goes on).
    #[derive(Debug)]
    pub struct StreamRecorder {
        recording: Recording,
        frames: Vec<(f64, PathBuf)>,
        failure: Option<anyhow::Error>,
    }

    fn floats(bytes: &[u8]) -> Vec<f32> {
        bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    }

    fn triples<T: Copy>(values: &[T]) -> Vec<[T; 3]> {
        values.chunks_exact(3).map(|v| [v[0], v[1], v[2]]).collect()
    }

    impl StreamRecorder {
        pub fn create(path: &Path, seq: &TumSequence) -> anyhow::Result<Self> {
            Ok(StreamRecorder {
                recording: Recording::create(path, &seq.camera)?,
                frames: seq
                    .frames
                    .iter()
                    .map(|f| (f.timestamp, f.rgb.clone()))
                    .collect(),
                failure: None,
            })
        }

        pub fn on_event(&mut self, event: &StreamEvent) {
            if self.failure.is_none()
                && let Err(e) = self.record(event)
            {
                self.failure = Some(e);
            }
        }

        fn record(&mut self, event: &StreamEvent) -> anyhow::Result<()> {
            let r = &mut self.recording;
            match event {
                StreamEvent::Sent { frame_id } => {
                    let (timestamp, path) = usize::try_from(*frame_id)
                        .ok()
                        .and_then(|i| self.frames.get(i))
                        .context("a frame id outside the sequence")?;
                    let bytes = std::fs::read(path)
                        .with_context(|| format!("reading {}", path.display()))?;
                    r.image(*frame_id, *timestamp, bytes)?;
                }
                StreamEvent::Pose(p) if p.state != "lost" => {
                    let pose = Pose {
                        t: p.t,
                        q: p.q,
                        s: p.s,
                    };
                    r.pose(p.frame_id, p.timestamp, &pose)?;
                }
                StreamEvent::Keyframe {
                    keyframe_id,
                    pose,
                    depth,
                    ..
                } => {
                    r.keyframe(
                        *keyframe_id,
                        &Pose {
                            t: pose.t,
                            q: pose.q,
                            s: pose.s,
                        },
                    )?;
                    if let Some(d) = depth
                        && let Some(c) = &d.camera
                    {
                        let inverse_depth = floats(&d.inverse_depth);
                        r.keyframe_depth(
                            *keyframe_id,
                            &DepthRef {
                                width: d.width as usize,
                                height: d.height as usize,
                                inverse_depth: &inverse_depth,
                                fx: c.fx,
                                fy: c.fy,
                                cx: c.cx,
                                cy: c.cy,
                            },
                        )?;
                    }
                }
                StreamEvent::Mesh { update } => {
                    for b in &update.removed_blocks {
                        r.mesh_block_removed([b.x, b.y, b.z])?;
                    }
                    for b in &update.changed_blocks {
                        let index = b.index.as_ref().map_or([0; 3], |i| [i.x, i.y, i.z]);
                        let positions = triples(&floats(&b.vertices));
                        let normals = triples(&floats(&b.normals));
                        let colors = triples(&b.colors);
                        r.mesh_block(&MeshBlockRef {
                            index,
                            positions: &positions,
                            colors: &colors,
                            normals: &normals,
                            indices: &b.indices,
                        })?;
                    }
                }
                StreamEvent::Session { .. }
                | StreamEvent::Pose(_)
                | StreamEvent::ServerError { .. } => {}
            }
            Ok(())
        }

        pub fn finish(self) -> anyhow::Result<RecordingCounts> {
            if let Some(e) = self.failure {
                return Err(e.context("writing the rerun recording"));
            }
            Ok(self.recording.finish()?)
        }
    }

    /// The recording of a local run: the pipeline's events after each frame.
    #[derive(Debug)]
    pub struct RunRecorder {
        recording: Recording,
    }

    impl RunRecorder {
        pub fn create(path: &Path, seq: &TumSequence) -> anyhow::Result<Self> {
            Ok(RunRecorder {
                recording: Recording::create(path, &seq.camera)?,
            })
        }

        /// Frame `index` of `seq` went through the pipeline and these events came out.
        pub fn on_frame(
            &mut self,
            seq: &TumSequence,
            index: usize,
            events: &[Event],
        ) -> anyhow::Result<()> {
            let frame = &seq.frames[index];
            let bytes = std::fs::read(&frame.rgb)
                .with_context(|| format!("reading {}", frame.rgb.display()))?;
            self.recording.image(index as u64, frame.timestamp, bytes)?;
            self.on_events(events)
        }

        pub fn on_events(&mut self, events: &[Event]) -> anyhow::Result<()> {
            let r = &mut self.recording;
            for event in events {
                match event {
                    Event::Pose(p) if p.state != TrackingState::Lost => {
                        r.pose(p.frame_id, p.timestamp, &Pose::from(&p.world_from_camera))?;
                    }
                    Event::Keyframe(k) => {
                        r.keyframe(k.keyframe_id as u64, &Pose::from(&k.world_from_keyframe))?;
                    }
                    Event::KeyframePoses { poses } => {
                        for (id, pose) in poses {
                            r.keyframe(*id as u64, &Pose::from(pose))?;
                        }
                    }
                    Event::KeyframeDensified {
                        keyframe_id,
                        keyframe,
                        ..
                    } => {
                        let c = &keyframe.camera;
                        r.keyframe_depth(
                            *keyframe_id as u64,
                            &DepthRef {
                                width: keyframe.idepth.width,
                                height: keyframe.idepth.height,
                                inverse_depth: &keyframe.idepth.data,
                                fx: c.fx,
                                fy: c.fy,
                                cx: c.cx,
                                cy: c.cy,
                            },
                        )?;
                    }
                    Event::MeshUpdated { delta, .. } => {
                        for b in &delta.removed {
                            r.mesh_block_removed([b.x, b.y, b.z])?;
                        }
                        for b in &delta.changed {
                            r.mesh_block(&MeshBlockRef {
                                index: [b.index.x, b.index.y, b.index.z],
                                positions: &b.positions,
                                colors: &b.colors,
                                normals: &b.normals,
                                indices: &b.indices,
                            })?;
                        }
                    }
                    Event::Pose(_) => {}
                }
            }
            Ok(())
        }

        pub fn finish(self) -> Result<RecordingCounts, RecordingError> {
            self.recording.finish()
        }
    }
}

#[cfg(not(feature = "rerun"))]
mod without_rerun {
    use std::path::Path;

    use relfusion_sdk::dataset_stream::StreamEvent;
    use relfusion_slam::dataset::TumSequence;
    use relfusion_slam::pipeline::Event;

    fn unavailable() -> anyhow::Error {
        anyhow::anyhow!(
            "this relfusion was built without rerun recordings: cargo build --release -p relfusion-client --features rerun"
        )
    }

    /// Stands in for the recorder: creating one fails with how to build it.
    #[derive(Debug)]
    pub enum StreamRecorder {}

    impl StreamRecorder {
        pub fn create(_: &Path, _: &TumSequence) -> anyhow::Result<Self> {
            Err(unavailable())
        }
        pub fn on_event(&mut self, _: &StreamEvent) {
            match *self {}
        }
        pub fn finish(self) -> anyhow::Result<serde_json::Value> {
            match self {}
        }
    }

    /// Stands in for the recorder: creating one fails with how to build it.
    #[derive(Debug)]
    pub enum RunRecorder {}

    impl RunRecorder {
        pub fn create(_: &Path, _: &TumSequence) -> anyhow::Result<Self> {
            Err(unavailable())
        }
        pub fn on_frame(&mut self, _: &TumSequence, _: usize, _: &[Event]) -> anyhow::Result<()> {
            match *self {}
        }
        pub fn on_events(&mut self, _: &[Event]) -> anyhow::Result<()> {
            match *self {}
        }
        pub fn finish(self) -> anyhow::Result<serde_json::Value> {
            match self {}
        }
    }
}

/// Opens the recorder of `--rerun`, when given.
pub fn open<R>(
    path: Option<&Path>,
    create: impl FnOnce(&Path) -> anyhow::Result<R>,
) -> anyhow::Result<Option<R>> {
    path.map(create).transpose()
}
