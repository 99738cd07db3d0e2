//! Sessions on ROS 2 (`[ros2]`, issue 38): a robot on rmw_zenoh sees a session as a node with
//! topics, and can feed it from its camera topics, through the server's own Zenoh session —
//! no bridge, no DDS. The wire format is rmw_zenoh's ([`crate::ros2_names`]): CDR payloads
//! (`relfusion_viz::ros2`), keys `<domain>/<topic>/<type>/<hash>`, the 33-byte attachment,
//! and liveliness tokens for the node, its publishers and its subscriptions, so
//! `ros2 node list`, `ros2 topic list` and `ros2 topic echo` on an rmw_zenoh machine that
//! reaches the same router see them. Type hashes are REP-2011's (Jazzy, Kilted).
//!
//! A session opts in when it is created (`ros2` of `POST /v1/sessions` or of the Zenoh
//! `SessionConfig`, parsed once into a [`Ros2Request`]):
//! - `publish`: [`publish`] puts its `pose`, `tf`, `path`, `points` and `mesh` under
//!   `/relfusion/<tenant>/<session>/` (`relfusion_viz::ros2::log` says what and when);
//! - `image_topic` (+ `camera_info_topic`): [`input`] takes its frames from a ROS 2 camera.
//!
//! Tenants: every name is inside `/relfusion/<tenant>`, and with tokens the Zenoh access
//! control lets a tenant's user reach only `*/relfusion/<tenant>/**` and its tokens
//! ([`crate::zenoh_api::setup`]), as for relfusion's own keys.

pub mod input;
pub mod publish;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use relfusion_proto::http::Ros2Session;
use relfusion_viz::ros2::types::{COMPRESSED_IMAGE, IMAGE, RosType};
use serde::Serialize;
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::ApiError;
use crate::config::Ros2Config;
use crate::ros2_names as names;
use crate::session::{Session, SessionManager};

/// A create request's ROS 2 side, checked: names resolved in the tenant's namespace.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Ros2Request {
    pub publish: bool,
    pub input: Option<Ros2Input>,
    /// Where the camera comes from when the request has none.
    pub camera_info_topic: Option<String>,
}

/// A session's frames from a ROS 2 camera topic.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Ros2Input {
    pub image_topic: String,
    /// `sensor_msgs/CompressedImage` (the name ends in `/compressed`) or `sensor_msgs/Image`.
    pub image_type: RosType,
}

impl Ros2Request {
    /// The typed form of the JSON `ros2` (the protobuf `Ros2Options` converts to it first);
    /// `None` when it asks for nothing.
    pub fn parse(json: &Ros2Session, tenant: &str) -> Result<Option<Self>, ApiError> {
        let resolve = |field: &str, name: &Option<String>| -> Result<Option<String>, ApiError> {
            match name.as_deref().map(str::trim) {
                None | Some("") => Ok(None),
                Some(name) => names::resolve_topic(name, tenant)
                    .map(Some)
                    .map_err(|e| ApiError::bad_request(format!("ros2.{field}: {e}"))),
            }
        };
        let image_topic = resolve("image_topic", &json.image_topic)?;
        let camera_info_topic = resolve("camera_info_topic", &json.camera_info_topic)?;
        if camera_info_topic.is_some() && image_topic.is_none() {
            return Err(ApiError::bad_request(
                "ros2.camera_info_topic belongs with ros2.image_topic",
            ));
        }
        let input = image_topic.map(|image_topic| Ros2Input {
            image_type: if image_topic.ends_with("/compressed") {
                COMPRESSED_IMAGE
            } else {
                IMAGE
            },
            image_topic,
        });
        if !json.publish && input.is_none() {
            return Ok(None);
        }
        Ok(Some(Ros2Request {
            publish: json.publish,
            input,
            camera_info_topic,
        }))
    }
}

