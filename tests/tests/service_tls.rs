//! TLS end to end (issue 25, item 5): relfusiond with its own TLS listener (a certificate the
//! test makes, signed by a CA the test makes), and the real client over `https://` and `wss://`
//! trusting that CA (`--ca-cert`). Fails when the stream or the download does not go through
//! TLS, when a client that does not trust the CA gets through, when plain HTTP is answered on
//! the TLS port, or when a bad certificate does not stop relfusiond at start.

use std::path::Path;
use std::process::{Command, Output};

use rcgen::{BasicConstraints, CertificateParams, IsCa, KeyPair};
use relfusion_tests::{Relfusiond, bin_path, json_lines, relfusion, synth_sequence, temp_dir};
use serde_json::Value;

const TOKENS: (&str, &str) = ("RELFUSIOND_TOKENS", "alice:secret-a");

/// Writes `ca.pem`, `server.pem` (for 127.0.0.1 and localhost) and `server.key` into `dir`.
fn make_certificates(dir: &Path) {
    let ca_key = KeyPair::generate().expect("CA key");
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).expect("CA params");
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "relfusion test CA");
    let ca = ca_params.self_signed(&ca_key).expect("CA");
    let key = KeyPair::generate().expect("server key");
    let params = CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()])
        .expect("server params");
    let cert = params
        .signed_by(&key, &ca, &ca_key)
        .expect("server certificate");
    std::fs::write(dir.join("ca.pem"), ca.pem()).expect("ca.pem");
    std::fs::write(dir.join("server.pem"), cert.pem()).expect("server.pem");
    std::fs::write(dir.join("server.key"), key.serialize_pem()).expect("server.key");
}

fn ok(what: &str, out: &Output, server: &Relfusiond) -> Vec<Value> {
    json_lines(&server.ok_stdout(what, out))
}

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 path")
}

#[test]
fn the_client_streams_and_fetches_over_tls_with_the_ca_it_is_given() {
    let work = temp_dir("tls");
    make_certificates(&work);
    let (ca, cert, key) = (
        work.join("ca.pem"),
        work.join("server.pem"),
        work.join("server.key"),
    );
    let server = Relfusiond::spawn(
        &work.join("data"),
        std::iter::empty::<&str>(),
        &[
            TOKENS,
            ("RELFUSIOND_TLS_CERT", s(&cert)),
            ("RELFUSIOND_TLS_KEY", s(&key)),
        ],
    );
    let url = server.url().replacen("http://", "https://", 1);
    assert!(url.starts_with("https://127.0.0.1:"), "{url}");
    let seq = synth_sequence("tls", 40, 3);
    let config = work.join("deterministic.json");
    std::fs::write(&config, r#"{"pipeline":{"deterministic":true}}"#).expect("config");

    // Frames in and poses out over wss://, then the results over https://.
    let lines = ok(
        "stream over wss",
        &relfusion(&[
            "stream",
            s(&seq),
            "--server",
            &url,
            "--token",
            "secret-a",
            "--ca-cert",
            s(&ca),
            "--wait",
            "--fast",
            "--config",
            s(&config),
        ]),
        &server,
    );
    let session = lines[0]["session"].as_str().expect("session").to_string();
    let poses = lines.iter().filter(|l| l.get("state").is_some()).count();
    assert_eq!(poses, 40, "a pose per frame over wss://");
    let summary = &lines.last().expect("summary")["summary"];
    assert_eq!(summary["state"], "finished", "{summary}");
    let fetched = work.join("fetched");
    let fetch = |extra: &[&str]| {
        let mut args = vec![
            "fetch",
            session.as_str(),
            "--server",
            url.as_str(),
            "--token",
            "secret-a",
            "--out",
            s(&fetched),
        ];
        args.extend_from_slice(extra);
        relfusion(&args)
    };
    ok("fetch over https", &fetch(&["--ca-cert", s(&ca)]), &server);
    let trajectory = std::fs::read_to_string(fetched.join("trajectory.txt")).expect("trajectory");
    assert!(trajectory.lines().filter(|l| !l.starts_with('#')).count() >= 30);

    // Without the CA the certificate is refused.
    let out = fetch(&[]);
    assert!(!out.status.success(), "a client without the CA got through");
    let why = String::from_utf8_lossy(&out.stderr).to_lowercase();
    assert!(why.contains("certificate"), "{why}");

    // Plain HTTP on the TLS port gets no HTTP answer.
    let plain = server.url();
    assert!(
        ureq::get(&format!("{plain}/healthz")).call().is_err(),
        "plain HTTP answered on the TLS port"
    );

    // A certificate that is not one stops relfusiond before it listens.
    std::fs::write(work.join("bad.pem"), "not a certificate").expect("bad.pem");
    let out = Command::new(bin_path("relfusiond"))
        .args(["--listen", "127.0.0.1:0", "--data-dir"])
        .arg(work.join("data-bad"))
        .env("RELFUSIOND_TLS_CERT", work.join("bad.pem"))
        .env("RELFUSIOND_TLS_KEY", &key)
        .output()
        .expect("run relfusiond");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("tls.cert"), "{stderr}");
    assert!(!String::from_utf8_lossy(&out.stdout).contains("listening"));
    drop(server);
    let _ = std::fs::remove_dir_all(&work);
}
