//! Three relfusiond nodes and one Zenoh router on loopback, sharing a real S3-compatible store
//! (s3s-fs), as one service:
//! - a session created through node A (full) is placed on the node with free slots, streamed
//!   over a WebSocket through another node while its server-sent events are followed through
//!   A, and fetched through A with the same trajectory as a single-node run of the same
//!   deterministic config;
//! - another tenant cannot reach it through any node; any node lists a caller's sessions of
//!   all nodes; its map is saved through a node that does not run it;
//! - an upload sent to A (full) is placed on another node; when that node is killed with
//!   SIGKILL mid-processing, the upload completes on a node left with every frame and the
//!   same trajectory as a single-node run, a live session on the killed node ends with an
//!   error for its client streaming through another node, and the killed node's finished
//!   session is served again.

use super::client::*;
use relfusion_tests::s3::S3Server;

const ALICE: &str = "alice-cluster-token";
const BOB: &str = "bob-cluster-token";
const TOKENS: &str = "alice:alice-cluster-token,bob:bob-cluster-token";
/// Nodes log in to the router as this user (the router's protection: deploy/zenoh).
const NODE_ENV: [(&str, &str); 3] = [
    ("RELFUSIOND_TOKENS", TOKENS),
    ("RELFUSIOND_ZENOH_USER", "relfusiond"),
    ("RELFUSIOND_ZENOH_PASSWORD", "cluster-node-secret"),
];

fn deterministic(seq: &TumSequence) -> Value {
    json!({
        "camera": camera_json(seq),
        "policy": "wait",
        "config": { "pipeline": { "deterministic": true } },
    })
}

/// Creates a deterministic live session through `server`; returns its info.
fn create(server: &Relfusiond, seq: &TumSequence, token: &str) -> Value {
    let created = post_json(server, "/v1/sessions", Some(token), &deterministic(seq));
    assert_eq!(created.status, 201, "{}\n{}", created.body, server.log());
    created.json()["session"].clone()
}

/// Streams every frame of `seq` over a WebSocket to `server`, then the end; returns the frame
/// ids of the poses that came back before the server closed the socket.
fn stream(server: &Relfusiond, id: &str, seq: &TumSequence, token: &str) -> Vec<u64> {
    let mut socket = ws_connect(server, id, Some(token)).expect("websocket");
    for i in 0..seq.len() {
        ws_send(&mut socket, ws_frame(seq, i, frame_bytes(seq, i)));
    }
    ws_send(
        &mut socket,
        client_message::Message::EndOfStream(EndOfStream {}),
    );
    let mut poses = Vec::new();
    while let Some(message) = ws_next(&mut socket) {
        match message {
            server_message::Message::Pose(pose) => poses.push(pose.frame_id),
            server_message::Message::Error(e) => panic!("error through {}: {e:?}", server.addr()),
            _ => {}
        }
    }
    poses
}

fn text(server: &Relfusiond, path: &str, token: &str) -> String {
    let reply = get(server, path, Some(token));
    assert_eq!(reply.status, 200, "{path}: {}", reply.body);
    reply.body
}

/// A binary download.
fn bytes(server: &Relfusiond, path: &str, token: &str) -> Vec<u8> {
    let mut response = agent()
        .get(format!("{}{path}", server.url()))
        .header("Authorization", format!("Bearer {token}"))
        .call()
        .expect("download");
    assert_eq!(response.status().as_u16(), 200, "{path}");
    response
        .body_mut()
        .with_config()
        .limit(1 << 30)
        .read_to_vec()
        .expect("body")
}

