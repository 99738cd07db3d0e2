//! The service over Zenoh, end to end: a real `relfusiond` listening on a loopback Zenoh
//! endpoint, and a real Zenoh session in client mode (explicit endpoint, multicast and gossip
//! scouting off) speaking the key space of `relfusion_proto::zenoh_keys`.
//!
//! - A session created through the create queryable (deterministic config, `wait` policy)
//!   gives a pose for every frame published, mesh deltas on `mesh` that add up to the map's
//!   mesh, announces its end on `finished`, and its map (the map queryable) holds a trajectory
//!   whose ATE equals `relfusion run --deterministic` on the same data.
//! - With tokens configured: a create without a token or with an unknown one is refused
//!   (UNAUTHENTICATED), another token's map query is NOT_FOUND, malformed messages and corrupt
//!   frames are answered with an `Error` on `poses`, counted, and the session goes on.

use std::collections::BTreeSet;
use std::net::TcpListener;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use relfusion_proto::Message as _;
use relfusion_proto::v1::{
    self, CreateSessionReply, EndOfStream, ErrorCode, Frame, FramePolicy, ImageEncoding,
    MapSnapshot, ServerMessage, SessionConfig, SessionFinished, server_message,
};
use relfusion_proto::zenoh_keys::{
    CREATE, END, FINISHED, FRAMES, MAP, MESH, POSES, session_key, session_wildcard,
};
use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::trajectory::{StampedPose, read_tum_trajectory};
use relfusion_slam::eval::{AlignMode, ate};
use relfusion_slam::geometry::SE3;
use relfusion_tests::{Relfusiond, bin_path, synth_sequence, temp_dir};
use zenoh::Wait as _;
use zenoh::handlers::{FifoChannel, FifoChannelHandler};
use zenoh::pubsub::Subscriber;
use zenoh::qos::CongestionControl;
use zenoh::sample::{Locality, Sample};

/// Frames of the test sequence (320×240).
const FRAMES_N: usize = 100;
const SEED: u64 = 29;
/// Longest wait for any single message (a pose, a reply).
const PATIENCE: Duration = Duration::from_secs(60);

/// A port nobody listens on now (the OS's pick for a listener that is dropped at once).
fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("bind a free port")
        .port()
}

/// `relfusiond` with Zenoh listening on a free loopback port; returns it and the endpoint.
fn spawn_server(work: &Path, envs: &[(&str, &str)]) -> (Relfusiond, String) {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let server = Relfusiond::spawn(&work.join("data"), ["--zenoh-listen", &endpoint], envs);
    (server, endpoint)
}

/// A Zenoh session in client mode connected to `endpoint` only, no scouting. Retries while
/// the server's Zenoh side is still starting (it comes up right after the HTTP listener).
fn zenoh_client(endpoint: &str, server: &Relfusiond) -> zenoh::Session {
    let mut config = zenoh::Config::default();
    let endpoints = format!("[\"{endpoint}\"]");
    for (key, value) in [
        ("mode", "\"client\""),
        ("connect/endpoints", endpoints.as_str()),
        ("scouting/multicast/enabled", "false"),
        ("scouting/gossip/enabled", "false"),
    ] {
        config.insert_json5(key, value).expect("zenoh config");
    }
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        match zenoh::open(config.clone()).wait() {
            Ok(session) => return session,
            Err(e) if Instant::now() < deadline => {
                eprintln!("zenoh connect to {endpoint} failed ({e}); retrying");
                std::thread::sleep(Duration::from_millis(200));
            }
            Err(e) => panic!("cannot connect to {endpoint}: {e}\n{}", server.log()),
        }
    }
}

/// Waits for the node's status (published every 2 s once the queryables are declared) and
/// returns it.
fn node_status(
    z: &zenoh::Session,
    until: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let sub = z
        .declare_subscriber("relfusion/nodes/*/status")
        .with(FifoChannel::new(16))
        .wait()
        .expect("subscribe to node status");
    let deadline = Instant::now() + Duration::from_secs(20);
    while Instant::now() < deadline {
        if let Ok(Some(sample)) = sub.recv_timeout(Duration::from_secs(1)) {
            let status: serde_json::Value =
                serde_json::from_slice(&sample.payload().to_bytes()).expect("status is JSON");
            if until(&status) {
                return status;
            }
        }
    }
    panic!("no matching node status within 20 s");
}

