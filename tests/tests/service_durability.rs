//! Durability: an acknowledged upload survives `kill -9` mid-processing, its processing re-runs
//! after the restart and completes with a pose for every frame, and the finished results stay
//! downloadable across another crash. Real `relfusiond`, real HTTP, real files.

use std::path::Path;
use std::time::{Duration, Instant};

use relfusion_slam::dataset::trajectory::{parse_tum_trajectory, read_tum_trajectory};
use relfusion_slam::eval::{AlignMode, ate};
use relfusion_tests::{Relfusiond, bin_path, synth_sequence, temp_dir};
use serde_json::Value;

const FRAMES: usize = 120;

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(60)))
        .build()
        .into()
}

/// (status, body) of a request.
fn call(req: Result<ureq::http::Response<ureq::Body>, ureq::Error>) -> (u16, String) {
    let mut resp = req.expect("HTTP request");
    let status = resp.status().as_u16();
    let body = resp
        .body_mut()
        .with_config()
        .limit(64 << 20)
        .read_to_string()
        .expect("read body");
    (status, body)
}

fn get(agent: &ureq::Agent, url: &str) -> (u16, String) {
    call(agent.get(url).call())
}

fn get_json(agent: &ureq::Agent, url: &str) -> Value {
    let (status, body) = get(agent, url);
    assert_eq!(status, 200, "GET {url}: {body}");
    serde_json::from_str(&body).expect("JSON body")
}

/// The dataset as a tar with its files one folder down (`synth/…`), as a user would pack it.
fn tar_dataset(dir: &Path) -> Vec<u8> {
    let mut b = tar::Builder::new(Vec::new());
    for name in ["rgb.txt", "groundtruth.txt", "calibration.txt"] {
        b.append_path_with_name(dir.join(name), format!("synth/{name}"))
            .expect("add file");
    }
    b.append_dir_all("synth/rgb", dir.join("rgb"))
        .expect("add rgb/");
    b.into_inner().expect("finish tar")
}

