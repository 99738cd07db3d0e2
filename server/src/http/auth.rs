//! Bearer-token authentication of the `/v1` routes: the [`Auth`] extractor over
//! [`crate::auth`] (the one token parser and check of HTTP, Zenoh and the cluster).
//!
//! Another owner's session is a 404, so ids cannot be probed.

use std::sync::Arc;

use axum::extract::FromRequestParts;
use axum::http::request::Parts;

use crate::session::Owner;
use crate::{ApiError, AppState};

/// The authenticated caller of a request (extractor: rejects with 401).
#[derive(Clone, Debug)]
pub struct Auth(pub Owner);

impl FromRequestParts<Arc<AppState>> for Auth {
    type Rejection = ApiError;

    async fn from_request_parts(
        parts: &mut Parts,
        state: &Arc<AppState>,
    ) -> Result<Self, Self::Rejection> {
        crate::auth::authenticate_request(&state.config.auth, &parts.headers, &parts.uri).map(Auth)
    }
}

/// The caller's token as an `Authorization` value, for a call relayed to another node (which
/// checks it again): from the header or from `?access_token=`.
pub fn relayed_authorization(
    headers: &axum::http::HeaderMap,
    uri: &axum::http::Uri,
) -> Option<String> {
    crate::auth::presented_token(headers, uri)
        .ok()
        .flatten()
        .map(|token| format!("Bearer {token}"))
}
