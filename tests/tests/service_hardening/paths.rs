//! Hole 1: an upload's `rgb.txt` named files outside the upload (absolute paths, `../` into
//! another tenant's upload), the answer told which files exist, and errors showed the server's
//! absolute paths. Every name must resolve inside the upload, every refusal looks the same,
//! and errors name files relative to the upload.

use super::*;

#[test]
fn upload_lists_cannot_reach_outside_their_folder() {
    const FRAMES: usize = 6;
    let dir = synth_sequence("hardening-paths", FRAMES, 17);
    let server = spawn(
        "paths",
        None,
        &[("RELFUSIOND_TOKENS", "alice:tok-a,bob:tok-b")],
    );
    let list = rgb_txt(&dir);
    let created = upload(&server, Some("tok-a"), &tar_with_list(&dir, &list));
    assert_eq!(created.status, 201, "{}", created.body);
    let alice_id = created.json()["id"].as_str().expect("id").to_string();
    wait_finished(&server, &alice_id, Some("tok-a"));

    // Each list starts with a good frame (so the first image decodes) and then names a file
    // outside bob's upload folder.
    let (first_stamp, first_file) = list
        .lines()
        .find(|l| !l.starts_with('#') && !l.trim().is_empty())
        .and_then(|l| l.split_once(' '))
        .expect("first line");
    let absolute_existing = dir.join(first_file);
    let alice_file = format!("../../../{alice_id}/upload/seq/{first_file}");
    let outside = [
        absolute_existing.to_string_lossy().into_owned(),
        alice_file,
        "/etc/passwd".into(),
        "/etc/no-such-file".into(),
        "../../meta.json".into(),
        "rgb/../../../../../../etc/passwd".into(),
    ];
    let mut messages = Vec::new();
    for name in &outside {
        let text = format!("{first_stamp} {first_file}\n99.0 {name}\n");
        let refused = upload(&server, Some("tok-b"), &tar_with_list(&dir, &text));
        let message = refused.expect_error(400, "invalid_argument", name);
        assert!(
            message.contains("must be a relative path inside the dataset folder"),
            "{name}: {message}"
        );
        // Beyond the name it was given, the error names nothing of the machine.
        let rest = message.replace(name.as_str(), "NAME");
        assert!(
            !rest.contains(&*server.data_dir().to_string_lossy()) && !rest.contains("/tmp/"),
            "{name}: the error shows the server's paths: {message}"
        );
        messages.push(rest);
    }
    // Existing and missing files outside are refused alike: nothing leaks about them.
    assert!(
        messages.windows(2).all(|w| w[0] == w[1]),
        "refusals differ: {messages:#?}"
    );
    // Bob has no session, and alice's results are hers alone.
    let listed = get(&server, "/v1/sessions", Some("tok-b")).json();
    assert_eq!(
        listed["sessions"].as_array().map(Vec::len),
        Some(0),
        "{listed}"
    );
    let theirs = get(
        &server,
        &format!("/v1/sessions/{alice_id}/trajectory"),
        Some("tok-b"),
    );
    assert_eq!(theirs.status, 404);

    // A missing file inside the upload is named relative to it.
    let text = format!("{first_stamp} {first_file}\n99.0 rgb/missing.png\n");
    let missing = upload(&server, Some("tok-b"), &tar_with_list(&dir, &text));
    let message = missing.expect_error(400, "invalid_argument", "missing file");
    assert!(
        message.contains("rgb/missing.png does not exist"),
        "{message}"
    );
    assert!(
        !message.contains(&*server.data_dir().to_string_lossy()),
        "{message}"
    );
    assert_healthy(&server, "path attacks");
}
