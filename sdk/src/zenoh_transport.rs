//! The Zenoh transport: a live session over the relfusion key space
//! ([`relfusion_proto::zenoh_keys`]) instead of HTTP + WebSocket.
//!
//! The client opens a Zenoh session in client mode connected to one endpoint (a relfusiond
//! listening with `--zenoh-listen`, or a Zenoh router the nodes join), with multicast and gossip
//! scouting off so it talks to exactly what it was told. On a server with tokens it logs in as
//! its token's name with the token as password ([`Identity`]) and may then use only its
//! tenant's keys (`relfusion/tenants/<name>/…`). It creates the session through its tenant's
//! `create` queryable (payload `SessionConfig`, attachment = bearer token), then subscribes to
//! the session's keys, publishes `Frame`s on `frames` (congestion control
//! `block`: with the `wait` policy the server's back-pressure reaches the sender) and `end`
//! after the last. Updates arrive on `poses` (`ServerMessage`) and `mesh` (`MeshUpdate`);
//! `finished` (`SessionFinished`) closes the stream, so a [`SessionLink`] over Zenoh behaves
//! like one over the WebSocket.
//!
//! Errors of the queryables come back as [`ClientError::Api`] with the status and code the
//! HTTP API would have used (UNAUTHENTICATED = 401 `unauthorized`, NOT_FOUND = 404, ...).

use std::time::{Duration, Instant};

use relfusion_proto::Message as _;
use relfusion_proto::http::MapMode;
use relfusion_proto::v1::{
    self, CreateSessionReply, EndOfStream, MapSnapshot, MeshUpdate, ServerMessage, SessionConfig,
    SessionFinished, client_message, server_message,
};
use relfusion_proto::zenoh_keys::{
    END, FINISHED, FRAMES, MAP, MESH, POSES, PUBLIC_TENANT, create_key, session_key,
    session_wildcard,
};
use tokio::sync::mpsc;
use zenoh::Session;
use zenoh::handlers::FifoChannel;
use zenoh::qos::CongestionControl;
use zenoh::sample::Locality;

use crate::api::{CreateSession, FramePolicy};
use crate::error::ClientError;
use crate::link::{FRAME_CHANNEL, SessionLink, TaskGuard, UPDATE_CHANNEL};

/// How long a query (create, map) waits for its reply.
pub const QUERY_TIMEOUT: Duration = Duration::from_secs(10);
/// How long the client waits for the endpoint to accept its connection.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);
/// How long the stream may stay without any connection before it fails (the server is gone).
pub const DISCONNECTED_LIMIT: Duration = Duration::from_secs(10);

fn transport(what: &str, e: impl std::fmt::Display) -> ClientError {
    ClientError::Transport(format!("Zenoh {what}: {e}"))
}

/// Who the client is on Zenoh: its token's name (the Zenoh user and its tenant) and the token
/// (password and query attachment). Both empty on a server without tokens (public tenant).
#[derive(Clone, Debug, Default)]
pub struct Identity {
    pub user: Option<String>,
    pub token: Option<String>,
}

impl Identity {
    /// The HTTP client's user and token.
    pub fn of(client: &crate::api::Client) -> Self {
        Identity {
            user: client.user().map(str::to_owned),
            token: client.token().map(str::to_owned),
        }
    }

    /// The tenant whose keys the client uses.
    pub fn tenant(&self) -> &str {
        self.user.as_deref().unwrap_or(PUBLIC_TENANT)
    }
}

/// The Zenoh configuration of a client connected to `endpoint` (e.g. `tcp/127.0.0.1:7447`):
/// client mode, that one endpoint, no scouting; with a user, Zenoh's user/password login.
pub fn client_config(endpoint: &str, identity: &Identity) -> Result<zenoh::Config, ClientError> {
    let mut config = zenoh::Config::default();
    let endpoints = serde_json::Value::from(vec![endpoint.to_string()]).to_string();
    let timeout = CONNECT_TIMEOUT.as_millis().to_string();
    let mut settings = vec![
        ("mode", "\"client\"".to_string()),
        ("connect/endpoints", endpoints),
        ("connect/timeout_ms", timeout),
        ("scouting/multicast/enabled", "false".to_string()),
        ("scouting/gossip/enabled", "false".to_string()),
    ];
    if let (Some(user), Some(token)) = (&identity.user, &identity.token) {
        settings.push((
            "transport/auth/usrpwd/user",
            serde_json::Value::from(user.as_str()).to_string(),
        ));
        settings.push((
            "transport/auth/usrpwd/password",
            serde_json::Value::from(token.as_str()).to_string(),
        ));
    }
    for (key, value) in settings {
        config
            .insert_json5(key, &value)
            .map_err(|e| ClientError::InvalidOption(format!("Zenoh {key}: {e}")))?;
    }
    Ok(config)
}

