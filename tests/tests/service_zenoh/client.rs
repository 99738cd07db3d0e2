//! The test client of the Zenoh tests: a real Zenoh session in client mode (explicit endpoint,
//! multicast and gossip scouting off, optionally logged in with a token's user and password)
//! speaking the key space of `relfusion_proto::zenoh_keys`, and a real `relfusiond` listening
//! on a loopback Zenoh endpoint.

pub use std::path::Path;
pub use std::time::{Duration, Instant};

pub use relfusion_proto::Message as _;
pub use relfusion_proto::v1::{
    self, CreateSessionReply, EndOfStream, ErrorCode, Frame, FramePolicy, ImageEncoding,
    MapSnapshot, ServerMessage, SessionConfig, SessionFinished, server_message,
};
pub use relfusion_proto::zenoh_keys::{
    END, FINISHED, FRAMES, MAP, MESH, POSES, PUBLIC_TENANT, create_key, session_key,
    session_wildcard,
};
pub use relfusion_slam::dataset::TumSequence;
use relfusion_slam::dataset::trajectory::StampedPose;
use relfusion_slam::geometry::SE3;
pub use relfusion_tests::{Relfusiond, bin_path, synth_sequence, temp_dir};
pub use zenoh::Wait as _;
pub use zenoh::handlers::{FifoChannel, FifoChannelHandler};
pub use zenoh::pubsub::Subscriber;
pub use zenoh::qos::CongestionControl;
pub use zenoh::sample::{Locality, Sample};

/// Tests with nodes that dial a Zenoh endpoint (a router) take this exclusively, the others
/// shared. A node waiting for a late router dials a port nothing listens on yet, which
/// `free_port` may hand to a concurrent test's server: the node would then join that server's
/// network and answer its queries. That is the likely cause of two failures seen here, where
/// the stream test's map query got Zenoh's routing `Timeout` instead of its snapshot.
pub static ENDPOINTS: std::sync::RwLock<()> = std::sync::RwLock::new(());

/// Frames of the test sequence (320×240).
pub const FRAMES_N: usize = 100;
pub const SEED: u64 = 29;
/// Longest wait for any single message (a pose, a reply).
pub const PATIENCE: Duration = Duration::from_secs(60);

/// `relfusiond` with Zenoh listening on a free loopback port; returns it and the endpoint.
pub fn spawn_server(work: &Path, envs: &[(&str, &str)]) -> (Relfusiond, String) {
    Relfusiond::spawn_zenoh_peer::<&str>(&work.join("data"), &[], envs)
}

/// The Zenoh configuration of a client of `endpoint` only (no scouting), logged in as
/// `login` (user, password) when given.
pub fn client_config(endpoint: &str, login: Option<(&str, &str)>) -> zenoh::Config {
    let mut config = zenoh::Config::default();
    let endpoints = format!("[\"{endpoint}\"]");
    let mut settings = vec![
        ("mode", "\"client\"".to_string()),
        ("connect/endpoints", endpoints),
        ("scouting/multicast/enabled", "false".into()),
        ("scouting/gossip/enabled", "false".into()),
    ];
    if let Some((user, password)) = login {
        settings.push(("transport/auth/usrpwd/user", format!("\"{user}\"")));
        settings.push(("transport/auth/usrpwd/password", format!("\"{password}\"")));
    }
    for (key, value) in settings {
        config.insert_json5(key, &value).expect("zenoh config");
    }
    config
}

