//! `relfusion fetch SESSION --server URL --out DIR`: a session's results into a folder
//! (`trajectory.txt`, `keyframes.txt`, `pointcloud.ply`, and `mesh.ply` / `mesh.glb` when the
//! server has them); prints one JSON object naming what was written.

use std::path::PathBuf;
use std::time::Duration;

use relfusion_sdk::fetch::fetch;
use serde_json::json;

use super::connect::{ConnectArgs, print_line, runtime};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Session id (as `relfusion stream` / `upload` printed it).
    pub session: String,
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Output folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Wait until the session has finished first (results are final then).
    #[arg(long)]
    pub wait: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let client = args.connect.client()?;
    runtime()?.block_on(async {
        let info = if args.wait {
            client
                .wait_finished(&args.session, Duration::from_millis(250), |_| {})
                .await?
        } else {
            client.session(&args.session).await?
        };
        let fetched = fetch(&client, &args.session, &args.out).await?;
        print_line(&json!({
            "session": args.session,
            "state": info.state,
            "files": fetched.files.iter().map(|(p, n)| json!({"path": p, "bytes": n})).collect::<Vec<_>>(),
            "missing": fetched.missing.iter().map(|(f, why)| json!({"file": f, "reason": why})).collect::<Vec<_>>(),
        }));
        anyhow::Ok(())
    })
}
