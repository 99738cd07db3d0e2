//! Helpers shared by the end-to-end tests: where the real binaries and the shared data are.

use std::collections::HashMap;
use std::path::PathBuf;
use std::process::{Command, Output};
use std::sync::{Mutex, OnceLock};

pub mod attacks;
pub mod s3;
pub mod server;
pub use server::{Relfusiond, synth_sequence};

/// Path of a workspace binary (`relfusion`, `relfusiond`), built fresh for this test run.
///
/// `cargo test` builds binaries only for packages that have integration tests of their own, and
/// a binary left over from an older build would test stale code. So the first call for each
/// binary runs `cargo build --workspace --bins --tests` with this test's profile and target
/// directory (cargo releases its build lock before running tests, so this nested build is
/// allowed); later calls reuse the result.
pub fn bin_path(name: &str) -> PathBuf {
    static BUILT: OnceLock<Mutex<HashMap<String, PathBuf>>> = OnceLock::new();
    let mut built = BUILT
        .get_or_init(Default::default)
        .lock()
        .unwrap_or_else(|e| e.into_inner());
    if let Some(path) = built.get(name) {
        return path.clone();
    }
    let exe = std::env::current_exe().expect("current test executable");
    let profile_dir = exe
        .parent()
        .and_then(|deps| deps.parent())
        .expect("test executable lives in target/<profile>/deps");
    let target_dir = profile_dir.parent().expect("target/<profile> has a parent");
    let profile = match profile_dir.file_name().and_then(|n| n.to_str()) {
        Some("debug") => "dev",
        Some(other) => other,
        None => "dev",
    };
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut command = Command::new(cargo);
    // The variables cargo set for this test (CARGO_PKG_NAME, CARGO_MANIFEST_DIR, ...) must not
    // reach the nested build: build scripts that watch them (ring's) would see them change and
    // rebuild, here and again in the next `cargo test`. Nor RUSTC_BOOTSTRAP, which a test binary
    // run by hand with `-Z unstable-options --report-time` needs: build scripts that probe the
    // compiler watch it (proc-macro2's), and the nested build rebuilt most of the tree (18 min).
    command.env_remove("RUSTC_BOOTSTRAP");
    for (key, _) in std::env::vars_os() {
        if key.to_str().is_some_and(|k| {
            [
                "CARGO_PKG_",
                "CARGO_MANIFEST_",
                "CARGO_CRATE_",
                "CARGO_BIN_",
            ]
            .iter()
            .any(|prefix| k.starts_with(prefix))
                || k == "CARGO_PRIMARY_PACKAGE"
                || k == "CARGO_TARGET_TMPDIR"
        }) {
            command.env_remove(key);
        }
    }
    command.args([
        "build",
        "--quiet",
        "--workspace",
        "--profile",
        profile,
        "--target-dir",
    ]);
    command.arg(target_dir);
    if cfg!(feature = "rerun") {
        // `make test-rerun` (one test): the `relfusion` it runs writes rerun recordings too
        // (`--rerun`); relfusiond keeps its feature set.
        command.args(["--bin", name]);
        if name == "relfusion" {
            command.args(["--features", "relfusion-client/rerun"]);
        }
    } else {
        // The binaries and the tests, as `cargo test --workspace` selects them: dev-dependencies
        // then enable the same features, every library is already built, and only the binaries
        // compile. `--bin NAME` resolved other features and rebuilt much of the dependency tree
        // (about 4 minutes of a cold `make test`); `--all-targets` also compiled each binary as
        // a test harness, `test = false` or not (docs/build-time.md).
        command.args(["--bins", "--tests"]);
    }
    let status = command
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .status()
        .expect("run cargo build");
    assert!(status.success(), "cargo build for {name} failed");
    let path = profile_dir.join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    assert!(
        path.exists(),
        "{} missing after cargo build",
        path.display()
    );
    built.insert(name.to_string(), path.clone());
    path
}

/// The shared real data folder: `RELFUSION_DATA`, else `../shared/data` beside the checkout.
pub use relfusion_slam::dataset::shared_data_dir as data_dir;

