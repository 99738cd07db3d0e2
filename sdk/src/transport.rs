//! Choosing a transport: a session opened over HTTP + WebSocket or over Zenoh, as the same
//! [`SessionLink`].

use crate::api::{Client, CreateSession};
use crate::error::ClientError;
use crate::link::SessionLink;
use crate::zenoh_transport::Identity;

/// How frames reach the server and updates come back.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub enum Transport {
    /// `POST /v1/sessions` to open, then the session's WebSocket (`/v1/sessions/{id}/stream`).
    #[default]
    Http,
    /// Zenoh: the session is created through `relfusion/sessions/create` and frames/poses
    /// travel on its key space; `endpoint` is the router or peer to connect to
    /// (`tcp/127.0.0.1:7447`).
    Zenoh { endpoint: String },
}

/// Creates a session as `req` says and connects to it over `transport`.
pub async fn open_session(
    client: &Client,
    transport: &Transport,
    req: &CreateSession,
) -> Result<SessionLink, ClientError> {
    match transport {
        Transport::Http => {
            let info = client.create_session(req).await?;
            let mut link = crate::ws::connect(client, &info.id).await?;
            link.info = Some(info);
            Ok(link)
        }
        Transport::Zenoh { endpoint } => open_zenoh(client, endpoint, req).await,
    }
}

/// The Zenoh transport ([`crate::zenoh_transport`]) as the client's user and token.
async fn open_zenoh(
    client: &Client,
    endpoint: &str,
    req: &CreateSession,
) -> Result<SessionLink, ClientError> {
    crate::zenoh_transport::open(endpoint, &Identity::of(client), req).await
}
