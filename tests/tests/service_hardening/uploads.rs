//! Hole 5: uploads were admitted after their bytes were written (two concurrent uploads could
//! both pass the last queue place), a small zip expanding to gigabytes was stored, and a zip
//! with a million entries was parsed whole before its 413. Now an upload reserves its place
//! before its body is read, extraction is bounded relative to the archive's size, and a zip's
//! entry count is read from its end record first.

use std::io::{Read as _, Write as _};

use relfusion_tests::attacks::zip_archive;

use super::*;

fn post_zip(server: &Relfusiond, body: &[u8]) -> (Reply, Duration) {
    let t0 = Instant::now();
    let reply = send(
        server,
        "POST",
        "/v1/uploads?format=zip",
        None,
        "application/zip",
        body,
    );
    (reply, t0.elapsed())
}

#[test]
fn zip_bombs_and_entry_floods_are_refused_early() {
    let server = spawn("zipbomb", None, &[]);
    let bomb = zip_archive(0, 256 << 20);
    assert!(
        bomb.len() < 2 << 20,
        "the bomb is small: {} bytes",
        bomb.len()
    );
    let (reply, _) = post_zip(&server, &bomb);
    let message = reply.expect_error(413, "payload_too_large", "zip bomb");
    assert!(message.contains("max_expansion_ratio"), "{message}");
    let flood = zip_archive(50_000, 0);
    let (reply, took) = post_zip(&server, &flood);
    let message = reply.expect_error(413, "payload_too_large", "50 000 entries");
    assert!(message.contains("50000 entries"), "{message}");
    assert!(
        took < Duration::from_secs(5),
        "the flood took {took:?} to refuse"
    );
    // Nothing of either stays on disk.
    let sessions = server.data_dir().join("sessions");
    let left = std::fs::read_dir(&sessions).map_or(0, |d| d.count());
    assert_eq!(left, 0, "{} holds leftovers", sessions.display());
    assert_healthy(&server, "zip attacks");
}

#[test]
fn an_upload_reserves_its_place_before_its_body_is_read() {
    let dir = synth_sequence("hardening-admission", 6, 31);
    let server = spawn(
        "admission",
        Some("[limits]\nmax_queued_uploads = 1\n[http]\nbody_timeout_s = 5\n"),
        &[],
    );
    let archive = tar_with_list(&dir, &rgb_txt(&dir));
    // The first upload announces its size and sends half: it holds the only place.
    let head = format!(
        "POST /v1/uploads?format=tar HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-tar\r\n\
         Content-Length: {}\r\n\r\n",
        archive.len()
    );
    let mut first = raw(&server, head.as_bytes());
    first
        .write_all(&archive[..archive.len() / 2])
        .expect("half");
    std::thread::sleep(Duration::from_millis(300));
    // The second is refused at once, before its body is read.
    let t0 = Instant::now();
    let second = raw_post_status(
        &server,
        "/v1/uploads?format=tar",
        "application/x-tar",
        archive.clone(),
    );
    assert_eq!(second, 503, "a second upload passed the only place");
    assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
    // The first completes and is acknowledged.
    first
        .write_all(&archive[archive.len() / 2..])
        .expect("rest");
    first
        .set_read_timeout(Some(Duration::from_secs(30)))
        .expect("timeout");
    let mut answer = vec![0u8; 4096];
    let n = first.read(&mut answer).expect("answer");
    let answer = String::from_utf8_lossy(&answer[..n]);
    assert!(answer.starts_with("HTTP/1.1 201"), "{answer}");
    assert_healthy(&server, "admission");
}
