//! relfusiond configuration: one TOML file plus environment overrides; every field has a
//! working default.
//!
//! Precedence, highest first: command-line flag > environment variable > file > default
//! ([`Config::resolve`]). The environment variables exist for containers, where editing a file
//! is awkward; the flags for scripts and tests.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::ServerError;

mod limits;
mod ros2;
mod storage;

pub use limits::{HttpLimits, Limits, Quotas, Retention};
pub use ros2::Ros2Config;
pub use storage::{S3Config, StorageBackend, StorageConfig};

/// The whole server configuration. Unknown keys are rejected so that typos are caught.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// HTTP listen address. Port 0 asks the OS for a free port (printed at start).
    pub listen: SocketAddr,
    /// Where uploads, session metadata and results are stored.
    pub data_dir: PathBuf,
    /// Admission control, request sizes, memory and the bound of every queue.
    pub limits: Limits,
    /// Connections and request timeouts.
    pub http: HttpLimits,
    /// What one owner may hold.
    pub quotas: Quotas,
    /// How long finished sessions are kept.
    pub retention: Retention,
    /// The GPU worker pool.
    pub pool: PoolConfig,
    /// The default depth model of sessions.
    pub model: ModelSettings,
    /// The pipeline settings the operator chooses for every session.
    pub pipeline: PipelineSettings,
    /// Bearer tokens.
    pub auth: AuthConfig,
    /// The Zenoh endpoints.
    pub zenoh: ZenohConfig,
    /// Sessions on ROS 2 (rmw_zenoh's wire format, on the Zenoh session).
    pub ros2: Ros2Config,
    /// HTTPS/WSS on `listen` instead of plain HTTP, when a certificate is given.
    pub tls: TlsConfig,
    /// Where sessions and maps are kept: local files or a shared S3-compatible bucket.
    pub storage: StorageConfig,
}

/// The optional TLS listener: a certificate chain and its private key, PEM files (what an
/// ingress or `certbot` hands out). Both or neither.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TlsConfig {
    /// The server's certificate chain, leaf first (`RELFUSIOND_TLS_CERT`).
    pub cert: Option<PathBuf>,
    /// Its private key, PKCS#8, PKCS#1 or SEC1 (`RELFUSIOND_TLS_KEY`).
    pub key: Option<PathBuf>,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 8780)),
            data_dir: PathBuf::from("relfusion-data"),
            limits: Limits::default(),
            http: HttpLimits::default(),
            quotas: Quotas::default(),
            retention: Retention::default(),
            pool: PoolConfig::default(),
            model: ModelSettings::default(),
            pipeline: PipelineSettings::default(),
            auth: AuthConfig::default(),
            zenoh: ZenohConfig::default(),
            ros2: Ros2Config::default(),
            tls: TlsConfig::default(),
            storage: StorageConfig::default(),
        }
    }
}

/// The GPU worker pool.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoolConfig {
    /// Worker threads; 0 = one per GPU adapter (a CPU adapter such as lavapipe counts as one
    /// when there is no real GPU). Sessions are placed on the adapters whatever the count;
    /// each adapter needs at least one worker, so fewer workers than GPUs leaves GPUs unused.
    pub workers: usize,
}

/// Pipeline settings of the operator's scope (`relfusion_slam::pipeline::user_config`) that
/// apply to every session: a client cannot set them, since they change what a session costs.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineSettings {
    /// What poses the frames: `"lsd"` (the default) or `"dso"`, the DSO-class odometry
    /// (issue 35). Sessions that extend a saved map keep `"lsd"`, the one front end that can.
    pub frontend: relfusion_slam::pipeline::Frontend,
}

/// The default depth model (the DeepRelativeFusion prior) of new sessions.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelSettings {
    /// ONNX model file; empty = no model (SLAM runs without the prior: random
    /// initialisation). Loaded once at start and shared by every session.
    pub path: PathBuf,
    /// Model description for models relfusion does not recognise; empty = recognise the
    /// model from the file.
    pub config: PathBuf,
}

impl ModelSettings {
    /// Whether a model is configured.
    pub fn is_set(&self) -> bool {
        !self.path.as_os_str().is_empty()
    }

    /// The name sessions know the model by: its file stem (`"none"` when unset).
    pub fn name(&self) -> String {
        if !self.is_set() {
            return "none".into();
        }
        self.path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "default".into())
    }
}

