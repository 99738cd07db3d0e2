//! Saved maps in the service (issue 24, item 3), end to end through the real binaries: session
//! A maps a rendered room (WebSocket), its map is kept with `POST /v1/maps` (`relfusion maps
//! save`), relfusiond restarts, and sessions B (WebSocket) and C (Zenoh) localise another
//! sequence of the same room — other poses, sensor noise — in that map. Fails when the map is
//! lost in the restart, when fewer than 90 % of B's or C's frames get a pose, when their poses
//! (under the Sim(3) that aligns the map's own keyframes to the first sequence's ground truth)
//! are off, or when another token can see, use or delete the map. Session D then extends the
//! map with the second sequence: its new keyframes must land in the map's frame, the old ones
//! stay, and its map is kept as a second map.

use std::path::{Path, PathBuf};
use std::process::Output;

use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::trajectory::{StampedPose, parse_tum_trajectory};
use relfusion_slam::eval::{AlignMode, DEFAULT_MAX_DT, align, associate_poses};
use relfusion_slam::geometry::{SE3, SO3, Sim3};
use relfusion_tests::{Relfusiond, json_lines, relfusion, synth_sequence, temp_dir};
use serde_json::Value;

const MAP_FRAMES: usize = 150;
const LOCALISED_FRAMES: usize = 100;
const SEED: u64 = 5;
const TOKENS: (&str, &str) = ("RELFUSIOND_TOKENS", "alice:secret-a,bob:secret-b");

fn ok(what: &str, out: &Output, server: &Relfusiond) -> Vec<Value> {
    json_lines(&server.ok_stdout(what, out))
}

