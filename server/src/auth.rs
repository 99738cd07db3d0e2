//! Who a caller is: bearer tokens, the one parser and the one check that HTTP, Zenoh and the
//! cluster's relay all use.
//!
//! With no tokens configured auth is off and every caller is [`Owner`]`(None)`. With tokens, a
//! caller presents one and acts as the token's name; sessions are scoped to that owner by the
//! session manager. A token travels as `Authorization: Bearer <token>` (HTTP; the scheme is
//! case-insensitive, RFC 9110 §11.1), as `?access_token=` (browsers cannot set headers on
//! WebSocket or EventSource requests), or as a Zenoh query's attachment (`Bearer <token>` or
//! the bare token).

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use axum::extract::Query;
use axum::http::header::AUTHORIZATION;
use axum::http::{HeaderMap, Uri};

use crate::ApiError;
use crate::config::AuthConfig;

/// Who owns a session: the name of the bearer token that created it (`None` when auth is off).
/// A token sees only its own sessions.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Owner(pub Option<String>);

impl Owner {
    /// The owner's Zenoh tenant (`relfusion/tenants/<tenant>/…`): its token name, or the
    /// public tenant when auth is off.
    pub fn tenant(&self) -> &str {
        self.0
            .as_deref()
            .unwrap_or(relfusion_proto::zenoh_keys::PUBLIC_TENANT)
    }
}

/// The token of an `Authorization` value `Bearer <token>` (any case of the scheme), or `None`
/// when it names another scheme or no token.
pub fn bearer(value: &str) -> Option<&str> {
    let value = value.trim();
    let (scheme, token) = value.split_once(char::is_whitespace)?;
    let token = token.trim();
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

/// The token of a Zenoh attachment or a relayed authorization: `Bearer <token>` or the bare
/// token.
pub fn bearer_or_bare(value: &str) -> Option<&str> {
    let value = value.trim();
    bearer(value).or((!value.is_empty() && !value.contains(char::is_whitespace)).then_some(value))
}

/// The token an HTTP request presents: the `Authorization: Bearer` header, else
/// `?access_token=`.
pub fn presented_token(headers: &HeaderMap, uri: &Uri) -> Result<Option<String>, ApiError> {
    if let Some(value) = headers.get(AUTHORIZATION) {
        let value = value
            .to_str()
            .map_err(|_| ApiError::unauthorized("the Authorization header is not ASCII"))?;
        return bearer(value).map(|t| Some(t.to_string())).ok_or_else(|| {
            ApiError::unauthorized("the Authorization header must be `Bearer <token>`")
        });
    }
    let query: HashMap<String, String> = Query::try_from_uri(uri)
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

/// The caller of an HTTP request (header or query token).
pub fn authenticate_request(
    auth: &AuthConfig,
    headers: &HeaderMap,
    uri: &Uri,
) -> Result<Owner, ApiError> {
    authenticate(auth, presented_token(headers, uri)?.as_deref())
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::config::TokenEntry;

    #[test]
    fn the_bearer_scheme_is_case_insensitive_and_needs_a_token() {
        assert_eq!(bearer("Bearer abc"), Some("abc"));
        assert_eq!(bearer("bearer abc"), Some("abc"));
        assert_eq!(bearer("BEARER  abc "), Some("abc"));
        assert_eq!(bearer("bEaReR\tabc"), Some("abc"));
        assert_eq!(bearer("Basic abc"), None);
        assert_eq!(bearer("Bearer"), None);
        assert_eq!(bearer("Bearer   "), None);
        assert_eq!(bearer("Bearerabc"), None);
        assert_eq!(bearer_or_bare("abc"), Some("abc"));
        assert_eq!(bearer_or_bare("BEARER abc"), Some("abc"));
        assert_eq!(bearer_or_bare("Basic abc"), None);
        assert_eq!(bearer_or_bare(""), None);
    }

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
        let headers = |v: &str| {
            let mut h = HeaderMap::new();
            h.insert(AUTHORIZATION, v.parse().expect("header"));
            h
        };
        let uri: Uri = "/v1/sessions?access_token=tok-a".parse().expect("uri");
        assert_eq!(
            authenticate_request(tokens, &HeaderMap::new(), &uri),
            Ok(Owner(Some("alice".into())))
        );
        assert_eq!(
            authenticate_request(tokens, &headers("BEARER tok-b"), &uri),
            Ok(Owner(Some("bob".into()))),
            "the header wins over the query"
        );
    }
}
