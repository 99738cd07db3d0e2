//! The HTTP half of the client: one method per `/v1` route of `relfusiond` (Contract 2).
//!
//! Request and answer types mirror the server's JSON but are the client's own, and tolerant:
//! fields the client does not know are kept in `other` rather than rejected, so a newer server
//! does not break an older client.

use std::time::Duration;

use bytes::Bytes;
use relfusion_slam::geometry::PinholeCamera;
use reqwest::{Method, RequestBuilder, Response, StatusCode};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use url::Url;

use crate::error::ClientError;

/// Intrinsics as the server's JSON (`POST /v1/sessions`' `camera`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraJson {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    /// Brown-Conrady `k1 k2 p1 p2 k3`; absent for undistorted images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<[f64; 5]>,
}

impl From<&PinholeCamera> for CameraJson {
    fn from(c: &PinholeCamera) -> Self {
        Self {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            width: c.width,
            height: c.height,
            distortion: c.distortion.map(|d| [d.k1, d.k2, d.p1, d.p2, d.k3]),
        }
    }
}

/// What a session does with a frame that arrives while its queue is full.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FramePolicy {
    /// Live streams: the oldest queued frame is dropped (and counted), latency stays low.
    #[default]
    DropOldest,
    /// Replays: the server stops reading until there is room, so every frame is processed.
    Wait,
}

/// Body of `POST /v1/sessions`.
#[derive(Clone, Debug, Serialize)]
pub struct CreateSessionRequest {
    pub camera: CameraJson,
    /// Partial pipeline config as a JSON object (`{"pipeline":{"deterministic":true}}`);
    /// `null` keeps every default.
    #[serde(skip_serializing_if = "Value::is_null")]
    pub config: Value,
    /// `"none"`, `"default"` or a model name the server knows; `None`: the server default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    pub policy: FramePolicy,
}

/// Progress of an upload session.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Progress {
    #[serde(default)]
    pub processed: u64,
    /// Frames in the uploaded sequence (absent for live sessions).
    #[serde(default)]
    pub total: Option<u64>,
}

/// A session as the server describes it (`GET /v1/sessions/{id}`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SessionInfo {
    pub id: String,
    /// `live` or `upload`.
    #[serde(default)]
    pub kind: String,
    /// `queued`, `running`, `finishing`, `finished` or `failed`.
    #[serde(default)]
    pub state: String,
    #[serde(default)]
    pub frames_received: u64,
    #[serde(default)]
    pub frames_processed: u64,
    #[serde(default)]
    pub frames_dropped: u64,
    #[serde(default)]
    pub frames_lost: u64,
    #[serde(default)]
    pub keyframes: u64,
    #[serde(default)]
    pub progress: Option<Progress>,
    #[serde(default)]
    pub error: Option<String>,
    /// Every other field the server sent (camera, model, created_unix, ...).
    #[serde(flatten)]
    pub other: serde_json::Map<String, Value>,
}

impl SessionInfo {
    /// Finished or failed: nothing will change any more.
    pub fn is_done(&self) -> bool {
        matches!(self.state.as_str(), "finished" | "failed")
    }
}

/// Answer of `POST /v1/sessions` and `POST /v1/uploads`.
#[derive(Clone, Debug, Deserialize)]
struct Created {
    id: String,
    session: SessionInfo,
}

/// A connection to one `relfusiond` (cheap to clone: the HTTP connection pool is shared).
#[derive(Clone, Debug)]
pub struct Client {
    base: Url,
    token: Option<String>,
    /// The token's name: the Zenoh user and tenant (HTTP does not need it).
    user: Option<String>,
    http: reqwest::Client,
}