/// A Zenoh session in client mode connected to `endpoint` only, no scouting, logged in as
/// `login`. Retries while the server's Zenoh side is still starting (it comes up right after
/// the HTTP listener).
pub fn zenoh_client(
    endpoint: &str,
    server: &Relfusiond,
    login: Option<(&str, &str)>,
) -> zenoh::Session {
    let config = client_config(endpoint, login);
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
pub fn node_status(
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

/// A query's first reply: `Ok(payload)`, or `Err(error payload)`; panics when nobody answers.
pub fn query(
    z: &zenoh::Session,
    key: &str,
    payload: Option<Vec<u8>>,
    token: Option<&str>,
) -> Result<Vec<u8>, Vec<u8>> {
    // 60 s (was 20): the `Timeout` of `ENDPOINTS` came a third time (2026-12-04), with that
    // lock held, in a cold `make test` on a slowed machine (the slam unit tests at 2.2× their
    // time alone). Whether the reply was only late is not known; a longer wait costs a
    // passing run nothing.
    let mut get = z.get(key).timeout(Duration::from_secs(60));
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

/// Creates a session of `tenant` through its queryable: its id, or the refusal's `Error`.
pub fn create(
    z: &zenoh::Session,
    tenant: &str,
    token: Option<&str>,
    payload: Vec<u8>,
) -> Result<String, v1::Error> {
    match query(z, &create_key(tenant), Some(payload), token) {
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

pub fn map(
    z: &zenoh::Session,
    tenant: &str,
    token: Option<&str>,
    id: &str,
) -> Result<MapSnapshot, v1::Error> {
    match query(z, &session_key(tenant, id, MAP), None, token) {
        Ok(bytes) => Ok(MapSnapshot::decode(bytes.as_slice()).expect("MapSnapshot")),
        Err(bytes) => Err(v1::Error::decode(bytes.as_slice()).unwrap_or_else(|e| {
            panic!("not an Error ({e}): {:?}", String::from_utf8_lossy(&bytes))
        })),
    }
}

pub fn session_config(seq: &TumSequence, policy: FramePolicy, config_json: &str) -> SessionConfig {
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
        ..Default::default()
    }
}

/// Every message of one session from the server (poses, mesh, finished), in order.
pub fn subscribe(
    z: &zenoh::Session,
    tenant: &str,
    id: &str,
) -> Subscriber<FifoChannelHandler<Sample>> {
    z.declare_subscriber(session_wildcard(tenant, id))
        .allowed_origin(Locality::Remote)
        // Room for every update of the test: the client never makes the server wait.
        .with(FifoChannel::new(8192))
        .wait()
        .expect("subscribe to the session")
}

/// The next update: `Ok(message on poses, or a MeshUpdate on mesh wrapped as a
/// ServerMessage)` or `Err(SessionFinished)`.
pub fn next_update(
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

pub fn frame_bytes(seq: &TumSequence, i: usize) -> Frame {
    Frame {
        frame_id: i as u64,
        timestamp: seq.frames[i].timestamp,
        image: std::fs::read(&seq.frames[i].rgb).expect("read frame"),
        encoding: ImageEncoding::Png as i32,
        camera: None,
    }
}

/// `relfusion run --deterministic` on `seq_dir` (output in `work/local`): its trajectory, what
/// a session of the same frames must give.
pub fn run_deterministic(seq_dir: &Path, work: &Path) -> Vec<StampedPose> {
    let local = work.join("local");
    let out = std::process::Command::new(bin_path("relfusion"))
        .arg("run")
        .arg(seq_dir)
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
    relfusion_slam::dataset::trajectory::read_tum_trajectory(&local.join("trajectory.txt"))
        .expect("run trajectory")
}

/// The Sim(3)-aligned ATE (RMSE) of `poses` against `seq`'s ground truth.
pub fn ate_rmse(seq: &TumSequence, poses: &[StampedPose]) -> f64 {
    let gt = seq.groundtruth_poses();
    relfusion_slam::eval::ate(&gt, poses, relfusion_slam::eval::AlignMode::Sim3)
        .expect("ATE")
        .rmse
}

/// Publishes frames `0..n` of `seq` to session `id` (congestion control `block`), then its end.
pub fn stream_frames(z: &zenoh::Session, tenant: &str, id: &str, seq: &TumSequence, n: usize) {
    let frames = z
        .declare_publisher(session_key(tenant, id, FRAMES))
        .congestion_control(CongestionControl::Block)
        .wait()
        .expect("frames publisher");
    for i in 0..n {
        frames
            .put(frame_bytes(seq, i).encode_to_vec())
            .wait()
            .expect("publish frame");
    }
    put(
        z,
        session_key(tenant, id, END),
        EndOfStream {}.encode_to_vec(),
    );
}

pub fn put(z: &zenoh::Session, key: String, payload: Vec<u8>) {
    z.put(key, payload)
        .congestion_control(CongestionControl::Block)
        .wait()
        .expect("publish");
}

pub fn to_slam(poses: &[v1::StampedPose]) -> Vec<StampedPose> {
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
