//! The test client: HTTP requests (ureq), raw-socket requests, WebSocket (tungstenite) and
//! server-sent events, plus the synthetic data they send. The test modules glob-import it (`use super::client::*`)
//! together with the few types it re-exports.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
pub use std::path::{Path, PathBuf};
use std::sync::mpsc;
pub use std::time::{Duration, Instant};

pub use relfusion_proto::Message as _;
pub use relfusion_proto::v1::{
    ClientMessage, EndOfStream, ErrorCode, Frame, ImageEncoding, ServerMessage, client_message,
    server_message,
};
pub use relfusion_slam::dataset::tum::TumSequence;
pub use relfusion_tests::{Relfusiond, synth_sequence, temp_dir};
pub use serde_json::{Value, json};
use tungstenite::stream::MaybeTlsStream;

pub type Socket = tungstenite::WebSocket<MaybeTlsStream<TcpStream>>;

/// Limits small enough to exceed cheaply; a 320×240 synthetic PNG is ~130 KB.
pub const SMALL_LIMITS: &str = "[limits]\nmax_frame_bytes = 262144\nmax_upload_bytes = 2097152\n";

pub fn spawn(tag: &str, limits: Option<&str>, envs: &[(&str, &str)]) -> Relfusiond {
    let dir = temp_dir(&format!("http-{tag}"));
    let mut args: Vec<PathBuf> = Vec::new();
    if let Some(toml) = limits {
        let path = dir.join("relfusiond.toml");
        std::fs::write(&path, toml).expect("write config");
        args.extend(["--config".into(), path]);
    }
    Relfusiond::spawn(&dir.join("data"), args, envs)
}

pub fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(60)))
        .build()
        .into()
}

/// A response as (status, body text).
#[derive(Debug)]
pub struct Reply {
    pub status: u16,
    pub body: String,
}

impl Reply {
    pub fn json(&self) -> Value {
        serde_json::from_str(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {:?}", self.body))
    }

    /// Asserts the API's error shape with this status and code; returns the message.
    pub fn expect_error(&self, status: u16, code: &str, what: &str) -> String {
        assert_eq!(self.status, status, "{what}: {}", self.body);
        let json = self.json();
        assert_eq!(json["error"]["code"], code, "{what}: {json}");
        let message = json["error"]["message"].as_str().unwrap_or_default();
        assert!(!message.is_empty(), "{what}: empty message");
        message.to_string()
    }
}

pub fn reply(result: Result<ureq::http::Response<ureq::Body>, ureq::Error>) -> Reply {
    let mut response = result.expect("HTTP request");
    let status = response.status().as_u16();
    let body = response.body_mut().read_to_string().expect("read body");
    Reply { status, body }
}

pub fn get(server: &Relfusiond, path: &str, token: Option<&str>) -> Reply {
    let mut request = agent().get(format!("{}{path}", server.url()));
    if let Some(token) = token {
        request = request.header("Authorization", format!("Bearer {token}"));
    }
    reply(request.call())
}

pub fn send(
    server: &Relfusiond,
    method: &str,
    path: &str,
    token: Option<&str>,
    content_type: &str,
    body: &[u8],
) -> Reply {
    let url = format!("{}{path}", server.url());
    let agent = agent();
    let auth = token.map(|t| format!("Bearer {t}"));
    match method {
        "DELETE" => {
            let mut request = agent.delete(url);
            if let Some(auth) = &auth {
                request = request.header("Authorization", auth);
            }
            reply(request.call())
        }
        _ => {
            let mut request = agent.post(url).content_type(content_type);
            if let Some(auth) = &auth {
                request = request.header("Authorization", auth);
            }
            reply(request.send(body))
        }
    }
}

pub fn post_json(server: &Relfusiond, path: &str, token: Option<&str>, body: &Value) -> Reply {
    send(
        server,
        "POST",
        path,
        token,
        "application/json",
        body.to_string().as_bytes(),
    )
}

pub fn assert_healthy(server: &Relfusiond, after: &str) {
    let health = get(server, "/healthz", None);
    assert_eq!(
        (health.status, health.body.as_str()),
        (200, "ok"),
        "after {after}"
    );
}

/// Sends a request with a raw socket and returns the status: bodies over a limit are refused
/// before they are read, and a socket client is the one that reliably sees that answer.
pub fn raw_post_status(server: &Relfusiond, path: &str, content_type: &str, body: Vec<u8>) -> u16 {
    let mut stream = TcpStream::connect(server.addr()).expect("connect");
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .expect("timeout");
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: {}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        server.addr(),
        body.len()
    );
    let mut writer = stream.try_clone().expect("clone socket");
    let sender = std::thread::spawn(move || {
        let _ = writer.write_all(head.as_bytes());
        let _ = writer.write_all(&body);
    });
    let mut status_line = String::new();
    BufReader::new(&mut stream)
        .read_line(&mut status_line)
        .expect("read status line");
    let _ = stream.shutdown(std::net::Shutdown::Both);
    let _ = sender.join();
    status_line
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no status in {status_line:?}"))
}