/// Whether `name` can name an owner: it appears in Zenoh keys and as a Zenoh user name.
pub fn is_owner_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// One bearer token and the name its sessions are owned by.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenEntry {
    pub name: String,
    pub token: String,
}

/// Bearer-token authentication. No tokens = auth off (everyone is the same anonymous owner).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AuthConfig {
    pub tokens: Vec<TokenEntry>,
    /// Refuse to start without tokens (deployments set it, so that a missing secret cannot
    /// silently open the service to everyone).
    pub required: bool,
}

impl AuthConfig {
    /// Whether requests must carry a token.
    pub fn enabled(&self) -> bool {
        !self.tokens.is_empty()
    }

    /// The owner name of `token`, if it is one of ours. Compares every entry in constant time
    /// per byte so the answer time does not reveal how much of a token matched.
    pub fn name_for(&self, token: &str) -> Option<&str> {
        let mut found = None;
        for entry in &self.tokens {
            if constant_time_eq(entry.token.as_bytes(), token.as_bytes()) {
                found = Some(entry.name.as_str());
            }
        }
        found
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Zenoh endpoints (see the key space in ARCHITECTURE.md).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ZenohConfig {
    /// Start the Zenoh endpoints (also set by `--zenoh-listen` and the Zenoh environment
    /// variables).
    pub enabled: bool,
    /// `"peer"` or `"client"` (client mode needs a router in `connect`).
    pub mode: String,
    /// Endpoints to listen on, e.g. `tcp/127.0.0.1:7447`.
    pub listen: Vec<String>,
    /// Endpoints (routers or peers) to connect to.
    pub connect: Vec<String>,
    /// Multicast and gossip scouting (off by default: explicit endpoints are predictable).
    pub scouting: bool,
    /// This node's name in `relfusion/nodes/<node>/status` and in the cluster
    /// (`RELFUSIOND_ZENOH_NODE`); defaults to the host name. Unique per node.
    pub node: String,
    /// The HTTP address clients may reach this node at (`RELFUSIOND_ADVERTISE`, e.g.
    /// `https://node-1.example.com`), shown in the node status and in a session's placement;
    /// empty = not advertised.
    pub advertise: String,
    /// The Zenoh user this node authenticates as when it connects to a router or peer that
    /// requires it (deploy/zenoh); empty = none. Its password is `password`.
    pub user: String,
    pub password: String,
    /// Largest Zenoh message this node (and the router config it prints) reassembles, in MiB;
    /// 0 = twice `limits.max_frame_bytes`, at least 16 MiB. Zenoh's own default is 1 GiB, and
    /// access rules are checked only after reassembly: without this bound any peer could make
    /// a node hold a gigabyte per message. Cluster replies (forwarded downloads) are bounded
    /// by it too.
    pub max_message_mb: u64,
}

impl Default for ZenohConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            mode: "peer".into(),
            listen: Vec::new(),
            connect: Vec::new(),
            scouting: false,
            node: host_name(),
            advertise: String::new(),
            user: String::new(),
            password: String::new(),
            max_message_mb: 0,
        }
    }
}

impl Config {
    /// The effective `zenoh.max_message_mb` in bytes (see its doc).
    pub fn zenoh_max_message_bytes(&self) -> usize {
        let mb = match self.zenoh.max_message_mb {
            0 => (2 * self.limits.max_frame_bytes).div_ceil(1 << 20).max(16),
            n => n,
        };
        usize::try_from(mb.saturating_mul(1 << 20)).unwrap_or(usize::MAX)
    }
}

/// The machine's host name (Linux), else `relfusiond`.
fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '-'))
        .unwrap_or_else(|| "relfusiond".into())
}

/// The command-line flags that override the file and the environment.
#[derive(Clone, Debug, Default)]
pub struct FlagOverrides {
    pub listen: Option<SocketAddr>,
    pub data_dir: Option<PathBuf>,
    /// `--zenoh-listen` (repeatable); non-empty also enables Zenoh.
    pub zenoh_listen: Vec<String>,
}

