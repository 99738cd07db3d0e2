//! A real `relfusiond` process on a loopback port answers its health and version endpoints.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};

use relfusion_tests::{bin_path, temp_dir};

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn get(addr: &str, path: &str) -> String {
    let mut stream = TcpStream::connect(addr).expect("connect");
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .expect("send");
    let mut response = String::new();
    stream.read_to_string(&mut response).expect("read response");
    response
}

#[test]
fn relfusiond_serves_health_and_version() {
    let data = temp_dir("health");
    let mut child = Command::new(bin_path("relfusiond"))
        .args(["--listen", "127.0.0.1:0", "--data-dir"])
        .arg(&data)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start relfusiond");
    let stdout = child.stdout.take().expect("stdout");
    let server = Server(child);
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("read the listening line");
    let addr = line
        .trim()
        .strip_prefix("listening on ")
        .expect("listening line")
        .to_string();

    let health = get(&addr, "/healthz");
    assert!(health.starts_with("HTTP/1.1 200"), "{health}");
    assert!(health.ends_with("ok"), "{health}");
    let version = get(&addr, "/v1/version");
    assert!(version.contains("\"name\":\"relfusiond\""), "{version}");
    let missing = get(&addr, "/v1/nope");
    assert!(missing.starts_with("HTTP/1.1 404"), "{missing}");
    drop(server);
}

#[test]
fn relfusiond_prints_a_default_config_it_can_read_back() {
    let out = Command::new(bin_path("relfusiond"))
        .arg("--print-default-config")
        .output()
        .expect("run relfusiond");
    assert!(out.status.success());
    let dir = temp_dir("config");
    let path = dir.join("relfusiond.toml");
    std::fs::write(&path, &out.stdout).expect("write config");
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, "listen = 12\n").expect("write bad config");
    let status = Command::new(bin_path("relfusiond"))
        .args(["--config"])
        .arg(&bad)
        .stderr(Stdio::piped())
        .output()
        .expect("run relfusiond");
    assert!(
        !status.status.success(),
        "a malformed config must be refused"
    );
    assert!(String::from_utf8_lossy(&status.stderr).contains("bad.toml"));
}
