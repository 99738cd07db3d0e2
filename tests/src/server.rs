//! A real `relfusiond` process for end-to-end tests: started on 127.0.0.1 port 0, its bound
//! address read from the one stdout line it prints, killed when dropped.

use std::ffi::OsStr;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use crate::{bin_path, free_port};

/// A running `relfusiond`.
#[derive(Debug)]
pub struct Relfusiond {
    child: Option<Child>,
    addr: String,
    data_dir: PathBuf,
    /// Where this process's part of the log starts (the file is appended across restarts).
    log_start: usize,
}

impl Relfusiond {
    /// Starts `relfusiond --listen 127.0.0.1:0 --data-dir DATA_DIR ARGS...` with the extra
    /// environment `envs`, and waits until it listens. Its stderr (logs) goes to
    /// `DATA_DIR/../relfusiond-<pid>.log` so a failing test can show it.
    pub fn spawn<I, S>(data_dir: &Path, args: I, envs: &[(&str, &str)]) -> Self
    where
        I: IntoIterator<Item = S>,
        S: AsRef<OsStr>,
    {
        Self::spawn_until(data_dir, args, envs, "listening on ")
    }

    /// A cluster node named `name`, data in `work/<name>`: a Zenoh client of the router at
    /// `endpoint` with `max_sessions` slots; `extra` is appended to its config after that line
    /// (more `[limits]` keys, then other sections).
    pub fn spawn_node(
        work: &Path,
        name: &str,
        endpoint: &str,
        max_sessions: usize,
        extra: &str,
        envs: &[(&str, &str)],
    ) -> Self {
        let config = work.join(format!("{name}.toml"));
        std::fs::create_dir_all(work).expect("create work dir");
        std::fs::write(
            &config,
            format!(
                "[zenoh]\nenabled = true\nmode = \"client\"\nnode = \"{name}\"\n\
                 connect = [\"{endpoint}\"]\n[limits]\nmax_sessions = {max_sessions}\n{extra}"
            ),
        )
        .expect("node config");
        Self::spawn(
            &work.join(name),
            ["--config", config.to_str().expect("path")],
            envs,
        )
    }

    /// `relfusiond --zenoh-router ENDPOINT` on a free loopback port: a cluster's Zenoh router
    /// (no HTTP), up when this returns; returns it and its endpoint.
    pub fn spawn_router(data_dir: &Path, envs: &[(&str, &str)]) -> (Self, String) {
        on_free_endpoint(|endpoint| {
            Self::try_spawn_until(
                data_dir,
                ["--zenoh-router", endpoint],
                envs,
                "zenoh router on ",
            )
        })
    }

    /// `relfusiond ARGS --zenoh-listen ENDPOINT` on a free loopback port (a Zenoh peer that
    /// routes for its clients), its Zenoh side up when this returns; returns it and its
    /// endpoint.
    pub fn spawn_zenoh_peer<S: AsRef<OsStr>>(
        data_dir: &Path,
        args: &[S],
        envs: &[(&str, &str)],
    ) -> (Self, String) {
        on_free_endpoint(|endpoint| Self::try_spawn_zenoh_peer(data_dir, args, envs, endpoint))
    }

    /// `relfusiond ARGS --zenoh-listen ENDPOINT`, its Zenoh side up when this returns; an
    /// error with its log when it exits first (the endpoint taken).
    pub fn try_spawn_zenoh_peer<S: AsRef<OsStr>>(
        data_dir: &Path,
        args: &[S],
        envs: &[(&str, &str)],
        endpoint: &str,
    ) -> Result<Self, String> {
        let listen = [OsStr::new("--zenoh-listen"), OsStr::new(endpoint)];
        let all = args.iter().map(AsRef::as_ref).chain(listen);
        let mut server = Self::spawn(data_dir, all, envs);
        // HTTP listens first; a peer that cannot bind its endpoint exits after that.
        server.wait_for_log("Zenoh endpoints up").map(|()| server)
    }