/// Environment variables read by [`Config::apply_env`].
pub const ENV_VARS: &[&str] = &[
    "RELFUSIOND_LISTEN",
    "RELFUSIOND_DATA_DIR",
    "RELFUSIOND_MAX_SESSIONS",
    "RELFUSIOND_MODEL",
    "RELFUSIOND_ZENOH",
    "RELFUSIOND_ZENOH_LISTEN",
    "RELFUSIOND_ZENOH_CONNECT",
    "RELFUSIOND_TOKENS",
    "RELFUSIOND_ZENOH_USER",
    "RELFUSIOND_ZENOH_PASSWORD",
    "RELFUSIOND_MEMORY_BUDGET_MB",
    "RELFUSIOND_TLS_CERT",
    "RELFUSIOND_TLS_KEY",
    "RELFUSIOND_ZENOH_NODE",
    "RELFUSIOND_ADVERTISE",
    "RELFUSIOND_STORAGE",
    "RELFUSIOND_S3_ENDPOINT",
    "RELFUSIOND_S3_BUCKET",
    "RELFUSIOND_S3_PREFIX",
    "AWS_ACCESS_KEY_ID",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_REGION",
];

impl Config {
    /// Reads a TOML file; missing keys take their defaults. Values are validated by
    /// [`Config::resolve`], once the environment and flags are applied (a file may leave the
    /// tokens to the environment).
    pub fn load(path: &Path) -> Result<Self, ServerError> {
        let err = |message: String| ServerError::Config {
            path: path.display().to_string(),
            message,
        };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        toml::from_str(&text).map_err(|e| err(e.to_string()))
    }

    /// The configuration in force: default, then `file`, then the environment (`env` looks a
    /// variable up; `std::env::var` in the binary), then `flags`.
    pub fn resolve(
        file: Option<&Path>,
        env: impl Fn(&str) -> Option<String>,
        flags: &FlagOverrides,
    ) -> Result<Self, ServerError> {
        let mut config = match file {
            Some(path) => Config::load(path)?,
            None => Config::default(),
        };
        config.apply_env(env)?;
        config.apply_flags(flags);
        config.validate().map_err(|message| ServerError::Config {
            path: "(environment and flags)".into(),
            message,
        })?;
        Ok(config)
    }

    /// Applies the `RELFUSIOND_*` variables ([`ENV_VARS`]). Lists are comma-separated;
    /// Zenoh endpoints also enable Zenoh; tokens are `name:token,name:token`.
    pub fn apply_env(&mut self, env: impl Fn(&str) -> Option<String>) -> Result<(), ServerError> {
        let bad = |var: &str, message: String| ServerError::Config {
            path: format!("${var}"),
            message,
        };
        let list = |value: &str| -> Vec<String> {
            value
                .split(',')
                .map(str::trim)
                .filter(|s| !s.is_empty())
                .map(String::from)
                .collect()
        };
        if let Some(v) = env("RELFUSIOND_LISTEN") {
            self.listen = v
                .trim()
                .parse()
                .map_err(|e| bad("RELFUSIOND_LISTEN", format!("{v:?}: {e}")))?;
        }
        if let Some(v) = env("RELFUSIOND_DATA_DIR") {
            self.data_dir = PathBuf::from(v);
        }
        if let Some(v) = env("RELFUSIOND_MAX_SESSIONS") {
            self.limits.max_sessions = v
                .trim()
                .parse()
                .map_err(|e| bad("RELFUSIOND_MAX_SESSIONS", format!("{v:?}: {e}")))?;
        }
        if let Some(v) = env("RELFUSIOND_MODEL") {
            self.model.path = PathBuf::from(v);
        }
        if let Some(v) = env("RELFUSIOND_ZENOH_LISTEN") {
            self.zenoh.listen = list(&v);
            self.zenoh.enabled = true;
        }
        if let Some(v) = env("RELFUSIOND_ZENOH_CONNECT") {
            self.zenoh.connect = list(&v);
            self.zenoh.enabled = true;
        }
        if let Some(v) = env("RELFUSIOND_TLS_CERT") {
            self.tls.cert = Some(PathBuf::from(v));
        }
        if let Some(v) = env("RELFUSIOND_TLS_KEY") {
            self.tls.key = Some(PathBuf::from(v));
        }
        if let Some(v) = env("RELFUSIOND_ZENOH") {
            self.zenoh.enabled = match v.trim() {
                "on" | "true" | "1" => true,
                "off" | "false" | "0" => false,
                other => {
                    return Err(bad(
                        "RELFUSIOND_ZENOH",
                        format!("{other:?}: on or off (true/false, 1/0)"),
                    ));
                }
            };
        }
        if let Some(v) = env("RELFUSIOND_ZENOH_NODE") {
            self.zenoh.node = v.trim().to_string();
        }
        if let Some(v) = env("RELFUSIOND_ADVERTISE") {
            self.zenoh.advertise = v.trim().to_string();
        }
        self.storage
            .apply_env(&env)
            .map_err(|message| bad("RELFUSIOND_STORAGE", message))?;
        self.ros2
            .apply_env(&env)
            .map_err(|message| bad("RELFUSIOND_ROS2", message))?;
        if let Some(v) = env("RELFUSIOND_ZENOH_USER") {
            self.zenoh.user = v.trim().to_string();
        }
        if let Some(v) = env("RELFUSIOND_ZENOH_PASSWORD") {
            self.zenoh.password = v.trim().to_string();
        }
        if let Some(v) = env("RELFUSIOND_MEMORY_BUDGET_MB") {
            self.limits.memory_budget_mb = v
                .trim()
                .parse()
                .map_err(|e| bad("RELFUSIOND_MEMORY_BUDGET_MB", format!("{v:?}: {e}")))?;
        }
        if let Some(v) = env("RELFUSIOND_TOKENS") {
            self.auth.tokens = list(&v)
                .into_iter()
                .map(|pair| match pair.split_once(':') {
                    Some((name, token)) if !name.is_empty() && !token.is_empty() => {
                        Ok(TokenEntry {
                            name: name.to_string(),
                            token: token.to_string(),
                        })
                    }
                    _ => Err(bad(
                        "RELFUSIOND_TOKENS",
                        "expected name:token[,name:token...]".into(),
                    )),
                })
                .collect::<Result<_, _>>()?;
        }
        Ok(())
    }

