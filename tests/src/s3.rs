//! A real S3-compatible server for the object-store tests: `s3s-fs` (crates.io, installed by
//! `scripts/setup.sh --test`, found through `RELFUSION_S3S_FS`), serving one bucket from a
//! temporary folder on a free loopback port; killed when dropped.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::{free_port, temp_dir};

/// The bucket every test uses.
pub const BUCKET: &str = "relfusion";
const ACCESS_KEY: &str = "relfusion-test";
const SECRET_KEY: &str = "relfusion-test-secret";

/// A running `s3s-fs`.
#[derive(Debug)]
pub struct S3Server {
    child: Child,
    endpoint: String,
    root: PathBuf,
}

impl S3Server {
    /// Starts it with an empty bucket and waits until it accepts connections.
    pub fn start(tag: &str) -> Self {
        let binary = std::env::var_os("RELFUSION_S3S_FS").map(PathBuf::from).unwrap_or_else(|| {
            panic!("RELFUSION_S3S_FS is not set: run the tests through `make test` (scripts/setup.sh --test installs s3s-fs)")
        });
        let root = temp_dir(&format!("s3-{tag}"));
        std::fs::create_dir_all(root.join(BUCKET)).expect("bucket folder");
        let port = free_port();
        let child = Command::new(&binary)
            .args(["--host", "127.0.0.1", "--port", &port.to_string()])
            .args(["--access-key", ACCESS_KEY, "--secret-key", SECRET_KEY])
            .arg(&root)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", binary.display()));
        let deadline = Instant::now() + Duration::from_secs(20);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "s3s-fs did not listen on {port}");
            std::thread::sleep(Duration::from_millis(50));
        }
        Self {
            child,
            endpoint: format!("http://127.0.0.1:{port}"),
            root,
        }
    }

    /// The `[storage]` section of a relfusiond config that keeps everything in this server.
    pub fn storage_toml(&self) -> String {
        format!(
            "[storage]\nbackend = \"s3\"\n[storage.s3]\nendpoint = \"{}\"\nbucket = \"{BUCKET}\"\n\
             allow_http = true\naccess_key_id = \"{ACCESS_KEY}\"\nsecret_access_key = \"{SECRET_KEY}\"\n",
            self.endpoint
        )
    }

    /// How many objects the bucket holds below `prefix` (files of the server's folder).
    pub fn objects(&self, prefix: &str) -> usize {
        fn count(dir: &std::path::Path) -> usize {
            std::fs::read_dir(dir).map_or(0, |entries| {
                entries
                    .flatten()
                    .map(|e| {
                        let path = e.path();
                        if path.is_dir() { count(&path) } else { 1 }
                    })
                    .sum()
            })
        }
        count(&self.root.join(BUCKET).join(prefix))
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.root);
    }
}
