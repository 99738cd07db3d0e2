//! The `relfusion/tenants/<tenant>/create` queryables (one per tenant): a query whose payload
//! is a protobuf `SessionConfig` (and whose attachment is the tenant's bearer token) creates a
//! live session of that tenant and puts it on Zenoh before the reply goes out, so the creator
//! can publish frames at once.
//!
//! The reply is a protobuf `CreateSessionReply`: a normal reply with `session_id` on success,
//! an error reply with `error` set otherwise (invalid camera or config: INVALID_ARGUMENT,
//! missing or unknown token: UNAUTHENTICATED, at capacity: RESOURCE_EXHAUSTED). The queryable
//! is declared complete, so a client's default query target asks exactly one node. That node
//! places the session like an HTTP create: when another member has more room, the query is
//! relayed to that member's own create queryable and its reply comes back as it is.
//! Queries on wildcard keys (`relfusion/**`) are ignored: creating needs the exact key.

use std::sync::Arc;

use relfusion_proto::Message as _;
use relfusion_proto::v1::{self, CreateSessionReply, SessionConfig};
use relfusion_proto::zenoh_keys::create_key;
use tokio::task::JoinHandle;
use zenoh::query::Query;

use super::{Shared, bump, proto_error, serve_queryable};
use crate::convert::camera_from_proto;
use crate::session::types::{FramePolicy, SessionRequest};
use crate::{ApiError, ServerError};
use relfusion_proto::http::{MapMode, MapStart, Ros2Session};

/// Declares `tenant`'s queryables and serves them until shutdown: the public one, whose
/// sessions are placed ([`crate::locator::Locator::place`]), and this node's own
/// ([`crate::locator::Locator::placed_create_key`]), which creates here what another node
/// placed on this one.
pub(crate) async fn serve(
    shared: Arc<Shared>,
    tenant: &str,
) -> Result<Vec<JoinHandle<()>>, ServerError> {
    let public = create_key(tenant);
    let own = shared.locator.placed_create_key(tenant);
    let mut tasks = Vec::new();
    for (key, place) in [(public, true), (own, false)] {
        let tenant = tenant.to_string();
        tasks.push(
            serve_queryable(shared.clone(), key.clone(), true, move |shared, query| {
                let (key, tenant) = (key.clone(), tenant.clone());
                async move {
                    if query.key_expr().as_str() == key {
                        answer(&shared, &query, &key, &tenant, place).await;
                    }
                }
            })
            .await?,
        );
    }
    Ok(tasks)
}

async fn answer(shared: &Arc<Shared>, query: &Query, key: &str, tenant: &str, place: bool) {
    if place && let Some(relayed) = create_where_placed(shared, query, tenant).await {
        // The chosen node's reply, as it is.
        let sent = match relayed {
            Ok(reply) => query.reply(key, reply).await,
            Err(refusal) => query.reply_err(refusal).await,
        };
        if let Err(e) = sent {
            tracing::warn!("replying to {key}: {e}");
        }
        return;
    }
    match create(shared, query, tenant).await {
        Ok(session_id) => {
            let reply = CreateSessionReply {
                session_id,
                error: None,
            };
            if let Err(e) = query.reply(key, reply.encode_to_vec()).await {
                tracing::warn!("replying to {key}: {e}");
            }
        }
        Err(error) => {
            bump(&shared.stats.queries_refused);
            tracing::info!(
                status = error.status,
                "Zenoh create refused: {}",
                error.message
            );
            let reply = CreateSessionReply {
                session_id: String::new(),
                error: Some(proto_error(&error)),
            };
            if let Err(e) = query.reply_err(reply.encode_to_vec()).await {
                tracing::warn!("replying to {key}: {e}");
            }
        }
    }
}

/// Relays a create with a valid token to the node placement chose and returns its reply (or
/// refusal); `None`: this node creates the session (no better node, or it did not answer in
/// time).
async fn create_where_placed(
    shared: &Shared,
    query: &Query,
    tenant: &str,
) -> Option<Result<Vec<u8>, Vec<u8>>> {
    shared.owner(query.attachment(), tenant).ok()?;
    let node = shared.locator.place()?;
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let relayed = node
        .create(tenant, payload, query.attachment().cloned())
        .await;
    match &relayed {
        Some(_) => tracing::info!(node = %node.name(), "Zenoh create placed on another node"),
        None => tracing::warn!(
            node = %node.name(),
            "a Zenoh create placed on another node got no answer; creating it here"
        ),
    }
    relayed
}

