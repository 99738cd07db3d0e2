//! Hole 4: nothing timed out. Connections with half-sent headers stayed open, frame bodies
//! stalled one byte short held their buffers, a session that got a frame now and then kept its
//! slot, and finished sessions never expired. Now headers and bodies have deadlines, a live
//! session needs a minimum frame rate, each owner has quotas, and finished sessions expire
//! (410 Gone).

use std::io::{Read as _, Write as _};

use super::*;

const CONFIG: &str = "[http]\nheader_timeout_s = 2\nbody_timeout_s = 2\n\
    [limits]\nidle_timeout_s = 5\nmin_frame_rate = 1.0\n\
    [retention]\nfinished_ttl_s = 12\nsweep_interval_s = 1\n\
    [quotas]\nmax_active_sessions = 1\n";

/// Whether the server closed `stream` within `within` (a read returns end of file or a reset).
fn closed_within(stream: &mut std::net::TcpStream, within: Duration) -> bool {
    stream.set_read_timeout(Some(within)).expect("read timeout");
    let mut buf = [0u8; 4096];
    loop {
        match stream.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => continue, // a 408 page may come first
            Err(e)
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut =>
            {
                return false;
            }
            Err(_) => return true,
        }
    }
}

#[test]
fn slow_clients_idle_sessions_and_old_sessions_are_cut_off() {
    let dir = synth_sequence("hardening-timeouts", 8, 29);
    let seq = TumSequence::open(&dir, None).expect("synth");
    let server = spawn(
        "timeouts",
        Some(CONFIG),
        &[("RELFUSIOND_TOKENS", "alice:tok-a,bob:tok-b")],
    );

    // Half-sent headers: every connection is closed at the header deadline.
    let t0 = Instant::now();
    let mut slow: Vec<_> = (0..40)
        .map(|_| raw(&server, b"GET /healthz HTTP/1.1\r\nHost: x\r\n"))
        .collect();
    assert_healthy(&server, "40 half-open connections");
    for stream in &mut slow {
        assert!(
            closed_within(stream, Duration::from_secs(6)),
            "a half-sent request stayed open {:?}",
            t0.elapsed()
        );
    }

    // A frame body one byte short: 408 at the body deadline, the buffer released.
    let id = {
        let body = json!({"camera": camera_json(&seq), "policy": "wait"});
        let created = post_json(&server, "/v1/sessions", Some("tok-a"), &body);
        assert_eq!(created.status, 201, "{}", created.body);
        created.json()["id"].as_str().expect("id").to_string()
    };
    let head = format!(
        "POST /v1/sessions/{id}/frames?timestamp=1 HTTP/1.1\r\nHost: x\r\n\
         Authorization: Bearer tok-a\r\nContent-Type: image/png\r\nContent-Length: 100000\r\n\r\n"
    );
    let mut stalled = raw(&server, head.as_bytes());
    stalled.write_all(&vec![0u8; 99_999]).expect("body");
    stalled
        .set_read_timeout(Some(Duration::from_secs(8)))
        .expect("timeout");
    let mut answer = String::new();
    let _ = stalled.read_to_string(&mut answer);
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer:?}");

    // Quotas: alice holds one active session (her quota); bob is not affected.
    let body = json!({"camera": camera_json(&seq), "policy": "wait"});
    let second = post_json(&server, "/v1/sessions", Some("tok-a"), &body);
    second.expect_error(429, "quota_exceeded", "alice's second session");
    let bobs = post_json(&server, "/v1/sessions", Some("tok-b"), &body);
    assert_eq!(bobs.status, 201, "{}", bobs.body);
    let bob_id = bobs.json()["id"].as_str().expect("id").to_string();

    // A trickle (one frame every 2.5 s, under min_frame_rate over idle_timeout_s) ends bob's
    // session as idle although frames keep coming.
    let trickle = Instant::now();
    let mut ended = None;
    for i in 0..seq.len() {
        let path = format!(
            "/v1/sessions/{bob_id}/frames?timestamp={}",
            seq.frames[i].timestamp
        );
        let reply = send(
            &server,
            "POST",
            &path,
            Some("tok-b"),
            "image/png",
            &frame_bytes(&seq, i),
        );
        // 409 once it ended; 410 if it has expired too (finished_ttl_s is short here).
        if matches!(reply.status, 409 | 410) {
            ended = Some(i);
            break;
        }
        assert_eq!(reply.status, 202, "{}", reply.body);
        std::thread::sleep(Duration::from_millis(2500));
    }
    assert!(
        ended.is_some_and(|i| i >= 1),
        "a trickling session kept its slot for {:?} ({ended:?})",
        trickle.elapsed()
    );
    // Alice's session got no frame at all: idle too, and her quota is free again.
    let info = wait_info(&server, &id, Some("tok-a"), |i| i["state"] == "finished");
    assert!(
        info["notice"].as_str().unwrap_or_default().contains("idle"),
        "{info}"
    );
    let again = post_json(&server, "/v1/sessions", Some("tok-a"), &body);
    assert_eq!(again.status, 201, "{}", again.body);

    // Retention: bob's finished session expires (410 for him, 404 for others) and its files
    // are gone.
    let folder = server.data_dir().join("sessions").join(&bob_id);
    let deadline = Instant::now() + Duration::from_secs(40);
    let gone = loop {
        let reply = get(&server, &format!("/v1/sessions/{bob_id}"), Some("tok-b"));
        if reply.status == 410 || Instant::now() > deadline {
            break reply;
        }
        std::thread::sleep(Duration::from_millis(250));
    };
    gone.expect_error(410, "gone", "expired session");
    // The id answers 410 from the moment it expires; its files are deleted right after
    // (`SessionManager::expire_finished`), on a loaded machine a moment later.
    while folder.exists() && Instant::now() < deadline + Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(!folder.exists(), "{} still exists", folder.display());
    let other = get(&server, &format!("/v1/sessions/{bob_id}"), Some("tok-a"));
    assert_eq!(
        other.status, 404,
        "another owner learns nothing: {}",
        other.body
    );
    assert_healthy(&server, "timeouts");
}

#[test]
fn connections_beyond_the_limit_wait_and_are_served_once_others_close() {
    let server = spawn(
        "connections",
        Some("[http]\nmax_connections = 4\nheader_timeout_s = 2\n"),
        &[],
    );
    let held: Vec<_> = (0..4)
        .map(|_| raw(&server, b"GET /healthz HTTP/1.1\r\n"))
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    // The fifth is accepted by the kernel but not served until a slot frees (the header
    // deadline closes the held ones).
    let t0 = Instant::now();
    let mut fifth = raw(
        &server,
        b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
    );
    fifth
        .set_read_timeout(Some(Duration::from_secs(10)))
        .expect("timeout");
    let mut answer = String::new();
    let _ = fifth.read_to_string(&mut answer);
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer:?}");
    assert!(
        t0.elapsed() >= Duration::from_millis(1000),
        "served at once ({:?}): the limit did not hold",
        t0.elapsed()
    );
    drop(held);
}