/// A Zenoh session connected to `endpoint` as `identity`.
pub async fn connect(endpoint: &str, identity: &Identity) -> Result<Session, ClientError> {
    zenoh::open(client_config(endpoint, identity)?)
        .await
        .map_err(|e| transport(&format!("connecting to {endpoint}"), e))
}

/// The error of a refused query, in the HTTP API's terms.
pub fn api_error(error: &v1::Error) -> ClientError {
    let (status, code) = match error.code() {
        v1::ErrorCode::InvalidArgument => (400, "invalid_argument"),
        v1::ErrorCode::Unauthenticated => (401, "unauthorized"),
        v1::ErrorCode::NotFound => (404, "not_found"),
        v1::ErrorCode::ResourceExhausted => (503, "resource_exhausted"),
        v1::ErrorCode::Internal | v1::ErrorCode::Unspecified => (500, "internal"),
    };
    ClientError::Api {
        status,
        code: code.into(),
        message: error.message.clone(),
    }
}

/// The protobuf `SessionConfig` for an HTTP-style create request.
pub fn session_config(req: &CreateSession) -> SessionConfig {
    SessionConfig {
        camera: req.camera.map(v1::Camera::from),
        config_json: if req.config.is_null() {
            String::new()
        } else {
            req.config.to_string()
        },
        model_name: req.model.clone().unwrap_or_default(),
        policy: match req.policy {
            FramePolicy::DropOldest => v1::FramePolicy::DropOldest,
            FramePolicy::Wait => v1::FramePolicy::Wait,
        } as i32,
        map_id: req.map.as_ref().map(|m| m.id.clone()).unwrap_or_default(),
        map_mode: match req.map.as_ref().map(|m| m.mode) {
            Some(MapMode::Localize) => v1::MapMode::Localize,
            Some(MapMode::Extend) => v1::MapMode::Extend,
            None => v1::MapMode::Unspecified,
        } as i32,
        ros2: req.ros2.as_ref().map(|r| v1::Ros2Options {
            publish: r.publish,
            image_topic: r.image_topic.clone().unwrap_or_default(),
            camera_info_topic: r.camera_info_topic.clone().unwrap_or_default(),
        }),
    }
}

/// Sends a query to `key` and returns the first successful reply's payload; with none, the
/// first error reply's payload as `Err(Some(bytes))`, or `Err(None)` when nobody answered.
async fn query(
    zenoh: &Session,
    key: &str,
    payload: Option<Vec<u8>>,
    token: Option<&str>,
) -> Result<Result<Vec<u8>, Option<Vec<u8>>>, ClientError> {
    let mut get = zenoh.get(key).timeout(QUERY_TIMEOUT);
    if let Some(payload) = payload {
        get = get.payload(payload);
    }
    if let Some(token) = token {
        get = get.attachment(token.to_string());
    }
    let replies = get
        .await
        .map_err(|e| transport(&format!("query {key}"), e))?;
    let mut first_error = None;
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => return Ok(Ok(sample.payload().to_bytes().into_owned())),
            Err(error) => {
                first_error.get_or_insert_with(|| error.payload().to_bytes().into_owned());
            }
        }
    }
    Ok(Err(first_error))
}

