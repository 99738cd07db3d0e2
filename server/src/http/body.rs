//! Request bodies, bounded before a handler sees them.
//!
//! Every body except an upload's (streamed to disk by its handler, which applies the same
//! per-chunk timeout) and a WebSocket upgrade's is read here, whole, before the handler runs:
//! - at most `limits.max_frame_bytes` bytes (413 beyond; a declared `Content-Length` over it
//!   is refused before a byte is read);
//! - within `http.body_timeout_s` (408 after): a client that stops one byte short cannot
//!   hold its buffer;
//! - against a server-wide budget of buffered bytes (`limits.max_buffered_body_mb`) and the
//!   caller's share of it (`quotas.max_buffered_body_mb`, with auth on), reserved up front
//!   from the declared length (or the largest allowed body when none is declared): a request
//!   that finds no room gets 503 (429 over the caller's share) at once, so many slow bodies
//!   together cannot grow memory past the budget;
//! - only once the caller is authenticated: a `/v1` request without a valid token is refused
//!   before anything is reserved or read, so strangers cannot hold the budget, and no one
//!   tenant can hold more than its share of it.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{Method, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::session::Owner;
use crate::{ApiError, AppState};

/// Raw bytes in a request or response body (an image, an archive, a PLY or glTF file).
#[derive(Debug, utoipa::ToSchema)]
#[schema(value_type = String, format = Binary)]
pub struct Binary(pub Vec<u8>);

/// The budget's unit: permits count KiB (a `Semaphore` holds at most `u32::MAX >> 3` permits).
const UNIT: u64 = 1024;

fn units_of(mb: u64) -> u64 {
    (mb.saturating_mul(1 << 20) / UNIT).min(Semaphore::MAX_PERMITS as u64)
}

/// The budget of buffered request bodies: the server's, and each owner's share of it.
#[derive(Debug)]
pub struct BodyBudget {
    permits: Arc<Semaphore>,
    total_units: u64,
    /// Units one owner may hold at once.
    owner_units: u64,
    /// Each owner's share; owners are the configured tokens' names (a bounded set).
    owners: Mutex<HashMap<Owner, Arc<Semaphore>>>,
}

/// Room held for one body: its owner's share and the server's budget.
#[derive(Debug)]
pub struct Reservation {
    _owner: OwnedSemaphorePermit,
    _server: OwnedSemaphorePermit,
}

impl BodyBudget {
    /// A budget of `mb` MiB, of which one owner may hold `owner_mb` MiB.
    pub fn new(mb: u64, owner_mb: u64) -> Self {
        let total_units = units_of(mb);
        Self {
            permits: Arc::new(Semaphore::new(total_units as usize)),
            total_units,
            owner_units: units_of(owner_mb).min(total_units),
            owners: Mutex::new(HashMap::new()),
        }
    }

    /// Reserves `units` for `owner`: 429 beyond its share, 503 when the server's budget has
    /// no room. Never waits.
    fn reserve(&self, owner: &Owner, units: u32) -> Result<Reservation, ApiError> {
        let share = {
            let mut owners = self.owners.lock().unwrap_or_else(|e| e.into_inner());
            owners
                .entry(owner.clone())
                .or_insert_with(|| Arc::new(Semaphore::new(self.owner_units as usize)))
                .clone()
        };
        let owner_permit = share.try_acquire_many_owned(units).map_err(|_| {
            ApiError::quota(
                "this token has too many request bodies in flight (quotas.max_buffered_body_mb); \
                 retry shortly",
            )
        })?;
        let server_permit = self
            .permits
            .clone()
            .try_acquire_many_owned(units)
            .map_err(|_| {
                ApiError::unavailable(
                    "too many request bodies are being received (limits.max_buffered_body_mb); \
                     retry shortly",
                )
            })?;
        Ok(Reservation {
            _owner: owner_permit,
            _server: server_permit,
        })
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
) -> Result<(Request, Reservation), ApiError> {
    // Every buffered-body route is below /v1 and needs the caller: refuse strangers before
    // anything is reserved or read.
    let owner = if request.uri().path().starts_with("/v1/") {
        crate::auth::authenticate_request(&state.config.auth, request.headers(), request.uri())?
    } else {
        Owner(None)
    };
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
    let reservation = state.body_budget.reserve(&owner, units)?;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_owner_holds_at_most_its_share_and_the_server_its_budget() {
        // 4 MiB in all, 1 MiB per owner; bodies of 512 KiB.
        let budget = BodyBudget::new(4, 1);
        let units = (512 << 10) / UNIT as u32;
        let bob = Owner(Some("bob".into()));
        let held: Vec<_> = (0..2)
            .map(|_| budget.reserve(&bob, units).expect("within bob's share"))
            .collect();
        assert_eq!(
            budget.reserve(&bob, units).map_err(|e| e.status).err(),
            Some(429)
        );
        let others: Vec<_> = (0..6)
            .map(|i| {
                budget
                    .reserve(&Owner(Some(format!("t{i}"))), units)
                    .expect("room")
            })
            .collect();
        assert_eq!(budget.in_use_bytes(), 4 << 20);
        let alice = Owner(Some("alice".into()));
        assert_eq!(
            budget.reserve(&alice, units).map_err(|e| e.status).err(),
            Some(503)
        );
        drop(held);
        budget.reserve(&alice, units).expect("room again");
        drop(others);
    }
}