    /// Waits up to 60 s for `needle` in this process's log; an error with the log when the
    /// process exits first or the time runs out.
    fn wait_for_log(&mut self, needle: &str) -> Result<(), String> {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let log = self.log();
            let own = log.get(self.log_start..).unwrap_or_default();
            if own.contains(needle) {
                return Ok(());
            }
            let exited = self
                .child
                .as_mut()
                .and_then(|c| c.try_wait().ok().flatten());
            if exited.is_some() || Instant::now() > deadline {
                return Err(format!(
                    "relfusiond ({exited:?}) did not log {needle:?}:\n{own}"
                ));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn spawn_until<I, S>(data_dir: &Path, args: I, envs: &[(&str, &str)], ready: &str) -> Self
    where
        I: IntoIterator<Item = S>,
        S: AsRef<OsStr>,
    {
        Self::try_spawn_until(data_dir, args, envs, ready).unwrap_or_else(|e| panic!("{e}"))
    }

    fn try_spawn_until<I, S>(
        data_dir: &Path,
        args: I,
        envs: &[(&str, &str)],
        ready: &str,
    ) -> Result<Self, String>
    where
        I: IntoIterator<Item = S>,
        S: AsRef<OsStr>,
    {
        std::fs::create_dir_all(data_dir).expect("create data dir");
        let log_path = data_dir.with_extension("log");
        let log_start = std::fs::metadata(&log_path).map_or(0, |m| m.len() as usize);
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .expect("open server log");
        let mut command = Command::new(bin_path("relfusiond"));
        command
            .args(["--listen", "127.0.0.1:0", "--data-dir"])
            .arg(data_dir)
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log));
        for (key, value) in envs {
            command.env(key, value);
        }
        let mut child = command.spawn().expect("start relfusiond");
        let stdout = child.stdout.take().expect("stdout");
        let mut line = String::new();
        BufReader::new(stdout)
            .read_line(&mut line)
            .expect("read the listening line");
        let Some(addr) = line.trim().strip_prefix(ready) else {
            let _ = child.kill();
            let _ = child.wait();
            let log = std::fs::read_to_string(&log_path).unwrap_or_default();
            let own = log.get(log_start..).unwrap_or_default();
            return Err(format!("relfusiond did not start: {line:?}\n{own}"));
        };
        Ok(Self {
            addr: addr.to_string(),
            child: Some(child),
            data_dir: data_dir.to_path_buf(),
            log_start,
        })
    }

    /// `127.0.0.1:PORT`.
    pub fn addr(&self) -> &str {
        &self.addr
    }

    /// `http://127.0.0.1:PORT`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// The data directory it was started with.
    pub fn data_dir(&self) -> &Path {
        &self.data_dir
    }

    /// The server's log so far (its stderr).
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.data_dir.with_extension("log")).unwrap_or_default()
    }

    /// The stdout of a client command `what` that talked to this server, after asserting it
    /// succeeded (its stderr and this server's log otherwise).
    pub fn ok_stdout(&self, what: &str, out: &Output) -> String {
        assert!(
            out.status.success(),
            "{what} failed: {}\n--- server log ---\n{}",
            String::from_utf8_lossy(&out.stderr),
            self.log()
        );
        String::from_utf8(out.stdout.clone()).expect("stdout is UTF-8")
    }

    /// The process id (for RSS measurements).
    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// SIGKILL, no chance to clean up (the durability tests' crash).
    pub fn kill9(mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// SIGTERM and wait for a graceful exit; returns whether it exited successfully.
    pub fn terminate(mut self) -> bool {
        let Some(mut child) = self.child.take() else {
            return false;
        };
        let _ = Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status();
        child.wait().map(|s| s.success()).unwrap_or(false)
    }
}

impl Drop for Relfusiond {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Runs `start` on `tcp/127.0.0.1:PORT` with a free port, and again on another when that
/// port was taken in between: [`free_port`] lets its port go, and another process may bind it,
/// or get it as an outgoing connection's ephemeral port, before relfusiond does (a CI run
/// lost a test to that). Any other failure panics with what `start` said.
pub fn on_free_endpoint<T>(mut start: impl FnMut(&str) -> Result<T, String>) -> (T, String) {
    const TRIES: usize = 5;
    for attempt in 1..=TRIES {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        match start(&endpoint) {
            Ok(started) => return (started, endpoint),
            Err(e) if attempt < TRIES && e.contains("Address already in use") => {
                eprintln!("{endpoint} was taken before relfusiond bound it; another port");
            }
            Err(e) => panic!("{e}"),
        }
    }
    unreachable!("the last try returns or panics")
}

/// A 320×240 synthetic TUM-layout sequence rendered once per test process by the real
/// `relfusion synth` (orbit motion, exact ground truth).
pub fn synth_sequence(tag: &str, frames: usize, seed: u64) -> PathBuf {
    // Tests of one binary run in parallel threads: render each sequence once.
    static RENDERING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = RENDERING.lock().unwrap_or_else(|e| e.into_inner());
    crate::sweep_stale_temp_dirs();
    let dir = std::env::temp_dir().join(format!(
        "relfusion-test-synth-{tag}-{frames}-{seed}-{}",
        std::process::id()
    ));
    if dir.join("rgb.txt").exists() {
        return dir;
    }
    let status = Command::new(bin_path("relfusion"))
        .args(["synth", "--width", "320", "--height", "240", "--frames"])
        .arg(frames.to_string())
        .arg("--seed")
        .arg(seed.to_string())
        .arg("--out")
        .arg(&dir)
        .stdout(Stdio::null())
        .status()
        .expect("run relfusion synth");
    assert!(status.success(), "relfusion synth failed");
    dir
}