/// Creates a session through the tenant's `create` queryable; returns its id. A server that
/// is still starting may not have declared the queryable yet: a query nobody answers is
/// retried for up to [`QUERY_TIMEOUT`].
pub async fn create_session(
    zenoh: &Session,
    identity: &Identity,
    config: &SessionConfig,
) -> Result<String, ClientError> {
    let deadline = Instant::now() + QUERY_TIMEOUT;
    let key = create_key(identity.tenant());
    let token = identity.token.as_deref();
    loop {
        match query(zenoh, &key, Some(config.encode_to_vec()), token).await? {
            Ok(bytes) => {
                let reply = CreateSessionReply::decode(bytes.as_slice()).map_err(|e| {
                    ClientError::Protocol(format!("{key} replied something else: {e}"))
                })?;
                if let Some(error) = &reply.error {
                    return Err(api_error(error));
                }
                return Ok(reply.session_id);
            }
            Err(Some(bytes)) => {
                let error = CreateSessionReply::decode(bytes.as_slice())
                    .ok()
                    .and_then(|r| r.error)
                    .unwrap_or_else(|| v1::Error {
                        code: v1::ErrorCode::Internal as i32,
                        message: String::from_utf8_lossy(&bytes).into_owned(),
                    });
                return Err(api_error(&error));
            }
            Err(None) if Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(None) => {
                return Err(ClientError::Transport(format!(
                    "no relfusiond answered {key} (is Zenoh enabled on the server, and are the \
                     user and token right?)"
                )));
            }
        }
    }
}

/// The whole current map of a session (`…/sessions/<id>/map`).
pub async fn map_snapshot(
    zenoh: &Session,
    identity: &Identity,
    session_id: &str,
) -> Result<MapSnapshot, ClientError> {
    let key = session_key(identity.tenant(), session_id, MAP);
    match query(zenoh, &key, None, identity.token.as_deref()).await? {
        Ok(bytes) => MapSnapshot::decode(bytes.as_slice())
            .map_err(|e| ClientError::Protocol(format!("{key} replied something else: {e}"))),
        Err(Some(bytes)) => Err(match v1::Error::decode(bytes.as_slice()) {
            Ok(error) => api_error(&error),
            Err(_) => ClientError::Protocol(format!("{key}: undecodable error reply")),
        }),
        Err(None) => Err(ClientError::Transport(format!(
            "no relfusiond answered {key}"
        ))),
    }
}

/// Connects to `endpoint`, creates a session as `req` says and returns it as a
/// [`SessionLink`] (frames in, updates out), like the WebSocket transport.
pub async fn open(
    endpoint: &str,
    identity: &Identity,
    req: &CreateSession,
) -> Result<SessionLink, ClientError> {
    let zenoh = connect(endpoint, identity).await?;
    let session_id = create_session(&zenoh, identity, &session_config(req)).await?;
    attach(zenoh, identity.tenant(), session_id).await
}

/// Streams to an existing session `session_id` of `tenant` over `zenoh` (see [`open`]).
pub async fn attach(
    zenoh: Session,
    tenant: &str,
    session_id: String,
) -> Result<SessionLink, ClientError> {
    // Subscribe before the first frame goes out, so no update is missed. Only remote
    // publications: our own frames are not updates.
    let subscriber = zenoh
        .declare_subscriber(session_wildcard(tenant, &session_id))
        .allowed_origin(Locality::Remote)
        .with(FifoChannel::new(UPDATE_CHANNEL))
        .await
        .map_err(|e| transport("subscribing to the session", e))?;
    let declare = |leaf: &'static str| {
        zenoh
            .declare_publisher(session_key(tenant, &session_id, leaf))
            .congestion_control(CongestionControl::Block)
    };
    let frames_pub = declare(FRAMES)
        .await
        .map_err(|e| transport("declaring the frames publisher", e))?;
    let end_pub = declare(END)
        .await
        .map_err(|e| transport("declaring the end publisher", e))?;

    let (frames_tx, mut frames_rx) = mpsc::channel::<v1::ClientMessage>(FRAME_CHANNEL);
    let (updates_tx, updates_rx) = mpsc::channel(UPDATE_CHANNEL);

    let writer = tokio::spawn(async move {
        while let Some(message) = frames_rx.recv().await {
            let sent = match message.message {
                Some(client_message::Message::Frame(frame)) => {
                    frames_pub.put(frame.encode_to_vec()).await
                }
                Some(client_message::Message::EndOfStream(end)) => {
                    end_pub.put(end.encode_to_vec()).await
                }
                // The session was configured when it was created.
                Some(client_message::Message::Config(_)) | None => Ok(()),
            };
            if let Err(e) = sent {
                tracing::warn!("Zenoh publish failed: {e}");
                break;
            }
        }
    });

    let id = session_id.clone();
    let reader = tokio::spawn(async move {
        let mut check = tokio::time::interval(Duration::from_secs(1));
        let mut disconnected_since: Option<Instant> = None;
        loop {
            let sample = tokio::select! {
                sample = subscriber.recv_async() => match sample {
                    Ok(sample) => sample,
                    Err(_) => break,
                },
                _ = check.tick() => {
                    if !lost_connection(&zenoh, &mut disconnected_since).await {
                        continue;
                    }
                    let _ = updates_tx
                        .send(Err(ClientError::Transport(format!(
                            "lost the Zenoh connection for more than {DISCONNECTED_LIMIT:?}"
                        ))))
                        .await;
                    break;
                }
            };
            let key = sample.key_expr().as_str();
            let update = match decode_update(key, sample.payload().to_bytes().as_ref()) {
                Update::Message(update) => update,
                Update::Finished => break,
                Update::Other => continue,
            };
            if updates_tx.send(update).await.is_err() {
                break;
            }
        }
        let _ = subscriber.undeclare().await;
        tracing::debug!(session = %id, "Zenoh stream over");
    });

    Ok(SessionLink {
        session_id,
        info: None,
        frames: frames_tx,
        updates: updates_rx,
        tasks: TaskGuard(vec![writer, reader]),
    })
}

