//! The viewer in a real browser (Debian's headless Chromium, through chromedriver) against a
//! real relfusiond: a synthetic sequence is streamed live by `relfusion stream`; one page
//! watches from the start, a second joins after half of the frames; both must end with one
//! trajectory point per frame of the service's trajectory and the triangles of its mesh.ply,
//! and no page error. The mesh must cover a clear share of a saved screenshot. A token in a
//! link leaves the address bar at once and never replaces a stored one without asking.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use fantoccini::{Client, Locator};
use relfusion_client::browser::{self, Driver};
use relfusion_tests::{Relfusiond, bin_path, ply_faces, synth_sequence, temp_dir};
use serde_json::Value;

const TOKEN: &str = "viewer-secret";
const BACKGROUND: [u8; 3] = [0x15, 0x18, 0x1d];

fn get(server: &Relfusiond, path: &str) -> Vec<u8> {
    let mut response = ureq::get(format!("{}{path}", server.url()))
        .header("Authorization", format!("Bearer {TOKEN}"))
        .call()
        .unwrap_or_else(|e| panic!("GET {path}: {e}"));
    response.body_mut().read_to_vec().expect("body")
}

fn tum_lines(bytes: &[u8]) -> u64 {
    String::from_utf8_lossy(bytes)
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .count() as u64
}

/// Share of the canvas's pixels that differ clearly from the background.
fn covered_share(png: &[u8]) -> f64 {
    let image = image::load_from_memory(png)
        .expect("screenshot PNG")
        .to_rgb8();
    let covered = image
        .pixels()
        .filter(|p| p.0.iter().zip(BACKGROUND).any(|(&c, b)| c.abs_diff(b) > 24))
        .count();
    covered as f64 / (image.width() * image.height()) as f64
}

async fn eval(page: &Client, expression: &str) -> Value {
    browser::eval(page, expression)
        .await
        .unwrap_or_else(|e| panic!("{expression}: {e}"))
}

async fn wait_until(page: &Client, expression: &str, timeout: Duration, what: &str) {
    if let Err(e) = browser::wait_until(page, expression, timeout, what).await {
        panic!("{e}");
    }
}

async fn open(page: &Client, url: &str) {
    page.goto(url)
        .await
        .unwrap_or_else(|e| panic!("{url}: {e}"));
    wait_until(
        page,
        "!!window.relfusionViewer && window.relfusionViewer.ready",
        Duration::from_secs(60),
        "viewer ready",
    )
    .await;
}

async fn counts(page: &Client) -> Value {
    eval(page, "window.relfusionViewer.counts()").await
}

