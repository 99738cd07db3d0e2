//! Soak: the attacks of both hardening rounds run together for 60 s against a real
//! `relfusiond` on 127.0.0.1 (tokens on, Zenoh listening) while two honest tenants, alice and
//! bob, each stream a session over the WebSocket:
//! - round one: 8192² cameras, oversized frames, a PNG claiming 12000² pixels, hundreds of
//!   connections with half-sent headers and frame bodies stalled one byte short, zip bombs,
//!   zips of 50 000 entries, uploads that stall mid-body;
//! - round two (issue 34, items 1-7), by mallory (a token) and strangers (none): lists naming
//!   one image 20 000 times at one instant, million-line lists, images padded past the frame
//!   limit, stalled 8 MiB bodies without a token and with one, WebSockets that never read
//!   nor answer a ping, floods of event streams, 100 MiB Zenoh messages.
//!
//! Both honest sessions must keep getting poses (every 10 s window has some), `/healthz` must
//! answer 200 within 1 s to every probe, and the server's peak resident memory must stay under
//! its configured budget; it is printed. Every loop is bounded in time; only loopback is used.

use std::io::{Read as _, Write as _};
use std::net::TcpStream;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use relfusion_proto::Message as _;
use relfusion_proto::v1::{ClientMessage, Frame, ImageEncoding, ServerMessage, client_message};
use relfusion_slam::dataset::TumSequence;
use relfusion_tests::attacks::{peak_rss, png_claiming, tar_of, tum_tar, zip_archive};
use relfusion_tests::{Relfusiond, synth_sequence, temp_dir};
use serde_json::{Value, json};
use tungstenite::client::IntoClientRequest as _;
use zenoh::Wait as _;

const SOAK: Duration = Duration::from_secs(60);
const BUDGET_MB: u64 = 4096;
/// Three session slots (alice, bob, mallory's live session): each honest share (1.3 GiB)
/// holds the map of a minute of its 8 fps stream (about 45 keyframes at 320×240).
const CONFIG: &str = "[limits]\nmemory_budget_mb = 4096\nmax_sessions = 3\nmax_buffered_body_mb = 128\n\
    [http]\nheader_timeout_s = 5\nbody_timeout_s = 5\nmax_connections = 768\nstream_idle_timeout_s = 6\n\
    [quotas]\nmax_active_sessions = 1\n";
const TOKENS: &str = "alice:tok-a,bob:tok-b,mallory:tok-m";

fn agent(timeout: Duration) -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(timeout))
        .build()
        .into()
}

/// Status of a request, 0 when the connection failed (the server may close attackers).
fn status(result: Result<ureq::http::Response<ureq::Body>, ureq::Error>) -> u16 {
    result.map_or(0, |mut r| {
        let _ = r.body_mut().read_to_vec();
        r.status().as_u16()
    })
}

/// The JSON body of a response (Null when there is none).
fn json_of(result: Result<ureq::http::Response<ureq::Body>, ureq::Error>) -> (u16, Value) {
    result.map_or((0, Value::Null), |mut r| {
        let body = r.body_mut().read_to_string().unwrap_or_default();
        (
            r.status().as_u16(),
            serde_json::from_str(&body).unwrap_or(Value::Null),
        )
    })
}

/// Raw bytes on a new connection (`None` when the server does not take it now).
fn open(addr: &str, bytes: &[u8]) -> Option<TcpStream> {
    let mut stream = TcpStream::connect(addr).ok()?;
    stream
        .set_write_timeout(Some(Duration::from_secs(2)))
        .ok()?;
    stream.write_all(bytes).ok()?;
    Some(stream)
}

/// Repeats `attack` until `stop`, counting rounds.
fn attacker(
    stop: Arc<AtomicBool>,
    rounds: Arc<AtomicU64>,
    mut attack: impl FnMut() + Send + 'static,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        while !stop.load(Ordering::Relaxed) {
            attack();
            rounds.fetch_add(1, Ordering::Relaxed);
        }
    })
}