    /// Applies command-line flags (highest precedence).
    pub fn apply_flags(&mut self, flags: &FlagOverrides) {
        if let Some(listen) = flags.listen {
            self.listen = listen;
        }
        if let Some(dir) = &flags.data_dir {
            self.data_dir = dir.clone();
        }
        if !flags.zenoh_listen.is_empty() {
            self.zenoh.listen = flags.zenoh_listen.clone();
            self.zenoh.enabled = true;
        }
    }

    /// Checks values serde cannot: positive limits, a known Zenoh mode, unique tokens whose
    /// names are usable as Zenoh user names and key chunks.
    pub fn validate(&self) -> Result<(), String> {
        limits::validate(&self.limits, &self.http, &self.quotas, &self.retention)?;
        if self.tls.cert.is_some() != self.tls.key.is_some() {
            return Err("tls: give both cert and key (PEM files), or neither".into());
        }
        self.storage.validate()?;
        if !is_owner_name(&self.zenoh.node) {
            return Err(format!(
                "zenoh.node {:?} must be 1-64 characters of a-z, A-Z, 0-9, '-', '_' (it is a \
                 Zenoh key chunk)",
                self.zenoh.node
            ));
        }
        if !matches!(self.zenoh.mode.as_str(), "peer" | "client") {
            return Err(format!(
                "zenoh.mode must be \"peer\" or \"client\", got {:?}",
                self.zenoh.mode
            ));
        }
        let mut tokens: Vec<&str> = self.auth.tokens.iter().map(|t| t.token.as_str()).collect();
        tokens.sort_unstable();
        if tokens.windows(2).any(|w| w[0] == w[1]) {
            return Err("auth.tokens: the same token is listed twice".into());
        }
        if self.auth.required && self.auth.tokens.is_empty() {
            return Err(
                "auth.required is set but no tokens are configured: set RELFUSIOND_TOKENS \
                 (name:token,...) or [auth] tokens"
                    .into(),
            );
        }
        for t in &self.auth.tokens {
            if t.token.is_empty() || t.token.contains(char::is_whitespace) {
                return Err(format!(
                    "auth.tokens: the token of {:?} must be non-empty, without spaces",
                    t.name
                ));
            }
            if !is_owner_name(&t.name) {
                return Err(format!(
                    "auth.tokens: name {:?} must be 1-64 characters of a-z, A-Z, 0-9, '-', '_' \
                     (it names the owner in Zenoh keys and Zenoh user names)",
                    t.name
                ));
            }
        }
        let mut names: Vec<&str> = self.auth.tokens.iter().map(|t| t.name.as_str()).collect();
        names.sort_unstable();
        if self.zenoh.enabled && names.windows(2).any(|w| w[0] == w[1]) {
            return Err(
                "auth.tokens: with Zenoh on, each name has one token (it is the Zenoh password \
                 of that user)"
                    .into(),
            );
        }
        if !self.zenoh.user.is_empty() && self.zenoh.password.is_empty() {
            return Err("zenoh.user needs zenoh.password".into());
        }
        self.ros2.validate(self.zenoh.enabled, &names)
    }

