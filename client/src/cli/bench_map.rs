//! `relfusion bench map --map OUT/map`: what a saved map costs — load and save times, size on
//! disk per keyframe (by part), memory of the loaded map and of a localiser built on it.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use relfusion_slam::map::{LocalizeConfig, Localizer, disk_bytes_by_file, read_map, write_map};
use relfusion_slam::tracking::TrackingConfig;
use serde_json::json;

#[derive(Debug, clap::Args)]
pub struct MapArgs {
    /// A saved map (`OUT/map` of `relfusion run`).
    #[arg(long)]
    pub map: PathBuf,
    /// Timed loads and saves (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub iters: usize,
}

pub fn map(args: &MapArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.iters > 0, "--iters must be positive");
    let mut loads = Vec::new();
    let mut map = None;
    for _ in 0..args.iters {
        let t = Instant::now();
        map = Some(
            read_map(&args.map, None).with_context(|| format!("loading {}", args.map.display()))?,
        );
        loads.push(t.elapsed().as_secs_f64());
    }
    let map = map.context("no load ran")?;
    let n = map.keyframes.len().max(1);
    let scratch = std::env::temp_dir().join(format!("relfusion-bench-map-{}", std::process::id()));
    let copy = scratch.join("map");
    let mut saves = Vec::new();
    for _ in 0..args.iters {
        let t = Instant::now();
        write_map(&copy, &map)?;
        saves.push(t.elapsed().as_secs_f64());
    }
    let parts = disk_bytes_by_file(&copy)?;
    let total: u64 = parts.values().sum();
    let _ = std::fs::remove_dir_all(&scratch);
    let t = Instant::now();
    let localizer = Localizer::new(&map, TrackingConfig::default(), LocalizeConfig::default())?;
    let localizer_s = t.elapsed().as_secs_f64();
    let per_keyframe: serde_json::Map<String, serde_json::Value> = parts
        .iter()
        .map(|(name, bytes)| (name.clone(), json!(*bytes as f64 / n as f64)))
        .collect();
    println!(
        "{}",
        json!({
            "map": args.map,
            "keyframes": map.keyframes.len(),
            "edges": map.edges.len(),
            "load_s": median(&mut loads),
            "save_s": median(&mut saves),
            "localizer_build_s": localizer_s,
            "disk_bytes": total,
            "disk_bytes_per_keyframe": total as f64 / n as f64,
            "disk_bytes_per_keyframe_by_part": per_keyframe,
            "memory_bytes": map.memory_bytes(),
            "memory_bytes_per_keyframe": map.memory_bytes() as f64 / n as f64,
            "localizer_tracking_points": localizer.tracking_points(),
        })
    );
    Ok(())
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}
