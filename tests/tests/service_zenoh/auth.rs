//! Zenoh with tokens: the create and map queries need the tenant's own token (UNAUTHENTICATED
//! otherwise; an unknown session is NOT_FOUND), malformed messages and corrupt frames are
//! answered with an `Error` on `poses`, counted, and the session goes on. The intruder tests
//! are in [`super::intruder`].

use super::client::*;

#[test]
fn tokens_scope_sessions_and_bad_messages_get_errors() {
    let _machine = ENDPOINTS.read().unwrap_or_else(|e| e.into_inner());
    let seq_dir = synth_sequence("zenoh", FRAMES_N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("zenoh-auth");
    let (server, endpoint) = spawn_server(&work, &[("RELFUSIOND_TOKENS", "alice:tok-a,bob:tok-b")]);
    let z = zenoh_client(&endpoint, &server, Some(("alice", "tok-a")));
    node_status(&z, |_| true);
    let config = session_config(&seq, FramePolicy::Wait, "").encode_to_vec();

    let alice = "alice";
    // The attachment must be the tenant's own token, whoever the connection logged in as.
    for token in [None, Some("tok-c"), Some(""), Some("tok-b")] {
        let e = create(&z, alice, token, config.clone()).expect_err("refused without her token");
        assert_eq!(e.code(), ErrorCode::Unauthenticated, "{token:?}: {e:?}");
    }
    let id = create(&z, alice, Some("tok-a"), config.clone()).expect("alice creates");
    let e = map(&z, alice, Some("tok-b"), &id).expect_err("bob's token on alice's session");
    assert_eq!(e.code(), ErrorCode::Unauthenticated, "{e:?}");
    let e = map(&z, alice, None, &id).expect_err("no token");
    assert_eq!(e.code(), ErrorCode::Unauthenticated, "{e:?}");
    let e = map(&z, alice, Some("Bearer tok-a"), "s-000000000000").expect_err("unknown session");
    assert_eq!(e.code(), ErrorCode::NotFound, "{e:?}");
    let snapshot = map(&z, alice, Some("Bearer tok-a"), &id).expect("alice sees her session");
    assert_eq!(snapshot.state, "running");
    assert!(snapshot.trajectory.is_empty(), "no frame yet");

    let mut bad_camera = session_config(&seq, FramePolicy::Wait, "");
    if let Some(c) = bad_camera.camera.as_mut() {
        c.fx = 0.0;
    }
    let e = create(&z, alice, Some("tok-a"), bad_camera.encode_to_vec()).expect_err("fx = 0");
    assert_eq!(e.code(), ErrorCode::InvalidArgument, "{e:?}");
    let e = create(&z, alice, Some("tok-a"), vec![0xff; 16]).expect_err("not a SessionConfig");
    assert_eq!(e.code(), ErrorCode::InvalidArgument, "{e:?}");
    assert!(e.message.contains("SessionConfig"), "{e:?}");

    let updates = subscribe(&z, alice, &id);
    let frames_key = session_key(alice, &id, FRAMES);
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
    put(
        &z,
        session_key(alice, &id, END),
        EndOfStream {}.encode_to_vec(),
    );
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
