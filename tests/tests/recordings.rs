//! A session for viewers, read back with the viewers' own tools: `--rerun FILE.rrd` (issue 23,
//! item 5) with the rerun crate's decoder; `--mcap FILE` and `--foxglove PORT` (issue 38) with
//! the `mcap` Python package and its protobuf decoder, and a client of the Foxglove WebSocket
//! protocol that offers what the Foxglove app offers (`tests/py/foxglove_check.py`). `relfusion stream` against a real relfusiond and
//! `relfusion run` locally: every frame's image, one camera transform per tracked frame, one
//! entity per keyframe with its dense points, and mesh blocks whose last state adds up to the
//! triangles of the session's mesh.ply.

use std::collections::{BTreeMap, BTreeSet};
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::process::Command;

use relfusion_tests::{Relfusiond, bin_path, data_dir, ply_faces, synth_sequence, temp_dir};
use rerun::external::re_log_encoding::Decoder;
use rerun::log::{Chunk, LogMsg, RowId};
use serde_json::{Value, json};

/// What a recording holds, by entity path.
#[derive(Debug, Default)]
struct Contents {
    images: BTreeMap<String, usize>,
    transforms: BTreeMap<String, usize>,
    points: BTreeMap<String, usize>,
    line_strips: BTreeSet<String>,
    pinholes: BTreeSet<String>,
    /// Mesh block entity → its (row, triangles; `None` = Clear) in logging order.
    mesh: BTreeMap<String, Vec<(RowId, Option<usize>)>>,
}

impl Contents {
    /// Triangles of the blocks whose last entry is a mesh (not a Clear).
    fn mesh_triangles(&self) -> usize {
        self.mesh
            .values()
            .filter_map(|rows| {
                rows.iter()
                    .max_by_key(|(row, _)| *row)
                    .and_then(|(_, t)| *t)
            })
            .sum()
    }

    fn clears(&self) -> usize {
        self.mesh
            .values()
            .flatten()
            .filter(|(_, t)| t.is_none())
            .count()
    }
}

fn rows_with(chunk: &Chunk, component: &rerun::ComponentDescriptor) -> Vec<RowId> {
    chunk
        .iter_component_indices("frame".into(), component.component)
        .map(|(_, row)| row)
        .collect()
}

fn read_rrd(path: &Path) -> Contents {
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut contents = Contents::default();
    let messages = Decoder::<LogMsg>::decode_eager(BufReader::new(file)).expect("an .rrd file");
    for message in messages {
        let LogMsg::ArrowMsg(_, arrow) = message.expect("decodable message") else {
            continue;
        };
        let chunk = Chunk::from_arrow_msg(&arrow).expect("chunk");
        let entity = chunk.entity_path().to_string();
        let entity = entity.trim_start_matches('/').to_string();
        let count =
            |d: rerun::ComponentDescriptor| rows_with(&chunk, &d).len() + static_rows(&chunk, &d);
        let images = count(rerun::EncodedImage::descriptor_blob());
        if images > 0 {
            *contents.images.entry(entity.clone()).or_default() += images;
        }
        let transforms = count(rerun::Transform3D::descriptor_translation());
        if transforms > 0 {
            *contents.transforms.entry(entity.clone()).or_default() += transforms;
        }
        let points = count(rerun::Points3D::descriptor_positions());
        if points > 0 {
            *contents.points.entry(entity.clone()).or_default() += points;
        }
        if count(rerun::LineStrips3D::descriptor_strips()) > 0 {
            contents.line_strips.insert(entity.clone());
        }
        if count(rerun::Pinhole::descriptor_image_from_camera()) > 0 {
            contents.pinholes.insert(entity.clone());
        }
        let triangles = rerun::Mesh3D::descriptor_triangle_indices();
        let rows = rows_with(&chunk, &triangles);
        let sizes = chunk
            .iter_component::<rerun::components::TriangleIndices>(triangles.component)
            .map(|batch| batch.len());
        for (row, size) in rows.into_iter().zip(sizes) {
            contents
                .mesh
                .entry(entity.clone())
                .or_default()
                .push((row, Some(size)));
        }
        for row in rows_with(&chunk, &rerun::Clear::descriptor_is_recursive()) {
            contents
                .mesh
                .entry(entity.clone())
                .or_default()
                .push((row, None));
        }
    }
    contents
}

/// Rows of a static chunk (no timeline) that carry the component.
fn static_rows(chunk: &Chunk, d: &rerun::ComponentDescriptor) -> usize {
    if chunk.is_static() && chunk.components().contains_component(d.component) {
        chunk.num_rows()
    } else {
        0
    }
}

fn mesh_ply_faces(path: &Path) -> usize {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    ply_faces(&bytes) as usize
}

fn tum_lines(path: &Path) -> usize {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .count()
}

/// Runs `tests/py/foxglove_check.py ARGS`.
fn foxglove_check(args: &[&str]) -> Value {
    python_check("foxglove_check.py", args)
}