async fn create(shared: &Arc<Shared>, query: &Query, tenant: &str) -> Result<String, ApiError> {
    let owner = shared.owner(query.attachment(), tenant)?;
    let payload = query.payload().map(|p| p.to_bytes()).unwrap_or_default();
    let config = SessionConfig::decode(payload.as_ref()).map_err(|e| {
        bump(&shared.stats.malformed_messages);
        ApiError::bad_request(format!(
            "malformed query payload: not a protobuf relfusion.v1.SessionConfig ({e})"
        ))
    })?;
    let mut config = config;
    let ros2_json = config.ros2.as_ref().map(|r| {
        let topic = |t: &str| Some(t.trim().to_string()).filter(|t| !t.is_empty());
        Ros2Session {
            publish: r.publish,
            image_topic: topic(&r.image_topic),
            camera_info_topic: topic(&r.camera_info_topic),
        }
    });
    let mut ros2 = crate::ros2_api::prepare(
        &shared.sessions,
        ros2_json.as_ref(),
        config.camera.is_some(),
        tenant,
    )
    .await?;
    if let Some(c) = ros2.as_mut().and_then(|r| r.camera.take()) {
        config.camera = Some(v1::Camera::from(c));
    }
    let request = create_request(&config)?;
    let session = shared.sessions.create(request, &owner)?;
    if let Err(e) = shared.attach(session.clone()).await {
        // A session nobody can stream to would only hold a slot until its idle timeout.
        let _ = shared.sessions.delete(session.id(), &owner);
        return Err(e);
    }
    if let Some(ros2) = ros2 {
        ros2.attach(&shared.sessions, session.clone()).await?;
    }
    bump(&shared.stats.sessions_created);
    tracing::info!(session = %session.id(), "session created over Zenoh");
    Ok(session.id().to_string())
}

/// The typed create request of a protobuf `SessionConfig` (what HTTP's `CreateSession` parses
/// into).
pub fn create_request(config: &SessionConfig) -> Result<SessionRequest, ApiError> {
    let camera = config
        .camera
        .as_ref()
        .ok_or_else(|| ApiError::bad_request("SessionConfig.camera is required"))?;
    let overrides = match config.config_json.trim() {
        "" => serde_json::Value::Null,
        text => serde_json::from_str(text)
            .map_err(|e| ApiError::bad_request(format!("SessionConfig.config_json: {e}")))?,
    };
    let model = Some(config.model_name.trim())
        .filter(|m| !m.is_empty())
        .map(String::from);
    let policy = match config.policy() {
        v1::FramePolicy::Wait => FramePolicy::Wait,
        v1::FramePolicy::DropOldest | v1::FramePolicy::Unspecified => FramePolicy::DropOldest,
    };
    let map = match config.map_id.trim() {
        "" => None,
        id => Some(MapStart {
            id: id.to_string(),
            mode: match config.map_mode() {
                v1::MapMode::Localize | v1::MapMode::Unspecified => MapMode::Localize,
                v1::MapMode::Extend => MapMode::Extend,
            },
        }),
    };
    Ok(SessionRequest {
        map,
        ..SessionRequest::live(camera_from_proto(camera)?, &overrides, model, policy)?
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> v1::Camera {
        v1::Camera {
            fx: 300.0,
            fy: 300.0,
            cx: 160.0,
            cy: 120.0,
            width: 320,
            height: 240,
            distortion: None,
        }
    }

    #[test]
    fn session_config_becomes_the_typed_create_request() {
        let req = create_request(&SessionConfig {
            camera: Some(camera()),
            config_json: r#"{"pipeline":{"deterministic":true}}"#.into(),
            model_name: " none ".into(),
            policy: v1::FramePolicy::Wait as i32,
            map_id: "m-0123456789abcdef01234567".into(),
            map_mode: v1::MapMode::Unspecified as i32,
            ros2: None,
        })
        .expect("valid");
        assert_eq!(
            req.map,
            Some(MapStart {
                id: "m-0123456789abcdef01234567".into(),
                mode: MapMode::Localize
            })
        );
        assert_eq!(req.camera.width, 320);
        assert!(req.config.pipeline.deterministic);
        assert!(
            !req.config.pipeline.mapping_thread,
            "a waiting stream maps in step"
        );
        assert_eq!(req.model.as_deref(), Some("none"));
        assert_eq!(req.policy, FramePolicy::Wait);

        let defaults = create_request(&SessionConfig {
            camera: Some(camera()),
            ..Default::default()
        })
        .expect("valid");
        assert!(defaults.model.is_none());
        assert!(defaults.map.is_none());
        assert!(defaults.config.pipeline.mapping_thread);
        assert_eq!(defaults.policy, FramePolicy::DropOldest);
    }

    #[test]
    fn missing_camera_and_bad_json_are_invalid_arguments() {
        let e = create_request(&SessionConfig::default()).expect_err("no camera");
        assert_eq!(e.status, 400);
        let e = create_request(&SessionConfig {
            camera: Some(camera()),
            config_json: "{not json".into(),
            ..Default::default()
        })
        .expect_err("bad json");
        assert_eq!(e.status, 400);
        assert_eq!(proto_error(&e).code(), v1::ErrorCode::InvalidArgument);
        assert_eq!(
            proto_error(&ApiError::unauthorized("x")).code(),
            v1::ErrorCode::Unauthenticated
        );
    }
}
