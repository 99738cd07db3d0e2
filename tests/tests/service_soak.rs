//! Soak: the attacks of the hardening issue's holes 3-5 run together for 60 s against a real
//! `relfusiond` on 127.0.0.1 while one honest session streams over the WebSocket:
//! - memory: 8192² cameras, oversized frames, an upload whose PNG claims 12000² pixels;
//! - timeouts: hundreds of connections with half-sent headers and frame bodies that stall one
//!   byte short, re-opened as the server closes them;
//! - uploads: zip bombs, zips with 50 000 entries, uploads that stall mid-body.
//!
//! The honest session must keep getting poses (every 10 s window has some), `/healthz` must
//! answer 200 to every probe, and the server's resident memory must stay under its configured
//! budget; the peak is printed. Every loop is bounded in time; only loopback is used.

use std::io::{Read as _, Write as _};
use std::net::TcpStream;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use relfusion_proto::Message as _;
use relfusion_proto::v1::{ClientMessage, Frame, ImageEncoding, ServerMessage, client_message};
use relfusion_slam::dataset::TumSequence;
use relfusion_tests::attacks::{png_claiming, rss, tar_of, zip_archive};
use relfusion_tests::{Relfusiond, synth_sequence, temp_dir};
use serde_json::{Value, json};

const SOAK: Duration = Duration::from_secs(60);
const BUDGET_MB: u64 = 3072;
/// Two session slots: the honest session's share (1.3 GiB) holds the map of a minute of its
/// 8 fps stream (about 45 keyframes at 320×240).
const CONFIG: &str = "[limits]\nmemory_budget_mb = 3072\nmax_sessions = 2\nmax_buffered_body_mb = 128\n\
    [http]\nheader_timeout_s = 5\nbody_timeout_s = 5\nmax_connections = 768\n";

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(20)))
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