/// What one sample on a session's keys means to a client (one at a time, never stored: its
/// size does not matter).
#[allow(clippy::large_enum_variant)]
enum Update {
    Message(Result<ServerMessage, ClientError>),
    /// The session finished: the stream is over.
    Finished,
    /// Not an update (another leaf of the session's key space).
    Other,
}

/// Decodes a sample published on `key` (poses, mesh, finished).
fn decode_update(key: &str, payload: &[u8]) -> Update {
    let leaf = key.rsplit('/').next().unwrap_or_default();
    let update = match leaf {
        POSES => ServerMessage::decode(payload).map_err(|e| e.to_string()),
        MESH => MeshUpdate::decode(payload)
            .map(|mesh| ServerMessage {
                message: Some(server_message::Message::Mesh(mesh)),
            })
            .map_err(|e| e.to_string()),
        FINISHED => {
            if let Err(e) = SessionFinished::decode(payload) {
                tracing::warn!("undecodable {key}: {e}");
            }
            return Update::Finished;
        }
        _ => return Update::Other,
    };
    Update::Message(
        update.map_err(|e| ClientError::Protocol(format!("{key}: undecodable message ({e})"))),
    )
}

/// Whether `zenoh` has had no router or peer for [`DISCONNECTED_LIMIT`] (`since` keeps when
/// the links went).
async fn lost_connection(zenoh: &Session, since: &mut Option<Instant>) -> bool {
    let info = zenoh.info();
    let links = info.routers_zid().await.count() + info.peers_zid().await.count();
    if links > 0 {
        *since = None;
        return false;
    }
    since.get_or_insert_with(Instant::now).elapsed() >= DISCONNECTED_LIMIT
}

/// What [`ingest_rate`] measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct IngestRate {
    pub frames_published: u64,
    /// Frames the server accepted (decoded, validated, queued).
    pub frames_received: u64,
    /// Seconds from the first frame published until the server had accepted the last one.
    pub wall_s: f64,
    pub frames_per_s: f64,
}