/// Counters of the ROS 2 side (in the node status).
#[derive(Debug, Default)]
pub struct Ros2Stats {
    pub sessions: AtomicU64,
    pub messages_published: AtomicU64,
    pub frames_in: AtomicU64,
    /// Input messages that were not the CDR of their type, or frames the session refused.
    pub messages_refused: AtomicU64,
}

/// A snapshot of [`Ros2Stats`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Ros2Counts {
    pub sessions: u64,
    pub messages_published: u64,
    pub frames_in: u64,
    pub messages_refused: u64,
}

/// The ROS 2 side of a node: its Zenoh session, its ROS 2 context (the entity ids), and the
/// tasks of the sessions on ROS 2.
#[derive(Debug)]
pub struct Ros2Bridge {
    zenoh: zenoh::Session,
    domain: u32,
    zid: String,
    /// rmw_zenoh's context-wide entity counter (node and endpoint ids).
    next_entity: AtomicU64,
    camera_info_timeout: Duration,
    frame_queue: usize,
    pub stats: Arc<Ros2Stats>,
    shutdown: watch::Receiver<bool>,
    tasks: Mutex<Vec<JoinHandle<()>>>,
}

impl Ros2Bridge {
    pub fn new(
        zenoh: zenoh::Session,
        config: &Ros2Config,
        frame_queue: usize,
        shutdown: watch::Receiver<bool>,
    ) -> Self {
        Ros2Bridge {
            zid: zenoh.zid().to_string(),
            zenoh,
            domain: config.domain_id,
            next_entity: AtomicU64::new(0),
            camera_info_timeout: Duration::from_secs(config.camera_info_timeout_s),
            frame_queue: frame_queue.max(1),
            stats: Arc::default(),
            shutdown,
            tasks: Mutex::default(),
        }
    }

    pub fn counts(&self) -> Ros2Counts {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        Ros2Counts {
            sessions: get(&self.stats.sessions),
            messages_published: get(&self.stats.messages_published),
            frames_in: get(&self.stats.frames_in),
            messages_refused: get(&self.stats.messages_refused),
        }
    }

    fn next_id(&self) -> u64 {
        self.next_entity.fetch_add(1, Ordering::Relaxed)
    }

    fn place<'a>(&'a self, node_id: u64, entity_id: u64, namespace: &'a str) -> names::Place<'a> {
        names::Place {
            domain: self.domain,
            zid: &self.zid,
            node_id,
            entity_id,
            namespace,
        }
    }

    /// Puts `session` on ROS 2 as `request` asks: its node, its publishers and its camera
    /// subscription, each with its liveliness token, until the session ends.
    pub async fn attach(
        &self,
        session: Arc<Session>,
        request: &Ros2Request,
    ) -> Result<(), ApiError> {
        let namespace = names::session_namespace(session.owner().tenant(), session.id());
        let node_id = self.next_id();
        let node_key = names::liveliness_key(
            &self.place(node_id, node_id, &namespace),
            names::Entity::Node,
        );
        let node = self
            .zenoh
            .liveliness()
            .declare_token(node_key)
            .await
            .map_err(|e| ApiError::internal(format!("ROS 2 node token: {e}")))?;
        let mut tasks = Vec::new();
        if request.publish {
            tasks.push(publish::start(self, session.clone(), &namespace, node_id).await?);
        }
        if let Some(input) = &request.input {
            tasks.push(input::start(self, session.clone(), input, &namespace, node_id).await?);
        }
        // The node lives as long as its last endpoint.
        let watcher = {
            let session = session.clone();
            let mut shutdown = self.shutdown.clone();
            tokio::spawn(async move {
                tokio::select! {
                    _ = session.wait_finished() => {}
                    _ = session.deleted() => {}
                    _ = shutdown.wait_for(|stop| *stop) => {}
                }
                drop(node);
            })
        };
        tasks.push(watcher);
        self.stats.sessions.fetch_add(1, Ordering::Relaxed);
        let mut all = self.tasks.lock().unwrap_or_else(|e| e.into_inner());
        all.retain(|t| !t.is_finished());
        all.extend(tasks);
        tracing::info!(session = %session.id(), %namespace, "session on ROS 2");
        Ok(())
    }

