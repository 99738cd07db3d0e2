//! Debian's headless Chromium driven through its chromedriver (WebDriver): the viewer's
//! benchmark (`relfusion bench viewer`) and browser tests. Without a GPU, WebGL runs on
//! SwiftShader, Chromium's software renderer.

use std::net::TcpListener;
use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::{Client, ClientBuilder};
use serde_json::{Value, json};

/// Why the browser could not do what was asked.
#[derive(Debug, thiserror::Error)]
pub enum BrowserError {
    #[error(
        "cannot start {path} ({source}): install Debian's chromium and chromium-driver (make test does), or set RELFUSION_CHROMEDRIVER"
    )]
    NoDriver {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("chromedriver did not answer on port {0} within 30 s")]
    DriverSilent(u16),
    #[error("chromedriver could not open a browser: {0}")]
    Session(#[from] fantoccini::error::NewSessionError),
    #[error("browser command failed: {0}")]
    Command(#[from] fantoccini::error::CmdError),
    #[error("{what}: not true after {timeout:?} ({expression}); page errors: {errors}")]
    Timeout {
        what: String,
        expression: String,
        timeout: Duration,
        errors: Value,
    },
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// Where Debian's packages put them (`chromium`, `chromium-driver`); overridable.
fn chromium() -> PathBuf {
    std::env::var_os("RELFUSION_CHROMIUM").map_or_else(|| "/usr/bin/chromium".into(), PathBuf::from)
}

fn chromedriver() -> PathBuf {
    std::env::var_os("RELFUSION_CHROMEDRIVER")
        .map_or_else(|| "/usr/bin/chromedriver".into(), PathBuf::from)
}

/// A running chromedriver; killed on drop.
#[derive(Debug)]
pub struct Driver {
    child: Child,
    url: String,
    profiles: PathBuf,
    opened: usize,
}

impl Driver {
    /// Starts chromedriver on a free loopback port and waits until it answers; browser
    /// profiles and the driver's log go into `work`.
    pub fn start(work: &Path) -> Result<Driver, BrowserError> {
        let port = TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let log = std::fs::File::create(work.join("chromedriver.log"))?;
        let path = chromedriver();
        let child = Command::new(&path)
            .arg(format!("--port={port}"))
            // Its own process group: dropping the driver ends the browsers it started too,
            // even when a test panics before closing them.
            .process_group(0)
            .stdout(log)
            .stderr(Stdio::null())
            .spawn()
            .map_err(|source| BrowserError::NoDriver { path, source })?;
        let mut driver = Driver {
            child,
            url: format!("http://127.0.0.1:{port}"),
            profiles: work.to_path_buf(),
            opened: 0,
        };
        let deadline = Instant::now() + Duration::from_secs(30);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            if Instant::now() > deadline || driver.child.try_wait()?.is_some() {
                return Err(BrowserError::DriverSilent(port));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(driver)
    }

    /// A new headless browser (its own profile) with a `width`×`height` window.
    pub async fn browser(&mut self, width: u32, height: u32) -> Result<Client, BrowserError> {
        self.opened += 1;
        let profile = self
            .profiles
            .join(format!("chromium-profile-{}", self.opened));
        let args = [
            "--headless=new".to_string(),
            "--no-sandbox".into(),
            "--disable-dev-shm-usage".into(),
            // The machine's network may be closed: no background calls home.
            "--disable-background-networking".into(),
            "--disable-component-update".into(),
            "--disable-sync".into(),
            "--disable-quic".into(),
            "--no-first-run".into(),
            // No GPU needed: WebGL on SwiftShader.
            "--use-angle=swiftshader".into(),
            "--enable-unsafe-swiftshader".into(),
            format!("--window-size={width},{height}"),
            format!("--user-data-dir={}", profile.display()),
        ];
        let mut caps = serde_json::Map::new();
        caps.insert(
            "goog:chromeOptions".into(),
            json!({ "binary": chromium(), "args": args }),
        );
        // A page's dialog stays open for the test to read and answer (WebDriver would
        // otherwise dismiss it on the next command).
        caps.insert("unhandledPromptBehavior".into(), json!("ignore"));
        Ok(
            ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
                .capabilities(caps)
                .connect(&self.url)
                .await?,
        )
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        // The whole group: chromedriver and every Chromium process it started.
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", self.child.id())])
            .stderr(Stdio::null())
            .status();
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Evaluates `expression` in the page and returns its JSON value.
pub async fn eval(page: &Client, expression: &str) -> Result<Value, BrowserError> {
    Ok(page
        .execute(&format!("return ({expression});"), vec![])
        .await?)
}

/// Polls `expression` until it is `true`, at most `timeout`.
pub async fn wait_until(
    page: &Client,
    expression: &str,
    timeout: Duration,
    what: &str,
) -> Result<(), BrowserError> {
    let deadline = Instant::now() + timeout;
    loop {
        if eval(page, expression).await? == Value::Bool(true) {
            return Ok(());
        }
        if Instant::now() > deadline {
            let errors = eval(
                page,
                "window.relfusionViewer ? window.relfusionViewer.errors : []",
            )
            .await?;
            return Err(BrowserError::Timeout {
                what: what.into(),
                expression: expression.into(),
                timeout,
                errors,
            });
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}
