//! `relfusiond`: starts the relfusion service.
//!
//! Configuration precedence: flag > environment (`RELFUSIOND_*`) > `--config` file > default.
//! SIGTERM and Ctrl-C shut down gracefully: no new connections, live sessions finish their
//! queued frames and persist results, uploads stop and re-run on the next start.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use clap::Parser;
use relfusion_server::config::FlagOverrides;
use relfusion_server::{AppState, Config};

#[derive(Debug, Parser)]
#[command(name = "relfusiond", version, about = "relfusion service")]
struct Args {
    /// TOML configuration file (every key optional).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print the default configuration as TOML and exit.
    #[arg(long)]
    print_default_config: bool,
    /// Listen address (overrides the file and RELFUSIOND_LISTEN), e.g. 127.0.0.1:0.
    #[arg(long)]
    listen: Option<SocketAddr>,
    /// Data directory (overrides the file and RELFUSIOND_DATA_DIR).
    #[arg(long)]
    data_dir: Option<PathBuf>,
    /// Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable; enables Zenoh).
    #[arg(long)]
    zenoh_listen: Vec<String>,
    /// Print a zenohd router configuration (JSON5) with this server's Zenoh protection (user
    /// login, per-tenant access rules from the configured tokens) and exit; the router
    /// listens on ENDPOINT and reads its users from --zenoh-users-file.
    #[arg(long, value_name = "ENDPOINT")]
    print_zenoh_router_config: Option<String>,
    /// The users file the printed router configuration names (see --print-zenoh-users).
    #[arg(long, default_value = "/etc/zenoh/users")]
    zenoh_users_file: String,
    /// Run only a Zenoh router on ENDPOINT (e.g. tcp/0.0.0.0:7447) with this configuration's
    /// protection, for the nodes of a cluster to meet when no zenohd runs; serves no sessions.
    #[arg(long, value_name = "ENDPOINT")]
    zenoh_router: Option<String>,
    /// Print the router's users file (`name:token` lines, and the node user) and exit.
    #[arg(long)]
    print_zenoh_users: bool,
}

/// Resolves on SIGTERM (container stop, `kill`) or Ctrl-C.
async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::warn!("cannot listen for SIGTERM: {e}");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => tracing::info!("Ctrl-C received"),
        () = term => tracing::info!("SIGTERM received"),
    }
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    relfusion_server::memory::configure_allocator();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    if args.print_default_config {
        print!("{}", Config::default_toml());
        return Ok(());
    }
    let flags = FlagOverrides {
        listen: args.listen,
        data_dir: args.data_dir,
        zenoh_listen: args.zenoh_listen,
    };
    let config = Config::resolve(args.config.as_deref(), |k| std::env::var(k).ok(), &flags)?;
    if let Some(listen) = &args.print_zenoh_router_config {
        println!(
            "{}",
            relfusion_server::zenoh_api::setup::router_config(
                &config,
                listen,
                &args.zenoh_users_file
            )
        );
        return Ok(());
    }
    if args.print_zenoh_users {
        print!(
            "{}",
            relfusion_server::zenoh_api::setup::users_text(&config)
        );
        return Ok(());
    }
    if let Some(listen) = &args.zenoh_router {
        relfusion_server::zenoh_api::setup::run_router(
            &config,
            listen,
            Box::pin(shutdown_signal()),
        )
        .await?;
        return Ok(());
    }
    // A bad certificate or key stops the start, before anything listens.
    let tls = relfusion_server::http::tls::acceptor(&config.tls).map_err(anyhow::Error::msg)?;
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .with_context(|| format!("binding {}", config.listen))?;
    let addr = listener.local_addr()?;
    // Opening recovers the previous run's sessions (uploads resume) before we announce.
    let state = tokio::task::spawn_blocking(move || AppState::open(config))
        .await
        .context("starting the session manager")??;
    // The one stdout line: scripts and tests read the bound address from it (port 0).
    println!("listening on {addr}");
    tracing::info!(%addr, data_dir = %state.config.data_dir.display(), "relfusiond ready");
    relfusion_server::run(listener, tls, Arc::new(state), Box::pin(shutdown_signal())).await?;
    tracing::info!("stopped");
    Ok(())
}
