//! What every service subcommand (`stream`, `upload`, `fetch`, `bench serve`) needs to reach a
//! `relfusiond`: its URL (`http://` or `https://`; WebSockets follow as `ws://`/`wss://`),
//! a CA to trust beyond the web's roots, and, when the server has auth on, a bearer token.

use relfusion_sdk::Client;

/// Where relfusiond listens by default (its config's `listen`).
pub const DEFAULT_SERVER: &str = "http://127.0.0.1:8780";

#[derive(Debug, Clone, clap::Args)]
pub struct ConnectArgs {
    /// Server URL [default: $RELFUSION_SERVER, else http://127.0.0.1:8780].
    #[arg(long)]
    pub server: Option<String>,
    /// Bearer token, when the server has auth on [default: $RELFUSION_TOKEN].
    #[arg(long)]
    pub token: Option<String>,
    /// The token's name on the server, which Zenoh logs in with (`--zenoh` on a server with
    /// tokens) [default: $RELFUSION_USER].
    #[arg(long)]
    pub user: Option<String>,
    /// PEM file of a CA certificate to trust for `https://` servers besides the web's roots (a
    /// private CA that signed the server's certificate) [default: $RELFUSION_CA_CERT].
    #[arg(long, value_name = "PEM")]
    pub ca_cert: Option<std::path::PathBuf>,
}

impl ConnectArgs {
    /// The server URL: the flag, else `RELFUSION_SERVER`, else the default.
    pub fn server(&self) -> String {
        self.server
            .clone()
            .or_else(|| std::env::var("RELFUSION_SERVER").ok())
            .unwrap_or_else(|| DEFAULT_SERVER.to_string())
    }

    /// A client for the server, with the flag's token or `RELFUSION_TOKEN` (and user, or
    /// `RELFUSION_USER`).
    pub fn client(&self) -> anyhow::Result<Client> {
        let token = self
            .token
            .clone()
            .or_else(|| std::env::var("RELFUSION_TOKEN").ok());
        let user = self
            .user
            .clone()
            .or_else(|| std::env::var("RELFUSION_USER").ok());
        let client = Client::new(&self.server(), token)?.with_user(user);
        let ca = self
            .ca_cert
            .clone()
            .or_else(|| std::env::var_os("RELFUSION_CA_CERT").map(Into::into));
        Ok(match ca {
            Some(path) => {
                let pem = std::fs::read(&path)
                    .map_err(|e| anyhow::anyhow!("--ca-cert {}: {e}", path.display()))?;
                client.with_root_ca(&pem)?
            }
            None => client,
        })
    }
}

/// The async runtime of one service command (two workers: the client does I/O, not compute).
pub fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}

/// Prints one JSON line on stdout (flushed: consumers read it live).
pub fn print_line(value: &serde_json::Value) {
    use std::io::Write as _;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{value}");
    let _ = out.flush();
}

/// A progress bar on stderr counting `unit`s.
pub fn progress_bar(len: u64, unit: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    let template = format!("{{elapsed_precise}} [{{bar:40}}] {{pos}}/{{len}} {unit} {{msg}}");
    bar.set_style(
        indicatif::ProgressStyle::with_template(&template)
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar
}