/// Frames/s the server ingests over Zenoh: a session created as `req` says (use the
/// `drop_oldest` policy: with `wait` this measures the pipeline), every frame of `frames`
/// (`(timestamp, encoded image)`) published as fast as the transport takes them, and the
/// session's map queried every 20 ms until the server has accepted them all (publishing alone
/// would only measure the client's buffers). The session is ended afterwards.
pub async fn ingest_rate<B: AsRef<[u8]>>(
    endpoint: &str,
    identity: &Identity,
    req: &CreateSession,
    frames: &[(f64, B)],
) -> Result<IngestRate, ClientError> {
    let zenoh = connect(endpoint, identity).await?;
    let id = create_session(&zenoh, identity, &session_config(req)).await?;
    let tenant = identity.tenant();
    let publisher = zenoh
        .declare_publisher(session_key(tenant, &id, FRAMES))
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| transport("declaring the frames publisher", e))?;
    let t0 = Instant::now();
    for (i, (timestamp, image)) in frames.iter().enumerate() {
        let frame = v1::Frame {
            frame_id: i as u64,
            timestamp: *timestamp,
            image: image.as_ref().to_vec(),
            encoding: v1::ImageEncoding::Unspecified as i32,
            camera: None,
        };
        publisher
            .put(frame.encode_to_vec())
            .await
            .map_err(|e| transport("publishing a frame", e))?;
    }
    let n = frames.len() as u64;
    let deadline = Instant::now() + QUERY_TIMEOUT;
    let received = loop {
        let snapshot = map_snapshot(&zenoh, identity, &id).await?;
        if snapshot.frames_received >= n || Instant::now() > deadline {
            break snapshot.frames_received;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let wall_s = t0.elapsed().as_secs_f64();
    let _ = zenoh
        .put(
            session_key(tenant, &id, END),
            EndOfStream {}.encode_to_vec(),
        )
        .congestion_control(CongestionControl::Block)
        .await;
    let _ = zenoh.close().await;
    Ok(IngestRate {
        frames_published: n,
        frames_received: received,
        wall_s,
        frames_per_s: received as f64 / wall_s.max(1e-9),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn create_request_becomes_a_session_config() {
        let req = CreateSession {
            camera: Some(crate::api::CameraJson {
                fx: 300.0,
                fy: 301.0,
                cx: 160.0,
                cy: 120.0,
                width: 320,
                height: 240,
                distortion: Some([0.1, 0.0, 0.0, 0.0, 0.0]),
            }),
            config: serde_json::json!({"pipeline": {"deterministic": true}}),
            model: None,
            policy: FramePolicy::Wait,
            map: Some(relfusion_proto::http::MapStart {
                id: "m-0123456789abcdef01234567".into(),
                mode: MapMode::Localize,
            }),
            ros2: Some(relfusion_proto::http::Ros2Session {
                publish: true,
                ..Default::default()
            }),
        };
        let c = session_config(&req);
        assert!(
            c.ros2
                .as_ref()
                .is_some_and(|r| r.publish && r.image_topic.is_empty())
        );
        assert_eq!(c.map_id, "m-0123456789abcdef01234567");
        assert_eq!(c.map_mode(), v1::MapMode::Localize);
        let camera = c.camera.expect("camera");
        assert_eq!((camera.fy, camera.width), (301.0, 320));
        assert_eq!(camera.distortion.expect("distortion").k1, 0.1);
        assert_eq!(c.policy(), v1::FramePolicy::Wait);
        let json: serde_json::Value = serde_json::from_str(&c.config_json).expect("json");
        assert_eq!(json["pipeline"]["deterministic"], true);
        assert!(c.model_name.is_empty());
    }

    #[test]
    fn refusals_map_to_the_http_apis_codes() {
        let e = api_error(&v1::Error {
            code: v1::ErrorCode::Unauthenticated as i32,
            message: "no token".into(),
        });
        assert_eq!((e.status(), e.code()), (Some(401), Some("unauthorized")));
        let e = api_error(&v1::Error {
            code: v1::ErrorCode::NotFound as i32,
            message: "x".into(),
        });
        assert_eq!(e.status(), Some(404));
    }

    #[test]
    fn client_config_is_client_mode_without_scouting() {
        let anonymous = Identity::default();
        let c = client_config("tcp/127.0.0.1:7447", &anonymous).expect("valid");
        assert_eq!(c.get_json("mode").expect("mode"), "\"client\"");
        assert_eq!(
            c.get_json("scouting/multicast/enabled").expect("multicast"),
            "false"
        );
        assert!(client_config("nonsense", &anonymous).is_err());
        let alice = Identity {
            user: Some("alice".into()),
            token: Some("tok".into()),
        };
        let c = client_config("tcp/127.0.0.1:7447", &alice).expect("valid");
        assert_eq!(
            c.get_json("transport/auth/usrpwd/user").expect("user"),
            "\"alice\""
        );
        assert_eq!(alice.tenant(), "alice");
        assert_eq!(anonymous.tenant(), PUBLIC_TENANT);
    }
}
