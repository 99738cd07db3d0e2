//! What the viewer-recording tests share: the Python readers of MCAP and ROS 2 bags
//! (`tests/py/`), the checks of an MCAP against a session's own files, and small readers.
//! Two test binaries use it (`recordings`, and `rerun_recordings` with the feature `rerun`),
//! each only part of it.
#![allow(dead_code)]

use std::path::Path;
use std::process::Command;

use relfusion_tests::{Relfusiond, ply_faces};
use serde_json::Value;

/// A sequence streamed to a real service with `relfusion stream --wait --fast EXTRA…`, and
/// the session's results fetched back: what the recordings are checked against.
pub struct Streamed {
    /// The stream's last line: `{"summary": …}`.
    pub summary: Value,
    /// Tracked frames in the fetched `trajectory.txt`.
    pub poses: usize,
    pub keyframes: usize,
    /// Faces of the fetched `mesh.ply`.
    pub triangles: usize,
    /// The service's own MCAP of the session (`recording.mcap`).
    pub recording: std::path::PathBuf,
}

pub fn stream_and_fetch(seq: &str, server: &Relfusiond, work: &Path, extra: &[&str]) -> Streamed {
    let url = server.url();
    let mut args = vec!["stream", seq, "--server", &url, "--wait", "--fast"];
    args.extend_from_slice(extra);
    let lines = relfusion(&args);
    let id = lines[0]["session"].as_str().expect("session").to_string();
    let summary = lines.last().expect("summary")["summary"].clone();
    let fetched = work.join("fetched");
    let out = fetched.to_str().expect("path");
    relfusion(&["fetch", &id, "--server", &url, "--out", out]);
    Streamed {
        poses: tum_lines(&fetched.join("trajectory.txt")),
        keyframes: summary["keyframes"].as_u64().expect("keyframes") as usize,
        triangles: mesh_ply_faces(&fetched.join("mesh.ply")),
        recording: fetched.join("recording.mcap"),
        summary,
    }
}

/// The service's recording of a streamed session: no images, the same poses, keyframes and
/// mesh as its fetched results.
pub fn check_service_recording(streamed: &Streamed) {
    let recorded = foxglove_check(&["mcap", streamed.recording.to_str().expect("path")]);
    check_mcap(
        &recorded,
        0,
        streamed.poses,
        streamed.keyframes,
        streamed.triangles,
    );
}

pub fn mesh_ply_faces(path: &Path) -> usize {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    ply_faces(&bytes) as usize
}

pub fn tum_lines(path: &Path) -> usize {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .count()
}

/// Runs `tests/py/foxglove_check.py ARGS`.
pub fn foxglove_check(args: &[&str]) -> Value {
    python_check("foxglove_check.py", args)
}

/// Runs `tests/py/SCRIPT ARGS` with the Python packages `scripts/setup.sh --test` installed,
/// and parses its JSON summary.
pub fn python_check(script: &str, args: &[&str]) -> Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("py")
        .join(script);
    let mut command = Command::new("python3");
    command.arg(&script).args(args);
    if let Some(deps) = std::env::var_os("RELFUSION_CLIENT_PYDEPS") {
        command.env("PYTHONPATH", deps);
    }
    let out = command.output().expect("python3");
    assert!(
        out.status.success(),
        "{} {args:?}: {}",
        script.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("a JSON summary")
}

/// The schema of every channel, as Foxglove names them.
pub const FOXGLOVE_SCHEMAS: [(&str, &str); 7] = [
    ("/camera/image", "foxglove.CompressedImage"),
    ("/camera/calibration", "foxglove.CameraCalibration"),
    ("/camera/pose", "foxglove.PoseInFrame"),
    ("/tf", "foxglove.FrameTransforms"),
    ("/trajectory", "foxglove.PosesInFrame"),
    ("/keyframes/points", "foxglove.PointCloud"),
    ("/mesh", "foxglove.SceneUpdate"),
];

/// The topics of the camera's images: a recording without images has neither.
pub const IMAGE_TOPICS: [&str; 2] = ["/camera/image", "/camera/calibration"];

/// An MCAP read back: one image and calibration per frame, one pose and camera transform per
/// tracked frame, one keyframe frame per keyframe, and SceneUpdates that add up to the mesh.
/// `frames` 0: a recording without images (the service's).
pub fn check_mcap(mcap: &Value, frames: usize, poses: usize, keyframes: usize, triangles: usize) {
    let count = |topic: &str| mcap["counts"][topic].as_u64().unwrap_or(0) as usize;
    let with_images = frames > 0;
    for (topic, schema) in FOXGLOVE_SCHEMAS {
        if !with_images && IMAGE_TOPICS.contains(&topic) {
            continue;
        }
        assert_eq!(mcap["schemas"][topic], schema, "{topic}: {mcap}");
        assert_eq!(mcap["encodings"][topic], "protobuf", "{topic}: {mcap}");
    }
    assert_eq!(
        mcap["indexed_channels"],
        if with_images { 7 } else { 5 },
        "{mcap}"
    );
    assert_eq!(mcap["times_ordered_per_topic"], true, "{mcap}");
    assert_eq!(count("/camera/image"), frames, "{mcap}");
    assert_eq!(count("/camera/calibration"), frames, "{mcap}");
    assert_eq!(count("/camera/pose"), poses, "{mcap}");
    assert_eq!(mcap["camera_transforms"], poses, "{mcap}");
    assert_eq!(mcap["keyframe_frames"], keyframes, "{mcap}");
    assert!(count("/trajectory") >= 1, "{mcap}");
    assert!(count("/keyframes/points") >= 1, "{mcap}");
    assert!(
        mcap["cloud_points_max"].as_u64().unwrap_or(0) > 100,
        "{mcap}"
    );
    assert!(mcap["mesh_blocks"].as_u64().unwrap_or(0) > 10, "{mcap}");
    assert_eq!(mcap["mesh_triangles"], triangles, "mesh triangles: {mcap}");
}

/// Every JSON line `relfusion ARGS` printed (it must succeed).
pub fn relfusion(args: &[&str]) -> Vec<Value> {
    relfusion_tests::relfusion_stdout(args)
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}