    /// The default configuration as TOML, for `--print-default-config`.
    pub fn default_toml() -> String {
        toml::to_string_pretty(&Config::default()).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    #[test]
    fn default_config_round_trips_through_toml() {
        let parsed: Config = toml::from_str(&Config::default_toml()).expect("parse default");
        assert_eq!(parsed, Config::default());
        assert!(Config::default().validate().is_ok());
    }

    #[test]
    fn unknown_keys_are_rejected() {
        assert!(toml::from_str::<Config>("lisen = \"127.0.0.1:1\"").is_err());
        assert!(toml::from_str::<Config>("[limits]\nmax_sesions = 3\n").is_err());
    }

    #[test]
    fn precedence_is_flag_then_env_then_file_then_default() {
        let dir = std::env::temp_dir().join(format!("relfusiond-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let file = dir.join("c.toml");
        std::fs::write(
            &file,
            "listen = \"127.0.0.1:1111\"\ndata_dir = \"from-file\"\n[limits]\nmax_sessions = 7\nframe_queue = 3\n",
        )
        .expect("write");
        let env: HashMap<&str, &str> = [
            ("RELFUSIOND_LISTEN", "127.0.0.1:2222"),
            ("RELFUSIOND_DATA_DIR", "from-env"),
            ("RELFUSIOND_TOKENS", "alice:a1,bob:b2"),
            (
                "RELFUSIOND_ZENOH_CONNECT",
                "tcp/127.0.0.1:7447, tcp/127.0.0.1:7448",
            ),
        ]
        .into_iter()
        .collect();
        let lookup = |k: &str| env.get(k).map(|v| v.to_string());
        let flags = FlagOverrides {
            listen: Some("127.0.0.1:3333".parse().expect("addr")),
            ..Default::default()
        };
        let c = Config::resolve(Some(&file), lookup, &flags).expect("resolve");
        assert_eq!(c.listen.port(), 3333, "flag beats env and file");
        assert_eq!(c.data_dir, PathBuf::from("from-env"), "env beats file");
        assert_eq!(c.limits.max_sessions, 7, "file beats default");
        assert_eq!(c.limits.frame_queue, 3);
        assert_eq!(
            c.limits.event_buffer,
            Limits::default().event_buffer,
            "default"
        );
        assert_eq!(c.auth.name_for("b2"), Some("bob"));
        assert_eq!(c.auth.name_for("b3"), None);
        assert_eq!(c.zenoh.connect.len(), 2);
        assert!(c.zenoh.enabled, "endpoints enable zenoh");

        let none = Config::resolve(None, |_| None, &FlagOverrides::default()).expect("defaults");
        assert_eq!(none, Config::default());
        let bad = Config::resolve(
            None,
            |k| (k == "RELFUSIOND_MAX_SESSIONS").then(|| "many".to_string()),
            &FlagOverrides::default(),
        );
        assert!(bad.is_err());
        let zero = Config::resolve(
            None,
            |k| (k == "RELFUSIOND_MAX_SESSIONS").then(|| "0".to_string()),
            &FlagOverrides::default(),
        );
        assert!(zero.is_err(), "max_sessions = 0 is refused");
        let flags = FlagOverrides {
            zenoh_listen: vec!["tcp/127.0.0.1:0".into()],
            ..Default::default()
        };
        let z = Config::resolve(None, |_| None, &flags).expect("zenoh flag");
        assert!(z.zenoh.enabled);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_deployment_config_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/relfusiond.toml");
        let flags = FlagOverrides::default();
        let no_tokens = Config::resolve(Some(&path), |_| None, &flags);
        assert!(
            no_tokens.is_err_and(|e| e.to_string().contains("RELFUSIOND_TOKENS")),
            "the deployment refuses to start without tokens"
        );
        let env = |k: &str| match k {
            "RELFUSIOND_TOKENS" => Some("alice:secret-a".to_string()),
            "RELFUSIOND_ZENOH_USER" => Some("relfusiond".to_string()),
            "RELFUSIOND_ZENOH_PASSWORD" => Some("node-secret".to_string()),
            _ => None,
        };
        let config = Config::resolve(Some(&path), env, &flags).expect("deploy config loads");
        assert!(config.auth.enabled() && config.auth.required);
        assert!(config.zenoh.enabled && config.zenoh.mode == "client");
        assert_eq!(config.data_dir, PathBuf::from("/data"));
    }
}
