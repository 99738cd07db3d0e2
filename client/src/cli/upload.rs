//! `relfusion upload DATASET --server URL`: uploads a TUM-layout sequence (a tar archive built
//! on the fly) and follows its processing on the server.
//!
//! On a terminal: a byte bar while uploading, then a frame bar while the server processes.
//! Otherwise JSON lines on stdout: `{"uploaded": {"session", "bytes", "seconds"}}` once the
//! server has stored the archive durably, `{"progress": {"state", "processed", "total"}}` on
//! each change, and finally `{"session": ID, ...the session's final info}`. The exit status is
//! non-zero when the session failed.

use std::io::IsTerminal as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use relfusion_sdk::SessionState;
use relfusion_sdk::upload::{UploadOptions, UploadPlan, upload_dataset};
use serde_json::json;

use super::connect::{ConnectArgs, print_line, progress_bar, runtime};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Sequence folder in TUM layout.
    pub dataset: PathBuf,
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Return once the server has stored the upload, without following its processing.
    #[arg(long)]
    pub no_follow: bool,
    /// How often to ask the server for progress, milliseconds.
    #[arg(long, default_value_t = 250)]
    pub poll_ms: u64,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let client = args.connect.client()?;
    let tty = std::io::stderr().is_terminal();
    let opts = UploadOptions::default();
    let plan = UploadPlan::new(&args.dataset, &opts)?;
    let sent = Arc::new(AtomicU64::new(0));
    let byte_bar = tty.then(|| {
        let bar = indicatif::ProgressBar::new(plan.payload_bytes);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:40}] {bytes}/{total_bytes} uploading {bytes_per_sec}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar
    });
    runtime()?.block_on(async {
        let t0 = Instant::now();
        let (sent_w, bar_w) = (sent.clone(), byte_bar.clone());
        let info = upload_dataset(&client, &args.dataset, &opts, move |n, _| {
            sent_w.store(n, Ordering::Relaxed);
            if let Some(bar) = &bar_w {
                bar.set_position(n);
            }
        })
        .await?;
        if let Some(bar) = &byte_bar {
            bar.finish_and_clear();
        }
        let id = info.id.clone();
        if !tty || args.no_follow {
            print_line(&json!({ "uploaded": {
                "session": id,
                "bytes": sent.load(Ordering::Relaxed),
                "seconds": t0.elapsed().as_secs_f64(),
            }}));
        }
        if args.no_follow {
            return anyhow::Ok(());
        }
        let frame_bar = tty.then(|| progress_bar(plan.frames as u64, "frames"));
        let mut last = None;
        let done = client
            .wait_finished(&id, Duration::from_millis(args.poll_ms.max(10)), |info| {
                let progress = &info.progress;
                let now = (info.state, progress.processed);
                if last.as_ref() == Some(&now) {
                    return;
                }
                match &frame_bar {
                    Some(bar) => {
                        bar.set_position(progress.processed);
                        bar.set_message(json!(info.state).as_str().unwrap_or_default().to_string());
                    }
                    None => print_line(&json!({ "progress": {
                        "state": info.state,
                        "processed": progress.processed,
                        "total": progress.total,
                    }})),
                }
                last = Some(now);
            })
            .await?;
        if let Some(bar) = &frame_bar {
            bar.finish_and_clear();
        }
        let mut line = serde_json::to_value(&done)?;
        line["session"] = json!(id);
        print_line(&line);
        if done.state == SessionState::Failed {
            anyhow::bail!(
                "session {id} failed: {}",
                done.error.as_deref().unwrap_or("no reason given")
            );
        }
        anyhow::Ok(())
    })
}
