//! Hole 2 of the hardening issue: with tokens, nothing of a session can be read or written over
//! Zenoh without its owner's credentials. A real second Zenoh session plays the intruder:
//! - without credentials (or with a wrong password) it cannot connect at all;
//! - logged in as another tenant (bob), its wildcard subscriptions (`relfusion/**`, alice's
//!   prefix) receive none of alice's frames, poses, meshes or session ids, its queryables on
//!   alice's create key receive none of her queries (and tokens), its frame and `end`
//!   published on alice's session keys are not counted and do not end her session, and its
//!   query of her map gets no answer — while bob's own session and the node status work.

use super::client::*;

/// Frames alice streams.
const ALICE_FRAMES: usize = 12;

/// Whatever `sub` received (without waiting).
fn drained(sub: &Subscriber<FifoChannelHandler<Sample>>) -> Vec<String> {
    let mut keys = Vec::new();
    while let Ok(Some(sample)) = sub.try_recv() {
        keys.push(sample.key_expr().as_str().to_string());
    }
    keys
}

/// Sends a query and returns every successful reply within 3 s.
fn answers(z: &zenoh::Session, key: &str, token: &str) -> usize {
    let replies = z
        .get(key)
        .attachment(token.to_string())
        .timeout(Duration::from_secs(3))
        .wait()
        .expect("send query");
    let mut n = 0;
    while let Ok(reply) = replies.recv() {
        if reply.result().is_ok() {
            n += 1;
        }
    }
    n
}

#[test]
fn a_zenoh_intruder_reads_and_writes_nothing_of_another_tenant() {
    let _machine = ENDPOINTS.read().unwrap_or_else(|e| e.into_inner());
    let seq_dir = synth_sequence("zenoh", FRAMES_N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("zenoh-intruder");
    let (server, endpoint) = spawn_server(&work, &[("RELFUSIOND_TOKENS", "alice:tok-a,bob:tok-b")]);
    let alice = zenoh_client(&endpoint, &server, Some(("alice", "tok-a")));
    node_status(&alice, |_| true);

    // No credentials, or a wrong password: Zenoh refuses the connection itself.
    for login in [None, Some(("alice", "tok-b")), Some(("mallory", "tok-a"))] {
        let opened = zenoh::open(client_config(&endpoint, login)).wait();
        assert!(opened.is_err(), "{login:?} connected");
    }

    // Bob is a tenant too: logged in, he spies on everything he can name.
    let bob = zenoh_client(&endpoint, &server, Some(("bob", "tok-b")));
    let spy = |key: &str| {
        // Remote samples only: bob's own publications below are not leaks.
        bob.declare_subscriber(key.to_string())
            .allowed_origin(Locality::Remote)
            .with(FifoChannel::new(4096))
            .wait()
            .expect("bob declares a subscriber")
    };
    let spy_all = spy("relfusion/**");
    let spy_alice = spy("relfusion/tenants/alice/**");
    let trap = |key: String| {
        bob.declare_queryable(key)
            .allowed_origin(Locality::Remote)
            .with(FifoChannel::new(64))
            .wait()
            .expect("bob declares a queryable")
    };
    let trap_create = trap(create_key("alice"));
    let trap_all = trap("relfusion/**".into());
    // Give the declarations time to reach the server (they must be refused there).
    std::thread::sleep(Duration::from_millis(500));

    let config = session_config(
        &seq,
        FramePolicy::Wait,
        r#"{"pipeline":{"deterministic":true}}"#,
    );
    let id = create(&alice, "alice", Some("tok-a"), config.encode_to_vec()).expect("alice creates");
    let updates = subscribe(&alice, "alice", &id);
    for i in 0..ALICE_FRAMES {
        put(
            &alice,
            session_key("alice", &id, FRAMES),
            frame_bytes(&seq, i).encode_to_vec(),
        );
    }
    // Bob writes into alice's session: a frame and the end of her stream.
    let mut forged = frame_bytes(&seq, ALICE_FRAMES);
    forged.frame_id = 1_000;
    put(
        &bob,
        session_key("alice", &id, FRAMES),
        forged.encode_to_vec(),
    );
    put(
        &bob,
        session_key("alice", &id, END),
        EndOfStream {}.encode_to_vec(),
    );
    assert_eq!(
        answers(&bob, &session_key("alice", &id, MAP), "tok-b"),
        0,
        "bob's query of alice's map was answered"
    );
    assert_eq!(
        answers(&bob, &session_key("alice", &id, MAP), "tok-a"),
        0,
        "even with alice's token, bob's connection may not query her keys"
    );

    // Alice's session took none of it: her frames only, still running.
    let deadline = Instant::now() + PATIENCE;
    let snapshot = loop {
        let s = map(&alice, "alice", Some("tok-a"), &id).expect("alice's map");
        if s.frames_processed >= ALICE_FRAMES as u64 || Instant::now() > deadline {
            break s;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(
        snapshot.frames_received, ALICE_FRAMES as u64,
        "{snapshot:?}"
    );
    assert_eq!(
        snapshot.state, "running",
        "bob's `end` finished alice's session"
    );

    put(
        &alice,
        session_key("alice", &id, END),
        EndOfStream {}.encode_to_vec(),
    );
    let mut posed = Vec::new();
    let finished = loop {
        match next_update(&updates, &server) {
            Ok(message) => {
                if let Some(server_message::Message::Pose(p)) = message.message {
                    posed.push(p.frame_id);
                }
            }
            Err(finished) => break finished,
        }
    };
    assert_eq!(posed, (0..ALICE_FRAMES as u64).collect::<Vec<_>>());
    assert_eq!(finished.frames_received, ALICE_FRAMES as u64);

    // Bob's own session works: he is confined, not cut off.
    let bobs = create(&bob, "bob", Some("tok-b"), config.encode_to_vec()).expect("bob creates");
    assert_ne!(bobs, id);
    let status = node_status(&bob, |_| true);
    assert!(status["sessions_active"].is_u64(), "{status}");

    let leaked_all = drained(&spy_all);
    let leaked_alice = drained(&spy_alice);
    assert!(
        leaked_all.iter().all(|k| !k.contains("/tenants/alice/")),
        "bob's relfusion/** subscriber received alice's keys: {leaked_all:?}"
    );
    assert!(leaked_alice.is_empty(), "bob received {leaked_alice:?}");
    assert!(
        matches!(trap_create.try_recv(), Ok(None)),
        "alice's create query (with her token) reached bob"
    );
    while let Ok(Some(query)) = trap_all.try_recv() {
        assert!(
            !query.key_expr().as_str().contains("/tenants/alice/"),
            "alice's query reached bob: {}",
            query.key_expr()
        );
    }
    drop(server);
}
