//! Bearer tokens: 401 without a valid one, another owner's session is a 404, open routes
//! stay open; admission control answers 503 beyond max_sessions.

use super::client::*;

#[test]
fn tokens_scope_sessions_and_capacity_is_enforced() {
    let seq = TumSequence::open(&synth_sequence("http-bad", 8, 5), None).expect("synth");
    let server = spawn(
        "auth",
        None,
        &[
            ("RELFUSIOND_TOKENS", "alice:alice-secret,bob:bob-secret"),
            ("RELFUSIOND_MAX_SESSIONS", "2"),
        ],
    );
    let body = json!({ "camera": camera_json(&seq) });
    post_json(&server, "/v1/sessions", None, &body).expect_error(401, "unauthorized", "no token");
    post_json(&server, "/v1/sessions", Some("mallory"), &body).expect_error(
        401,
        "unauthorized",
        "wrong token",
    );
    get(&server, "/v1/sessions", None).expect_error(401, "unauthorized", "list without token");
    let basic = agent()
        .get(format!("{}/v1/sessions", server.url()))
        .header("Authorization", "Basic YWxpY2U6YWxpY2Utc2VjcmV0")
        .call();
    reply(basic).expect_error(401, "unauthorized", "basic auth");
    for open in [
        "/healthz",
        "/readyz",
        "/metrics",
        "/openapi.json",
        "/v1/version",
        "/v1/proto",
        "/v1/proto/relfusion/v1/session.proto",
        "/docs",
        "/docs/swagger-ui.css",
        "/",
        "/view/s-000000000000",
        "/viewer/viewer.js",
        "/viewer/viewer.css",
        "/viewer/licenses.txt",
    ] {
        assert_eq!(
            get(&server, open, None).status,
            200,
            "{open} needs no token"
        );
    }

    let alice = Some("alice-secret");
    let bob = Some("bob-secret");
    let id = create_session(&server, &seq, alice);
    let mine = format!("/v1/sessions/{id}");
    assert_eq!(get(&server, &mine, alice).status, 200);
    get(&server, &mine, bob).expect_error(404, "not_found", "another owner's session");
    get(&server, &format!("{mine}/trajectory"), bob).expect_error(404, "not_found", "trajectory");
    get(&server, &format!("{mine}/map"), bob).expect_error(404, "not_found", "map");
    assert_eq!(get(&server, &format!("{mine}/map"), alice).status, 200);
    get(&server, &format!("{mine}/map"), None).expect_error(401, "unauthorized", "map");
    get(&server, &format!("{mine}/events"), bob).expect_error(404, "not_found", "events");
    send(
        &server,
        "POST",
        &format!("{mine}/frames?timestamp=0"),
        bob,
        "image/png",
        &frame_bytes(&seq, 0),
    )
    .expect_error(404, "not_found", "frames");
    send(&server, "DELETE", &mine, bob, "", b"").expect_error(404, "not_found", "delete");
    assert_eq!(
        ws_connect(&server, &id, bob).err(),
        Some(404),
        "bob's websocket"
    );
    assert_eq!(
        ws_connect(&server, &id, None).err(),
        Some(401),
        "anonymous websocket"
    );
    assert!(ws_connect(&server, &id, alice).is_ok(), "alice's websocket");
    let bobs = get(&server, "/v1/sessions", bob).json();
    assert_eq!(
        bobs["sessions"],
        json!([]),
        "bob sees none of alice's sessions"
    );
    let alices = get(&server, "/v1/sessions", alice).json();
    assert_eq!(
        alices["sessions"].as_array().map(Vec::len),
        Some(1),
        "{alices}"
    );
    let by_query = agent()
        .get(format!("{}{mine}?access_token=alice-secret", server.url()))
        .call();
    assert_eq!(reply(by_query).status, 200, "token as a query parameter");

    // Capacity: two sessions at most, whoever owns them; and each token at most its share
    // (quotas.max_active_sessions: half of them with auth on).
    let bobs_first = create_session(&server, &seq, bob);
    let refused = post_json(&server, "/v1/sessions", alice, &body);
    let message = refused.expect_error(503, "resource_exhausted", "third session");
    assert!(
        message.contains('2'),
        "the reason names the limit: {message}"
    );
    assert_healthy(&server, "the 503");
    assert_eq!(send(&server, "DELETE", &mine, alice, "", b"").status, 204);
    let deadline = Instant::now() + Duration::from_secs(10);
    let again = loop {
        let retry = post_json(&server, "/v1/sessions", alice, &body);
        if retry.status == 201 {
            break retry.json()["id"].as_str().expect("id").to_string();
        }
        assert!(
            Instant::now() < deadline,
            "a slot frees after delete: {}",
            retry.body
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    // A free slot is not bob's to take twice: his second session is over his quota.
    assert_eq!(
        send(
            &server,
            "DELETE",
            &format!("/v1/sessions/{again}"),
            alice,
            "",
            b""
        )
        .status,
        204
    );
    std::thread::sleep(Duration::from_millis(200));
    post_json(&server, "/v1/sessions", bob, &body).expect_error(
        429,
        "quota_exceeded",
        "bob's second session",
    );
    assert_eq!(
        get(&server, &format!("/v1/sessions/{bobs_first}"), bob).status,
        200
    );
}
