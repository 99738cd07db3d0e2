//! Sessions on ROS 2 (issue 38, item 1), checked by a robot that is not relfusion: a Python
//! process with `eclipse-zenoh` and `pycdr2` (`tests/py/ros2_check.py`) speaking rmw_zenoh's
//! wire format to a `relfusiond` with `[ros2]` on, through a Zenoh router.
//! - A session created with `ros2.publish` puts every output on its topics: each message
//!   decodes as its ROS 2 type, carries rmw_zenoh's attachment (sequence numbers from 1, the
//!   GID of its publisher's token), the poses are the session's own, the last path is the
//!   map's keyframes, and the node and its publishers are in the graph (liveliness tokens)
//!   while the session runs, and gone after.
//! - A session created with `ros2.image_topic` and `camera_info_topic` (and no camera) takes
//!   its camera and frames from a ROS 2 camera and gives the same trajectory as
//!   `relfusion run --deterministic` on the same images.

use std::io::{BufRead as _, BufReader};
use std::process::{Child, ChildStdout, Command, Stdio};

use relfusion_slam::dataset::trajectory::read_tum_trajectory;
use serde_json::{Value, json};

use super::client::*;

/// The namespace of a session of the public tenant.
fn namespace(id: &str) -> String {
    format!("/relfusion/{PUBLIC_TENANT}/{}", id.replace('-', "_"))
}

/// `tests/py/ros2_check.py ARGS` with the test's Python packages, its stdout piped.
fn ros2_check(args: &[&str]) -> Child {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("py/ros2_check.py");
    let mut command = Command::new("python3");
    command
        .arg(script)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped());
    if let Some(deps) = std::env::var_os("RELFUSION_CLIENT_PYDEPS") {
        command.env("PYTHONPATH", deps);
    }
    command.spawn().expect("python3")
}

fn summary(child: Child, what: &str) -> Value {
    let out = child.wait_with_output().expect("ros2_check.py");
    assert!(out.status.success(), "ros2_check.py {what} failed");
    let text = String::from_utf8_lossy(&out.stdout);
    let last = text.lines().last().unwrap_or_default();
    serde_json::from_str(last).unwrap_or_else(|e| panic!("{what}: not JSON ({e}): {text}"))
}

fn wait_ready(stdout: &mut BufReader<ChildStdout>) {
    let mut line = String::new();
    stdout.read_line(&mut line).expect("ros2_check.py output");
    assert_eq!(
        line.trim(),
        "ready",
        "ros2_check.py did not start: {line:?}"
    );
}

/// A router (`relfusiond --zenoh-router`) and a relfusiond with `[ros2]` on, its client.
fn spawn_ros2(work: &Path) -> (Relfusiond, Relfusiond, String) {
    let (router, endpoint) = Relfusiond::spawn_router(&work.join("router"), &[]);
    let server = Relfusiond::spawn_node(
        work,
        "ros2-node",
        &endpoint,
        2,
        "[ros2]\nenabled = true\n",
        &[],
    );
    (router, server, endpoint)
}

fn token_of<'a>(tokens: &'a [Value], kind: &str, topic: &str) -> Option<&'a Value> {
    tokens
        .iter()
        .find(|t| t["kind"] == kind && (topic.is_empty() || t["topic"] == topic))
}