/// The shared PyDNet++ stand-in model, when it and ONNX Runtime are present; `None` (with a
/// SKIP line saying why) otherwise, for the tests that need a real depth prior.
pub fn pydnet_model() -> Option<PathBuf> {
    let model =
        data_dir().join("models/pydnet_pp_matterport/pydnet_pp_matterport_448x640_nchw_fp32.onnx");
    if relfusion_slam::dense::runtime_library_path().is_err() || !model.exists() {
        eprintln!("SKIP: no ONNX Runtime or no {}", model.display());
        return None;
    }
    Some(model)
}

/// A fresh, empty temporary directory unique to this test process and `tag`.
pub fn temp_dir(tag: &str) -> PathBuf {
    sweep_stale_temp_dirs();
    let dir = std::env::temp_dir().join(format!("relfusion-test-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create temp dir");
    dir
}

/// Removes the temporary folders of test processes that have ended (`relfusion-test-…-PID`),
/// once per process: the folders of one test binary stay while it runs, and a failed test's
/// stay for inspection until the next binary starts, but a suite run over and over no longer
/// fills the disk (one CI run left about a hundred folders, several GB). Linux only: elsewhere
/// there is no `/proc` to tell a live process from an ended one.
pub(crate) fn sweep_stale_temp_dirs() {
    static SWEPT: std::sync::Once = std::sync::Once::new();
    SWEPT.call_once(|| sweep_ended(&std::env::temp_dir()));
}

/// [`sweep_stale_temp_dirs`] in `dir`.
fn sweep_ended(dir: &std::path::Path) {
    if !std::path::Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix("relfusion-test-"))
            .and_then(|rest| rest.rsplit('-').next())
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        let ended = !std::path::Path::new(&format!("/proc/{pid}")).exists();
        if pid != std::process::id() && ended {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

/// Runs `relfusion ARGS` and returns what it did (the caller checks the exit status).
pub fn relfusion(args: &[&str]) -> Output {
    Command::new(bin_path("relfusion"))
        .args(args)
        .output()
        .expect("run relfusion")
}

/// The JSON values of `text`, one per non-empty line (what `relfusion stream` and the other
/// service commands print).
pub fn json_lines(text: &str) -> Vec<serde_json::Value> {
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect()
}

/// A free loopback TCP port (for a server's or a Zenoh endpoint's listen address).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("bind a free port")
        .port()
}

/// Runs `relfusion ARGS`, asserts it succeeded and returns its stdout.
pub fn relfusion_stdout(args: &[&str]) -> String {
    let out = Command::new(bin_path("relfusion"))
        .args(args)
        .output()
        .expect("run relfusion");
    assert!(
        out.status.success(),
        "relfusion {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `relfusion ARGS`, asserts it succeeded and parses its JSON output (the last line, or
/// the whole of stdout for pretty-printed reports).
pub fn relfusion_json(args: &[&str]) -> serde_json::Value {
    let stdout = relfusion_stdout(args);
    let last = stdout.lines().last().unwrap_or_default().to_string();
    serde_json::from_str(&last)
        .or_else(|_| serde_json::from_str(&stdout))
        .unwrap_or_else(|e| panic!("not JSON ({e}): {stdout}"))
}

/// The face count a PLY header declares (`element face N`).
pub fn ply_faces(bytes: &[u8]) -> u64 {
    let header_end = bytes
        .windows(10)
        .position(|w| w == b"end_header")
        .expect("ply header");
    String::from_utf8_lossy(&bytes[..header_end])
        .lines()
        .find_map(|l| l.strip_prefix("element face "))
        .and_then(|n| n.trim().parse().ok())
        .expect("face count")
}

#[cfg(test)]
mod sweep_tests {
    #[test]
    fn only_folders_of_ended_processes_are_swept() {
        let root = std::env::temp_dir().join(format!("relfusion-sweep-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let me = std::process::id();
        // No process has a pid above the kernel's maximum (at most 2^22).
        let names = [
            "relfusion-test-gone-4294967295".to_owned(),
            format!("relfusion-test-mine-{me}"),
            "relfusion-test-init-1".to_owned(),
            "relfusion-other-4294967295".to_owned(),
            "relfusion-test-no-pid".to_owned(),
        ];
        for n in &names {
            std::fs::create_dir_all(root.join(n).join("inner")).expect("create");
        }
        super::sweep_ended(&root);
        let left: Vec<bool> = names.iter().map(|n| root.join(n).exists()).collect();
        assert_eq!(left, [false, true, true, true, true]);
        std::fs::remove_dir_all(&root).expect("clean up");
    }
}
