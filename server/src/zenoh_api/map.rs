//! The `relfusion/tenants/<tenant>/sessions/*/map` queryables (one per tenant): the whole
//! current map of one session as a protobuf `MapSnapshot` (trajectory, keyframes, mesh
//! blocks).
//!
//! The query attachment carries the bearer token; an unknown session, or one of another
//! token, is an error reply with a protobuf `Error` NOT_FOUND (missing or unknown token:
//! UNAUTHENTICATED). Poses are those of the downloadable TUM files, value for value: the
//! snapshot of a finished session equals `/v1/sessions/{id}/trajectory` and `/keyframes`.
//! Queries on wildcard keys (`…/sessions/*/map`) are ignored: a query names one session. The queryable is not complete, so in a multi-node deployment every node answers
//! and the node that has the session replies with the snapshot.

use std::sync::Arc;

use relfusion_proto::Message as _;
use relfusion_proto::zenoh_keys::{MAP, SessionKey, any_map, parse_session_key};
use tokio::task::JoinHandle;
use zenoh::query::Query;

use super::{Shared, bump, proto_error, serve_queryable};

use crate::session::snapshot::snapshot_bytes;
use crate::{ApiError, ServerError};

/// Declares `tenant`'s queryable and serves it until shutdown.
pub(crate) async fn serve(
    shared: Arc<Shared>,
    tenant: &str,
) -> Result<JoinHandle<()>, ServerError> {
    serve_queryable(shared, any_map(tenant), false, |shared, query| async move {
        answer(&shared, &query).await;
    })
    .await
}

async fn answer(shared: &Shared, query: &Query) {
    let key = query.key_expr().as_str().to_string();
    let Some(SessionKey {
        tenant,
        id,
        leaf: MAP,
    }) = parse_session_key(&key)
    else {
        return;
    };
    let result = match shared
        .owner(query.attachment(), tenant)
        .and_then(|owner| shared.sessions.get(id, &owner))
    {
        Ok(session) => tokio::task::spawn_blocking(move || snapshot_bytes(&session))
            .await
            .map_err(|e| ApiError::internal(format!("building the snapshot: {e}")))
            .and_then(|r| r),
        Err(e) => Err(e),
    };
    let sent = match result {
        Ok(bytes) => query.reply(key.as_str(), bytes).await,
        Err(error) => {
            bump(&shared.stats.queries_refused);
            query.reply_err(proto_error(&error).encode_to_vec()).await
        }
    };
    if let Err(e) = sent {
        tracing::warn!("replying to {key}: {e}");
    }
}