impl Client {
    /// A client for the server at `base` (`http://host:port`, optionally with a path prefix
    /// behind a proxy) that authenticates with the bearer `token` when given.
    pub fn new(base: &str, token: Option<String>) -> Result<Self, ClientError> {
        let bad = |reason: &str| ClientError::Url {
            url: base.to_string(),
            reason: reason.to_string(),
        };
        let mut url = Url::parse(base).map_err(|e| bad(&e.to_string()))?;
        if !matches!(url.scheme(), "http" | "https") {
            return Err(bad("the scheme must be http or https"));
        }
        if url.cannot_be_a_base() {
            return Err(bad("not a base URL"));
        }
        // Joining "v1/..." onto ".../prefix" would drop "prefix": make the path a folder.
        if !url.path().ends_with('/') {
            let path = format!("{}/", url.path());
            url.set_path(&path);
        }
        let http = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(10))
            .build()?;
        Ok(Self {
            base: url,
            token: token.filter(|t| !t.is_empty()),
            user: None,
            http,
        })
    }

    /// The server's base URL (always ends with `/`).
    pub fn base(&self) -> &Url {
        &self.base
    }

    /// The bearer token, if any.
    pub fn token(&self) -> Option<&str> {
        self.token.as_deref()
    }

    /// The same client as the token's `user` (its name on the server): Zenoh logs in with it.
    pub fn with_user(mut self, user: Option<String>) -> Self {
        self.user = user;
        self
    }

    /// Who the client is on Zenoh (user, token).
    pub fn zenoh_identity(&self) -> crate::zenoh_transport::Identity {
        crate::zenoh_transport::Identity {
            user: self.user.clone(),
            token: self.token.clone(),
        }
    }

    /// `base` joined with the relative `path` (no leading `/`).
    pub fn url(&self, path: &str) -> Result<Url, ClientError> {
        self.base.join(path).map_err(|e| ClientError::Url {
            url: format!("{}{path}", self.base),
            reason: e.to_string(),
        })
    }

    pub(crate) fn request(
        &self,
        method: Method,
        path: &str,
    ) -> Result<RequestBuilder, ClientError> {
        let rb = self.http.request(method, self.url(path)?);
        Ok(match &self.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        })
    }

    /// Sends `rb`; a non-2xx answer becomes [`ClientError::Api`].
    pub(crate) async fn send(rb: RequestBuilder) -> Result<Response, ClientError> {
        let resp = rb.send().await?;
        if resp.status().is_success() {
            return Ok(resp);
        }
        let status = resp.status().as_u16();
        let body = resp.bytes().await.unwrap_or_default();
        Err(ClientError::from_response(status, &body))
    }

    async fn json<T: DeserializeOwned>(rb: RequestBuilder) -> Result<T, ClientError> {
        let resp = Self::send(rb).await?;
        let body = resp.bytes().await?;
        serde_json::from_slice(&body).map_err(|e| {
            ClientError::Protocol(format!(
                "unexpected answer ({e}): {}",
                String::from_utf8_lossy(&body[..body.len().min(300)])
            ))
        })
    }

    /// `GET /healthz`: Ok when the server answers "ok".
    pub async fn health(&self) -> Result<(), ClientError> {
        Self::send(self.request(Method::GET, "healthz")?)
            .await
            .map(drop)
    }

    /// `GET /v1/version` (open route; the server's version and build facts as JSON).
    pub async fn version(&self) -> Result<Value, ClientError> {
        Self::json(self.request(Method::GET, "v1/version")?).await
    }

    /// `POST /v1/sessions`: opens a live session.
    pub async fn create_session(
        &self,
        req: &CreateSessionRequest,
    ) -> Result<SessionInfo, ClientError> {
        let created: Created =
            Self::json(self.request(Method::POST, "v1/sessions")?.json(req)).await?;
        Ok(with_id(created))
    }

    /// `POST /v1/sessions/{id}/frames`: one encoded image (JPEG or PNG). `frame_id` must be
    /// strictly increasing when given (else the server numbers frames itself). Returns the
    /// server's frame index.
    pub async fn push_frame(
        &self,
        id: &str,
        frame_id: Option<u64>,
        timestamp: f64,
        image: Bytes,
    ) -> Result<u64, ClientError> {
        #[derive(Deserialize)]
        struct Accepted {
            frame_index: u64,
        }
        let mut query = vec![("timestamp", timestamp.to_string())];
        if let Some(fid) = frame_id {
            query.push(("frame_id", fid.to_string()));
        }
        let content_type = match crate::link::sniff_encoding(&image) {
            crate::link::Encoding::Jpeg => "image/jpeg",
            crate::link::Encoding::Png => "image/png",
            crate::link::Encoding::Unknown => "application/octet-stream",
        };
        let rb = self
            .request(Method::POST, &session_path(id, "frames"))?
            .query(&query)
            .header(reqwest::header::CONTENT_TYPE, content_type)
            .body(image);
        let accepted: Accepted = Self::json(rb).await?;
        Ok(accepted.frame_index)
    }

    /// `POST /v1/sessions/{id}/finish`: end of stream; the session finishes its map.
    pub async fn finish(&self, id: &str) -> Result<(), ClientError> {
        Self::send(self.request(Method::POST, &session_path(id, "finish"))?)
            .await
            .map(drop)
    }

    /// `GET /v1/sessions/{id}`.
    pub async fn session(&self, id: &str) -> Result<SessionInfo, ClientError> {
        Self::json(self.request(Method::GET, &session_path(id, ""))?).await
    }

    /// `GET /v1/sessions`: the sessions this token may see.
    pub async fn list(&self) -> Result<Vec<SessionInfo>, ClientError> {
        #[derive(Deserialize)]
        struct List {
            sessions: Vec<SessionInfo>,
        }
        let list: List = Self::json(self.request(Method::GET, "v1/sessions")?).await?;
        Ok(list.sessions)
    }

    /// `DELETE /v1/sessions/{id}`: stops the session and removes its data.
    pub async fn delete(&self, id: &str) -> Result<(), ClientError> {
        Self::send(self.request(Method::DELETE, &session_path(id, ""))?)
            .await
            .map(drop)
    }

    /// `GET /v1/sessions/{id}/trajectory`: every frame's pose, TUM text.
    pub async fn trajectory(&self, id: &str) -> Result<String, ClientError> {
        self.text(id, "trajectory").await
    }

    /// `GET /v1/sessions/{id}/keyframes`: keyframe poses, TUM text.
    pub async fn keyframes(&self, id: &str) -> Result<String, ClientError> {
        self.text(id, "keyframes").await
    }

    async fn text(&self, id: &str, what: &str) -> Result<String, ClientError> {
        let resp = Self::send(self.request(Method::GET, &session_path(id, what))?).await?;
        Ok(resp.text().await?)
    }

    /// `GET /v1/sessions/{id}/{name}` as bytes (`pointcloud.ply`, `mesh.ply`, `mesh.glb`, ...).
    pub async fn download(&self, id: &str, name: &str) -> Result<Vec<u8>, ClientError> {
        let resp = Self::send(self.request(Method::GET, &session_path(id, name))?).await?;
        Ok(resp.bytes().await?.to_vec())
    }

    /// Polls `GET /v1/sessions/{id}` every `every` until the session is finished or failed,
    /// calling `on_info` with each answer; returns the last one.
    pub async fn wait_finished(
        &self,
        id: &str,
        every: Duration,
        mut on_info: impl FnMut(&SessionInfo),
    ) -> Result<SessionInfo, ClientError> {
        loop {
            let info = self.session(id).await?;
            on_info(&info);
            if info.is_done() {
                return Ok(info);
            }
            tokio::time::sleep(every).await;
        }
    }

    /// `POST /v1/uploads?format=tar` with `body` as the archive; see [`crate::upload`].
    pub(crate) async fn post_upload(
        &self,
        body: reqwest::Body,
        query: &[(&str, String)],
    ) -> Result<SessionInfo, ClientError> {
        let rb = self
            .request(Method::POST, "v1/uploads")?
            .query(query)
            .header(reqwest::header::CONTENT_TYPE, "application/x-tar")
            .body(body);
        let created: Created = Self::json(rb).await?;
        Ok(with_id(created))
    }
}

