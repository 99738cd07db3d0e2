//! HTTP requests over Zenoh: a node that does not hold a session forwards the request to the
//! node that does (`relfusion/cluster/nodes/<node>/http`), which runs it through its own HTTP
//! router and replies with the response.
//!
//! The query's attachment is the request head as JSON (method, path and query, the headers
//! that matter: auth, content type, accept), its payload the body (already read whole and
//! bounded by the body middleware); the reply's attachment is the response head, its payload
//! the body (bounded by one Zenoh message, `zenoh.max_message_mb`). The owner marks the request forwarded
//! ([`FORWARDED`]) so that it is never forwarded again: a session the owner no longer holds
//! is its 404, not a loop. Streaming responses (WebSocket, SSE) do not go this way.

use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::Request;
use axum::http::{HeaderName, HeaderValue, Method, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use tower::ServiceExt as _;

use super::{Cluster, node_key};
use crate::ApiError;

/// The header a forwarded request carries: the node it came from.
pub const FORWARDED: &str = "x-relfusion-forwarded-by";
/// Leaf of the HTTP queryable.
pub const HTTP: &str = "http";
/// How long a forwarded request may take (a frame that waits for queue room, a large
/// download).
pub const FORWARD_TIMEOUT: Duration = Duration::from_secs(120);
/// How long a listing waits for each other node.
pub const GATHER_TIMEOUT: Duration = Duration::from_secs(5);
/// Room for a reply's head and Zenoh's framing within one Zenoh message.
const REPLY_OVERHEAD: usize = 64 << 10;

/// Request headers that travel.
const REQUEST_HEADERS: [HeaderName; 4] = [
    header::AUTHORIZATION,
    header::CONTENT_TYPE,
    header::ACCEPT,
    header::IF_NONE_MATCH,
];
/// Response headers that travel.
const RESPONSE_HEADERS: [HeaderName; 5] = [
    header::CONTENT_TYPE,
    header::CONTENT_DISPOSITION,
    header::ETAG,
    header::RETRY_AFTER,
    header::LOCATION,
];

/// The request head on the wire.
#[derive(Debug, Serialize, Deserialize)]
struct Head {
    method: String,
    uri: String,
    headers: Vec<(String, String)>,
    from: String,
}

/// The response head on the wire.
#[derive(Debug, Serialize, Deserialize)]
struct ReplyHead {
    status: u16,
    headers: Vec<(String, String)>,
}

fn kept(headers: &axum::http::HeaderMap, names: &[HeaderName]) -> Vec<(String, String)> {
    names
        .iter()
        .filter_map(|name| {
            let value = headers.get(name)?.to_str().ok()?;
            Some((name.as_str().to_string(), value.to_string()))
        })
        .collect()
}

impl Cluster {
    /// The largest response body one Zenoh message carries back.
    fn max_reply_bytes(&self) -> usize {
        self.sessions
            .config()
            .zenoh_max_message_bytes()
            .saturating_sub(REPLY_OVERHEAD)
    }

    /// Sends `request` to `node` and returns its response; 502 when the node does not answer.
    pub async fn forward(&self, node: &str, request: Request) -> Response {
        match self.try_forward(node, request).await {
            Ok(response) => response,
            Err(message) => ApiError {
                status: 502,
                code: "unavailable",
                message,
            }
            .into_response(),
        }
    }

    /// `GET path` on every other member, with the caller's `authorization`: the bodies of the
    /// 200 answers (members that do not answer within [`GATHER_TIMEOUT`] are left out).
    pub async fn gather(&self, path: &str, authorization: Option<&str>) -> Vec<Vec<u8>> {
        if self.zenoh().is_none() {
            return Vec::new();
        }
        let others: Vec<String> = self
            .members()
            .into_iter()
            .filter(|n| *n != self.node)
            .collect();
        let calls = others.iter().map(|node| async move {
            let mut request = Request::builder().method(Method::GET).uri(path);
            if let Some(auth) = authorization {
                request = request.header(header::AUTHORIZATION, auth);
            }
            let request = request.body(Body::empty()).ok()?;
            let response = tokio::time::timeout(GATHER_TIMEOUT, self.try_forward(node, request))
                .await
                .ok()?
                .ok()?;
            if response.status() != StatusCode::OK {
                return None;
            }
            axum::body::to_bytes(response.into_body(), self.max_reply_bytes())
                .await
                .ok()
                .map(|b| b.to_vec())
        });
        futures_util::future::join_all(calls)
            .await
            .into_iter()
            .flatten()
            .collect()
    }

    async fn try_forward(&self, node: &str, request: Request) -> Result<Response, String> {
        let zenoh = self.zenoh().ok_or("the cluster is not joined")?;
        let (parts, body) = request.into_parts();
        let head = Head {
            method: parts.method.to_string(),
            uri: parts
                .uri
                .path_and_query()
                .map_or_else(|| parts.uri.path().to_string(), |pq| pq.to_string()),
            headers: kept(&parts.headers, &REQUEST_HEADERS),
            from: self.node.clone(),
        };
        // Bodies reach here read whole (the body middleware bounded them).
        let body = axum::body::to_bytes(body, usize::MAX)
            .await
            .map_err(|e| format!("reading the request body: {e}"))?;
        let head = serde_json::to_vec(&head).map_err(|e| e.to_string())?;
        let replies = zenoh
            .get(node_key(node, HTTP))
            .attachment(head)
            .payload(body.to_vec())
            .timeout(FORWARD_TIMEOUT)
            .await
            .map_err(|e| format!("forwarding to node {node}: {e}"))?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|_| format!("node {node}, which holds this session, did not answer"))?;
        let sample = reply
            .result()
            .map_err(|e| format!("node {node} refused the forwarded request: {e:?}"))?;
        let head: ReplyHead = sample
            .attachment()
            .and_then(|a| serde_json::from_slice(&a.to_bytes()).ok())
            .ok_or_else(|| format!("node {node} answered without a response head"))?;
        let mut response = Response::new(Body::from(sample.payload().to_bytes().into_owned()));
        *response.status_mut() =
            StatusCode::from_u16(head.status).unwrap_or(StatusCode::BAD_GATEWAY);
        for (name, value) in head.headers {
            if let (Ok(name), Ok(value)) = (
                HeaderName::try_from(name.as_str()),
                HeaderValue::from_str(&value),
            ) {
                response.headers_mut().insert(name, value);
            }
        }
        Ok(response)
    }
}