fn refused(out: &Output) -> String {
    assert!(
        !out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn spawn(data: &Path) -> (Relfusiond, String) {
    Relfusiond::spawn_zenoh_peer::<&str>(data, &[], &[TOKENS])
}

/// Downloads `session`'s results (alice's) into `out`; returns `out`.
fn fetch(server: &Relfusiond, session: &str, out: PathBuf) -> PathBuf {
    let url = server.url();
    let args = [
        "fetch",
        session,
        "--server",
        &url,
        "--token",
        "secret-a",
        "--out",
        s(&out),
    ];
    ok("fetch", &relfusion(&args), server);
    out
}

/// A fetched TUM trajectory file.
fn tum(dir: &Path, name: &str) -> Vec<StampedPose> {
    let text = std::fs::read_to_string(dir.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    parse_tum_trajectory(&text, name).expect("parse")
}

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

fn groundtruth(dir: &Path) -> Vec<StampedPose> {
    TumSequence::open(dir, None)
        .expect("sequence")
        .groundtruth_poses()
}

/// Localised poses of a `relfusion stream` run (lines with `state` "tracking"), and how many
/// pose lines there were.
fn localised(lines: &[Value]) -> (Vec<StampedPose>, usize) {
    let poses: Vec<&Value> = lines.iter().filter(|l| l.get("state").is_some()).collect();
    let kept = poses
        .iter()
        .filter(|l| l["state"] == "tracking")
        .map(|l| {
            let f = |v: &Value| v.as_f64().expect("number");
            let t = &l["t"];
            let q = &l["q"];
            let rotation = SO3::from_quaternion(nalgebra::UnitQuaternion::from_quaternion(
                nalgebra::Quaternion::new(f(&q[3]), f(&q[0]), f(&q[1]), f(&q[2])),
            ));
            // The camera centre is `t` whatever the scale (it acts on the map's points).
            StampedPose {
                timestamp: f(&l["timestamp"]),
                world_from_camera: SE3::new(
                    rotation,
                    nalgebra::Vector3::new(f(&t[0]), f(&t[1]), f(&t[2])),
                ),
            }
        })
        .collect();
    (kept, poses.len())
}

/// RMS and largest position error of `poses` against `gt` under `gt_from_map`.
fn errors(gt: &[StampedPose], poses: &[StampedPose], gt_from_map: &Sim3) -> (f64, f64) {
    let matched = associate_poses(gt, poses, DEFAULT_MAX_DT).expect("matched");
    let e: Vec<f64> = matched
        .gt
        .iter()
        .zip(&matched.est)
        .map(|(g, p)| {
            (g.world_from_camera.translation - gt_from_map.act(&p.world_from_camera.translation))
                .norm()
        })
        .collect();
    let rms = (e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64).sqrt();
    (rms, e.iter().copied().fold(0.0, f64::max))
}

#[test]
fn a_saved_map_outlives_its_session_and_a_restart_and_new_sessions_localise_in_it() {
    let map_seq = synth_sequence("maps", MAP_FRAMES, SEED);
    let work = temp_dir("service-maps");
    // The same room seen from other poses (27 frames/s on the same path) through a noisier
    // sensor.
    let other = work.join("other");
    let out = relfusion(&[
        "synth",
        "--width",
        "320",
        "--height",
        "240",
        "--frames",
        "100",
        "--fps",
        "27",
        "--seed",
        "5",
        "--noise",
        "2",
        "--out",
        s(&other),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let data = work.join("data");
    let (server, _) = spawn(&data);
    let url = server.url();
    let config = work.join("deterministic.json");
    std::fs::write(&config, r#"{"pipeline":{"deterministic":true}}"#).expect("config");

    // Session A maps the room.
    let lines = ok(
        "stream (mapping)",
        &relfusion(&[
            "stream",
            s(&map_seq),
            "--server",
            &url,
            "--token",
            "secret-a",
            "--wait",
            "--fast",
            "--config",
            s(&config),
        ]),
        &server,
    );
    let session = lines[0]["session"].as_str().expect("session").to_string();
    // Without a metric depth prior the session's unit is arbitrary, and its status says so.
    let summary = &lines.last().expect("summary")["summary"];
    assert_eq!(summary["scale"], "arbitrary", "{summary}");
    let keep = |token: &str| {
        relfusion(&[
            "maps", "--server", &url, "--token", token, "save", &session, "--name", "room 5",
        ])
    };
    // Only its owner can keep it.
    let why = refused(&keep("secret-b"));
    assert!(why.contains("404"), "{why}");
    let saved = ok("maps save", &keep("secret-a"), &server).remove(0);
    let map_id = saved["id"].as_str().expect("map id").to_string();
    assert!(
        saved["keyframes"].as_u64().is_some_and(|k| k >= 3),
        "{saved}"
    );
    assert_eq!(saved["session"], session.as_str());
    assert_eq!(saved["camera"]["width"], 320);
    // Made without a metric depth prior: no unit.
    assert_eq!(saved["scale"], "arbitrary", "{saved}");
    assert_eq!(saved["format_version"], 2, "{saved}");
    let fetched = fetch(&server, &session, work.join("a"));
    let keyframes = tum(&fetched, "keyframes.txt");
    let matched = associate_poses(&groundtruth(&map_seq), &keyframes, DEFAULT_MAX_DT).expect("kf");
    let gt_from_map = align(&matched, AlignMode::Sim3).expect("alignment");

    // A restart loses nothing: the map is listed again and serves new sessions.
    assert!(server.terminate(), "graceful exit");
    let (server, endpoint) = spawn(&data);
    let url = server.url();
    let list = |token: &str| relfusion(&["maps", "--server", &url, "--token", token, "list"]);
    let listed = ok("maps list", &list("secret-a"), &server).remove(0);
    assert_eq!(listed["maps"].as_array().map(Vec::len), Some(1), "{listed}");
    assert_eq!(listed["maps"][0]["id"], map_id.as_str());
    assert_eq!(listed["maps"][0]["name"], "room 5");
    // Another token neither sees nor uses it.
    let bobs = ok("maps list", &list("secret-b"), &server).remove(0);
    assert_eq!(bobs["maps"].as_array().map(Vec::len), Some(0), "{bobs}");
    let bob = ["--server", url.as_str(), "--token", "secret-b"];
    for args in [
        [&["maps"][..], &bob, &["show", &map_id]].concat(),
        [&["maps"][..], &bob, &["delete", &map_id]].concat(),
        [
            &[
                "stream",
                s(&other),
                "--map",
                &map_id,
                "--wait",
                "--fast",
                "--frames",
                "3",
            ][..],
            &bob,
        ]
        .concat(),
    ] {
        let why = refused(&relfusion(&args));
        assert!(why.contains("404"), "{args:?}: {why}");
    }

    // Session B (WebSocket) and session C (Zenoh) localise the other sequence in the map.
    let gt = groundtruth(&other);
    for (transport, extra) in [
        ("websocket", vec![]),
        ("zenoh", vec!["--zenoh", &endpoint, "--user", "alice"]),
    ] {
        let mut args = vec![
            "stream",
            s(&other),
            "--server",
            &url,
            "--token",
            "secret-a",
            "--wait",
            "--fast",
            "--map",
            &map_id,
        ];
        args.extend(extra);
        let lines = ok(transport, &relfusion(&args), &server);
        let (poses, all) = localised(&lines);
        assert_eq!(all, LOCALISED_FRAMES, "{transport}: a pose line per frame");
        let (rms, max) = errors(&gt, &poses, &gt_from_map);
        eprintln!(
            "{transport}: {} of {all} frames localised, rms {rms:.4} m, max {max:.4} m",
            poses.len()
        );
        assert!(
            poses.len() * 10 >= all * 9,
            "{transport}: {} of {all} localised",
            poses.len()
        );
        assert!(rms < 0.05 && max < 0.15, "{transport}: rms {rms} max {max}");
        let summary = &lines.last().expect("summary")["summary"];
        assert_eq!(summary["state"], "finished", "{summary}");
        assert_eq!(summary["map"]["id"], map_id.as_str(), "{summary}");
        assert_eq!(summary["keyframes"], 0, "the map is not changed: {summary}");
    }

    // Session D extends the map with the other sequence (WebSocket): it maps on from where
    // its frames are found, in the map's frame, and its map (kept like any other) holds the
    // old keyframes, unchanged, and the new ones.
    let lines = ok(
        "stream (extend)",
        &relfusion(&[
            "stream",
            s(&other),
            "--server",
            &url,
            "--token",
            "secret-a",
            "--wait",
            "--fast",
            "--config",
            s(&config),
            "--map",
            &map_id,
            "--map-mode",
            "extend",
        ]),
        &server,
    );
    let (poses, all) = localised(&lines);
    let (rms, max) = errors(&gt, &poses, &gt_from_map);
    eprintln!(
        "extend: {} of {all} frames tracked live, rms {rms:.4} m, max {max:.4} m",
        poses.len()
    );
    assert!(poses.len() * 10 >= all * 8, "{} of {all}", poses.len());
    let summary = &lines.last().expect("summary")["summary"];
    let old_keyframes = keyframes.len();
    let total = summary["keyframes"].as_u64().expect("keyframes") as usize;
    assert!(total > old_keyframes, "{summary}");
    let extending = lines[0]["session"].as_str().expect("session").to_string();
    let merged = ok(
        "maps save (extended)",
        &relfusion(&[
            "maps", "--server", &url, "--token", "secret-a", "save", &extending, "--name",
            "room 5+",
        ]),
        &server,
    )
    .remove(0);
    assert_eq!(merged["keyframes"].as_u64(), Some(total as u64), "{merged}");
    let fetched = fetch(&server, &extending, work.join("d"));
    let both = tum(&fetched, "keyframes.txt");
    assert_eq!(both.len(), total);
    for (a, b) in keyframes.iter().zip(&both) {
        let moved = (a.world_from_camera.translation - b.world_from_camera.translation).norm();
        assert!(moved < 1e-5, "an old keyframe moved by {moved}");
    }
    let (rms, _) = errors(&gt, &both[old_keyframes..], &gt_from_map);
    let trajectory = tum(&fetched, "trajectory.txt");
    let (frames_rms, frames_max) = errors(&gt, &trajectory, &gt_from_map);
    eprintln!(
        "extend: new keyframes rms {rms:.4} m; {} frames after the final optimisation: rms \
         {frames_rms:.4} m, max {frames_max:.4} m",
        trajectory.len()
    );
    assert!(rms < 0.05, "new keyframes: rms {rms}");
    assert!(frames_rms < 0.05, "frames: rms {frames_rms}");

    // A camera the map was not made with is refused with a clear error.
    let body = format!(
        r#"{{"camera":{{"fx":200,"fy":200,"cx":160,"cy":120,"width":320,"height":240}},"map":{{"id":"{map_id}","mode":"localize"}}}}"#
    );
    let response = ureq::post(&format!("{url}/v1/sessions"))
        .header("Authorization", "Bearer secret-a")
        .header("Content-Type", "application/json")
        .config()
        .http_status_as_error(false)
        .build()
        .send(body.as_bytes())
        .expect("request");
    assert_eq!(response.status().as_u16(), 400);

    // Deleted, it is gone; the extended map, made from it, stays.
    ok(
        "maps delete",
        &relfusion(&[
            "maps", "--server", &url, "--token", "secret-a", "delete", &map_id,
        ]),
        &server,
    );
    let listed = ok("maps list", &list("secret-a"), &server).remove(0);
    assert_eq!(listed["maps"].as_array().map(Vec::len), Some(1), "{listed}");
    assert_eq!(listed["maps"][0]["id"], merged["id"], "{listed}");
    let _ = std::fs::remove_dir_all(&work);
}
