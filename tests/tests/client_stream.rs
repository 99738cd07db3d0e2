//! The client end to end against a real `relfusiond`: `relfusion stream` (WebSocket, `wait`
//! policy, deterministic pipeline) gives a pose for every frame and a trajectory whose ATE is
//! exactly that of `relfusion run` on the same frames; `relfusion fetch` writes the results;
//! `relfusion upload` follows an upload to completion; server errors reach the user as the
//! server's code and message.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Output;

use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::trajectory::read_tum_trajectory;
use relfusion_slam::eval::{AlignMode, ate};
use relfusion_tests::{Relfusiond, json_lines, relfusion, synth_sequence, temp_dir};
use serde_json::Value;

/// Frames of the test sequence (320×240).
const FRAMES: usize = 100;
const SEED: u64 = 11;

fn path_str(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

#[test]
fn stream_gives_every_pose_and_the_same_trajectory_as_run() {
    let seq_dir = synth_sequence("client", FRAMES, SEED);
    let work = temp_dir("client-stream");
    let server = Relfusiond::spawn(&work.join("data"), Vec::<&str>::new(), &[]);
    let url = server.url();
    let config = work.join("deterministic.json");
    std::fs::write(&config, r#"{"pipeline":{"deterministic":true}}"#).expect("write config");

    let out = relfusion(&[
        "stream",
        path_str(&seq_dir),
        "--server",
        &url,
        "--wait",
        "--fast",
        "--config",
        path_str(&config),
    ]);
    let lines = json_lines(&server.ok_stdout("relfusion stream", &out));
    let id = lines[0]["session"]
        .as_str()
        .unwrap_or_else(|| panic!("first line names the session: {}", lines[0]))
        .to_string();
    let summary = &lines.last().expect("a summary line")["summary"];
    assert!(summary.is_object(), "last line is the summary: {lines:?}");
    let poses = &lines[1..lines.len() - 1];
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let mut ids = BTreeSet::new();
    for pose in poses {
        let frame_id = pose["frame_id"]
            .as_u64()
            .unwrap_or_else(|| panic!("a pose line: {pose}"));
        assert!(ids.insert(frame_id), "frame {frame_id} got two poses");
        let timestamp = pose["timestamp"].as_f64().expect("timestamp");
        assert_eq!(timestamp, seq.frames[frame_id as usize].timestamp);
        assert_eq!(pose["t"].as_array().map(Vec::len), Some(3), "{pose}");
        assert_eq!(pose["q"].as_array().map(Vec::len), Some(4), "{pose}");
        assert!(pose["s"].as_f64().is_some_and(|s| s > 0.0), "{pose}");
        assert!(
            ["initializing", "tracking", "lost"].contains(&pose["state"].as_str().unwrap_or("")),
            "{pose}"
        );
    }
    assert_eq!(
        ids,
        (0..FRAMES as u64).collect(),
        "a pose for every frame (wait policy drops nothing)"
    );
    assert_eq!(summary["frames_sent"], FRAMES);
    assert_eq!(summary["poses_received"], FRAMES);
    assert_eq!(summary["frames_dropped"], 0);
    assert_eq!(summary["server_errors"], 0);
    assert_eq!(summary["state"], "finished");
    assert!(summary["ate"]["rmse"].as_f64().is_some(), "{summary}");

    let fetched = work.join("fetched");
    let out = relfusion(&["fetch", &id, "--server", &url, "--out", path_str(&fetched)]);
    let report: Value =
        serde_json::from_str(server.ok_stdout("relfusion fetch", &out).trim()).expect("JSON");
    assert_eq!(report["session"], id.as_str());
    for file in ["trajectory.txt", "keyframes.txt", "pointcloud.ply"] {
        let len = std::fs::metadata(fetched.join(file))
            .unwrap_or_else(|e| panic!("{file} fetched: {e}"))
            .len();
        assert!(len > 0, "{file} is empty");
    }
    let ply = std::fs::read(fetched.join("pointcloud.ply")).expect("ply");
    assert!(ply.starts_with(b"ply"), "pointcloud.ply is a PLY file");
    let keyframes = read_tum_trajectory(&fetched.join("keyframes.txt")).expect("keyframes");
    assert!(!keyframes.is_empty(), "at least the first keyframe");

    let local = work.join("local");
    let out = relfusion(&[
        "run",
        path_str(&seq_dir),
        "--out",
        path_str(&local),
        "--deterministic",
        "--quiet",
    ]);
    server.ok_stdout("relfusion run", &out);
    let served = read_tum_trajectory(&fetched.join("trajectory.txt")).expect("served trajectory");
    let run = read_tum_trajectory(&local.join("trajectory.txt")).expect("run trajectory");
    assert_eq!(served.len(), run.len(), "same number of poses");
    assert_eq!(served.len(), FRAMES);
    let gt = seq.groundtruth_poses();
    let ate_served = ate(&gt, &served, AlignMode::Sim3).expect("ATE served").rmse;
    let ate_run = ate(&gt, &run, AlignMode::Sim3).expect("ATE run").rmse;
    assert!(
        (ate_served - ate_run).abs() <= 1e-9,
        "ATE over the service {ate_served} vs relfusion run {ate_run}"
    );
    assert!(
        (summary["ate"]["rmse"].as_f64().expect("rmse") - ate_run).abs() <= 1e-9,
        "the summary's ATE is the final trajectory's"
    );
}

#[test]
fn upload_follows_progress_to_completion() {
    let seq_dir = synth_sequence("client", FRAMES, SEED);
    let work = temp_dir("client-upload");
    let server = Relfusiond::spawn(&work.join("data"), Vec::<&str>::new(), &[]);
    let url = server.url();

    let out = relfusion(&["upload", path_str(&seq_dir), "--server", &url]);
    let lines = json_lines(&server.ok_stdout("relfusion upload", &out));
    let id = lines[0]["uploaded"]["session"]
        .as_str()
        .unwrap_or_else(|| panic!("first line acknowledges the upload: {}", lines[0]))
        .to_string();
    assert!(
        lines[0]["uploaded"]["bytes"]
            .as_u64()
            .is_some_and(|b| b > 0)
    );
    let last = lines.last().expect("a final line");
    assert_eq!(last["session"], id.as_str(), "{last}");
    assert_eq!(last["state"], "finished", "{last}");
    assert_eq!(last["frames_processed"], FRAMES, "{last}");
    let progress: Vec<u64> = lines[1..lines.len() - 1]
        .iter()
        .filter_map(|l| l["progress"]["processed"].as_u64())
        .collect();
    assert!(!progress.is_empty(), "progress was reported: {lines:?}");
    assert!(
        progress.windows(2).all(|w| w[0] <= w[1]),
        "progress never goes back: {progress:?}"
    );

    let fetched = work.join("fetched");
    let out = relfusion(&["fetch", &id, "--server", &url, "--out", path_str(&fetched)]);
    server.ok_stdout("relfusion fetch", &out);
    let trajectory = read_tum_trajectory(&fetched.join("trajectory.txt")).expect("trajectory");
    assert_eq!(trajectory.len(), FRAMES, "every uploaded frame has a pose");
}

#[test]
fn server_errors_reach_the_user_with_their_code() {
    let work = temp_dir("client-errors");
    let server = Relfusiond::spawn(
        &work.join("data"),
        Vec::<&str>::new(),
        &[("RELFUSIOND_TOKENS", "alice:secret-a")],
    );
    let url = server.url();
    let out_dir = work.join("out");
    let fetch = |token: &str| {
        relfusion(&[
            "fetch",
            "s-000000000000",
            "--server",
            &url,
            "--token",
            token,
            "--out",
            path_str(&out_dir),
        ])
    };
    let stderr = |out: &Output| String::from_utf8_lossy(&out.stderr).into_owned();

    let out = fetch("wrong");
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("401 unauthorized"),
        "{}",
        stderr(&out)
    );
    let out = fetch("secret-a");
    assert!(!out.status.success());
    assert!(stderr(&out).contains("404 not_found"), "{}", stderr(&out));
    assert!(
        !PathBuf::from(&out_dir).join("trajectory.txt").exists(),
        "nothing written for an unknown session"
    );
    // The server is still there.
    let out = relfusion(&["fetch", "x", "--server", &url, "--out", path_str(&out_dir)]);
    assert!(stderr(&out).contains("401"), "{}", stderr(&out));
}
