//! `GET /v1/sessions/{id}/events`: the session's events as server-sent events (JSON), for
//! browsers (`EventSource`) and scripts (`curl -N`). Each SSE event is named after the event's
//! `type` (`pose`, `keyframe`, `keyframe_poses`, `dropped`, `finished`, `failed`); the stream
//! ends after `finished` or `failed`. A subscriber that reads too slowly loses events (the
//! pipeline never waits for it) and is told so by a `lagged` event with the count skipped.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::{Path, State};
use axum::response::sse::{Event, KeepAlive, Sse};
use futures_util::Stream;
use tokio::sync::broadcast::{self, error::RecvError};

use super::auth::Auth;
use super::error::ErrorBody;
use crate::session::{SessionEvent, SessionState};
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

fn event_stream(phase: Phase) -> impl Stream<Item = Result<Event, Infallible>> {
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
    ),
    security(("bearer" = []))
)]
pub async fn events(
    State(state): State<Arc<AppState>>,
    Auth(owner): Auth,
    Path(id): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let session = state.sessions.get(&id, &owner)?;
    // Subscribe before looking at the state, so an end between the two is not missed.
    let receiver = session.subscribe();
    let info = session.info();
    let phase = if info.state.is_terminal() {
        let event = if info.state == SessionState::Failed {
            SessionEvent::Failed {
                message: info.error.clone().unwrap_or_default(),
            }
        } else {
            SessionEvent::Finished {
                info: Box::new(info),
            }
        };
        Phase::AlreadyEnded(Some(to_sse(&event)))
    } else {
        Phase::Live(receiver)
    };
    Ok(
        Sse::new(event_stream(phase))
            .keep_alive(KeepAlive::new().interval(Duration::from_secs(15))),
    )
}