fn query(
    z: &zenoh::Session,
    key: &str,
    payload: Option<Vec<u8>>,
    token: Option<&str>,
) -> Result<Vec<u8>, Vec<u8>> {
    let mut get = z.get(key).timeout(Duration::from_secs(20));
    if let Some(payload) = payload {
        get = get.payload(payload);
    }
    if let Some(token) = token {
        get = get.attachment(token.to_string());
    }
    let replies = get.wait().expect("send query");
    let reply = replies
        .recv()
        .unwrap_or_else(|_| panic!("no reply to {key}"));
    match reply.into_result() {
        Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
        Err(error) => Err(error.payload().to_bytes().into_owned()),
    }
}

/// Creates a session through the queryable: its id, or the refusal's `Error`.
fn create(z: &zenoh::Session, token: Option<&str>, payload: Vec<u8>) -> Result<String, v1::Error> {
    match query(z, CREATE, Some(payload), token) {
        Ok(bytes) => {
            let reply = CreateSessionReply::decode(bytes.as_slice()).expect("CreateSessionReply");
            assert!(
                reply.error.is_none(),
                "a normal reply carries no error: {reply:?}"
            );
            assert!(reply.session_id.starts_with("s-"), "{reply:?}");
            Ok(reply.session_id)
        }
        Err(bytes) => {
            let reply = CreateSessionReply::decode(bytes.as_slice()).expect("CreateSessionReply");
            assert!(reply.session_id.is_empty(), "{reply:?}");
            Err(reply.error.expect("an error reply carries the error"))
        }
    }
}

fn map(z: &zenoh::Session, token: Option<&str>, id: &str) -> Result<MapSnapshot, v1::Error> {
    match query(z, &session_key(id, MAP), None, token) {
        Ok(bytes) => Ok(MapSnapshot::decode(bytes.as_slice()).expect("MapSnapshot")),
        Err(bytes) => Err(v1::Error::decode(bytes.as_slice()).expect("an Error")),
    }
}

fn session_config(seq: &TumSequence, policy: FramePolicy, config_json: &str) -> SessionConfig {
    let c = &seq.camera;
    SessionConfig {
        camera: Some(v1::Camera {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            width: c.width,
            height: c.height,
            distortion: None,
        }),
        config_json: config_json.into(),
        model_name: String::new(),
        policy: policy as i32,
    }
}

/// Every message of one session from the server (poses, mesh, finished), in order.
fn subscribe(z: &zenoh::Session, id: &str) -> Subscriber<FifoChannelHandler<Sample>> {
    z.declare_subscriber(session_wildcard(id))
        .allowed_origin(Locality::Remote)
        // Room for every update of the test: the client never makes the server wait.
        .with(FifoChannel::new(8192))
        .wait()
        .expect("subscribe to the session")
}

/// The next update: `Ok(message on poses, or a MeshUpdate on mesh wrapped as a
/// ServerMessage)` or `Err(SessionFinished)`.
fn next_update(
    sub: &Subscriber<FifoChannelHandler<Sample>>,
    server: &Relfusiond,
) -> Result<ServerMessage, SessionFinished> {
    loop {
        let sample = sub
            .recv_timeout(PATIENCE)
            .expect("subscriber open")
            .unwrap_or_else(|| panic!("no update within {PATIENCE:?}\n{}", server.log()));
        let bytes = sample.payload().to_bytes();
        match sample.key_expr().as_str().rsplit('/').next() {
            Some(POSES) => return Ok(ServerMessage::decode(bytes.as_ref()).expect("ServerMessage")),
            Some(MESH) => {
                let update = v1::MeshUpdate::decode(bytes.as_ref()).expect("MeshUpdate");
                return Ok(ServerMessage {
                    message: Some(server_message::Message::Mesh(update)),
                });
            }
            Some(FINISHED) => {
                return Err(SessionFinished::decode(bytes.as_ref()).expect("SessionFinished"));
            }
            _ => {}
        }
    }
}

