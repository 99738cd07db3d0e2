//! Bearer-token authentication of the `/v1` routes.
//!
//! With no tokens configured auth is off and every request is [`Owner`]`(None)`. With tokens,
//! a request must present one (`Authorization: Bearer <token>`) and acts as the token's name;
//! sessions are scoped to that owner by the session manager (another owner's session is a 404,
//! so ids cannot be probed). Browsers cannot set headers on WebSocket or EventSource requests,
//! so the token is also accepted as the `access_token` query parameter.

use std::collections::HashMap;
use std::sync::Arc;

use axum::extract::{FromRequestParts, Query};
use axum::http::header::AUTHORIZATION;
use axum::http::request::Parts;

use crate::config::AuthConfig;
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
        authenticate(&state.config.auth, presented_token(parts)?.as_deref()).map(Auth)
    }
}

/// The token a request presents: the `Authorization: Bearer` header, else `?access_token=`.
fn presented_token(parts: &Parts) -> Result<Option<String>, ApiError> {
    if let Some(value) = parts.headers.get(AUTHORIZATION) {
        let value = value
            .to_str()
            .map_err(|_| ApiError::unauthorized("the Authorization header is not ASCII"))?;
        let Some(token) = value
            .strip_prefix("Bearer ")
            .or_else(|| value.strip_prefix("bearer "))
        else {
            return Err(ApiError::unauthorized(
                "the Authorization header must be `Bearer <token>`",
            ));
        };
        return Ok(Some(token.trim().to_string()));
    }
    let query: HashMap<String, String> = Query::try_from_uri(&parts.uri)
        .map(|Query(q)| q)
        .unwrap_or_default();
    Ok(query.get("access_token").cloned())
}

/// Resolves a presented token against the configured ones. No tokens: auth is off.
pub fn authenticate(auth: &AuthConfig, presented: Option<&str>) -> Result<Owner, ApiError> {
    if !auth.enabled() {
        return Ok(Owner(None));
    }
    let Some(presented) = presented else {
        return Err(ApiError::unauthorized(
            "this server needs a bearer token: send `Authorization: Bearer <token>`",
        ));
    };
    auth.name_for(presented)
        .map(|name| Owner(Some(name.to_string())))
        .ok_or_else(|| ApiError::unauthorized("unknown bearer token"))
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::config::TokenEntry;

    #[test]
    fn no_tokens_means_auth_off() {
        let off = AuthConfig::default();
        assert_eq!(authenticate(&off, None), Ok(Owner(None)));
        assert_eq!(authenticate(&off, Some("anything")), Ok(Owner(None)));
    }

    #[test]
    fn tokens_map_to_their_names_and_others_are_refused() {
        let entry = |name: &str, token: &str| TokenEntry {
            name: name.into(),
            token: token.into(),
        };
        let tokens = &AuthConfig {
            tokens: vec![entry("alice", "tok-a"), entry("bob", "tok-b")],
            required: true,
        };
        assert_eq!(
            authenticate(tokens, Some("tok-b")),
            Ok(Owner(Some("bob".into())))
        );
        assert_eq!(
            authenticate(tokens, Some("tok-c")).map_err(|e| e.status),
            Err(401)
        );
        assert_eq!(
            authenticate(tokens, Some("tok-")).map_err(|e| e.status),
            Err(401)
        );
        assert_eq!(authenticate(tokens, None).map_err(|e| e.status), Err(401));
    }
}
