//! What `relfusion run SEQ --map MAP --mode localize --out OUT` writes: every frame of SEQ is
//! localised in a saved map (the run's `relfusion_slam::pipeline::Engine` started with
//! `Start::Localize`), the map left as it is.
//!
//! Writes `OUT/trajectory.txt` (the localised frames, camera-to-world in the map's frame, TUM
//! format) and `OUT/localization.txt` (one line per frame: timestamp, `tracked`,
//! `relocalized` or `not_localized`, the map keyframe it was aligned to or -1, the
//! alignment's score and the frame's reach from that keyframe), then prints a one-line JSON summary.

use std::io::Write as _;
use std::path::PathBuf;

use anyhow::Context as _;
use relfusion_slam::geometry::Sim3;
use relfusion_slam::map::LocalizationState;
use relfusion_slam::pipeline::Engine;
use serde_json::{Value, json};

/// The per-frame log and the localised poses, as the frames go through.
#[derive(Debug)]
pub struct Log {
    path: PathBuf,
    file: std::io::BufWriter<std::fs::File>,
    trajectory: Vec<(f64, Sim3)>,
    /// Frames tracked, relocalised, not localised.
    counts: [usize; 3],
}

impl Log {
    /// `OUT/localization.txt`, with its header.
    pub fn create(out: &std::path::Path) -> anyhow::Result<Self> {
        let path = out.join("localization.txt");
        let mut file = std::io::BufWriter::new(
            std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?,
        );
        writeln!(file, "# timestamp state keyframe score reach")?;
        Ok(Self {
            path,
            file,
            trajectory: Vec::new(),
            counts: [0; 3],
        })
    }

    /// The frame the engine has just localised.
    pub fn frame(&mut self, engine: &Engine) -> anyhow::Result<()> {
        let Some(result) = engine.last_localization() else {
            anyhow::bail!("a localising run reported no localisation");
        };
        let (name, slot) = match result.state {
            LocalizationState::Tracked => ("tracked", 0),
            LocalizationState::Relocalized => ("relocalized", 1),
            LocalizationState::NotLocalized => ("not_localized", 2),
        };
        self.counts[slot] += 1;
        writeln!(
            self.file,
            "{:.6} {name} {} {:.3} {:.3}",
            result.timestamp,
            result.keyframe.map_or(-1, |k| k as i64),
            result.score,
            result.reach
        )
        .with_context(|| format!("writing {}", self.path.display()))?;
        if let Some(pose) = result.world_from_camera {
            self.trajectory.push((result.timestamp, pose));
        }
        Ok(())
    }

    /// The localised poses and the summary of `frames` frames localised in `wall_s` seconds.
    pub fn finish(
        mut self,
        frames: usize,
        wall_s: f64,
    ) -> anyhow::Result<(Vec<(f64, Sim3)>, Value)> {
        self.file
            .flush()
            .with_context(|| format!("writing {}", self.path.display()))?;
        let counts = self.counts;
        let summary = json!({
            "mode": "localize",
            "frames": frames,
            "localized": counts[0] + counts[1],
            "tracked": counts[0],
            "relocalized": counts[1],
            "not_localized": counts[2],
            "ms_per_frame": 1e3 * wall_s / frames.max(1) as f64,
        });
        Ok((self.trajectory, summary))
    }
}