#[test]
fn attacks_together_leave_an_honest_session_its_poses_and_memory_bounded() {
    let dir = synth_sequence("soak", 120, 47);
    let seq = TumSequence::open(&dir, None).expect("synth");
    let work = temp_dir("soak");
    std::fs::write(work.join("c.toml"), CONFIG).expect("config");
    let server = Relfusiond::spawn(
        &work.join("data"),
        ["--config".into(), work.join("c.toml")],
        &[],
    );
    let url = server.url();
    let addr = server.addr().to_string();
    let camera = {
        let c = &seq.camera;
        json!({"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height})
    };
    let (code, body) = {
        let mut r = agent()
            .post(format!("{url}/v1/sessions"))
            .header("Content-Type", "application/json")
            .send(json!({"camera": camera}).to_string().as_bytes())
            .expect("create");
        (
            r.status().as_u16(),
            r.body_mut().read_to_string().expect("body"),
        )
    };
    assert_eq!(code, 201, "{body}");
    let id = serde_json::from_str::<Value>(&body).expect("json")["id"]
        .as_str()
        .expect("id")
        .to_string();

    let stop = Arc::new(AtomicBool::new(false));
    let mut attackers = Vec::new();
    let rounds: Vec<Arc<AtomicU64>> = (0..5).map(|_| Arc::default()).collect();
    // Memory: huge cameras, oversized frames, a PNG header claiming 12000² pixels.
    {
        let (url, id) = (url.clone(), id.clone());
        let png = png_claiming(12000, 12000);
        let bomb = tar_of(&[
            ("seq/rgb.txt", b"0.0 rgb/b.png\n"),
            ("seq/calibration.txt", b"500 500 6000 6000\n"),
            ("seq/rgb/b.png", &png),
        ]);
        attackers.push(attacker(stop.clone(), rounds[0].clone(), move || {
            let a = agent();
            let huge = json!({"camera": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 8192, "height": 8192}});
            let s = status(a.post(format!("{url}/v1/sessions")).header("Content-Type", "application/json").send(huge.to_string().as_bytes()));
            // 503 when the attackers' own stalled bodies hold the body budget.
            assert!(matches!(s, 400 | 503 | 0), "8192² camera: {s}");
            let s = status(a.post(format!("{url}/v1/sessions/{id}/frames?timestamp=1")).header("Content-Type", "image/png").send(&vec![0u8; 9 << 20][..]));
            assert!(matches!(s, 413 | 0), "oversized frame: {s}");
            let s = status(a.post(format!("{url}/v1/uploads?format=tar")).header("Content-Type", "application/x-tar").send(&bomb[..]));
            assert!(matches!(s, 400 | 429 | 503 | 0), "PNG bomb upload: {s}");
        }));
    }
    // Timeouts: half-sent headers and stalled frame bodies, kept up as the server closes them.
    for (k, stalled_bodies) in [(1, false), (2, true)] {
        let (addr, id) = (addr.clone(), id.clone());
        attackers.push(attacker(stop.clone(), rounds[k].clone(), move || {
            let mut held = Vec::new();
            for _ in 0..150 {
                let request = if stalled_bodies {
                    let mut r = format!(
                        "POST /v1/sessions/{id}/frames?timestamp=1 HTTP/1.1\r\nHost: x\r\n\
                         Content-Type: image/png\r\nContent-Length: {}\r\n\r\n",
                        8 << 20
                    )
                    .into_bytes();
                    r.extend_from_slice(&vec![1u8; 1 << 20]);
                    r
                } else {
                    b"GET /healthz HTTP/1.1\r\nHost: x\r\n".to_vec()
                };
                if let Some(s) = open(&addr, &request) {
                    held.push(s);
                }
            }
            std::thread::sleep(Duration::from_secs(3));
        }));
    }
    // Uploads: zip bombs, entry floods, stalled uploads.
    {
        let url = url.clone();
        let bomb = zip_archive(0, 256 << 20);
        let flood = zip_archive(50_000, 0);
        attackers.push(attacker(stop.clone(), rounds[3].clone(), move || {
            let a = agent();
            for body in [&bomb, &flood] {
                let s = status(
                    a.post(format!("{url}/v1/uploads?format=zip"))
                        .header("Content-Type", "application/zip")
                        .send(&body[..]),
                );
                assert!(matches!(s, 413 | 429 | 503 | 0), "zip attack: {s}");
            }
        }));
    }
    {
        let addr = addr.clone();
        attackers.push(attacker(stop.clone(), rounds[4].clone(), move || {
            let head = format!(
                "POST /v1/uploads?format=tar HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-tar\r\n\
                 Content-Length: {}\r\n\r\n",
                1 << 30
            );
            let held: Vec<_> = (0..8).filter_map(|_| open(&addr, head.as_bytes())).collect();
            std::thread::sleep(Duration::from_secs(2));
            drop(held);
        }));
    }

    // The prober: /healthz every 200 ms, and the server's resident memory.
    let failures = Arc::new(AtomicU64::new(0));
    let probes = Arc::new(AtomicU64::new(0));
    let peak = Arc::new(AtomicU64::new(0));
    let prober = {
        let (url, stop, failures, probes, peak) = (
            url.clone(),
            stop.clone(),
            failures.clone(),
            probes.clone(),
            peak.clone(),
        );
        let pid = server.pid();
        std::thread::spawn(move || {
            let a = agent();
            while !stop.load(Ordering::Relaxed) {
                peak.fetch_max(rss(pid), Ordering::Relaxed);
                let s = status(a.get(format!("{url}/healthz")).call());
                probes.fetch_add(1, Ordering::Relaxed);
                if s != 200 {
                    failures.fetch_add(1, Ordering::Relaxed);
                    eprintln!("healthz answered {s}");
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        })
    };

    // The honest client: frames over the WebSocket at 8 fps, poses counted per 10 s.
    let (mut socket, _) =
        tungstenite::connect(format!("ws://{addr}/v1/sessions/{id}/stream")).expect("ws");
    if let tungstenite::stream::MaybeTlsStream::Plain(tcp) = socket.get_ref() {
        tcp.set_read_timeout(Some(Duration::from_millis(20)))
            .expect("timeout");
    }
    let images: Vec<Vec<u8>> = (0..seq.len())
        .map(|i| std::fs::read(&seq.frames[i].rgb).expect("frame"))
        .collect();
    let t0 = Instant::now();
    let mut windows = [0u64; 6];
    let mut sent = 0usize;
    while t0.elapsed() < SOAK {
        let i = sent % images.len();
        let frame = ClientMessage {
            message: Some(client_message::Message::Frame(Frame {
                frame_id: sent as u64,
                timestamp: sent as f64 / 8.0,
                image: images[i].clone(),
                encoding: ImageEncoding::Png as i32,
                camera: None,
            })),
        };
        socket
            .send(tungstenite::Message::binary(frame.encode_to_vec()))
            .expect("the honest stream is not cut");
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
                    let info = agent()
                        .get(format!("{url}/v1/sessions/{id}"))
                        .call()
                        .ok()
                        .and_then(|mut r| r.body_mut().read_to_string().ok());
                    panic!("honest stream broke: {e}; session: {info:?}");
                }
            }
        }
    }
    stop.store(true, Ordering::Relaxed);
    for a in attackers {
        a.join().expect("attacker");
    }
    prober.join().expect("prober");
    let peak = peak.load(Ordering::Relaxed);
    let counts: Vec<u64> = rounds.iter().map(|r| r.load(Ordering::Relaxed)).collect();
    println!(
        "soak: {sent} honest frames, poses per 10 s {windows:?}, attack rounds {counts:?}, \
         {} /healthz probes, peak RSS {} MiB (budget {BUDGET_MB} MiB)",
        probes.load(Ordering::Relaxed),
        peak >> 20
    );
    assert!(
        windows.iter().all(|&n| n > 0),
        "the honest session starved: {windows:?}"
    );
    assert_eq!(failures.load(Ordering::Relaxed), 0, "/healthz failed");
    assert!(probes.load(Ordering::Relaxed) >= 200, "too few probes");
    assert!(
        peak < BUDGET_MB << 20,
        "peak RSS {} MiB over the budget",
        peak >> 20
    );
    let _ = socket.close(None);
    let mut drain = [0u8; 1];
    let _ = socket.get_mut().read(&mut drain);
}
