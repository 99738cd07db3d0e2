//! `relfusion run SEQ --map MAP --mode localize --out OUT`: every frame of SEQ localised in a
//! saved map (`relfusion_slam::map::Localizer`), the map left as it is.
//!
//! Writes `OUT/trajectory.txt` (the localised frames, camera-to-world in the map's frame, TUM
//! format) and `OUT/localization.txt` (one line per frame: timestamp, `tracked`,
//! `relocalized` or `not_localized`, the map keyframe it was aligned to or -1, the
//! alignment's score and the frame's reach from that keyframe), then prints a one-line JSON summary.

use std::io::Write as _;
use std::path::Path;
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::map::{LocalizationState, Localizer, read_map};
use relfusion_slam::pipeline::Config;
use serde_json::json;

use super::run::{Args, write_trajectory};

pub fn run(args: &Args, map_dir: &Path) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let seq = TumSequence::open(&args.dataset, None)
        .with_context(|| format!("opening {}", args.dataset.display()))?;
    let n = args.frames.unwrap_or(seq.len()).min(seq.len());
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let t_load = Instant::now();
    let map = read_map(map_dir, Some(&seq.camera))
        .with_context(|| format!("loading the map {}", map_dir.display()))?;
    let load_s = t_load.elapsed().as_secs_f64();
    let mut localizer = Localizer::new(&map, config.tracking, config.localize)?;
    let map_keyframes = map.keyframes.len();
    drop(map);

    let log_path = args.out.join("localization.txt");
    let mut log = std::io::BufWriter::new(
        std::fs::File::create(&log_path)
            .with_context(|| format!("creating {}", log_path.display()))?,
    );
    writeln!(log, "# timestamp state keyframe score reach")?;
    let mut trajectory = Vec::new();
    let mut counts = [0usize; 3];
    let t0 = Instant::now();
    for (i, frame) in seq.frames.iter().enumerate().take(n) {
        let rgb = seq.load_rgb(i)?;
        let result = localizer.localize(frame.timestamp, rgb)?;
        let (name, slot) = match result.state {
            LocalizationState::Tracked => ("tracked", 0),
            LocalizationState::Relocalized => ("relocalized", 1),
            LocalizationState::NotLocalized => ("not_localized", 2),
        };
        counts[slot] += 1;
        writeln!(
            log,
            "{:.6} {name} {} {:.3} {:.3}",
            result.timestamp,
            result.keyframe.map_or(-1, |k| k as i64),
            result.score,
            result.reach
        )?;
        if let Some(pose) = result.world_from_camera {
            trajectory.push((result.timestamp, pose));
        }
    }
    let wall_s = t0.elapsed().as_secs_f64();
    log.flush()?;
    write_trajectory(&args.out.join("trajectory.txt"), &trajectory)?;
    println!(
        "{}",
        json!({
            "mode": "localize",
            "map": map_dir,
            "map_keyframes": map_keyframes,
            "map_load_s": load_s,
            "frames": n,
            "localized": counts[0] + counts[1],
            "tracked": counts[0],
            "relocalized": counts[1],
            "not_localized": counts[2],
            "ms_per_frame": 1e3 * wall_s / n.max(1) as f64,
            "out": args.out,
        })
    );
    Ok(())
}
