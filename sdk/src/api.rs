//! The HTTP half of the client: one method per `/v1` route of `relfusiond` (Contract 2).
//!
//! Request and answer types are the server's own, defined once in `relfusion_proto::http`;
//! answers ignore fields the client does not know, so a newer server does not break an older
//! client.

use std::time::Duration;

use bytes::Bytes;
use relfusion_core::geometry::PinholeCamera;
pub use relfusion_proto::http::{
    CameraJson, CreateSession, CreatedSession, FrameAccepted, FramePolicy, MapInfo, MapList,
    MapMode, MapStart, Progress, SaveMap, SessionInfo, SessionKind, SessionList, SessionState,
};
use reqwest::{Method, RequestBuilder, Response, StatusCode};
use serde::de::DeserializeOwned;
use serde_json::Value;
use url::Url;

use crate::error::ClientError;

/// The API's JSON form of `camera`.
pub fn camera_json(c: &PinholeCamera) -> CameraJson {
    CameraJson {
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        width: c.width,
        height: c.height,
        distortion: c.distortion.map(|d| [d.k1, d.k2, d.p1, d.p2, d.k3]),
    }
}

fn http_client(tls: &rustls::ClientConfig) -> Result<reqwest::Client, ClientError> {
    Ok(reqwest::Client::builder()
        .connect_timeout(Duration::from_secs(10))
        .use_preconfigured_tls(tls.clone())
        .build()?)
}