pub fn camera_json(seq: &TumSequence) -> Value {
    let c = &seq.camera;
    json!({ "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height })
}

pub fn create_session(server: &Relfusiond, seq: &TumSequence, token: Option<&str>) -> String {
    let created = post_json(
        server,
        "/v1/sessions",
        token,
        &json!({ "camera": camera_json(seq), "policy": "wait" }),
    );
    assert_eq!(created.status, 201, "{}", created.body);
    let json = created.json();
    assert_eq!(json["session"]["id"], json["id"], "{json}");
    json["id"].as_str().expect("id").to_string()
}

pub fn frame_bytes(seq: &TumSequence, i: usize) -> Vec<u8> {
    std::fs::read(&seq.frames[i].rgb).expect("read frame")
}

pub fn post_frame(server: &Relfusiond, id: &str, seq: &TumSequence, i: usize) -> Reply {
    let path = format!(
        "/v1/sessions/{id}/frames?timestamp={}&frame_id={i}",
        seq.frames[i].timestamp
    );
    send(
        server,
        "POST",
        &path,
        None,
        "image/png",
        &frame_bytes(seq, i),
    )
}

pub fn ws_connect(server: &Relfusiond, id: &str, token: Option<&str>) -> Result<Socket, u16> {
    use tungstenite::client::IntoClientRequest;
    let url = format!("ws://{}/v1/sessions/{id}/stream", server.addr());
    let mut request = url.into_client_request().expect("ws request");
    if let Some(token) = token {
        let value = format!("Bearer {token}").parse().expect("header value");
        request.headers_mut().insert("Authorization", value);
    }
    match tungstenite::connect(request) {
        Ok((socket, _)) => {
            if let MaybeTlsStream::Plain(tcp) = socket.get_ref() {
                tcp.set_read_timeout(Some(Duration::from_secs(60)))
                    .expect("timeout");
            }
            Ok(socket)
        }
        Err(tungstenite::Error::Http(response)) => Err(response.status().as_u16()),
        Err(e) => panic!("websocket connect: {e}"),
    }
}

pub fn ws_send(socket: &mut Socket, message: client_message::Message) {
    let bytes = ClientMessage {
        message: Some(message),
    }
    .encode_to_vec();
    socket
        .send(tungstenite::Message::binary(bytes))
        .expect("ws send");
}

pub fn ws_frame(seq: &TumSequence, i: usize, image: Vec<u8>) -> client_message::Message {
    client_message::Message::Frame(Frame {
        frame_id: i as u64,
        timestamp: seq.frames[i].timestamp,
        image,
        encoding: ImageEncoding::Png as i32,
        camera: None,
    })
}

/// The next protobuf message from the server; `None` once it closed the socket.
pub fn ws_next(socket: &mut Socket) -> Option<server_message::Message> {
    loop {
        match socket.read() {
            Ok(tungstenite::Message::Binary(data)) => {
                let message = ServerMessage::decode(data).expect("server sends ServerMessage");
                return Some(message.message.expect("a ServerMessage with a message"));
            }
            Ok(tungstenite::Message::Close(_)) => return None,
            Ok(_) => continue,
            Err(tungstenite::Error::ConnectionClosed | tungstenite::Error::AlreadyClosed) => {
                return None;
            }
            Err(e) => panic!("ws read: {e}"),
        }
    }
}

/// Sets how long a read on `socket` waits (a plain TCP socket; no TLS in these tests).
pub fn set_ws_read_timeout(socket: &mut Socket, timeout: Duration) {
    if let MaybeTlsStream::Plain(tcp) = socket.get_mut() {
        tcp.set_read_timeout(Some(timeout)).expect("timeout");
    }
}

/// The next message, or `None` when none came within the socket's read timeout.
pub fn ws_try_next(socket: &mut Socket) -> Option<server_message::Message> {
    match socket.read() {
        Ok(tungstenite::Message::Binary(data)) => {
            let message = ServerMessage::decode(data).expect("server sends ServerMessage");
            Some(message.message.expect("a ServerMessage with a message"))
        }
        Ok(_) => None,
        Err(tungstenite::Error::Io(e))
            if matches!(
                e.kind(),
                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
            ) =>
        {
            None
        }
        Err(e) => panic!("ws read: {e}"),
    }
}

/// Reads `/events` on a thread until `finished`/`failed`; returns once the stream is open
/// (the server has subscribed), so no event after this call is missed.
pub fn follow_events(
    server: &Relfusiond,
    id: &str,
) -> std::thread::JoinHandle<Vec<(String, Value)>> {
    follow_events_as(server, id, None)
}

/// [`follow_events`] with a bearer token.
pub fn follow_events_as(
    server: &Relfusiond,
    id: &str,
    token: Option<&str>,
) -> std::thread::JoinHandle<Vec<(String, Value)>> {
    let url = format!("{}/v1/sessions/{id}/events", server.url());
    let auth = token.map(|t| format!("Bearer {t}"));
    let (opened, is_open) = mpsc::channel();
    let handle = std::thread::spawn(move || {
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .timeout_global(Some(Duration::from_secs(80)))
            .build()
            .into();
        let mut request = agent.get(&url);
        if let Some(auth) = &auth {
            request = request.header("Authorization", auth);
        }
        let response = request.call().expect("open /events");
        let content_type = response
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default()
            .to_string();
        assert!(
            content_type.starts_with("text/event-stream"),
            "{content_type}"
        );
        let _ = opened.send(());
        let mut events = Vec::new();
        let mut name = String::new();
        for line in BufReader::new(response.into_body().into_reader()).lines() {
            let line = line.expect("read SSE line");
            if let Some(event) = line.strip_prefix("event:") {
                name = event.trim().to_string();
            } else if let Some(data) = line.strip_prefix("data:") {
                let value: Value = serde_json::from_str(data.trim()).expect("SSE data is JSON");
                let done = name == "finished" || name == "failed";
                events.push((std::mem::take(&mut name), value));
                if done {
                    break;
                }
            }
        }
        events
    });
    is_open
        .recv_timeout(Duration::from_secs(30))
        .expect("the SSE stream opens");
    handle
}

pub fn wait_finished(server: &Relfusiond, id: &str, token: Option<&str>) -> Value {
    let deadline = Instant::now() + Duration::from_secs(75);
    loop {
        let info = get(server, &format!("/v1/sessions/{id}"), token);
        assert_eq!(info.status, 200, "{}", info.body);
        let info = info.json();
        match info["state"].as_str() {
            Some("finished") => return info,
            Some("failed") => panic!("session failed: {info}\n{}", server.log()),
            _ if Instant::now() > deadline => panic!("not finished in time: {info}"),
            _ => std::thread::sleep(Duration::from_millis(200)),
        }
    }
}

/// Non-comment lines of a TUM file.
pub fn tum_lines(text: &str) -> Vec<Vec<f64>> {
    text.lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            l.split_whitespace()
                .map(|v| v.parse().expect("number"))
                .collect()
        })
        .collect()
}

/// The TUM part of a synthetic sequence (no depth) as a tar with one top folder.
pub fn dataset_tar(dir: &Path) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    for file in ["rgb.txt", "calibration.txt", "groundtruth.txt"] {
        builder
            .append_path_with_name(dir.join(file), format!("seq/{file}"))
            .expect("tar file");
    }
    builder
        .append_dir_all("seq/rgb", dir.join("rgb"))
        .expect("tar rgb");
    builder.into_inner().expect("tar")
}
