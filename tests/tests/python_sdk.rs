//! The Python SDK (`python/`, issue 38 item 4) as a user gets it: its wheel built and installed
//! into a private folder, its pytest suite run against a real relfusiond with tokens, on a
//! rendered sequence (stream sync and async, upload, fetch into numpy and trimesh, maps, errors).

use std::path::Path;
use std::process::Command;

use relfusion_tests::{Relfusiond, synth_sequence, temp_dir};

fn run(command: &mut Command, what: &str) -> String {
    let out = command.output().unwrap_or_else(|e| panic!("{what}: {e}"));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{what} failed:\n{text}");
    text
}

#[test]
fn the_python_sdk_wheel_passes_its_tests_against_a_real_service() {
    let python = Path::new(env!("CARGO_MANIFEST_DIR")).join("../python");
    let work = temp_dir("python-sdk");
    let deps = std::env::var_os("RELFUSION_CLIENT_PYDEPS").unwrap_or_default();
    // The wheel, built offline (flit_core from the test packages), then installed alone.
    run(
        Command::new("python3")
            .args([
                "-m",
                "pip",
                "wheel",
                "--no-deps",
                "--no-build-isolation",
                "-q",
                "-w",
            ])
            .arg(work.join("wheel"))
            .arg(&python)
            .env("PYTHONPATH", &deps),
        "pip wheel ./python",
    );
    let wheel = std::fs::read_dir(work.join("wheel"))
        .expect("wheel folder")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .find(|p| p.extension().is_some_and(|e| e == "whl"))
        .expect("a wheel");
    let site = work.join("site");
    run(
        Command::new("python3")
            .args([
                "-m",
                "pip",
                "install",
                "--no-deps",
                "-q",
                "--break-system-packages",
            ])
            .arg("--target")
            .arg(&site)
            .arg(&wheel),
        "pip install the wheel",
    );
    assert!(site.join("relfusion/py.typed").exists(), "typed package");

    let sequence = synth_sequence("python-sdk", 40, 17);
    let server = Relfusiond::spawn(
        &work.join("data"),
        Vec::<String>::new(),
        &[("RELFUSIOND_TOKENS", "py:py-secret")],
    );
    let mut path = site.into_os_string();
    path.push(":");
    path.push(&deps);
    let report = run(
        Command::new("python3")
            .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
            .arg(python.join("tests"))
            .env("PYTHONPATH", path)
            .env("RELFUSION_URL", server.url())
            .env("RELFUSION_TOKEN", "py-secret")
            .env("RELFUSION_TEST_SEQUENCE", &sequence),
        "pytest python/tests",
    );
    // Every test ran (none skipped for want of the service).
    assert!(report.contains("6 passed"), "{report}");
    assert!(!report.contains("skipped"), "{report}");
}
