//! `relfusion health --server URL`: exits 0 when relfusiond answers its liveness check, 1 with
//! the reason otherwise (the container image's HEALTHCHECK: it has no curl).

use super::connect::{ConnectArgs, runtime};

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub connect: ConnectArgs,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let client = args.connect.client()?;
    runtime()?.block_on(async {
        tokio::time::timeout(std::time::Duration::from_secs(5), client.health())
            .await
            .map_err(|_| anyhow::anyhow!("no answer within 5 s"))??;
        println!("ok");
        Ok(())
    })
}