/// The answer's session info, with the id filled in from `id` if the info lacked it.
fn with_id(created: Created) -> SessionInfo {
    let mut info = created.session;
    if info.id.is_empty() {
        info.id = created.id;
    }
    info
}

/// `v1/sessions/{id}` or `v1/sessions/{id}/{tail}`, the id percent-encoded so that an
/// arbitrary string can never escape its path segment.
pub(crate) fn session_path(id: &str, tail: &str) -> String {
    let mut url = Url::parse("http://x/v1/sessions/").expect("constant URL parses");
    if let Ok(mut segments) = url.path_segments_mut() {
        segments.pop_if_empty().push(id);
        if !tail.is_empty() {
            segments.push(tail);
        }
    }
    url.path().trim_start_matches('/').to_string()
}

/// Whether `e` is the server's "this does not exist (yet)" answer.
pub fn is_not_found(e: &ClientError) -> bool {
    e.status() == Some(StatusCode::NOT_FOUND.as_u16())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base_urls_keep_their_prefix() {
        let c = Client::new("http://127.0.0.1:8780", None).expect("valid");
        assert_eq!(
            c.url("v1/sessions").expect("joins").as_str(),
            "http://127.0.0.1:8780/v1/sessions"
        );
        let c = Client::new("https://example.org/relfusion", Some(String::new())).expect("valid");
        assert_eq!(
            c.url("healthz").expect("joins").as_str(),
            "https://example.org/relfusion/healthz"
        );
        assert_eq!(c.token(), None, "an empty token means no token");
        assert!(Client::new("ftp://x", None).is_err());
        assert!(Client::new("not a url", None).is_err());
    }

    #[test]
    fn session_ids_cannot_escape_their_segment() {
        assert_eq!(session_path("s-1", ""), "v1/sessions/s-1");
        assert_eq!(session_path("s-1", "frames"), "v1/sessions/s-1/frames");
        assert_eq!(
            session_path("../x", "trajectory"),
            "v1/sessions/..%2Fx/trajectory"
        );
    }

    #[test]
    fn session_info_tolerates_unknown_fields() {
        let info: SessionInfo = serde_json::from_str(
            r#"{"id":"s-1","kind":"upload","state":"running","frames_received":3,
                "progress":{"processed":2,"total":10},"camera":{"fx":1},"model":"none"}"#,
        )
        .expect("parses");
        assert_eq!(
            info.progress,
            Some(Progress {
                processed: 2,
                total: Some(10)
            })
        );
        assert!(info.other.contains_key("camera"));
        assert!(!info.is_done());
    }

    #[test]
    fn create_request_matches_the_servers_json() {
        let cam = PinholeCamera::new(262.5, 262.5, 159.5, 119.5, 320, 240).expect("camera");
        let req = CreateSessionRequest {
            camera: (&cam).into(),
            config: serde_json::json!({"pipeline": {"deterministic": true}}),
            model: None,
            policy: FramePolicy::Wait,
        };
        let v = serde_json::to_value(&req).expect("serialises");
        assert_eq!(v["policy"], "wait");
        assert_eq!(v["camera"]["width"], 320);
        assert!(v["camera"].get("distortion").is_none());
        assert!(v.get("model").is_none());
    }
}
