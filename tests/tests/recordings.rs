//! A session for viewers, read back with the viewers' own tools: `--mcap FILE` and
//! `--foxglove PORT` (issue 38) with the `mcap` Python package and its protobuf decoder, and a
//! client of the Foxglove WebSocket protocol that offers what the Foxglove app offers
//! (`tests/py/foxglove_check.py`); ROS 2 bags as `ros2 bag` reads them. `relfusion stream`
//! against a real relfusiond and `relfusion run` locally: every frame's image, one camera
//! transform per tracked frame, one keyframe frame per keyframe, and mesh updates whose last
//! state adds up to the triangles of the session's mesh.ply. The rerun recordings
//! (`--rerun`, an optional feature) are checked in `rerun_recordings.rs`.

mod viewers;

use std::io::BufReader;
use std::path::PathBuf;
use std::process::Command;

use relfusion_tests::{Relfusiond, bin_path, data_dir, synth_sequence, temp_dir};
use serde_json::{Value, json};
use viewers::{
    FOXGLOVE_SCHEMAS, check_mcap, check_service_recording, foxglove_check, python_check,
    stream_and_fetch, tum_lines,
};

/// A synthetic sequence streamed to a real service with `--mcap`: the client's MCAP holds
/// every frame, pose, keyframe and the mesh; the service's own recording the same session.
#[test]
fn stream_writes_an_mcap_of_the_session_and_the_service_records_it() {
    const FRAMES: usize = 40;
    let sequence = synth_sequence("mcap", FRAMES, 31);
    let seq = sequence.to_str().expect("utf-8 path");
    let work = temp_dir("mcap");
    let server = Relfusiond::spawn(&work.join("data"), Vec::<PathBuf>::new(), &[]);
    let mcap_path = work.join("stream.mcap");
    let mcap_arg = mcap_path.to_str().expect("path");
    let streamed = stream_and_fetch(seq, &server, &work, &["--mcap", mcap_arg]);
    let mcap = foxglove_check(&["mcap", mcap_arg]);
    let s = &streamed;
    check_mcap(&mcap, FRAMES, s.poses, s.keyframes, s.triangles);
    assert_eq!(
        mcap["counts"]["/mesh"],
        streamed.summary["foxglove"]["mesh_updates"]
    );
    check_service_recording(&streamed);
}

