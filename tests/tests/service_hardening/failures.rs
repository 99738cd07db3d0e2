//! Hole 6: failures cost more than their request. A panic in a session worker kept its slot,
//! an acknowledged upload that hit a full disk while saving its results failed for good,
//! `frame_id` wrapped at `u64::MAX`, and timestamps could jump anywhere or go backwards.

use std::process::Command;

use super::*;

#[test]
fn a_panicking_session_fails_alone_and_frees_its_slot() {
    let dir = synth_sequence("hardening-panic", 6, 37);
    let seq = TumSequence::open(&dir, None).expect("synth");
    // Debug builds (the tests') honour the fault-injection variable: frame 3 panics.
    let server = spawn(
        "panic",
        Some("[limits]\nmax_sessions = 1\n"),
        &[("RELFUSIOND_FAULT_PANIC_AT_FRAME", "3")],
    );
    let id = create_session(&server, &seq, None);
    for i in 0..5 {
        let reply = post_frame(&server, &id, &seq, i);
        assert!(matches!(reply.status, 202 | 409), "{}", reply.body);
    }
    let info = wait_info(&server, &id, None, |i| i["state"] == "failed");
    assert!(
        info["error"]
            .as_str()
            .unwrap_or_default()
            .contains("internal error"),
        "{info}"
    );
    assert_healthy(&server, "a session's panic");
    // The only slot is free again.
    let next = post_json(
        &server,
        "/v1/sessions",
        None,
        &json!({"camera": camera_json(&seq)}),
    );
    assert_eq!(next.status, 201, "{}", next.body);
}

#[test]
fn frame_ids_and_timestamps_are_checked() {
    let dir = synth_sequence("hardening-ids", 6, 41);
    let seq = TumSequence::open(&dir, None).expect("synth");
    let server = spawn("ids", None, &[]);
    let id = create_session(&server, &seq, None);
    let png = frame_bytes(&seq, 0);
    let post = |query: &str| {
        send(
            &server,
            "POST",
            &format!("/v1/sessions/{id}/frames?{query}"),
            None,
            "image/png",
            &png,
        )
    };
    assert_eq!(
        post(&format!("timestamp=10&frame_id={}", u64::MAX)).status,
        202
    );
    let message = post("timestamp=11").expect_error(400, "invalid_argument", "id after MAX");
    assert!(message.contains("used up"), "{message}");
    let id2 = create_session(&server, &seq, None);
    let post2 = |t: &str| {
        send(
            &server,
            "POST",
            &format!("/v1/sessions/{id2}/frames?timestamp={t}"),
            None,
            "image/png",
            &png,
        )
    };
    assert_eq!(post2("100").status, 202);
    for (t, why) in [
        ("99.5", "backwards"),
        ("100", "repeated"),
        ("1e9", "far ahead"),
        ("1e300", "out of range"),
        ("-1e300", "out of range"),
    ] {
        post2(t).expect_error(400, "invalid_argument", why);
    }
    assert_eq!(post2("100.033").status, 202, "the stream goes on");
}

/// A tmpfs of `mb` MiB mounted at `dir`, unmounted when dropped; `None` (with a SKIP line)
/// where this machine does not allow mounting.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, mb: u32) -> Option<Self> {
        std::fs::create_dir_all(dir).expect("mount point");
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mb}m"), "tmpfs"])
            .arg(dir)
            .status();
        if status.is_ok_and(|s| s.success()) {
            Some(Self(dir.to_path_buf()))
        } else {
            eprintln!("SKIP: cannot mount a tmpfs here (needs root); the full-disk test needs one");
            None
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

/// Fills the file system holding `dir` with one file; returns its path.
fn fill(dir: &Path) -> PathBuf {
    use std::io::Write as _;
    let path = dir.join("filler");
    let mut file = std::fs::File::create(&path).expect("filler");
    let chunk = vec![0xa5u8; 1 << 20];
    while file.write_all(&chunk).is_ok() {}
    let _ = file.sync_all();
    path
}

#[test]
fn an_acknowledged_upload_waits_for_disk_space_instead_of_failing() {
    const FRAMES: usize = 30;
    let dir = synth_sequence("hardening-enospc", FRAMES, 43);
    let work = temp_dir("http-enospc");
    let Some(disk) = Tmpfs::mount(&work.join("disk"), 48) else {
        return;
    };
    // The data dir is the small disk itself, so that the server's log (`<data dir>.log`, beside
    // it) stays off the disk that fills up: a full log file would fail the process's own
    // writes to stderr, which is not what this test is about.
    let data = disk.0.clone();
    let server = Relfusiond::spawn(
        &data,
        ["--config".into(), {
            let c = work.join("c.toml");
            std::fs::write(&c, "[limits]\ncheckpoint_keyframes = 1000\n").expect("config");
            c
        }],
        &[],
    );
    let created = upload(&server, None, &tar_with_list(&dir, &rgb_txt(&dir)));
    assert_eq!(created.status, 201, "{}", created.body);
    let id = created.json()["id"].as_str().expect("id").to_string();
    // The disk fills up while the upload is processed: its results cannot be stored.
    let filler = fill(&disk.0);
    let waiting = wait_info(&server, &id, None, |i| {
        i["notice"]
            .as_str()
            .is_some_and(|n| n.starts_with("waiting to store"))
            || i["state"] == "failed"
    });
    assert_eq!(waiting["state"], "finishing", "{waiting}");
    assert!(
        waiting["notice"]
            .as_str()
            .unwrap_or_default()
            .contains("No space left"),
        "{waiting}"
    );
    // Space comes back: the results are stored and the session finishes.
    std::fs::remove_file(&filler).expect("free the disk");
    let info = wait_finished(&server, &id, None);
    assert!(info.get("notice").is_none_or(Value::is_null), "{info}");
    let trajectory = get(&server, &format!("/v1/sessions/{id}/trajectory"), None);
    assert_eq!(tum_lines(&trajectory.body).len(), FRAMES);
    drop(server);
    drop(disk);
}
