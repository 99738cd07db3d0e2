//! Uploads: a good tar becomes a finished session; traversal, truncation, bad formats and
//! oversize are refused with nothing written outside the upload.

use super::client::*;

/// A ustar archive with one regular file, its name written as given (the `tar` crate refuses to
/// write `..`, which is exactly what this must send).
fn raw_tar(name: &str, data: &[u8]) -> Vec<u8> {
    let mut header = [0u8; 512];
    header[..name.len()].copy_from_slice(name.as_bytes());
    header[100..108].copy_from_slice(b"0000644\0");
    header[108..116].copy_from_slice(b"0000000\0");
    header[116..124].copy_from_slice(b"0000000\0");
    header[124..136].copy_from_slice(format!("{:011o}\0", data.len()).as_bytes());
    header[136..148].copy_from_slice(b"00000000000\0");
    header[148..156].copy_from_slice(b"        ");
    header[156] = b'0';
    header[257..263].copy_from_slice(b"ustar\0");
    header[263..265].copy_from_slice(b"00");
    let sum: u32 = header.iter().map(|&b| u32::from(b)).sum();
    header[148..156].copy_from_slice(format!("{sum:06o}\0 ").as_bytes());
    let mut tar = header.to_vec();
    tar.extend_from_slice(data);
    tar.resize(tar.len().div_ceil(512) * 512 + 1024, 0);
    tar
}

#[test]
fn uploads_are_processed_and_bad_archives_refused() {
    const FRAMES: usize = 8;
    let dir = synth_sequence("http-upload", FRAMES, 13);
    let server = spawn("upload", Some(SMALL_LIMITS), &[]);
    let good = dataset_tar(&dir);
    assert!(good.len() < 2 << 20, "the dataset fits the upload limit");

    let escape = raw_tar("../escaped.txt", b"outside the upload folder\n");
    let cases: [(&str, &str, Vec<u8>); 6] = [
        ("path traversal", "/v1/uploads?format=tar", escape),
        (
            "truncated tar",
            "/v1/uploads?format=tar",
            good[..good.len() / 3].to_vec(),
        ),
        (
            "not a zip",
            "/v1/uploads?format=zip",
            b"PK\x03\x04 but nothing else".to_vec(),
        ),
        // Refused from the query alone, before the body is read: small bodies, so the client
        // is not still sending when the answer comes.
        ("unknown format", "/v1/uploads?format=rar", b"x".to_vec()),
        ("empty", "/v1/uploads?format=tar", Vec::new()),
        (
            "partial intrinsics",
            "/v1/uploads?format=tar&fx=262.5",
            b"x".to_vec(),
        ),
    ];
    for (what, path, body) in cases {
        send(
            &server,
            "POST",
            path,
            None,
            "application/octet-stream",
            &body,
        )
        .expect_error(400, "invalid_argument", what);
        assert_healthy(&server, what);
    }
    let data_parent = server.data_dir().parent().expect("parent");
    for candidate in [
        data_parent.join("escaped.txt"),
        server.data_dir().join("escaped.txt"),
    ] {
        assert!(!candidate.exists(), "{} was written", candidate.display());
    }
    let oversized = raw_post_status(
        &server,
        "/v1/uploads?format=tar",
        "application/x-tar",
        vec![0; 3 << 20],
    );
    assert_eq!(oversized, 413, "upload over max_upload_bytes");
    assert_healthy(&server, "oversized upload");

    let created = send(
        &server,
        "POST",
        "/v1/uploads?format=tar",
        None,
        "application/x-tar",
        &good,
    );
    assert_eq!(created.status, 201, "{}", created.body);
    let id = created.json()["id"].as_str().expect("id").to_string();
    let info = wait_finished(&server, &id, None);
    assert_eq!(info["kind"], "upload", "{info}");
    assert_eq!(info["frames_processed"], FRAMES as u64, "{info}");
    let trajectory = get(&server, &format!("/v1/sessions/{id}/trajectory"), None);
    assert_eq!(
        tum_lines(&trajectory.body).len(),
        FRAMES,
        "{}",
        trajectory.body
    );
}
