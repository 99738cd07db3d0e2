//! The hardening issue's holes, each tried as an attacker would against a real `relfusiond`
//! process on 127.0.0.1 (one module per hole; every test failed on the server before the
//! fixes): upload lists that reach outside their folder (`paths`), memory without bounds
//! (`memory`), connections, bodies and sessions without timeouts (`timeouts`), uploads without
//! admission or expansion bounds (`uploads`), and failures that cost more than their session
//! (`failures`). Zenoh's holes are in `service_zenoh::intruder`; all attacks at once in
//! `service_soak`.

#[path = "../service_http/client.rs"]
#[allow(dead_code, unused_imports)]
mod client;
mod failures;
mod memory;
mod paths;
mod round_two;
mod timeouts;
mod uploads;

use std::io::Write as _;

use client::*;
pub use relfusion_tests::attacks::{rss, tar_of};

/// A TUM-layout tar: `seq/rgb.txt` with `rgb_txt`, `seq/calibration.txt` and the images of
/// `dir` (a synthetic sequence) under `seq/rgb/`.
pub fn tar_with_list(dir: &Path, rgb_txt: &str) -> Vec<u8> {
    let mut files: Vec<(String, Vec<u8>)> = vec![
        ("seq/rgb.txt".into(), rgb_txt.as_bytes().to_vec()),
        (
            "seq/calibration.txt".into(),
            std::fs::read(dir.join("calibration.txt")).expect("calibration"),
        ),
    ];
    for entry in std::fs::read_dir(dir.join("rgb")).expect("rgb folder") {
        let path = entry.expect("entry").path();
        let name = path
            .file_name()
            .expect("name")
            .to_string_lossy()
            .into_owned();
        files.push((
            format!("seq/rgb/{name}"),
            std::fs::read(&path).expect("image"),
        ));
    }
    let entries: Vec<(&str, &[u8])> = files.iter().map(|(n, d)| (n.as_str(), &d[..])).collect();
    tar_of(&entries)
}

/// The `rgb.txt` of `dir`.
pub fn rgb_txt(dir: &Path) -> String {
    std::fs::read_to_string(dir.join("rgb.txt")).expect("rgb.txt")
}

/// Uploads `body` (tar) as `token`.
pub fn upload(server: &Relfusiond, token: Option<&str>, body: &[u8]) -> Reply {
    send(
        server,
        "POST",
        "/v1/uploads?format=tar",
        token,
        "application/x-tar",
        body,
    )
}

/// Waits until the session's info satisfies `done` (75 s at most); returns it.
pub fn wait_info(
    server: &Relfusiond,
    id: &str,
    token: Option<&str>,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + Duration::from_secs(75);
    loop {
        let info = get(server, &format!("/v1/sessions/{id}"), token);
        if info.status == 200 && done(&info.json()) {
            return info.json();
        }
        assert!(
            Instant::now() < deadline,
            "session {id} never got there: {} {}\n{}",
            info.status,
            info.body,
            server.log()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Writes raw bytes on a fresh connection and returns it.
pub fn raw(server: &Relfusiond, bytes: &[u8]) -> std::net::TcpStream {
    let mut stream = std::net::TcpStream::connect(server.addr()).expect("connect");
    stream.write_all(bytes).expect("write");
    stream
}
