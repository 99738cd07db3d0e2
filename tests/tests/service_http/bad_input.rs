//! Bad frames, bad WebSocket messages and bad create requests: each gets its 4xx JSON error
//! (or protobuf `Error`) and the server, and the session, keep working.

use super::client::*;

#[test]
fn bad_frames_and_messages_get_errors_and_the_stream_goes_on() {
    let seq = TumSequence::open(&synth_sequence("http-bad", 8, 5), None).expect("synth");
    let server = spawn("bad", Some(SMALL_LIMITS), &[]);
    let id = create_session(&server, &seq, None);
    let png = frame_bytes(&seq, 0);
    let frames = format!("/v1/sessions/{id}/frames?timestamp=1.5");
    let mut corrupt_jpeg = vec![0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10, b'J', b'F', b'I', b'F'];
    corrupt_jpeg.extend((0..4000u32).map(|i| (i * 7919 % 251) as u8));
    let mut small = Vec::new();
    image::RgbImage::from_pixel(160, 120, image::Rgb([90, 120, 150]))
        .write_to(
            &mut std::io::Cursor::new(&mut small),
            image::ImageFormat::Png,
        )
        .expect("encode small png");

    let cases: [(&str, &str, Vec<u8>, u16, &str); 6] = [
        (
            "corrupt JPEG",
            "image/jpeg",
            corrupt_jpeg,
            400,
            "invalid_argument",
        ),
        (
            "truncated PNG",
            "image/png",
            png[..png.len() / 2].to_vec(),
            400,
            "invalid_argument",
        ),
        ("wrong size", "image/png", small, 400, "invalid_argument"),
        (
            "empty body",
            "image/png",
            Vec::new(),
            400,
            "invalid_argument",
        ),
        (
            "not an image type",
            "text/plain",
            png.clone(),
            415,
            "unsupported_media_type",
        ),
        (
            "random bytes",
            "application/octet-stream",
            vec![7; 1000],
            400,
            "invalid_argument",
        ),
    ];
    for (what, content_type, body, status, code) in cases {
        let message = send(&server, "POST", &frames, None, content_type, &body)
            .expect_error(status, code, what);
        if what == "wrong size" {
            assert!(
                message.contains("320") && message.contains("160"),
                "{message}"
            );
        }
        assert_healthy(&server, what);
    }
    let query_cases = [
        ("no timestamp", format!("/v1/sessions/{id}/frames")),
        (
            "NaN timestamp",
            format!("/v1/sessions/{id}/frames?timestamp=NaN"),
        ),
        (
            "text timestamp",
            format!("/v1/sessions/{id}/frames?timestamp=soon"),
        ),
    ];
    for (what, path) in query_cases {
        send(&server, "POST", &path, None, "image/png", &png).expect_error(
            400,
            "invalid_argument",
            what,
        );
        assert_healthy(&server, what);
    }
    let oversized = raw_post_status(&server, &frames, "image/png", vec![0x89; 300_000]);
    assert_eq!(oversized, 413, "frame over max_frame_bytes");
    assert_healthy(&server, "oversized frame");
    send(
        &server,
        "POST",
        "/v1/sessions/s-000000000000/frames?timestamp=1",
        None,
        "image/png",
        &png,
    )
    .expect_error(404, "not_found", "unknown session");
    get(&server, "/v1/sessions/s-000000000000", None).expect_error(404, "not_found", "unknown");
    get(&server, "/v1/sessions/nope/trajectory", None).expect_error(404, "not_found", "unknown");
    get(&server, "/v1/nothing-here", None).expect_error(404, "not_found", "unknown route");

    // The session still takes good frames; ids must increase.
    let ok = post_frame(&server, &id, &seq, 3);
    assert_eq!(ok.status, 202, "{}", ok.body);
    post_frame(&server, &id, &seq, 2).expect_error(400, "invalid_argument", "decreasing frame id");

    // Over the WebSocket: every bad message gets an Error back and the socket stays usable.
    let mut socket = ws_connect(&server, &id, None).expect("websocket");
    socket
        .send(tungstenite::Message::binary(vec![0xFF; 16]))
        .expect("send garbage");
    socket
        .send(tungstenite::Message::text("hello"))
        .expect("send text");
    ws_send(
        &mut socket,
        ws_frame(&seq, 4, png[..png.len() / 3].to_vec()),
    );
    ws_send(&mut socket, ws_frame(&seq, 5, frame_bytes(&seq, 5)));
    let mut errors = Vec::new();
    let mut poses = Vec::new();
    while !poses.contains(&5) {
        match ws_next(&mut socket).expect("socket stays open") {
            server_message::Message::Error(e) => errors.push(e),
            server_message::Message::Pose(p) => poses.push(p.frame_id),
            _ => {}
        }
    }
    assert_eq!(errors.len(), 3, "{errors:?}");
    for error in &errors {
        assert_eq!(error.code, ErrorCode::InvalidArgument as i32, "{error:?}");
    }
    assert!(errors[0].message.contains("malformed"), "{:?}", errors[0]);
    assert!(errors[2].message.contains("frame 4"), "{:?}", errors[2]);
    let _ = socket.close(None);
    assert_healthy(&server, "the websocket errors");
}

