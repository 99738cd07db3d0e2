//! Zenoh creates are placed like HTTP ones: behind a router that enforces the tokens' access
//! rules, with node A full, every session a tenant creates over Zenoh runs on node B, whichever
//! node's create queryable the query reached (in every run here the router sent them to A,
//! which relays them; without placement A refuses them), and the tenant streams to it through
//! the router as to any session.

use relfusion_tests::Relfusiond;

use super::client::*;

const TOKENS: &str = "alice:tok-a";
const NODE_ENV: [(&str, &str); 3] = [
    ("RELFUSIOND_TOKENS", TOKENS),
    ("RELFUSIOND_ZENOH_USER", "relfusiond"),
    ("RELFUSIOND_ZENOH_PASSWORD", "placement-node-secret"),
];
const FRAME_COUNT: usize = 20;

/// `GET path` on `server` with Alice's token: the JSON body of a 200.
fn get_json(server: &Relfusiond, path: &str) -> serde_json::Value {
    let mut reply = ureq::get(&format!("{}{path}", server.url()))
        .header("Authorization", "Bearer tok-a")
        .call()
        .unwrap_or_else(|e| panic!("GET {path}: {e}"));
    let text = reply.body_mut().read_to_string().expect("body");
    serde_json::from_str(&text).expect("JSON")
}

#[test]
fn zenoh_creates_go_to_the_node_with_room() {
    let _machine = ENDPOINTS.write().unwrap_or_else(|e| e.into_inner());
    let seq = TumSequence::open(&synth_sequence("zenoh-placement", FRAME_COUNT, SEED), None)
        .expect("open sequence");
    let work = temp_dir("zenoh-placement");
    let (router, endpoint) = Relfusiond::spawn_router(&work.join("router"), &NODE_ENV);
    let node = |name: &str, max_sessions: usize| {
        let extra = "[quotas]\nmax_active_sessions = 4\n";
        Relfusiond::spawn_node(&work, name, &endpoint, max_sessions, extra, &NODE_ENV)
    };
    let z = zenoh_client(&endpoint, &router, Some(("alice", "tok-a")));
    let config = session_config(
        &seq,
        FramePolicy::Wait,
        r#"{"pipeline":{"deterministic":true}}"#,
    )
    .encode_to_vec();

    // A, alone: the first session fills it.
    let a = node("a", 1);
    node_status(&z, |s| s["node"] == "a");
    let first = create(&z, "alice", Some("tok-a"), config.clone()).expect("created on A");
    assert_eq!(get_json(&a, &format!("/v1/sessions/{first}"))["node"], "a");
    let b = node("b", 3);
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let view = get_json(&a, "/v1/cluster");
        let nodes = view["nodes"].as_array().cloned().unwrap_or_default();
        if nodes.len() == 2 && nodes.iter().all(|n| n["max_sessions"].as_u64() > Some(0)) {
            break;
        }
        assert!(Instant::now() < deadline, "A never saw B: {view}");
        std::thread::sleep(Duration::from_millis(200));
    }

    // A is full: every create lands on B, whichever node answered the query.
    let placed: Vec<String> = (0..3)
        .map(|i| {
            create(&z, "alice", Some("tok-a"), config.clone())
                .unwrap_or_else(|e| panic!("create {i} refused: {e:?}\n{}", a.log()))
        })
        .collect();
    for id in &placed {
        let info = get_json(&a, &format!("/v1/sessions/{id}"));
        assert_eq!(info["node"], "b", "{info}");
    }
    // A wrong token is refused, not placed.
    let e = create(&z, "alice", Some("tok-x"), config).expect_err("wrong token");
    assert_eq!(e.code(), ErrorCode::Unauthenticated, "{e:?}");

    // Streamed over Zenoh to B: a pose for every frame, then the end.
    let id = &placed[0];
    let updates = subscribe(&z, "alice", id);
    for i in 0..FRAME_COUNT {
        put(
            &z,
            session_key("alice", id, FRAMES),
            frame_bytes(&seq, i).encode_to_vec(),
        );
    }
    put(
        &z,
        session_key("alice", id, END),
        EndOfStream {}.encode_to_vec(),
    );
    let mut poses = 0;
    let finished = loop {
        match next_update(&updates, &b) {
            Ok(ServerMessage {
                message: Some(server_message::Message::Pose(_)),
            }) => poses += 1,
            Ok(_) => {}
            Err(finished) => break finished,
        }
    };
    assert_eq!(poses, FRAME_COUNT, "{finished:?}\n{}", b.log());
    drop((a, b, router));
    let _ = std::fs::remove_dir_all(&work);
}