    /// The camera of a session created without one, from the first `sensor_msgs/CameraInfo`
    /// on `topic` within `[ros2] camera_info_timeout_s`.
    pub async fn camera_from_info(
        &self,
        topic: &str,
        tenant: &str,
    ) -> Result<relfusion_proto::http::CameraJson, ApiError> {
        input::camera_from_info(self, topic, tenant).await
    }

    /// The tasks of every session on ROS 2, for the server's shutdown.
    pub fn take_tasks(&self) -> Vec<JoinHandle<()>> {
        std::mem::take(&mut *self.tasks.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// A create request's ROS 2 side, ready to attach once the session exists.
#[derive(Debug)]
pub struct Prepared {
    bridge: Arc<Ros2Bridge>,
    request: Ros2Request,
    /// The camera read from the CameraInfo topic, for a request without one.
    pub camera: Option<relfusion_proto::http::CameraJson>,
}

/// The ROS 2 side of a create (HTTP or Zenoh), before the session exists: `json` parsed for
/// `tenant`, and, when the request has no camera (`has_camera` false), the camera read from
/// its CameraInfo topic. `None` when the request asks nothing of ROS 2.
pub async fn prepare(
    sessions: &SessionManager,
    json: Option<&Ros2Session>,
    has_camera: bool,
    tenant: &str,
) -> Result<Option<Prepared>, ApiError> {
    let Some(request) = json
        .map(|j| Ros2Request::parse(j, tenant))
        .transpose()?
        .flatten()
    else {
        return Ok(None);
    };
    let Some(bridge) = sessions.ros2() else {
        return Err(if sessions.config().ros2.enabled {
            ApiError::unavailable(
                "ROS 2 is not up yet (the Zenoh side is still joining its router)",
            )
        } else {
            ApiError::bad_request("this server does not serve ROS 2 ([ros2] enabled = false)")
        });
    };
    let camera = match (&request.camera_info_topic, has_camera) {
        (Some(topic), false) => Some(bridge.camera_from_info(topic, tenant).await?),
        _ => None,
    };
    Ok(Some(Prepared {
        bridge: bridge.clone(),
        request,
        camera,
    }))
}

impl Prepared {
    /// Puts the new session on ROS 2; a session that cannot be is deleted (nobody could feed
    /// or follow it as asked).
    pub async fn attach(
        self,
        sessions: &SessionManager,
        session: Arc<Session>,
    ) -> Result<(), ApiError> {
        if let Err(e) = self.bridge.attach(session.clone(), &self.request).await {
            let _ = sessions.delete(session.id(), session.owner());
            return Err(e);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_resolve_their_names_in_the_tenants_namespace() {
        let json = Ros2Session {
            publish: true,
            image_topic: Some("camera/image_raw/compressed".into()),
            camera_info_topic: Some("/relfusion/alice/camera/camera_info".into()),
        };
        let r = Ros2Request::parse(&json, "alice")
            .expect("valid")
            .expect("some");
        let input = r.input.expect("input");
        assert_eq!(
            input.image_topic,
            "/relfusion/alice/camera/image_raw/compressed"
        );
        assert_eq!(input.image_type, COMPRESSED_IMAGE);
        assert!(
            Ros2Request::parse(&Ros2Session::default(), "alice")
                .expect("ok")
                .is_none()
        );
        let e = Ros2Request::parse(&json, "bob").expect_err("outside");
        assert_eq!(e.status, 400);
        let lone_info = Ros2Session {
            camera_info_topic: Some("info".into()),
            ..Ros2Session::default()
        };
        assert!(Ros2Request::parse(&lone_info, "alice").is_err());
    }
}
