//! Request bodies, bounded before a handler sees them.
//!
//! Every body except an upload's (streamed to disk by its handler, which applies the same
//! per-chunk timeout) and a WebSocket upgrade's is read here, whole, before the handler runs:
//! - at most `limits.max_frame_bytes` bytes (413 beyond; a declared `Content-Length` over it
//!   is refused before a byte is read);
//! - within `http.body_timeout_s` (408 after): a client that stops one byte short cannot
//!   hold its buffer;
//! - against a server-wide budget of buffered bytes (`limits.max_buffered_body_mb`),
//!   reserved up front from the declared length (or the largest allowed body when none is
//!   declared): a request that finds no room gets 503 at once, so many slow bodies together
//!   cannot grow memory past the budget.

use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{Method, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use tokio::sync::Semaphore;

use crate::{ApiError, AppState};

/// The budget's unit: permits count KiB (a `Semaphore` holds at most `u32::MAX >> 3` permits).
const UNIT: u64 = 1024;

/// The budget of buffered request bodies.
#[derive(Debug)]
pub struct BodyBudget {
    permits: Arc<Semaphore>,
    total_units: u64,
}

impl BodyBudget {
    /// A budget of `mb` MiB.
    pub fn new(mb: u64) -> Self {
        let total_units = (mb.saturating_mul(1 << 20) / UNIT).min(Semaphore::MAX_PERMITS as u64);
        Self {
            permits: Arc::new(Semaphore::new(total_units as usize)),
            total_units,
        }
    }

    /// Bytes reserved now (for metrics).
    pub fn in_use_bytes(&self) -> u64 {
        (self.total_units - self.permits.available_permits() as u64) * UNIT
    }
}

/// Whether the request's body is streamed by its handler (uploads) or absent (WebSocket
/// upgrades, GET, DELETE).
fn streamed_or_empty(request: &Request) -> bool {
    let method = request.method();
    if method == Method::GET || method == Method::HEAD || method == Method::DELETE {
        return true;
    }
    request.uri().path() == "/v1/uploads"
}

/// The middleware (see the module docs).
pub async fn buffer_body(
    State(state): State<Arc<AppState>>,
    request: Request,
    next: Next,
) -> Response {
    if streamed_or_empty(&request) {
        return next.run(request).await;
    }
    match read_whole(&state, request).await {
        Ok((request, reservation)) => {
            let response = next.run(request).await;
            drop(reservation);
            response
        }
        Err(e) => e.into_response(),
    }
}

async fn read_whole(
    state: &AppState,
    request: Request,
) -> Result<(Request, tokio::sync::OwnedSemaphorePermit), ApiError> {
    let limit = state.config.limits.max_frame_bytes;
    let declared = request
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    if declared.is_some_and(|n| n > limit) {
        return Err(too_large(limit));
    }
    let units = declared.unwrap_or(limit).div_ceil(UNIT).max(1);
    let units = u32::try_from(units).unwrap_or(u32::MAX);
    let reservation = state
        .body_budget
        .permits
        .clone()
        .try_acquire_many_owned(units)
        .map_err(|_| {
            ApiError::unavailable(
                "too many request bodies are being received (limits.max_buffered_body_mb); \
                 retry shortly",
            )
        })?;
    let (parts, body) = request.into_parts();
    let deadline = Duration::from_secs(state.config.http.body_timeout_s);
    let max = usize::try_from(limit).unwrap_or(usize::MAX);
    let bytes = match tokio::time::timeout(deadline, axum::body::to_bytes(body, max)).await {
        Err(_) => {
            return Err(ApiError::request_timeout(format!(
                "the request body did not arrive within {} s (http.body_timeout_s)",
                deadline.as_secs()
            )));
        }
        Ok(Err(e)) if is_length_limit(&e) => return Err(too_large(limit)),
        Ok(Err(e)) => {
            return Err(ApiError::bad_request(format!(
                "reading the request body failed: {e}"
            )));
        }
        Ok(Ok(bytes)) => bytes,
    };
    Ok((Request::from_parts(parts, Body::from(bytes)), reservation))
}

fn is_length_limit(e: &axum::Error) -> bool {
    let mut source: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(err) = source {
        if err.is::<http_body_util::LengthLimitError>() {
            return true;
        }
        source = err.source();
    }
    false
}

fn too_large(limit: u64) -> ApiError {
    ApiError::payload_too_large(format!(
        "request body larger than limits.max_frame_bytes = {limit} bytes"
    ))
}