/// Polls the session until `done(info)`, failing after `timeout` or if it failed.
fn wait_for(
    agent: &ureq::Agent,
    server: &Relfusiond,
    id: &str,
    timeout: Duration,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let url = format!("{}/v1/sessions/{id}", server.url());
    let t0 = Instant::now();
    loop {
        let info = get_json(agent, &url);
        assert_ne!(
            info["state"],
            "failed",
            "session failed: {info}\n{}",
            server.log()
        );
        if done(&info) {
            return info;
        }
        assert!(
            t0.elapsed() < timeout,
            "timed out; last info {info}\n{}",
            server.log()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn upload_survives_kill9_and_completes_after_restart() {
    let seq = synth_sequence("durability", FRAMES, 5);
    let data = temp_dir("durability").join("data");
    let agent = agent();

    let server = Relfusiond::spawn(&data, [] as [&str; 0], &[]);
    let (status, body) = call(
        agent
            .post(format!("{}/v1/uploads?format=tar", server.url()))
            .header("Content-Type", "application/x-tar")
            .send(&tar_dataset(&seq)[..]),
    );
    assert_eq!(status, 201, "upload: {body}\n{}", server.log());
    let created: Value = serde_json::from_str(&body).expect("JSON");
    let id = created["id"].as_str().expect("id").to_string();
    assert_eq!(created["session"]["progress"]["total"], FRAMES);

    // Crash in the middle of processing.
    let info = wait_for(&agent, &server, &id, Duration::from_secs(60), |i| {
        i["frames_processed"].as_u64().unwrap_or(0) >= 10
    });
    server.kill9();
    let processed_at_crash = info["frames_processed"].as_u64().unwrap_or(0);
    assert!(
        processed_at_crash < FRAMES as u64 && info["state"] != "finished",
        "the upload finished before the crash could interrupt it: {info}"
    );
    eprintln!("killed with {processed_at_crash}/{FRAMES} frames processed");
    // The acknowledged upload is on disk.
    let session_dir = data.join("sessions").join(&id);
    assert!(session_dir.join("meta.json").is_file());
    assert!(session_dir.join("upload/synth/rgb.txt").is_file());

    // Restart on the same data: the upload re-runs from scratch and completes.
    let restarted = Instant::now();
    let server = Relfusiond::spawn(&data, [] as [&str; 0], &[]);
    let info = wait_for(&agent, &server, &id, Duration::from_secs(90), |i| {
        i["state"] == "finished"
    });
    eprintln!(
        "restart to finished: {:.1} s",
        restarted.elapsed().as_secs_f64()
    );
    assert_eq!(info["frames_processed"], FRAMES, "{info}");
    assert_eq!(info["progress"]["processed"], FRAMES, "{info}");
    assert_eq!(info["frames_lost"], 0, "{info}");
    let (status, trajectory) = get(
        &agent,
        &format!("{}/v1/sessions/{id}/trajectory", server.url()),
    );
    assert_eq!(status, 200, "{trajectory}");
    let est = parse_tum_trajectory(&trajectory, "server trajectory").expect("TUM text");
    assert_eq!(est.len(), FRAMES, "a pose for every frame");

    // Sane against the exact ground truth: ATE under 5 % of the path length.
    let gt = read_tum_trajectory(&seq.join("groundtruth.txt")).expect("ground truth");
    let path_length: f64 = gt
        .windows(2)
        .map(|w| (w[1].world_from_camera.translation - w[0].world_from_camera.translation).norm())
        .sum();
    let result = ate(&gt, &est, AlignMode::Sim3).expect("ATE");
    eprintln!("ATE {:.4} m over a {path_length:.3} m path", result.rmse);
    assert!(
        result.rmse < 0.05 * path_length,
        "ATE {} vs path length {path_length}",
        result.rmse
    );

    // The re-run is the deterministic pipeline from scratch: identical to a local run.
    let local = temp_dir("durability-local");
    let status = std::process::Command::new(bin_path("relfusion"))
        .args(["run", "--deterministic", "--quiet", "--out"])
        .arg(&local)
        .arg(&seq)
        .stdout(std::process::Stdio::null())
        .status()
        .expect("relfusion run");
    assert!(status.success());
    let local_trajectory =
        std::fs::read_to_string(local.join("trajectory.txt")).expect("local trajectory");
    assert_eq!(
        trajectory, local_trajectory,
        "re-run differs from a local run"
    );

    // Finished results stay downloadable after another crash.
    server.kill9();
    let server = Relfusiond::spawn(&data, [] as [&str; 0], &[]);
    let info = get_json(&agent, &format!("{}/v1/sessions/{id}", server.url()));
    assert_eq!(info["state"], "finished", "{info}");
    let (status, again) = get(
        &agent,
        &format!("{}/v1/sessions/{id}/trajectory", server.url()),
    );
    assert_eq!((status, again.as_str()), (200, trajectory.as_str()));
    let (status, keyframes) = get(
        &agent,
        &format!("{}/v1/sessions/{id}/keyframes", server.url()),
    );
    assert_eq!(status, 200);
    assert!(
        parse_tum_trajectory(&keyframes, "keyframes")
            .expect("TUM")
            .len()
            > 1
    );
    let resp = agent
        .get(format!("{}/v1/sessions/{id}/pointcloud.ply", server.url()))
        .call()
        .expect("point cloud");
    assert_eq!(resp.status().as_u16(), 200);
    let ply = resp
        .into_body()
        .with_config()
        .limit(256 << 20)
        .read_to_vec()
        .expect("read");
    assert!(
        ply.starts_with(b"ply\n") && ply.len() > 1000,
        "{} bytes",
        ply.len()
    );
    assert!(server.terminate(), "graceful exit on SIGTERM");
}