/// Answers forwarded requests with this node's router.
pub(crate) async fn answer(cluster: Arc<Cluster>, query: zenoh::query::Query) {
    let outcome = async {
        let router = cluster.router.get().ok_or("this node is starting")?.clone();
        let head: Head = query
            .attachment()
            .and_then(|a| serde_json::from_slice(&a.to_bytes()).ok())
            .ok_or("no request head")?;
        let body = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let method = Method::from_bytes(head.method.as_bytes()).map_err(|_| "bad method")?;
        let mut request = Request::builder()
            .method(method)
            .uri(&head.uri)
            .body(Body::from(body))
            .map_err(|_| "bad request head")?;
        for (name, value) in &head.headers {
            if let (Ok(name), Ok(value)) = (
                HeaderName::try_from(name.as_str()),
                HeaderValue::from_str(value),
            ) && REQUEST_HEADERS.contains(&name)
            {
                request.headers_mut().insert(name, value);
            }
        }
        if let Ok(from) = HeaderValue::from_str(&head.from) {
            request
                .headers_mut()
                .insert(HeaderName::from_static(FORWARDED), from);
        }
        let response = router
            .oneshot(request)
            .await
            .map_err(|_| "the router failed")?;
        let (parts, body) = response.into_parts();
        let limit = cluster.max_reply_bytes();
        let bytes = axum::body::to_bytes(body, limit).await.map_err(|_| {
            "the response is larger than one cluster message (zenoh.max_message_mb): fetch it \
             from the node that runs the session"
        })?;
        let head = ReplyHead {
            status: parts.status.as_u16(),
            headers: kept(&parts.headers, &RESPONSE_HEADERS),
        };
        Ok::<_, &'static str>((serde_json::to_vec(&head).unwrap_or_default(), bytes))
    }
    .await;
    let sent = match outcome {
        Ok((head, bytes)) => {
            query
                .reply(query.key_expr().clone(), bytes.to_vec())
                .attachment(head)
                .await
        }
        Err(message) => query.reply_err(message.as_bytes().to_vec()).await,
    };
    if let Err(e) = sent {
        tracing::debug!("replying to a forwarded request: {e}");
    }
}