fn frame_bytes(seq: &TumSequence, i: usize) -> Frame {
    Frame {
        frame_id: i as u64,
        timestamp: seq.frames[i].timestamp,
        image: std::fs::read(&seq.frames[i].rgb).expect("read frame"),
        encoding: ImageEncoding::Png as i32,
        camera: None,
    }
}

fn put(z: &zenoh::Session, key: String, payload: Vec<u8>) {
    z.put(key, payload)
        .congestion_control(CongestionControl::Block)
        .wait()
        .expect("publish");
}

fn to_slam(poses: &[v1::StampedPose]) -> Vec<StampedPose> {
    poses
        .iter()
        .map(|p| {
            let pose = p.world_from_camera.expect("pose");
            let t = pose.translation.expect("translation");
            let q = pose.rotation.expect("rotation");
            StampedPose {
                timestamp: p.timestamp,
                world_from_camera: SE3::from_quaternion_translation(
                    nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                        q.w, q.x, q.y, q.z,
                    )),
                    nalgebra::Vector3::new(t.x, t.y, t.z),
                ),
            }
        })
        .collect()
}

#[test]
fn stream_over_zenoh_gives_every_pose_and_the_same_trajectory_as_run() {
    let seq_dir = synth_sequence("zenoh", FRAMES_N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("zenoh-stream");
    let (server, endpoint) = spawn_server(&work, &[]);
    let z = zenoh_client(&endpoint, &server);
    let status = node_status(&z, |_| true);
    assert_eq!(status["accepting"], true, "{status}");
    assert!(
        status["max_sessions"].as_u64().is_some_and(|m| m >= 1),
        "{status}"
    );

    let config = session_config(
        &seq,
        FramePolicy::Wait,
        r#"{"pipeline":{"deterministic":true}}"#,
    );
    let id = create(&z, None, config.encode_to_vec()).expect("session created");
    let updates = subscribe(&z, &id);
    let frames = z
        .declare_publisher(session_key(&id, FRAMES))
        .congestion_control(CongestionControl::Block)
        .wait()
        .expect("frames publisher");
    for i in 0..FRAMES_N {
        frames
            .put(frame_bytes(&seq, i).encode_to_vec())
            .wait()
            .expect("publish frame");
    }
    put(&z, session_key(&id, END), EndOfStream {}.encode_to_vec());

    let mut posed = BTreeSet::new();
    let mut keyframes = 0;
    // The mesh as a subscriber patches it: block index → block, and the last revision.
    let mut mesh = std::collections::BTreeMap::new();
    let mut revision = 0;
    let finished = loop {
        match next_update(&updates, &server) {
            Ok(message) => match message.message {
                Some(server_message::Message::Pose(p)) => {
                    assert_eq!(p.session_id, id);
                    assert!(posed.insert(p.frame_id), "frame {} posed twice", p.frame_id);
                    assert_eq!(p.timestamp, seq.frames[p.frame_id as usize].timestamp);
                    let pose = p.world_from_camera.expect("pose");
                    assert!(pose.scale > 0.0 && pose.scale.is_finite(), "{pose:?}");
                }
                Some(server_message::Message::Keyframe(k)) => {
                    assert_eq!(k.session_id, id);
                    keyframes += 1;
                }
                Some(server_message::Message::Mesh(m)) => {
                    assert_eq!(m.session_id, id);
                    assert_eq!(m.revision, revision + 1, "mesh revisions have no gap");
                    revision = m.revision;
                    assert!(m.block_size > 0.0);
                    for b in &m.removed_blocks {
                        mesh.remove(&(b.x, b.y, b.z));
                    }
                    for b in m.changed_blocks {
                        let i = b.index.expect("block index");
                        assert_eq!(b.vertices.len(), 12 * (b.colors.len() / 3));
                        assert_eq!(b.normals.len(), b.vertices.len());
                        assert!(!b.indices.is_empty() && b.indices.len() % 3 == 0);
                        mesh.insert((i.x, i.y, i.z), b);
                    }
                }
                Some(server_message::Message::Error(e)) => {
                    panic!("unexpected error: {e:?}\n{}", server.log())
                }
                _ => {}
            },
            Err(finished) => break finished,
        }
    };
    assert_eq!(
        posed,
        (0..FRAMES_N as u64).collect(),
        "a pose for every frame (wait policy drops nothing)"
    );
    assert!(keyframes >= 1, "at least the first keyframe was announced");
    assert_eq!(finished.session_id, id);
    assert_eq!(finished.state, "finished", "{finished:?}");
    assert_eq!(finished.frames_received, FRAMES_N as u64);
    assert_eq!(finished.frames_processed, FRAMES_N as u64);
    assert_eq!(finished.frames_dropped, 0);

    let snapshot = map(&z, None, &id).expect("map of a finished session");
    assert_eq!(snapshot.session_id, id);
    assert_eq!(snapshot.state, "finished");
    assert_eq!(snapshot.frames_processed, FRAMES_N as u64);
    assert_eq!(snapshot.frames_received, FRAMES_N as u64);
    assert!(!snapshot.keyframes.is_empty(), "the map has keyframes");
    assert!(
        keyframes >= 2 * snapshot.keyframes.len(),
        "every keyframe is announced when made and again with its optimised pose \
         ({keyframes} updates, {} keyframes)",
        snapshot.keyframes.len()
    );
    assert!(revision >= 1, "the fused mesh was published on `mesh`");
    assert_eq!(snapshot.mesh_revision, revision);
    let served_mesh: std::collections::BTreeMap<_, _> = snapshot
        .mesh_blocks
        .iter()
        .map(|b| {
            let i = b.index.expect("block index");
            ((i.x, i.y, i.z), b.clone())
        })
        .collect();
    assert!(!served_mesh.is_empty(), "the map has the fused mesh");
    assert!(
        served_mesh == mesh,
        "applying every MeshUpdate gives the map's mesh ({} vs {} blocks)",
        mesh.len(),
        served_mesh.len()
    );
    let served = to_slam(&snapshot.trajectory);
    assert_eq!(served.len(), FRAMES_N, "every frame is in the trajectory");

    let local = work.join("local");
    let out = Command::new(bin_path("relfusion"))
        .arg("run")
        .arg(&seq_dir)
        .arg("--out")
        .arg(&local)
        .args(["--deterministic", "--quiet"])
        .output()
        .expect("run relfusion run");
    assert!(
        out.status.success(),
        "relfusion run failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let run = read_tum_trajectory(&local.join("trajectory.txt")).expect("run trajectory");
    assert_eq!(served.len(), run.len(), "same number of poses");
    let gt: Vec<StampedPose> = seq
        .groundtruth()
        .into_iter()
        .map(|(timestamp, world_from_camera)| StampedPose {
            timestamp,
            world_from_camera,
        })
        .collect();
    let ate_served = ate(&gt, &served, AlignMode::Sim3).expect("ATE served").rmse;
    let ate_run = ate(&gt, &run, AlignMode::Sim3).expect("ATE run").rmse;
    assert!(
        (ate_served - ate_run).abs() <= 1e-9,
        "ATE over Zenoh {ate_served} vs relfusion run {ate_run}"
    );
    for (a, b) in served.iter().zip(&run) {
        assert_eq!(a.timestamp, b.timestamp);
        let d = (a.world_from_camera.translation - b.world_from_camera.translation).norm();
        assert!(d <= 1e-9, "pose at {} differs by {d}", a.timestamp);
    }
}

#[test]
fn tokens_scope_sessions_and_bad_messages_get_errors() {
    let seq_dir = synth_sequence("zenoh", FRAMES_N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("zenoh-auth");
    let (server, endpoint) = spawn_server(&work, &[("RELFUSIOND_TOKENS", "alice:tok-a,bob:tok-b")]);
    let z = zenoh_client(&endpoint, &server);
    node_status(&z, |_| true);
    let config = session_config(&seq, FramePolicy::Wait, "").encode_to_vec();

    for token in [None, Some("tok-c"), Some("")] {
        let e = create(&z, token, config.clone()).expect_err("refused without a known token");
        assert_eq!(e.code(), ErrorCode::Unauthenticated, "{token:?}: {e:?}");
    }
    let id = create(&z, Some("tok-a"), config.clone()).expect("alice creates");
    let e = map(&z, Some("tok-b"), &id).expect_err("bob cannot see alice's session");
    assert_eq!(e.code(), ErrorCode::NotFound, "{e:?}");
    let e = map(&z, None, &id).expect_err("no token");
    assert_eq!(e.code(), ErrorCode::Unauthenticated, "{e:?}");
    let e = map(&z, Some("Bearer tok-a"), "s-000000000000").expect_err("unknown session");
    assert_eq!(e.code(), ErrorCode::NotFound, "{e:?}");
    let snapshot = map(&z, Some("Bearer tok-a"), &id).expect("alice sees her session");
    assert_eq!(snapshot.state, "running");
    assert!(snapshot.trajectory.is_empty(), "no frame yet");

    let mut bad_camera = session_config(&seq, FramePolicy::Wait, "");
    if let Some(c) = bad_camera.camera.as_mut() {
        c.fx = 0.0;
    }
    let e = create(&z, Some("tok-a"), bad_camera.encode_to_vec()).expect_err("fx = 0");
    assert_eq!(e.code(), ErrorCode::InvalidArgument, "{e:?}");
    let e = create(&z, Some("tok-a"), vec![0xff; 16]).expect_err("not a SessionConfig");
    assert_eq!(e.code(), ErrorCode::InvalidArgument, "{e:?}");
    assert!(e.message.contains("SessionConfig"), "{e:?}");

    let updates = subscribe(&z, &id);
    let frames_key = session_key(&id, FRAMES);
    // Not a protobuf Frame (an endless varint).
    put(&z, frames_key.clone(), vec![0xff; 16]);
    // A Frame whose PNG is cut short.
    let mut truncated = frame_bytes(&seq, 0);
    truncated.image.truncate(truncated.image.len() / 3);
    put(&z, frames_key.clone(), truncated.encode_to_vec());
    // Then good frames: the session goes on.
    for i in 0..3 {
        put(&z, frames_key.clone(), frame_bytes(&seq, i).encode_to_vec());
    }
    put(&z, session_key(&id, END), EndOfStream {}.encode_to_vec());
    let mut errors = Vec::new();
    let mut posed = Vec::new();
    let finished = loop {
        match next_update(&updates, &server) {
            Ok(message) => match message.message {
                Some(server_message::Message::Error(e)) => errors.push(e),
                Some(server_message::Message::Pose(p)) => posed.push(p.frame_id),
                _ => {}
            },
            Err(finished) => break finished,
        }
    };
    assert_eq!(errors.len(), 2, "{errors:?}");
    assert!(
        errors
            .iter()
            .all(|e| e.code() == ErrorCode::InvalidArgument),
        "{errors:?}"
    );
    assert!(errors[0].message.contains("malformed"), "{errors:?}");
    assert!(errors[1].message.starts_with("frame 0:"), "{errors:?}");
    assert_eq!(posed, vec![0, 1, 2], "the good frames were processed");
    assert_eq!(finished.state, "finished", "{finished:?}");
    assert_eq!(finished.frames_received, 3);

    let status = node_status(&z, |s| s["zenoh"]["malformed_messages"].as_u64() >= Some(2));
    assert_eq!(status["zenoh"]["frames_refused"], 1, "{status}");
    assert_eq!(status["zenoh"]["sessions_created"], 1, "{status}");
    assert!(
        status["zenoh"]["queries_refused"].as_u64() >= Some(8),
        "{status}"
    );
}