#[test]
fn invalid_session_requests_get_400() {
    let seq = TumSequence::open(&synth_sequence("http-bad", 8, 5), None).expect("synth");
    let server = spawn("create", None, &[]);
    let camera = camera_json(&seq);
    let with = |key: &str, value: Value| {
        let mut camera = camera.clone();
        camera[key] = value;
        json!({ "camera": camera })
    };
    let cases = [
        ("fx = 0", with("fx", json!(0.0))),
        ("fx < 0", with("fx", json!(-262.5))),
        ("fx NaN as a string", with("fx", json!("NaN"))),
        ("zero width", with("width", json!(0))),
        ("no camera", json!({ "policy": "wait" })),
        (
            "unknown config key",
            json!({ "camera": camera, "config": { "no_such_key": 1 } }),
        ),
        (
            "unknown model",
            json!({ "camera": camera, "model": "no-such-model" }),
        ),
        (
            "unknown policy",
            json!({ "camera": camera, "policy": "sometimes" }),
        ),
    ];
    for (what, body) in cases {
        post_json(&server, "/v1/sessions", None, &body).expect_error(400, "invalid_argument", what);
        assert_healthy(&server, what);
    }
    // JSON has no NaN or infinity: a literal that overflows f64 is the nearest a client can send.
    let valid = json!({ "camera": camera }).to_string();
    let fx = format!("\"fx\":{}", camera["fx"]);
    assert!(valid.contains(&fx), "{valid}");
    let overflow = valid.replacen(&fx, "\"fx\":1e999", 1);
    send(
        &server,
        "POST",
        "/v1/sessions",
        None,
        "application/json",
        overflow.as_bytes(),
    )
    .expect_error(400, "invalid_argument", "fx = 1e999");
    send(
        &server,
        "POST",
        "/v1/sessions",
        None,
        "application/json",
        b"{not json",
    )
    .expect_error(400, "invalid_argument", "not JSON");
    send(&server, "POST", "/v1/sessions", None, "text/plain", b"{}").expect_error(
        415,
        "unsupported_media_type",
        "not a JSON content type",
    );
    assert_healthy(&server, "the bad creates");
    let created = send(
        &server,
        "POST",
        "/v1/sessions",
        None,
        "application/json",
        valid.as_bytes(),
    );
    assert_eq!(
        created.status, 201,
        "a valid request still works: {}",
        created.body
    );
}

/// A mesh asked for before there is one gets a 404 that says why: the dense layer is off, or
/// nothing has been fused yet (with the keyframe counts).
#[test]
fn a_session_without_a_mesh_says_why() {
    let seq = TumSequence::open(&synth_sequence("http-bad", 8, 5), None).expect("synth");
    let server = spawn("no-mesh", None, &[]);
    let created = post_json(
        &server,
        "/v1/sessions",
        None,
        &json!({
            "camera": camera_json(&seq),
            "config": { "dense": { "enabled": false } },
        }),
    );
    assert_eq!(created.status, 201, "{}", created.body);
    let off = created.json()["id"].as_str().expect("id").to_string();
    let fresh = create_session(&server, &seq, None);
    for file in ["mesh.ply", "mesh.glb"] {
        let message = get(&server, &format!("/v1/sessions/{off}/{file}"), None).expect_error(
            404,
            "not_found",
            "dense layer off",
        );
        assert!(message.contains("dense layer is off"), "{message}");
        let message = get(&server, &format!("/v1/sessions/{fresh}/{file}"), None).expect_error(
            404,
            "not_found",
            "nothing fused",
        );
        assert!(
            message.contains("nothing fused yet: 0 keyframes"),
            "{message}"
        );
    }
}
