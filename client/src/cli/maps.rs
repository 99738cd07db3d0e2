//! `relfusion maps save|list|show|delete`: the saved maps of relfusiond (`/v1/maps`), one JSON
//! line each. A saved map is what `relfusion stream --map ID` localises in.

use serde_json::json;

use super::connect::{ConnectArgs, print_line, runtime};

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    pub command: MapsCommand,
    #[command(flatten)]
    pub connect: ConnectArgs,
}

#[derive(Debug, clap::Subcommand)]
pub enum MapsCommand {
    /// Keep the map of a finished session.
    Save {
        /// The session id.
        session: String,
        /// A name to recognise the map by.
        #[arg(long)]
        name: Option<String>,
    },
    /// This token's maps.
    List,
    /// One map.
    Show { id: String },
    /// Delete a map.
    Delete { id: String },
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let client = args.connect.client()?;
    runtime()?.block_on(async {
        let value = match &args.command {
            MapsCommand::Save { session, name } => {
                json!(client.save_map(session, name.as_deref()).await?)
            }
            MapsCommand::List => json!({ "maps": client.maps().await? }),
            MapsCommand::Show { id } => json!(client.map_info(id).await?),
            MapsCommand::Delete { id } => {
                client.delete_map(id).await?;
                json!({ "deleted": id })
            }
        };
        print_line(&value);
        anyhow::Ok(())
    })
}