/// Waits until `server` sees `n` members with their published capacity.
fn wait_members(server: &Relfusiond, n: usize) -> Value {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let view = get(server, "/v1/cluster", Some(ALICE)).json();
        let nodes = view["nodes"].as_array().cloned().unwrap_or_default();
        if view["joined"] == true
            && nodes.len() == n
            && nodes.iter().all(|n| n["max_sessions"].as_u64() > Some(0))
        {
            return view;
        }
        assert!(
            Instant::now() < deadline,
            "{n} members not seen: {view}\n{}",
            server.log()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn three_nodes_are_one_service_and_an_upload_survives_its_node() {
    const LIVE_FRAMES: usize = 30;
    const UPLOAD_FRAMES: usize = 80;
    let work = temp_dir("cluster");
    let live =
        TumSequence::open(&synth_sequence("cluster-live", LIVE_FRAMES, 21), None).expect("synth");
    let upload_dir = synth_sequence("cluster-upload", UPLOAD_FRAMES, 22);
    let s3 = S3Server::start("cluster");
    let (_router, endpoint) = Relfusiond::spawn_router(&work.join("router"), &NODE_ENV);
    let extra = format!("idle_timeout_s = 600\n{}", s3.storage_toml());
    let node = |name: &str, max_sessions: usize| {
        Relfusiond::spawn_node(&work, name, &endpoint, max_sessions, &extra, &NODE_ENV)
    };

    // A, alone first: its one slot goes to a session that stays open, so A is full.
    let a = node("a", 1);
    wait_members(&a, 1);
    let busy = create(&a, &live, ALICE);
    assert_eq!(busy["node"], "a", "{busy}");
    let b = node("b", 2);
    let c = node("c", 1);
    wait_members(&a, 3);

    // Created through A: placed on B (A is full, B has the most free slots).
    let session = create(&a, &live, ALICE);
    let id = session["id"].as_str().expect("id").to_string();
    assert_eq!(session["node"], "b", "{session}");
    // Its events followed through A (relayed server-sent events).
    let events = follow_events_as(&a, &id, Some(ALICE));
    // Streamed through C (frames forwarded, updates relayed), a pose for every frame.
    let poses = stream(&c, &id, &live, ALICE);
    assert_eq!(
        poses,
        (0..LIVE_FRAMES as u64).collect::<Vec<_>>(),
        "every pose relayed through C, in order\n{}",
        c.log()
    );
    let events = events.join().expect("SSE through A");
    assert_eq!(
        events.last().map(|(name, _)| name.as_str()),
        Some("finished"),
        "{events:?}"
    );
    let sse_poses = events.iter().filter(|(name, _)| name == "pose").count();
    assert_eq!(sse_poses, LIVE_FRAMES, "every pose's event through A");
    // Fetched through A.
    let info = wait_finished(&a, &id, Some(ALICE));
    assert_eq!(info["node"], "b");
    assert_eq!(info["frames_processed"], LIVE_FRAMES as u64, "{info}");
    let trajectory = text(&a, &format!("/v1/sessions/{id}/trajectory"), ALICE);
    let mesh = bytes(&a, &format!("/v1/sessions/{id}/mesh.ply"), ALICE);
    assert!(mesh.len() > 1000, "a mesh through A");
    assert_eq!(
        mesh,
        bytes(&b, &format!("/v1/sessions/{id}/mesh.ply"), ALICE),
        "as B serves it"
    );
    // Another tenant reaches it through no node; an unknown id is 404 everywhere.
    for server in [&a, &b, &c] {
        let other = get(server, &format!("/v1/sessions/{id}"), Some(BOB));
        other.expect_error(404, "not_found", "another tenant's session");
        let unknown = get(
            server,
            "/v1/sessions/s-000000000000000000000000",
            Some(ALICE),
        );
        unknown.expect_error(404, "not_found", "an unknown session");
    }
    assert!(s3.objects(&format!("sessions/{id}")) > 0, "results in S3");
    // Any node lists the caller's sessions of every node.
    let listed = get(&c, "/v1/sessions", Some(ALICE)).json();
    let ids: Vec<&str> = listed["sessions"]
        .as_array()
        .expect("sessions")
        .iter()
        .filter_map(|s| s["id"].as_str())
        .collect();
    assert!(
        ids.contains(&id.as_str()) && ids.contains(&busy["id"].as_str().expect("id")),
        "{listed}"
    );

    // Its map saved through A (B reads the session's results), listed through C.
    let saved = post_json(&a, "/v1/maps", Some(ALICE), &json!({ "session": id }));
    assert_eq!(saved.status, 201, "{}", saved.body);
    let map_id = saved.json()["id"].as_str().expect("map id").to_string();
    let maps = get(&c, "/v1/maps", Some(ALICE)).json();
    assert!(maps.to_string().contains(&map_id), "{maps}");

    // The same stream on a single node, no cluster, gives the same trajectory.
    let single = Relfusiond::spawn(&work.join("single"), Vec::<String>::new(), &[]);
    let solo = post_json(&single, "/v1/sessions", None, &deterministic(&live)).json();
    let solo_id = solo["id"].as_str().expect("id").to_string();
    let solo_poses = stream(&single, &solo_id, &live, "none");
    assert_eq!(solo_poses.len(), LIVE_FRAMES);
    wait_finished(&single, &solo_id, None);
    let solo_trajectory = get(&single, &format!("/v1/sessions/{solo_id}/trajectory"), None).body;
    assert_eq!(
        trajectory, solo_trajectory,
        "cluster and single-node runs differ"
    );

    // An upload through A (still full) is placed on B; B is killed mid-processing; another
    // node finishes it from the store.
    // A live session of Alice's on B (created there: the forwarded mark skips placement; one
    // slot each for Alice and Bob there), streamed through C: B's death must reach C's client as an error and a close.
    let doomed = reply(
        agent()
            .post(format!("{}/v1/sessions", b.url()))
            .header("Authorization", format!("Bearer {ALICE}"))
            .header("x-relfusion-forwarded-by", "test")
            .content_type("application/json")
            .send(deterministic(&live).to_string()),
    );
    assert_eq!(doomed.status, 201, "{}", doomed.body);
    let doomed = doomed.json()["id"].as_str().expect("id").to_string();
    let mut doomed_socket = ws_connect(&c, &doomed, Some(ALICE)).expect("websocket through C");
    for i in 0..3 {
        ws_send(
            &mut doomed_socket,
            ws_frame(&live, i, frame_bytes(&live, i)),
        );
    }
    let archive = dataset_tar(&upload_dir);
    let created = send(
        &a,
        "POST",
        "/v1/uploads?format=tar",
        Some(BOB),
        "application/x-tar",
        &archive,
    );
    assert_eq!(created.status, 201, "{}", created.body);
    let created = created.json();
    assert_eq!(created["session"]["node"], "b", "placed on B: {created}");
    let upload = created["id"].as_str().expect("id").to_string();
    let path = format!("/v1/sessions/{upload}");
    // A's slot freed, for the take-over.
    let deleted = send(
        &a,
        "DELETE",
        &format!("/v1/sessions/{}", busy["id"].as_str().expect("id")),
        Some(ALICE),
        "",
        b"",
    );
    assert_eq!(deleted.status, 204, "{}", deleted.body);
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let info = get(&a, &path, Some(BOB)).json();
        assert_eq!(info["node"], "b", "B runs it: {info}");
        let done = info["progress"]["processed"].as_u64().unwrap_or(0);
        assert!(
            info["state"] != "finished",
            "the upload finished before the kill: {info}"
        );
        if done >= 5 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the upload did not start: {info}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    b.kill9();
    let mut told = None;
    while let Some(message) = ws_next(&mut doomed_socket) {
        if let server_message::Message::Error(e) = message {
            told = Some(e.message);
        }
    }
    let told = told.expect("an error before the close");
    assert!(told.contains("node b") && told.contains("left"), "{told}");
    let deadline = Instant::now() + Duration::from_secs(120);
    let info = loop {
        let reply = get(&a, &path, Some(BOB));
        if reply.status == 200 {
            let info = reply.json();
            match info["state"].as_str() {
                Some("finished") => break info,
                Some("failed") => panic!("the upload failed: {info}\n{}\n{}", a.log(), c.log()),
                _ => {}
            }
        }
        assert!(
            Instant::now() < deadline,
            "the upload was not finished by another node: {} {}\n{}\n{}",
            reply.status,
            reply.body,
            a.log(),
            c.log()
        );
        std::thread::sleep(Duration::from_millis(250));
    };
    assert!(info["node"] == "a" || info["node"] == "c", "{info}");
    let ended = get(&a, &format!("/v1/sessions/{doomed}"), Some(ALICE)).json();
    assert_eq!(ended["state"], "failed", "{ended}");
    assert!(
        ended["error"]
            .as_str()
            .is_some_and(|e| e.contains("node b")),
        "{ended}"
    );
    assert_eq!(
        info["progress"]["processed"], UPLOAD_FRAMES as u64,
        "nothing lost: {info}"
    );
    // B's finished session outlives B: served from the bucket by the node that took it.
    assert_eq!(
        text(&a, &format!("/v1/sessions/{id}/trajectory"), ALICE),
        trajectory,
        "B's finished session after B"
    );
    let taken_over = text(&c, &format!("/v1/sessions/{upload}/trajectory"), BOB);
    assert_eq!(tum_lines(&taken_over).len(), UPLOAD_FRAMES);
    let solo = send(
        &single,
        "POST",
        "/v1/uploads?format=tar",
        None,
        "application/x-tar",
        &archive,
    );
    assert_eq!(solo.status, 201, "{}", solo.body);
    let solo = solo.json()["id"].as_str().expect("id").to_string();
    wait_finished(&single, &solo, None);
    let solo_trajectory = get(&single, &format!("/v1/sessions/{solo}/trajectory"), None).body;
    assert_eq!(
        taken_over, solo_trajectory,
        "the re-run differs from a single-node run"
    );
    drop((a, c, single));
    let _ = std::fs::remove_dir_all(&work);
}
