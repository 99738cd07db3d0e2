//! The deploy files (issue 25, item 4) checked by `scripts/check_deploy.py`: every Kubernetes
//! manifest against the Kubernetes API schema (kubernetes-validate from PyPI, installed by
//! `scripts/setup.sh --test`), and what the deploy docs promise (headless governing Service,
//! non-root pods and image, Prometheus annotations, images with a registry, a --locked build,
//! NVIDIA's Vulkan libraries, restart policies and healthchecks, a .dockerignore). Fails on the
//! checkout's files, and must fail on a copy with a known defect put back in.
//!
//! Also the shape of the code (issue 36): no module of the server, the CLI or the SDK imports
//! in a circle (`scripts/module_cycles.py`, top-level modules and one level down).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use relfusion_tests::temp_dir;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("repository root")
        .to_path_buf()
}

fn check(root: &Path) -> Output {
    let mut command = Command::new("python3");
    command
        .arg(repo().join("scripts/check_deploy.py"))
        .arg(root);
    if let Some(deps) = std::env::var_os("RELFUSION_PYDEPS") {
        command.env("PYTHONPATH", deps);
    }
    command.output().expect("run python3")
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("mkdir");
    for entry in std::fs::read_dir(from).expect("read dir") {
        let entry = entry.expect("entry");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("type").is_dir() {
            copy_tree(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).expect("copy");
        }
    }
}

#[test]
fn deploy_files_validate_and_keep_their_promises() {
    let out = check(&repo());
    let report = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        !report.contains("No module named"),
        "kubernetes-validate is missing: run `bash scripts/setup.sh --test` (make test does) \
         and export what it prints\n{report}"
    );
    assert!(out.status.success(), "{report}");

    // A copy with two defects of the old files put back must fail, naming both.
    let work = temp_dir("deploy-check");
    copy_tree(&repo().join("deploy"), &work.join("deploy"));
    std::fs::copy(repo().join(".dockerignore"), work.join(".dockerignore")).expect("copy");
    let sts = work.join("deploy/k8s/relfusiond.yaml");
    let text = std::fs::read_to_string(&sts).expect("read");
    std::fs::write(
        &sts,
        text.replace("serviceName: relfusiond-pods", "serviceName: relfusiond"),
    )
    .expect("write");
    let dockerfile = work.join("deploy/Dockerfile");
    let text = std::fs::read_to_string(&dockerfile).expect("read");
    std::fs::write(&dockerfile, text.replace(" --locked", "")).expect("write");
    let out = check(&work);
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success(), "defects not found:\n{report}");
    assert!(report.contains("headless"), "{report}");
    assert!(report.contains("--locked"), "{report}");
    let _ = std::fs::remove_dir_all(&work);
}

fn module_cycles(src: &Path, depth: u32) -> Output {
    Command::new("python3")
        .arg(repo().join("scripts/module_cycles.py"))
        .arg(src)
        .arg(depth.to_string())
        .output()
        .expect("run python3")
}

#[test]
fn no_module_imports_in_a_circle() {
    for krate in ["server", "client", "sdk"] {
        for depth in [1, 2] {
            let out = module_cycles(&repo().join(krate).join("src"), depth);
            let report = String::from_utf8_lossy(&out.stdout);
            assert!(out.status.success(), "{krate} at depth {depth}:\n{report}");
            assert!(report.contains(" imports, depth "), "{report}");
        }
    }

    // The circle this checks for (issue 36: relay <-> stream_ws <-> stream_remote), put back
    // in a copy, must be found.
    let work = temp_dir("module-cycles");
    let http = work.join("http");
    std::fs::create_dir_all(&http).expect("mkdir");
    std::fs::write(work.join("lib.rs"), "pub mod http;\npub mod cluster;\n").expect("write");
    std::fs::write(http.join("mod.rs"), "pub mod stream_ws;\n").expect("write");
    std::fs::write(
        http.join("stream_ws.rs"),
        "use crate::cluster::relay::Relay;\npub fn handle() {}\n",
    )
    .expect("write");
    std::fs::write(
        work.join("cluster.rs"),
        "pub mod relay { pub struct Relay; }\nfn call() { crate::http::stream_ws::handle() }\n",
    )
    .expect("write");
    let out = module_cycles(&work, 2);
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success(), "circle not found:\n{report}");
    assert!(
        report.contains("circle: cluster <-> http::stream_ws"),
        "{report}"
    );
    let _ = std::fs::remove_dir_all(&work);
}