#[test]
fn a_session_on_ros2_publishes_every_output_to_a_ros2_subscriber() {
    let _machine = ENDPOINTS.write().unwrap_or_else(|e| e.into_inner());
    let seq_dir = synth_sequence("ros2-out", FRAMES_N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("ros2-out");
    let (_router, server, endpoint) = spawn_ros2(&work);
    let z = zenoh_client(&endpoint, &server, None);
    node_status(&z, |_| true);
    let config = SessionConfig {
        ros2: Some(v1::Ros2Options {
            publish: true,
            ..Default::default()
        }),
        ..session_config(
            &seq,
            FramePolicy::Wait,
            r#"{"pipeline":{"deterministic":true}}"#,
        )
    };
    let id = create(&z, PUBLIC_TENANT, None, config.encode_to_vec()).expect("session created");
    let ns = namespace(&id);
    let mut robot = ros2_check(&["listen", &endpoint, "0", &ns]);
    let mut stdout = BufReader::new(robot.stdout.take().expect("stdout"));
    wait_ready(&mut stdout);
    robot.stdout = Some(stdout.into_inner());

    // The session's own updates on relfusion's keys, to compare with.
    let updates = subscribe(&z, PUBLIC_TENANT, &id);
    stream_frames(&z, PUBLIC_TENANT, &id, &seq, FRAMES_N);
    let mut poses = Vec::new();
    while let Ok(message) = next_update(&updates, &server) {
        if let Some(server_message::Message::Pose(p)) = message.message
            && p.tracking_state() != v1::TrackingState::Lost
        {
            poses.push((p.timestamp, p.world_from_camera.expect("pose")));
        }
    }
    let snapshot = map(&z, PUBLIC_TENANT, None, &id).expect("map");
    // Let the last messages arrive and the session's tokens go.
    std::thread::sleep(Duration::from_secs(1));
    drop(robot.stdin.take());
    let got = summary(robot, "listen");

    for topic in ["pose", "tf", "path", "points", "mesh"] {
        let t = &got["topics"][topic];
        assert!(t["count"].as_u64().is_some_and(|n| n > 0), "{topic}: {t}");
        assert_eq!(t["errors"], json!([]), "{topic} decodes as its ROS 2 type");
        assert_eq!(
            t["sequences_ok"], true,
            "{topic}: sequence numbers 1, 2, 3, … ({t})"
        );
        assert_eq!(
            t["gids"].as_array().map(Vec::len),
            Some(1),
            "{topic}: one publisher"
        );
    }
    // Every tracked pose, the same as on relfusion's own keys.
    let ros_poses = got["poses"].as_array().expect("poses");
    assert_eq!(
        ros_poses.len(),
        poses.len(),
        "one PoseStamped per tracked frame"
    );
    for (ros, (timestamp, pose)) in ros_poses.iter().zip(&poses) {
        let stamp = ros[0].as_f64().expect("stamp") * 1e-9;
        assert!(
            (stamp - timestamp).abs() < 1e-6,
            "stamp {stamp} vs {timestamp}"
        );
        let t = pose.translation.as_ref().expect("translation");
        let q = pose.rotation.as_ref().expect("rotation");
        let expected = [t.x, t.y, t.z, q.x, q.y, q.z, q.w];
        for (k, e) in expected.iter().enumerate() {
            assert_eq!(ros[k + 1].as_f64(), Some(*e), "pose at {timestamp}: {ros}");
        }
        assert_eq!(ros[8], "world");
    }
    // The last path is the final keyframes.
    let path = got["last_path"].as_array().expect("path");
    assert_eq!(path.len(), snapshot.keyframes.len(), "{path:?}");
    for (p, k) in path.iter().zip(&snapshot.keyframes) {
        let t = k
            .world_from_camera
            .as_ref()
            .and_then(|s| s.translation.as_ref())
            .expect("keyframe pose");
        assert_eq!(p, &json!([t.x, t.y, t.z]), "keyframe at {}", k.timestamp);
    }
    let tf: Vec<&str> = got["tf"]
        .as_array()
        .expect("tf")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    for edge in ["map->world", "world->camera", "world->keyframe_0"] {
        assert!(tf.contains(&edge), "{edge} in {tf:?}");
    }
    let clouds = got["clouds"].as_array().expect("clouds");
    assert!(
        clouds
            .iter()
            .all(|c| c["well_formed"] == true && c["points"].as_u64() > Some(0)),
        "{clouds:?}"
    );
    assert!(
        got["markers"]["add"].as_u64() > Some(0),
        "{}",
        got["markers"]
    );
    assert_eq!(got["markers"]["vertices"].as_u64().map(|v| v % 3), Some(0));

    // The graph: the node and its five publishers while the session ran, as rmw_zenoh writes
    // them; the GIDs of the attachments are those of the publishers' tokens.
    let seen = got["tokens_seen"].as_array().expect("tokens");
    let node = token_of(seen, "NN", "").expect("the node's token");
    assert_eq!(node["namespace"], ns.as_str());
    assert_eq!(node["node"], "relfusion");
    assert_eq!(node["enclave"], "/");
    for topic in ["pose", "tf", "path", "points", "mesh"] {
        let full = format!("{ns}/{topic}");
        let mp = token_of(seen, "MP", &full).unwrap_or_else(|| panic!("no MP token for {full}"));
        assert_eq!(mp["node_id"], node["node_id"], "{mp}");
        assert!(
            mp["hash"]
                .as_str()
                .is_some_and(|h| h.starts_with("RIHS01_") && h.len() == 71)
        );
        assert_eq!(mp["qos"], "::,10:,:,:,,");
        let gid = xxhash_rust::xxh3::xxh3_128(mp["key"].as_str().expect("key").as_bytes());
        let hex: String = gid
            .to_le_bytes()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        assert_eq!(
            got["topics"][topic]["gids"][0],
            hex.as_str(),
            "{topic}: GID of its token"
        );
    }
    let alive = got["tokens_alive"].as_array().expect("alive");
    assert!(
        !alive.iter().any(|t| t["namespace"] == ns.as_str()),
        "a finished session leaves the graph: {alive:?}"
    );
}

#[test]
fn a_ros2_camera_feeds_a_session_that_reads_its_camera_info() {
    let _machine = ENDPOINTS.write().unwrap_or_else(|e| e.into_inner());
    const N: usize = 60;
    let seq_dir = synth_sequence("ros2-in", N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("ros2-in");
    let (_router, server, endpoint) = spawn_ros2(&work);
    let z = zenoh_client(&endpoint, &server, None);
    node_status(&z, |_| true);
    // The camera's frames as raw RGB, for the robot to publish as sensor_msgs/Image.
    let raw = work.join("raw");
    std::fs::create_dir_all(&raw).expect("raw dir");
    let frames: Vec<Value> = seq
        .frames
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let rgb = image::open(&f.rgb).expect("frame").to_rgb8();
            let path = raw.join(format!("{i}.rgb"));
            std::fs::write(&path, rgb.as_raw()).expect("write raw");
            json!({"rgb": path, "timestamp": f.timestamp})
        })
        .collect();
    let c = &seq.camera;
    let spec = work.join("frames.json");
    std::fs::write(
        &spec,
        json!({"width": c.width, "height": c.height, "intrinsics": [c.fx, c.fy, c.cx, c.cy], "frames": frames})
            .to_string(),
    )
    .expect("frames.json");
    let tenant_ns = format!("/relfusion/{PUBLIC_TENANT}");
    let robot = ros2_check(&[
        "camera",
        &endpoint,
        "0",
        &tenant_ns,
        spec.to_str().expect("path"),
    ]);

    // Created without a camera: the server reads the robot's CameraInfo.
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(60)))
        .build()
        .into();
    let body = json!({
        "config": {"pipeline": {"deterministic": true}},
        "policy": "wait",
        "ros2": {"image_topic": "camera/image_raw", "camera_info_topic": "camera/camera_info"},
    });
    let mut created = agent
        .post(format!("{}/v1/sessions", server.url()))
        .content_type("application/json")
        .send(body.to_string())
        .expect("create");
    let text = created.body_mut().read_to_string().expect("body");
    assert_eq!(created.status(), 201, "{text}\n{}", server.log());
    let info: Value = serde_json::from_str(&text).expect("JSON");
    let id = info["id"].as_str().expect("id").to_string();
    let camera = &info["session"]["camera"];
    assert_eq!(
        camera["width"], c.width,
        "the camera of the CameraInfo: {info}"
    );
    assert_eq!(camera["fx"], c.fx, "{info}");

    let sent = summary(robot, "camera");
    assert_eq!(sent["frames_sent"], N, "{sent}");
    let subscriber = &sent["subscriber"];
    assert_eq!(
        subscriber["topic"],
        format!("{tenant_ns}/camera/image_raw"),
        "{sent}"
    );
    assert_eq!(
        subscriber["type"], "sensor_msgs::msg::dds_::Image_",
        "{sent}"
    );
    assert_eq!(subscriber["namespace"], namespace(&id), "{sent}");

    // Every frame queued (policy wait: the subscription pushes back), then the end.
    let info = |what: &str, done: &dyn Fn(&Value) -> bool| {
        let deadline = Instant::now() + PATIENCE;
        loop {
            let mut reply = agent
                .get(format!("{}/v1/sessions/{id}", server.url()))
                .call()
                .expect("info");
            let info: Value =
                serde_json::from_str(&reply.body_mut().read_to_string().expect("body"))
                    .expect("JSON");
            assert_ne!(info["state"], "failed", "{info}\n{}", server.log());
            if done(&info) {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "{what}: {info}\n{}",
                server.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    };
    info("every frame arrives", &|i| i["frames_received"] == N);
    let status = node_status(&z, |s| s["ros2"]["frames_in"] == N);
    assert_eq!(status["ros2"]["messages_refused"], 0, "{status}");
    let finish = agent
        .post(format!("{}/v1/sessions/{id}/finish", server.url()))
        .send_empty()
        .expect("finish");
    assert_eq!(finish.status(), 202);
    info("the session finishes", &|i| i["state"] == "finished");
    let mut trajectory = agent
        .get(format!("{}/v1/sessions/{id}/trajectory", server.url()))
        .call()
        .expect("trajectory");
    let served_path = work.join("served.txt");
    std::fs::write(
        &served_path,
        trajectory.body_mut().read_to_string().expect("body"),
    )
    .expect("write");
    let served = read_tum_trajectory(&served_path).expect("served trajectory");
    assert_eq!(served.len(), N, "a pose for every frame of the camera");

    let run = run_deterministic(&seq_dir, &work);
    let ate_ros = ate_rmse(&seq, &served);
    let ate_run = ate_rmse(&seq, &run);
    assert!(
        (ate_ros - ate_run).abs() <= 1e-9,
        "ATE from the ROS 2 camera {ate_ros} vs relfusion run {ate_run}"
    );
}

#[test]
fn ros2_topics_and_tokens_stay_with_their_tenant() {
    let _machine = ENDPOINTS.read().unwrap_or_else(|e| e.into_inner());
    let seq_dir = synth_sequence("zenoh", FRAMES_N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("ros2-tenants");
    let (server, endpoint) = spawn_server(
        &work,
        &[
            ("RELFUSIOND_TOKENS", "alice:tok-a,bob:tok-b"),
            ("RELFUSIOND_ROS2", "on"),
        ],
    );
    let alice = zenoh_client(&endpoint, &server, Some(("alice", "tok-a")));
    let bob = zenoh_client(&endpoint, &server, Some(("bob", "tok-b")));
    node_status(&alice, |_| true);
    let topics = "*/relfusion/alice/**";
    let sub = |z: &zenoh::Session, key: &str| {
        z.declare_subscriber(key.to_string())
            .with(FifoChannel::new(4096))
            .wait()
            .expect("subscriber")
    };
    let alice_topics = sub(&alice, topics);
    let bob_topics = sub(&bob, topics);
    let bob_everything = sub(&bob, "**");
    let config = SessionConfig {
        ros2: Some(v1::Ros2Options {
            publish: true,
            ..Default::default()
        }),
        ..session_config(
            &seq,
            FramePolicy::Wait,
            r#"{"pipeline":{"deterministic":true}}"#,
        )
    };
    // Bob cannot put a session of his on ROS 2 in alice's namespace either.
    let outside = SessionConfig {
        ros2: Some(v1::Ros2Options {
            image_topic: "/relfusion/alice/camera/image_raw".into(),
            ..Default::default()
        }),
        ..config.clone()
    };
    let e = create(&bob, "bob", Some("tok-b"), outside.encode_to_vec()).expect_err("outside");
    assert_eq!(e.code(), ErrorCode::InvalidArgument, "{e:?}");
    let id = create(&alice, "alice", Some("tok-a"), config.encode_to_vec()).expect("created");
    let ns = ros2_mangled(&format!("/relfusion/alice/{}", id.replace('-', "_")));
    // The graph: alice finds her session's node and publishers, bob finds nothing.
    let tokens = |z: &zenoh::Session, key: &str| -> Vec<String> {
        z.liveliness()
            .get(key)
            .timeout(Duration::from_secs(3))
            .wait()
            .expect("liveliness query")
            .iter()
            .filter_map(|r| r.into_result().ok().map(|s| s.key_expr().to_string()))
            .collect()
    };
    let mine = tokens(&alice, "@ros2_lv/*/*/*/*/*/*/%relfusion%alice%$*/**");
    assert_eq!(
        mine.iter().filter(|k| k.contains(&ns)).count(),
        6,
        "the node and its five publishers: {mine:?}"
    );
    for key in [
        "@ros2_lv/*/*/*/*/*/*/%relfusion%alice%$*/**",
        "@ros2_lv/0/**",
    ] {
        assert!(tokens(&bob, key).is_empty(), "bob sees no token on {key}");
    }
    stream_frames(&alice, "alice", &id, &seq, 10);
    let deadline = Instant::now() + PATIENCE;
    let mut poses = 0;
    while poses < 10 && Instant::now() < deadline {
        if let Ok(Some(sample)) = alice_topics.recv_timeout(Duration::from_secs(1))
            && sample.key_expr().as_str().contains("/pose/")
        {
            poses += 1;
        }
    }
    assert_eq!(poses, 10, "alice gets her poses on ROS 2\n{}", server.log());
    assert!(
        bob_topics.try_recv().ok().flatten().is_none(),
        "bob's subscription of alice's namespace is refused"
    );
    while let Ok(Some(sample)) = bob_everything.try_recv() {
        let key = sample.key_expr().as_str();
        assert!(!key.contains("/relfusion/alice/"), "bob got {key}");
    }
}

/// A ROS 2 name as liveliness tokens write it.
fn ros2_mangled(name: &str) -> String {
    name.replace('/', "%")
}