/// A real sequence run locally, written to MCAP (Foxglove's schemas, and a ROS 2 bag) and
/// served live at once; a Foxglove client offering `foxglove.websocket.v1` subscribes before
/// the first frame (`--foxglove-wait`) and decodes one message of every channel with the
/// schemas the server advertised.
#[test]
fn a_real_sequence_is_recorded_to_mcap_and_served_to_foxglove() {
    let seq = data_dir().join("sequences/7scenes_redkitchen_f0000-0299");
    let work = temp_dir("foxglove");
    let out = work.join("run");
    let mcap_path = work.join("run.mcap");
    let bag_path = work.join("run-ros2.mcap");
    let mut child = Command::new(bin_path("relfusion"))
        .args([
            "run",
            seq.to_str().expect("path"),
            "--frames",
            "60",
            "--deterministic",
        ])
        .args(["--quiet", "--out", out.to_str().expect("path")])
        .args(["--mcap", mcap_path.to_str().expect("path")])
        .args(["--mcap-ros2", bag_path.to_str().expect("path")])
        .args(["--foxglove", "0", "--foxglove-wait", "120"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("relfusion run");
    // The URL comes first on stderr; the rest is drained so the run never blocks on it.
    let stderr = child.stderr.take().expect("stderr");
    let (url_tx, url_rx) = std::sync::mpsc::channel();
    let drain = std::thread::spawn(move || {
        use std::io::BufRead as _;
        let mut log = String::new();
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Ok(v) = serde_json::from_str::<Value>(&line)
                && let Some(url) = v["foxglove"].as_str()
            {
                let _ = url_tx.send(url.to_string());
            }
            log.push_str(&line);
            log.push('\n');
        }
        log
    });
    let url = match url_rx.recv_timeout(std::time::Duration::from_secs(120)) {
        Ok(url) => url,
        Err(e) => {
            // The run ended (or hung) before serving: its log says why.
            let _ = child.kill();
            let status = child.wait();
            let log = drain.join().unwrap_or_default();
            panic!("no Foxglove URL on stderr ({e}); relfusion run {status:?}: {log}");
        }
    };
    // Offering only the protocol's published name, as Lichtblick and older Foxglove apps do.
    let live = foxglove_check(&["ws", &url, "240", "foxglove.websocket.v1"]);
    let finished = child.wait_with_output().expect("relfusion run");
    let log = drain.join().expect("stderr");
    assert!(finished.status.success(), "relfusion run: {log}");

    assert_eq!(live["subprotocol"], "foxglove.websocket.v1", "{live}");
    assert_eq!(live["server_name"], "relfusion", "{live}");
    for (topic, schema) in FOXGLOVE_SCHEMAS {
        assert!(
            live["advertised"]
                .as_array()
                .is_some_and(|a| a.iter().any(|t| t == topic)),
            "{topic} not advertised: {live}"
        );
        assert_eq!(live["received"][topic]["schema"], schema, "{topic}: {live}");
    }
    assert!(
        live["received"]["/camera/image"]["bytes"]
            .as_u64()
            .is_some_and(|b| b > 10_000),
        "{live}"
    );

    let summary: Value = String::from_utf8_lossy(&finished.stdout)
        .lines()
        .rev()
        .find_map(|l| serde_json::from_str(l).ok())
        .expect("the run's summary");
    let mcap = foxglove_check(&["mcap", mcap_path.to_str().expect("path")]);
    check_mcap(
        &mcap,
        60,
        tum_lines(&out.join("trajectory.txt")),
        tum_lines(&out.join("keyframes.txt")),
        summary["mesh_triangles"].as_u64().expect("mesh triangles") as usize,
    );
    assert_eq!(mcap["counts"]["/mesh"], summary["foxglove"]["mesh_updates"]);

    // The ROS 2 bag, read as `ros2 bag` reads it.
    let bag = python_check("ros2_check.py", &["bag", bag_path.to_str().expect("path")]);
    let sent = &summary["ros2_bag"]["messages"];
    for (topic, name, schema) in [
        (
            "/camera/image/compressed",
            "image/compressed",
            "sensor_msgs/msg/CompressedImage",
        ),
        (
            "/camera/camera_info",
            "camera_info",
            "sensor_msgs/msg/CameraInfo",
        ),
        ("/tf", "tf", "tf2_msgs/msg/TFMessage"),
        ("/relfusion/pose", "pose", "geometry_msgs/msg/PoseStamped"),
        ("/relfusion/path", "path", "nav_msgs/msg/Path"),
        ("/relfusion/points", "points", "sensor_msgs/msg/PointCloud2"),
        (
            "/relfusion/mesh",
            "mesh",
            "visualization_msgs/msg/MarkerArray",
        ),
    ] {
        assert_eq!(bag["counts"][topic], sent[name], "{topic}: {bag}");
        assert_eq!(
            bag["schemas"][topic],
            json!([schema, "ros2msg", "cdr"]),
            "{bag}"
        );
    }
    assert_eq!(bag["counts"]["/camera/image/compressed"], 60, "{bag}");
    assert_eq!(
        bag["counts"]["/relfusion/pose"],
        tum_lines(&out.join("trajectory.txt")),
        "a PoseStamped per tracked frame: {bag}"
    );
    assert_eq!(
        bag["counts"]["/relfusion/mesh"],
        summary["foxglove"]["mesh_updates"]
    );
    assert_eq!(bag["first"]["/camera/camera_info"]["width"], 640, "{bag}");
    assert_eq!(
        bag["first"]["/relfusion/pose"]["frame_id"], "world",
        "{bag}"
    );
}
