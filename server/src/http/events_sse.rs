//! `GET /v1/sessions/{id}/events`: the session's events as server-sent events (JSON), for
//! browsers (`EventSource`) and scripts (`curl -N`). Each SSE event is named after the event's
//! `type` (`pose`, `keyframe`, `keyframe_poses`, `dropped`, `finished`, `failed`); the stream
//! ends after `finished` or `failed`. A subscriber that reads too slowly loses events (the
//! pipeline never waits for it) and is told so by a `lagged` event with the count skipped.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::{Path, State};
use axum::response::sse::{Event, KeepAlive, KeepAliveStream, Sse};
use futures_util::StreamExt as _;
use futures_util::stream::BoxStream;
use tokio::sync::broadcast::{self, error::RecvError};

use super::auth::Auth;
use super::error::ErrorBody;
use super::streams::StreamSlot;
use crate::locator::{Feed, Hop, Located, RelayFormat, RelayedSse, Update};
use crate::session::SessionEvent;
use crate::{ApiError, AppState};

fn to_sse(event: &SessionEvent) -> Event {
    // Serialising these plain structs cannot fail; `null` would still be valid SSE data.
    let json = serde_json::to_string(event).unwrap_or_else(|_| "null".into());
    Event::default().event(event.kind()).data(json)
}

/// Where the stream is: forwarding events, or done (after the terminal event).
enum Phase {
    Live(broadcast::Receiver<SessionEvent>),
    /// The session had already ended when subscribing: send this, then stop.
    AlreadyEnded(Option<Event>),
    Done,
}

fn event_stream(
    phase: Phase,
) -> impl futures_util::Stream<Item = Result<Event, Infallible>> + Send + 'static {
    futures_util::stream::unfold(phase, |phase| async move {
        match phase {
            Phase::Done => None,
            Phase::AlreadyEnded(event) => event.map(|e| (Ok(e), Phase::AlreadyEnded(None))),
            Phase::Live(mut receiver) => match receiver.recv().await {
                Ok(event) => {
                    let sse = to_sse(&event);
                    let next = if event.is_last() {
                        Phase::Done
                    } else {
                        Phase::Live(receiver)
                    };
                    Some((Ok(sse), next))
                }
                Err(RecvError::Lagged(skipped)) => {
                    let data = serde_json::json!({ "type": "lagged", "skipped": skipped });
                    let sse = Event::default().event("lagged").data(data.to_string());
                    Some((Ok(sse), Phase::Live(receiver)))
                }
                Err(RecvError::Closed) => None,
            },
        }
    })
}

/// One server-sent event as the OpenAPI document describes it (never built: the stream is
/// written by axum's `Sse`).
#[derive(Debug, utoipa::ToSchema)]
#[allow(dead_code)]
pub struct SseEvent {
    /// The event's type: `pose`, `keyframe`, `keyframe_poses`, `keyframe_densified`, `mesh`,
    /// `dropped`, `lagged`, `finished` or `failed`.
    pub event: String,
    /// The `SessionEvent` as JSON.
    pub data: String,
}

/// Follows a session's events (server-sent events, JSON data).
#[utoipa::path(
    get, path = "/v1/sessions/{id}/events", tag = "streams",
    params(("id" = String, Path, description = "Session id")),
    responses(
        (status = 200, description = "text/event-stream of JSON SessionEvents; `event:` is the event's type; ends after `finished` or `failed`", content_type = "text/event-stream", body = SseEvent),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
        (status = 404, description = "No such session", body = ErrorBody),
        (status = 410, description = "The session expired (retention.finished_ttl_s)", body = ErrorBody),
        (status = 429, description = "The session has limits.max_streams_per_session streams open, or the token quotas.max_streams", body = ErrorBody),
    ),
    security(("bearer" = []))
)]
pub async fn events(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
    headers: axum::http::HeaderMap,
    uri: axum::http::Uri,
) -> Result<Sse<KeepAliveStream<Events>>, ApiError> {
    // Counted against the owner's and the session's stream caps while it is open (once the
    // session is found: a cap must not tell whether another tenant's session exists).
    let open = || super::streams::open_stream(&state, &owner, &id);
    let session = match state.locator.locate(&id, &owner, Hop::of(&headers)).await? {
        Located::Here(session) => session,
        // Its node relays the events (and checks the token).
        Located::Elsewhere(remote) => {
            let authorization = super::auth::relayed_authorization(&headers, &uri);
            let slot = open()?;
            let limit = state.config.limits.event_buffer;
            let feed = remote
                .follow(authorization, limit, RelayFormat::Sse)
                .await?;
            return Ok(sse(remote_stream(feed), slot));
        }
    };
    let slot = open()?;
    // Subscribe before looking at the state, so an end between the two is not missed.
    let receiver = session.subscribe();
    let info = session.info();
    let phase = if info.state.is_terminal() {
        Phase::AlreadyEnded(Some(to_sse(&SessionEvent::last_of(info))))
    } else {
        Phase::Live(receiver)
    };
    Ok(sse(event_stream(phase).boxed(), slot))
}

/// The events of a session, from here or relayed from its node.
pub type Events = BoxStream<'static, Result<Event, Infallible>>;

/// The response: `events` with keep-alive comments, holding `slot` until the stream ends
/// or the client goes.
fn sse(events: Events, slot: StreamSlot) -> Sse<KeepAliveStream<Events>> {
    let events = events
        .map(move |event| {
            let _held = &slot;
            event
        })
        .boxed();
    Sse::new(events).keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
}

/// The events another node relays (its own SSE encoding); a `failed` event when that node
/// leaves the cluster.
fn remote_stream(feed: Feed) -> Events {
    futures_util::stream::unfold(Some(feed), |feed| async move {
        let mut feed = feed?;
        loop {
            let event = match feed.next().await {
                Update::Message(bytes) => match serde_json::from_slice::<RelayedSse>(&bytes) {
                    Ok(sse) => Event::default().event(sse.event).data(sse.data),
                    Err(_) => continue,
                },
                Update::NodeLeft(message) => {
                    let failed = RelayedSse::of(&SessionEvent::Failed { message });
                    let event = Event::default().event(failed.event).data(failed.data);
                    return Some((Ok(event), None));
                }
                Update::End | Update::Lost => return None,
            };
            return Some((Ok(event), Some(feed)));
        }
    })
    .boxed()
}