/// A connection to one `relfusiond` (cheap to clone: the HTTP connection pool is shared).
#[derive(Clone, Debug)]
pub struct Client {
    base: Url,
    token: Option<String>,
    /// The token's name: the Zenoh user and tenant (HTTP does not need it).
    user: Option<String>,
    http: reqwest::Client,
    /// What HTTPS and WSS trust ([`crate::tls`]).
    tls: std::sync::Arc<rustls::ClientConfig>,
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
        let tls = crate::tls::client_config(&[])?;
        Ok(Self {
            base: url,
            token: token.filter(|t| !t.is_empty()),
            user: None,
            http: http_client(&tls)?,
            tls,
        })
    }

    /// The same client trusting also the CA certificates in `pem` (a private CA that signed
    /// the server's certificate), for HTTPS and WSS alike.
    pub fn with_root_ca(mut self, pem: &[u8]) -> Result<Self, ClientError> {
        self.tls = crate::tls::client_config(pem)?;
        self.http = http_client(&self.tls)?;
        Ok(self)
    }

    /// The TLS configuration the WebSocket transport connects with.
    pub(crate) fn tls(&self) -> std::sync::Arc<rustls::ClientConfig> {
        self.tls.clone()
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

    /// The token's name on the server, if given (Zenoh logs in with it).
    pub fn user(&self) -> Option<&str> {
        self.user.as_deref()
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

    /// `GET /metrics`: the server's Prometheus metrics (OpenMetrics text).
    pub async fn metrics(&self) -> Result<String, ClientError> {
        let resp = Self::send(self.request(Method::GET, "metrics")?).await?;
        Ok(resp.text().await?)
    }

    /// `GET /v1/cluster`: the nodes of the server's cluster and their load, as JSON.
    pub async fn cluster(&self) -> Result<Value, ClientError> {
        Self::json(self.request(Method::GET, "v1/cluster")?).await
    }

    /// `POST /v1/sessions`: opens a live session.
    pub async fn create_session(&self, req: &CreateSession) -> Result<SessionInfo, ClientError> {
        let created: CreatedSession =
            Self::json(self.request(Method::POST, "v1/sessions")?.json(req)).await?;
        Ok(created.session)
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
        let mut query = vec![("timestamp", timestamp.to_string())];
        if let Some(fid) = frame_id {
            query.push(("frame_id", fid.to_string()));
        }
        let content_type = match crate::message::sniff_encoding(&image) {
            crate::message::Encoding::Jpeg => "image/jpeg",
            crate::message::Encoding::Png => "image/png",
            crate::message::Encoding::Unknown => "application/octet-stream",
        };
        let rb = self
            .request(Method::POST, &session_path(id, "frames"))?
            .query(&query)
            .header(reqwest::header::CONTENT_TYPE, content_type)
            .body(image);
        let accepted: FrameAccepted = Self::json(rb).await?;
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
        let list: SessionList = Self::json(self.request(Method::GET, "v1/sessions")?).await?;
        Ok(list.sessions)
    }

    /// `POST /v1/maps`: keeps the map of the finished session `session` (one of this token's).
    pub async fn save_map(
        &self,
        session: &str,
        name: Option<&str>,
    ) -> Result<MapInfo, ClientError> {
        let body = SaveMap {
            session: session.to_string(),
            name: name.map(String::from),
        };
        Self::json(self.request(Method::POST, "v1/maps")?.json(&body)).await
    }

    /// `GET /v1/maps`: this token's saved maps.
    pub async fn maps(&self) -> Result<Vec<MapInfo>, ClientError> {
        let list: MapList = Self::json(self.request(Method::GET, "v1/maps")?).await?;
        Ok(list.maps)
    }

    /// `GET /v1/maps/{id}`.
    pub async fn map_info(&self, id: &str) -> Result<MapInfo, ClientError> {
        Self::json(self.request(Method::GET, &map_path(id))?).await
    }

    /// `DELETE /v1/maps/{id}`.
    pub async fn delete_map(&self, id: &str) -> Result<(), ClientError> {
        Self::send(self.request(Method::DELETE, &map_path(id))?)
            .await
            .map(drop)
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
            if info.state.is_terminal() {
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
        let created: CreatedSession = Self::json(rb).await?;
        Ok(created.session)
    }
}

/// `v1/sessions/{id}` or `v1/sessions/{id}/{tail}`, the id percent-encoded so that an
/// arbitrary string can never escape its path segment.
/// `v1/maps/{id}` with `id` percent-encoded as one path segment.
fn map_path(id: &str) -> String {
    let mut url = Url::parse("http://x/v1/maps/").expect("constant URL parses");
    if let Ok(mut segments) = url.path_segments_mut() {
        segments.pop_if_empty().push(id);
    }
    url.path().trim_start_matches('/').to_string()
}

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
    fn session_info_ignores_fields_it_does_not_know() {
        let info: SessionInfo = serde_json::from_value(serde_json::json!({
            "id": "s-1", "kind": "upload", "state": "running", "frames_received": 3,
            "frames_processed": 2, "frames_dropped": 0, "frames_lost": 0, "keyframes": 1,
            "keyframes_densified": 0, "mesh_revision": 0, "mesh_triangles": 0,
            "dense_mode": "off", "progress": {"processed": 2, "total": 10},
            "created_unix": 1, "model": "none", "a_field_of_a_newer_server": [1, 2],
            "camera": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 16, "height": 16}
        }))
        .expect("parses");
        assert_eq!(
            info.progress,
            Progress {
                processed: 2,
                total: Some(10)
            }
        );
        assert_eq!(
            (info.kind, info.state),
            (SessionKind::Upload, SessionState::Running)
        );
        assert!(!info.state.is_terminal());
    }

    #[test]
    fn create_request_matches_the_servers_json() {
        let cam = PinholeCamera::new(262.5, 262.5, 159.5, 119.5, 320, 240).expect("camera");
        let req = CreateSession {
            camera: Some(camera_json(&cam)),
            config: serde_json::json!({"pipeline": {"deterministic": true}}),
            model: None,
            policy: FramePolicy::Wait,
            map: None,
            ros2: None,
        };
        let v = serde_json::to_value(&req).expect("serialises");
        assert_eq!(v["policy"], "wait");
        assert_eq!(v["camera"]["width"], 320);
        assert!(v["camera"].get("distortion").is_none());
        assert!(v.get("model").is_none());
    }
}