async fn assert_no_errors(page: &Client, what: &str) {
    let errors = eval(page, "window.relfusionViewer.errors").await;
    assert_eq!(errors, Value::Array(vec![]), "{what}: page errors");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_viewer_follows_a_live_session_and_a_late_joiner_catches_up() {
    const FRAMES: usize = 60;
    let t0 = std::time::Instant::now();
    let stage = |what: &str| eprintln!("{:6.1} s  {what}", t0.elapsed().as_secs_f64());
    let sequence = synth_sequence("viewer", FRAMES, 23);
    let work = temp_dir("viewer");
    let server = Relfusiond::spawn(
        &work.join("data"),
        Vec::<PathBuf>::new(),
        &[("RELFUSIOND_TOKENS", &format!("viewer:{TOKEN}"))],
    );
    let mut driver = Driver::start(&work).expect("chromedriver");

    // The first browser is up before the stream starts: Chromium's start must not eat into the
    // seconds the session runs.
    let early = driver.browser(1024, 700).await.expect("browser");

    // The camera: a real client streaming at a camera's pace, every frame processed.
    let mut stream = Command::new(bin_path("relfusion"))
        .arg("stream")
        .arg(&sequence)
        .args([
            "--server",
            &server.url(),
            "--token",
            TOKEN,
            "--fps",
            "8",
            "--wait",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("relfusion stream");
    let (lines_tx, lines) = mpsc::channel::<Value>();
    let stdout = stream.stdout.take().expect("stdout");
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Ok(value) = serde_json::from_str(&line) {
                let _ = lines_tx.send(value);
            }
        }
    });
    let first = lines
        .recv_timeout(Duration::from_secs(60))
        .expect("session line");
    let id = first["session"].as_str().expect("session id").to_string();
    let view = format!("{}/view/{id}?access_token={TOKEN}", server.url());

    stage("streaming");
    open(&early, &view).await;

    // Join late: after half of the frames have a pose.
    let mut poses = 0;
    while poses < FRAMES / 2 {
        let line = lines
            .recv_timeout(Duration::from_secs(120))
            .expect("pose lines");
        if line.get("frame_id").is_some() {
            poses += 1;
        }
    }
    stage("half of the frames posed");
    let late = driver.browser(1024, 700).await.expect("browser");
    open(&late, &view).await;
    let late_start = counts(&late).await;
    assert!(
        late_start["trajectoryPoints"].as_u64().unwrap_or(0) > 0,
        "the late page starts from the snapshot: {late_start}"
    );

    let status = tokio::task::spawn_blocking(move || stream.wait())
        .await
        .expect("join")
        .expect("wait");
    assert!(status.success(), "relfusion stream failed");
    stage("stream finished");
    let trajectory = tum_lines(&get(&server, &format!("/v1/sessions/{id}/trajectory")));
    let triangles = ply_faces(&get(&server, &format!("/v1/sessions/{id}/mesh.ply")));
    assert!(
        trajectory >= (FRAMES as u64) * 9 / 10,
        "{trajectory} poses of {FRAMES}"
    );
    assert!(triangles > 1000, "a mesh: {triangles} triangles");

    for (page, what) in [(&early, "watching from the start"), (&late, "joining late")] {
        wait_until(
            page,
            "window.relfusionViewer.finished",
            Duration::from_secs(120),
            what,
        )
        .await;
        let live = eval(page, "window.relfusionViewer.live").await;
        assert_eq!(
            live["trajectoryPoints"].as_u64(),
            Some(trajectory),
            "{what}: {live}"
        );
        assert_eq!(
            live["meshTriangles"].as_u64(),
            Some(triangles),
            "{what}: {live}"
        );
        let shown = counts(page).await;
        assert_eq!(
            shown["trajectoryPoints"].as_u64(),
            Some(trajectory),
            "{what}: {shown}"
        );
        assert_eq!(
            shown["meshTriangles"].as_u64(),
            Some(triangles),
            "{what}: {shown}"
        );
        assert_no_errors(page, what).await;
    }

    stage("both pages agree with the service");
    // The screenshot: the mesh alone must cover a clear share of the canvas.
    eval(
        &early,
        "(window.relfusionViewer.setLayers({mesh: true, trajectory: false, keyframes: false, camera: false, grid: false}), window.relfusionViewer.scene.frameAll(true), true)",
    )
    .await;
    tokio::time::sleep(Duration::from_millis(800)).await;
    let canvas = early
        .find(Locator::Css("#canvas canvas"))
        .await
        .expect("canvas");
    let mesh_only = canvas.screenshot().await.expect("screenshot");
    std::fs::write(work.join("viewer-mesh.png"), &mesh_only).expect("save screenshot");
    let share = covered_share(&mesh_only);
    assert!(
        share > 0.10,
        "the mesh covers {:.1} % of the canvas",
        share * 100.0
    );
    eval(
        &early,
        "(window.relfusionViewer.setLayers({mesh: true, trajectory: true, keyframes: true, camera: true, grid: true}), window.relfusionViewer.scene.frameAll(true), true)",
    )
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let page_png = early.screenshot().await.expect("page screenshot");
    std::fs::write(work.join("viewer.png"), &page_png).expect("save screenshot");
    if let Some(path) = std::env::var_os("RELFUSION_VIEWER_SCREENSHOT") {
        std::fs::write(path, &page_png).expect("save screenshot copy");
    }
    eprintln!(
        "viewer screenshots: {} (mesh {:.1} % of the canvas)",
        work.join("viewer.png").display(),
        share * 100.0
    );

    // A finished session: mesh.glb and the final trajectory. The token is remembered.
    early
        .goto(&format!("{}/view/{id}", server.url()))
        .await
        .expect("goto");
    wait_until(
        &early,
        "!!window.relfusionViewer && window.relfusionViewer.finished",
        Duration::from_secs(60),
        "finished view",
    )
    .await;
    let finished = counts(&early).await;
    assert_eq!(
        finished["trajectoryPoints"].as_u64(),
        Some(trajectory),
        "{finished}"
    );
    assert_eq!(
        finished["meshTriangles"].as_u64(),
        Some(triangles),
        "{finished}"
    );
    assert_no_errors(&early, "finished session").await;

    // The sessions list links to the viewer.
    early
        .goto(&format!("{}/", server.url()))
        .await
        .expect("goto /");
    let link = early
        .wait()
        .at_most(Duration::from_secs(30))
        .for_element(Locator::Css(&format!("a[href='/view/{id}']")))
        .await
        .expect("a link to the session's viewer");
    assert_eq!(link.text().await.expect("text"), id);

    // A link's token is taken once: gone from the address bar (and history) at once.
    let search = eval(&late, "location.search").await;
    assert_eq!(
        search,
        Value::String(String::new()),
        "the token stays in the URL"
    );
    // A link with another token does not sign this browser in as someone else without
    // asking: the page asks, the answer is no, the stored token stays.
    early
        .goto(&format!(
            "{}/view/{id}?access_token=attacker-token",
            server.url()
        ))
        .await
        .expect("goto");
    let question = early
        .get_alert_text()
        .await
        .expect("the page asks before replacing the token");
    assert!(question.contains("token"), "{question}");
    early.dismiss_alert().await.expect("dismiss");
    let stored = eval(&early, "localStorage.getItem('relfusion.token')").await;
    assert_eq!(
        stored,
        Value::String(TOKEN.into()),
        "the stored token was replaced"
    );
    let search = eval(&early, "location.search").await;
    assert_eq!(
        search,
        Value::String(String::new()),
        "the other token stays in the URL"
    );

    early.close().await.expect("close");
    late.close().await.expect("close");
}