fn camera_of(seq: &TumSequence) -> Value {
    let c = &seq.camera;
    json!({"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height})
}

/// A new live session of `token`'s tenant.
fn create(url: &str, token: &str, seq: &TumSequence) -> String {
    let (code, body) = json_of(
        agent(Duration::from_secs(20))
            .post(format!("{url}/v1/sessions"))
            .header("Authorization", format!("Bearer {token}"))
            .header("Content-Type", "application/json")
            .send(json!({"camera": camera_of(seq)}).to_string().as_bytes()),
    );
    assert_eq!(code, 201, "{body}");
    body["id"].as_str().expect("id").to_string()
}

/// One honest tenant: frames over the WebSocket at 8 fps for the soak's length; poses
/// counted per 10 s window.
fn honest(
    addr: String,
    url: String,
    id: String,
    token: &'static str,
    images: Arc<Vec<Vec<u8>>>,
) -> [u64; 6] {
    let mut request = format!("ws://{addr}/v1/sessions/{id}/stream")
        .into_client_request()
        .expect("ws request");
    request.headers_mut().insert(
        "Authorization",
        format!("Bearer {token}").parse().expect("header"),
    );
    let (mut socket, _) = tungstenite::connect(request).expect("ws");
    if let tungstenite::stream::MaybeTlsStream::Plain(tcp) = socket.get_ref() {
        tcp.set_read_timeout(Some(Duration::from_millis(20)))
            .expect("timeout");
    }
    let t0 = Instant::now();
    let mut windows = [0u64; 6];
    let mut sent = 0usize;
    while t0.elapsed() < SOAK {
        let frame = ClientMessage {
            message: Some(client_message::Message::Frame(Frame {
                frame_id: sent as u64,
                timestamp: sent as f64 / 8.0,
                image: images[sent % images.len()].clone(),
                encoding: ImageEncoding::Png as i32,
                camera: None,
            })),
        };
        socket
            .send(tungstenite::Message::binary(frame.encode_to_vec()))
            .unwrap_or_else(|e| panic!("{token}'s stream was cut: {e}"));
        sent += 1;
        let next = t0 + Duration::from_millis(125 * sent as u64);
        while Instant::now() < next {
            match socket.read() {
                Ok(tungstenite::Message::Binary(data)) => {
                    let message = ServerMessage::decode(data).expect("ServerMessage");
                    if let Some(relfusion_proto::v1::server_message::Message::Pose(_)) =
                        message.message
                    {
                        let w = (t0.elapsed().as_secs() / 10).min(5) as usize;
                        windows[w] += 1;
                    }
                }
                Ok(_) => {}
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(e) => {
                    let info = agent(Duration::from_secs(5))
                        .get(format!("{url}/v1/sessions/{id}"))
                        .header("Authorization", format!("Bearer {token}"))
                        .call()
                        .ok()
                        .and_then(|mut r| r.body_mut().read_to_string().ok());
                    panic!("{token}'s stream broke: {e}; session: {info:?}");
                }
            }
        }
    }
    let _ = socket.close(None);
    let mut drain = [0u8; 1];
    let _ = socket.get_mut().read(&mut drain);
    windows
}

#[test]
fn attacks_together_leave_honest_tenants_their_poses_and_memory_bounded() {
    let dir = synth_sequence("soak", 120, 47);
    let seq = TumSequence::open(&dir, None).expect("synth");
    let work = temp_dir("soak");
    std::fs::write(work.join("c.toml"), CONFIG).expect("config");
    let (server, endpoint) = Relfusiond::spawn_zenoh_peer(
        &work.join("data"),
        &[
            std::ffi::OsStr::new("--config"),
            work.join("c.toml").as_os_str(),
        ],
        &[("RELFUSIOND_TOKENS", TOKENS)],
    );
    let url = server.url();
    let addr = server.addr().to_string();
    let alice = create(&url, "tok-a", &seq);
    let bob = create(&url, "tok-b", &seq);
    let mallory = create(&url, "tok-m", &seq);
    let png = std::fs::read(&seq.frames[0].rgb).expect("frame");

    let stop = Arc::new(AtomicBool::new(false));
    let mut attackers = Vec::new();
    let rounds: Vec<Arc<AtomicU64>> = (0..9).map(|_| Arc::default()).collect();
    let bearer_m = "Bearer tok-m";
    // Round one, memory: huge cameras, oversized frames, a PNG header claiming 12000² pixels.
    {
        let (url, id) = (url.clone(), mallory.clone());
        let bomb = tar_of(&[
            ("seq/rgb.txt", b"0.0 rgb/b.png\n"),
            ("seq/calibration.txt", b"500 500 6000 6000\n"),
            ("seq/rgb/b.png", &png_claiming(12000, 12000)),
        ]);
        attackers.push(attacker(stop.clone(), rounds[0].clone(), move || {
            let a = agent(Duration::from_secs(20));
            let huge = json!({"camera": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 8192, "height": 8192}});
            let s = status(a.post(format!("{url}/v1/sessions")).header("Authorization", bearer_m).header("Content-Type", "application/json").send(huge.to_string().as_bytes()));
            assert!(matches!(s, 400 | 429 | 503 | 0), "8192² camera: {s}");
            let s = status(a.post(format!("{url}/v1/sessions/{id}/frames?timestamp=1")).header("Authorization", bearer_m).header("Content-Type", "image/png").send(&vec![0u8; 9 << 20][..]));
            assert!(matches!(s, 413 | 0), "oversized frame: {s}");
            let s = status(a.post(format!("{url}/v1/uploads?format=tar")).header("Authorization", bearer_m).header("Content-Type", "application/x-tar").send(&bomb[..]));
            assert!(matches!(s, 400 | 429 | 503 | 0), "PNG bomb upload: {s}");
            std::thread::sleep(Duration::from_millis(500));
        }));
    }
    // Round one, timeouts: half-sent headers; round two, item 4: 8 MiB bodies stalled one
    // byte in, by strangers and by mallory (a quarter of the budget at most).
    for (k, kind) in [(1, "headers"), (2, "stranger"), (3, "mallory")] {
        let (addr, id) = (addr.clone(), mallory.clone());
        attackers.push(attacker(stop.clone(), rounds[k].clone(), move || {
            let mut held = Vec::new();
            for _ in 0..150 {
                let request = match kind {
                    "headers" => b"GET /healthz HTTP/1.1\r\nHost: x\r\n".to_vec(),
                    _ => {
                        let auth = if kind == "mallory" { "Authorization: Bearer tok-m\r\n" } else { "" };
                        let mut r = format!(
                            "POST /v1/sessions/{id}/frames?timestamp=1 HTTP/1.1\r\nHost: x\r\n{auth}\
                             Content-Type: image/png\r\nContent-Length: {}\r\n\r\n",
                            8 << 20
                        )
                        .into_bytes();
                        r.extend_from_slice(&[1u8; 1024]);
                        r
                    }
                };
                if let Some(s) = open(&addr, &request) {
                    held.push(s);
                }
            }
            std::thread::sleep(Duration::from_secs(3));
        }));
    }
    // Round one, uploads: zip bombs, entry floods, stalled uploads.
    {
        let url = url.clone();
        let bomb = zip_archive(0, 256 << 20);
        let flood = zip_archive(50_000, 0);
        attackers.push(attacker(stop.clone(), rounds[4].clone(), move || {
            let a = agent(Duration::from_secs(20));
            for body in [&bomb, &flood] {
                let s = status(
                    a.post(format!("{url}/v1/uploads?format=zip"))
                        .header("Authorization", bearer_m)
                        .header("Content-Type", "application/zip")
                        .send(&body[..]),
                );
                assert!(matches!(s, 413 | 429 | 503 | 0), "zip attack: {s}");
            }
            std::thread::sleep(Duration::from_millis(500));
        }));
    }
    {
        let addr = addr.clone();
        attackers.push(attacker(stop.clone(), rounds[5].clone(), move || {
            let head = format!(
                "POST /v1/uploads?format=tar HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer tok-m\r\n\
                 Content-Type: application/x-tar\r\nContent-Length: {}\r\n\r\n",
                1 << 30
            );
            let held: Vec<_> = (0..8)
                .filter_map(|_| open(&addr, head.as_bytes()))
                .collect();
            std::thread::sleep(Duration::from_secs(2));
            drop(held);
        }));
    }
    // Items 1-3: repeated stamps, million-line lists, images padded past the frame limit.
    {
        let url = url.clone();
        let repeated = "0 rgb/0.png\n".repeat(20_000);
        let quadratic = tum_tar(&repeated, Some(&repeated), &[("seq/rgb/0.png", &png)]);
        let long = tum_tar(
            &"0 rgb/0.png\n".repeat(1_000_000),
            None,
            &[("seq/rgb/0.png", &png)],
        );
        let mut padded = png.clone();
        padded.resize(64 << 20, 0);
        let padded = tum_tar("0 rgb/p.png\n", None, &[("seq/rgb/p.png", &padded)]);
        attackers.push(attacker(stop.clone(), rounds[6].clone(), move || {
            let a = agent(Duration::from_secs(30));
            for (body, what) in [
                (&quadratic, "repeated"),
                (&long, "long"),
                (&padded, "padded"),
            ] {
                let (s, info) = json_of(
                    a.post(format!("{url}/v1/uploads?format=tar"))
                        .header("Authorization", bearer_m)
                        .header("Content-Type", "application/x-tar")
                        .send(&body[..]),
                );
                assert!(matches!(s, 201 | 400 | 429 | 503 | 0), "{what} list: {s}");
                if let Some(id) = info["id"].as_str() {
                    let _ = status(
                        a.delete(format!("{url}/v1/sessions/{id}"))
                            .header("Authorization", bearer_m)
                            .call(),
                    );
                }
            }
            std::thread::sleep(Duration::from_millis(500));
        }));
    }
    // Items 5 and 6: WebSockets that never read nor answer, and floods of event streams, on
    // mallory's own session.
    {
        let (addr, id) = (addr.clone(), mallory.clone());
        attackers.push(attacker(stop.clone(), rounds[7].clone(), move || {
            let (mut sockets, mut streams) = (Vec::new(), Vec::new());
            for _ in 0..40 {
                let mut request = format!("ws://{addr}/v1/sessions/{id}/stream")
                    .into_client_request()
                    .expect("ws request");
                request.headers_mut().insert("Authorization", "Bearer tok-m".parse().expect("header"));
                if let Ok((socket, _)) = tungstenite::connect(request) {
                    sockets.push(socket);
                }
                let sse = format!(
                    "GET /v1/sessions/{id}/events HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer tok-m\r\n\r\n"
                );
                streams.extend(open(&addr, sse.as_bytes()));
            }
            std::thread::sleep(Duration::from_secs(4));
            drop((sockets, streams));
        }));
    }
    // Item 7: 100 MiB Zenoh messages to keys mallory may and may not use.
    {
        let mut config = zenoh::Config::default();
        for (key, value) in [
            ("mode", "\"client\"".to_string()),
            ("connect/endpoints", format!("[\"{endpoint}\"]")),
            ("scouting/multicast/enabled", "false".into()),
            ("scouting/gossip/enabled", "false".into()),
            ("transport/auth/usrpwd/user", "\"mallory\"".into()),
            ("transport/auth/usrpwd/password", "\"tok-m\"".into()),
        ] {
            config.insert_json5(key, &value).expect("zenoh config");
        }
        let z = zenoh::open(config).wait().expect("mallory's zenoh session");
        attackers.push(attacker(stop.clone(), rounds[8].clone(), move || {
            for key in ["relfusion/tenants/alice/x", "relfusion/tenants/mallory/x"] {
                let _ = z.put(key, vec![9u8; 100 << 20]).wait();
            }
            std::thread::sleep(Duration::from_secs(1));
        }));
    }

    // The prober: /healthz every 200 ms (1 s to answer), and the server's peak memory.
    let failures = Arc::new(AtomicU64::new(0));
    let probes = Arc::new(AtomicU64::new(0));
    let prober = {
        let (url, stop, failures, probes) =
            (url.clone(), stop.clone(), failures.clone(), probes.clone());
        std::thread::spawn(move || {
            let a = agent(Duration::from_secs(1));
            while !stop.load(Ordering::Relaxed) {
                let t = Instant::now();
                let s = status(a.get(format!("{url}/healthz")).call());
                probes.fetch_add(1, Ordering::Relaxed);
                if s != 200 {
                    failures.fetch_add(1, Ordering::Relaxed);
                    eprintln!("healthz answered {s} after {:?}", t.elapsed());
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        })
    };

    let images: Arc<Vec<Vec<u8>>> = Arc::new(
        (0..seq.len())
            .map(|i| std::fs::read(&seq.frames[i].rgb).expect("frame"))
            .collect(),
    );
    let honest_tenants: Vec<_> = [(alice, "tok-a"), (bob, "tok-b")]
        .into_iter()
        .map(|(id, token)| {
            let (addr, url, images) = (addr.clone(), url.clone(), images.clone());
            std::thread::spawn(move || (token, honest(addr, url, id, token, images)))
        })
        .collect();
    let windows: Vec<(&str, [u64; 6])> = honest_tenants
        .into_iter()
        .map(|h| h.join().expect("honest tenant"))
        .collect();
    stop.store(true, Ordering::Relaxed);
    for a in attackers {
        a.join().expect("attacker");
    }
    prober.join().expect("prober");
    let peak = peak_rss(server.pid());
    let counts: Vec<u64> = rounds.iter().map(|r| r.load(Ordering::Relaxed)).collect();
    println!(
        "soak: poses per 10 s {windows:?}, attack rounds {counts:?}, {} /healthz probes, \
         peak RSS {} MiB (budget {BUDGET_MB} MiB)",
        probes.load(Ordering::Relaxed),
        peak >> 20
    );
    for (token, w) in &windows {
        assert!(w.iter().all(|&n| n > 0), "{token}'s session starved: {w:?}");
    }
    assert_eq!(
        failures.load(Ordering::Relaxed),
        0,
        "/healthz failed or was slow"
    );
    assert!(probes.load(Ordering::Relaxed) >= 200, "too few probes");
    assert!(
        peak < BUDGET_MB << 20,
        "peak RSS {} MiB over the budget",
        peak >> 20
    );
}