/// Runs `tests/py/SCRIPT ARGS` with the Python packages `scripts/setup.sh --test` installed,
/// and parses its JSON summary.
fn python_check(script: &str, args: &[&str]) -> Value {
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
const FOXGLOVE_SCHEMAS: [(&str, &str); 7] = [
    ("/camera/image", "foxglove.CompressedImage"),
    ("/camera/calibration", "foxglove.CameraCalibration"),
    ("/camera/pose", "foxglove.PoseInFrame"),
    ("/tf", "foxglove.FrameTransforms"),
    ("/trajectory", "foxglove.PosesInFrame"),
    ("/keyframes/points", "foxglove.PointCloud"),
    ("/mesh", "foxglove.SceneUpdate"),
];

/// The topics of the camera's images: a recording without images has neither.
const IMAGE_TOPICS: [&str; 2] = ["/camera/image", "/camera/calibration"];

/// An MCAP read back: one image and calibration per frame, one pose and camera transform per
/// tracked frame, one keyframe frame per keyframe, and SceneUpdates that add up to the mesh.
/// `frames` 0: a recording without images (the service's).
fn check_mcap(mcap: &Value, frames: usize, poses: usize, keyframes: usize, triangles: usize) {
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

fn relfusion(args: &[&str]) -> Vec<Value> {
    let out = Command::new(bin_path("relfusion"))
        .args(args)
        .output()
        .expect("relfusion");
    assert!(
        out.status.success(),
        "relfusion {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

/// The checks shared by both commands.
fn check(contents: &Contents, frames: usize, poses: usize, keyframes: usize, triangles: usize) {
    assert_eq!(
        contents.images.get("world/camera/image"),
        Some(&frames),
        "{contents:?}"
    );
    assert!(
        contents.pinholes.contains("world/camera/image"),
        "{contents:?}"
    );
    assert_eq!(
        contents.transforms.get("world/camera"),
        Some(&poses),
        "{contents:?}"
    );
    assert!(
        contents.line_strips.contains("world/trajectory"),
        "{contents:?}"
    );
    let keyframe_entities: BTreeSet<&String> = contents
        .transforms
        .keys()
        .filter(|e| e.starts_with("world/keyframes/"))
        .collect();
    assert_eq!(keyframe_entities.len(), keyframes, "{keyframe_entities:?}");
    let with_points = contents
        .points
        .keys()
        .filter(|e| e.ends_with("/points"))
        .count();
    assert!(
        with_points > 0 && with_points <= keyframes,
        "{:?}",
        contents.points
    );
    assert!(
        contents.mesh.len() > 10,
        "mesh blocks: {}",
        contents.mesh.len()
    );
    assert!(contents.mesh.keys().all(|e| e.starts_with("world/mesh/")));
    assert_eq!(contents.mesh_triangles(), triangles, "mesh triangles");
}

#[test]
fn stream_and_run_write_rerun_recordings_that_read_back() {
    const FRAMES: usize = 40;
    let sequence = synth_sequence("rerun", FRAMES, 31);
    let seq = sequence.to_str().expect("utf-8 path");
    let work = temp_dir("rerun");

    // Streamed to a real service.
    let server = Relfusiond::spawn(&work.join("data"), Vec::<PathBuf>::new(), &[]);
    let streamed = work.join("stream.rrd");
    let streamed_mcap = work.join("stream.mcap");
    let lines = relfusion(&[
        "stream",
        seq,
        "--server",
        &server.url(),
        "--wait",
        "--fast",
        "--rerun",
        streamed.to_str().expect("path"),
        "--mcap",
        streamed_mcap.to_str().expect("path"),
    ]);
    let id = lines[0]["session"].as_str().expect("session").to_string();
    let summary = &lines.last().expect("summary")["summary"];
    let fetched = work.join("fetched");
    relfusion(&[
        "fetch",
        &id,
        "--server",
        &server.url(),
        "--out",
        fetched.to_str().expect("path"),
    ]);
    let contents = read_rrd(&streamed);
    let poses = tum_lines(&fetched.join("trajectory.txt"));
    let keyframes = summary["keyframes"].as_u64().expect("keyframes") as usize;
    let triangles = mesh_ply_faces(&fetched.join("mesh.ply"));
    check(&contents, FRAMES, poses, keyframes, triangles);
    assert_eq!(
        contents.clears() as u64,
        summary["rerun"]["mesh_blocks_cleared"]
            .as_u64()
            .expect("counts"),
    );
    // The MCAP of the same stream holds the same updates.
    let mcap = foxglove_check(&["mcap", streamed_mcap.to_str().expect("path")]);
    check_mcap(&mcap, FRAMES, poses, keyframes, triangles);
    assert_eq!(mcap["mesh_deletions_total"], contents.clears(), "{mcap}");
    assert_eq!(
        mcap["mesh_entities_total"],
        contents
            .mesh
            .values()
            .flatten()
            .filter(|(_, t)| t.is_some())
            .count(),
        "{mcap}"
    );
    assert_eq!(mcap["counts"]["/mesh"], summary["foxglove"]["mesh_updates"]);
    // The service's own recording of the session: the same poses, keyframes and mesh.
    let recorded = foxglove_check(&[
        "mcap",
        fetched.join("recording.mcap").to_str().expect("path"),
    ]);
    check_mcap(&recorded, 0, poses, keyframes, triangles);

    // A local run.
    let out = work.join("run");
    let recorded = work.join("run.rrd");
    let run = relfusion(&[
        "run",
        seq,
        "--out",
        out.to_str().expect("path"),
        "--deterministic",
        "--quiet",
        "--rerun",
        recorded.to_str().expect("path"),
    ]);
    let contents = read_rrd(&recorded);
    check(
        &contents,
        FRAMES,
        tum_lines(&out.join("trajectory.txt")),
        tum_lines(&out.join("keyframes.txt")),
        run[0]["mesh_triangles"].as_u64().expect("mesh triangles") as usize,
    );
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
    let url = url_rx
        .recv_timeout(std::time::Duration::from_secs(120))
        .expect("the Foxglove URL on stderr");
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
