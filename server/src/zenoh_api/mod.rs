//! The service on Zenoh: the same sessions as the HTTP API, addressed by key expressions so a
//! client or subscriber reaches a session wherever it runs (see the key space in
//! [`relfusion_proto::zenoh_keys`]).
//!
//! - [`setup`]: the Zenoh configuration from `[zenoh]` and `[auth]` (mode, endpoints,
//!   scouting; with tokens, user/password authentication and per-tenant access control).
//! - [`create`]: the `relfusion/tenants/<tenant>/create` queryables.
//! - [`link`]: one created session on Zenoh: its frames in, its updates out.
//! - [`map`]: the `relfusion/tenants/<tenant>/sessions/*/map` queryables (the whole map).
//! - [`status`]: `relfusion/nodes/<node>/status`, published every 2 s.
//!
//! Auth: when the server has tokens, Zenoh itself refuses peers without a token's
//! credentials and confines each to its tenant's keys ([`setup`]): nothing of a session can
//! be read or written over Zenoh without its owner's credentials. The create and map queries
//! also carry the bearer token as their attachment (UTF-8, optionally prefixed `Bearer `),
//! which must belong to the tenant the key names (defence in depth; another tenant's session
//! is NOT_FOUND, so ids cannot be probed). Without tokens every session is in the public
//! tenant, open to every peer, as HTTP is then.
//!
//! Nothing here does SLAM: frames go through [`Session::push_frame`] exactly like HTTP frames,
//! so a Zenoh session gives the same result as any other.

pub mod create;
pub mod link;
pub mod map;
pub mod setup;
pub mod status;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use relfusion_proto::Message as _;
use relfusion_proto::v1;
use serde::Serialize;
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::config::Config;
use crate::locator::Locator;
use crate::session::{Owner, Session, SessionManager};
use crate::{ApiError, ServerError};

/// How long [`ZenohHandle::close`] waits for its tasks before aborting them.
const CLOSE_GRACE: Duration = Duration::from_secs(5);

/// Counters of the Zenoh side (published in the node status).
#[derive(Debug, Default)]
pub struct ZenohStats {
    /// Sessions created through `relfusion/sessions/create`.
    pub sessions_created: AtomicU64,
    /// Create or map queries refused (bad request, auth, capacity, unknown session).
    pub queries_refused: AtomicU64,
    /// Frames accepted into a session.
    pub frames_accepted: AtomicU64,
    /// Frames refused by the session (corrupt image, size mismatch, after end of stream, ...).
    pub frames_refused: AtomicU64,
    /// Messages that were not the protobuf their key carries.
    pub malformed_messages: AtomicU64,
}

/// A snapshot of [`ZenohStats`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct ZenohCounts {
    pub sessions_created: u64,
    pub queries_refused: u64,
    pub frames_accepted: u64,
    pub frames_refused: u64,
    pub malformed_messages: u64,
}

impl ZenohStats {
    pub fn counts(&self) -> ZenohCounts {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        ZenohCounts {
            sessions_created: get(&self.sessions_created),
            queries_refused: get(&self.queries_refused),
            frames_accepted: get(&self.frames_accepted),
            frames_refused: get(&self.frames_refused),
            malformed_messages: get(&self.malformed_messages),
        }
    }
}

pub(crate) fn bump(counter: &AtomicU64) {
    counter.fetch_add(1, Ordering::Relaxed);
}

/// What every Zenoh task shares.
#[derive(Debug)]
pub(crate) struct Shared {
    pub zenoh: zenoh::Session,
    pub sessions: Arc<SessionManager>,
    pub stats: Arc<ZenohStats>,
    /// Turns `true` when the server shuts down.
    pub shutdown: watch::Receiver<bool>,
    /// The tasks of each session on Zenoh ([`link`]), pruned as they end.
    pub links: Mutex<HashMap<String, Vec<JoinHandle<()>>>>,
    /// Where sessions are (placement of creates, this node's load in its status).
    pub locator: Arc<Locator>,
}

impl Shared {
    /// The owner a query's attachment authenticates, which must be `tenant`'s (see the
    /// module docs).
    pub fn owner(
        &self,
        attachment: Option<&zenoh::bytes::ZBytes>,
        tenant: &str,
    ) -> Result<Owner, ApiError> {
        let token = match attachment {
            None => None,
            Some(bytes) => {
                let text = bytes.try_to_string().map_err(|_| {
                    ApiError::unauthorized("the query attachment (bearer token) is not UTF-8")
                })?;
                crate::auth::bearer_or_bare(&text).map(String::from)
            }
        };
        let owner = crate::auth::authenticate(&self.sessions.config().auth, token.as_deref())?;
        if owner.tenant() != tenant {
            return Err(ApiError::unauthorized(format!(
                "this token does not belong to tenant {tenant:?}"
            )));
        }
        Ok(owner)
    }

    /// Puts `session` on Zenoh (its frames subscriber and update publishers).
    pub async fn attach(self: &Arc<Self>, session: Arc<Session>) -> Result<(), ApiError> {
        let tasks = link::attach(self.clone(), session.clone()).await?;
        let mut links = self.links.lock().unwrap_or_else(|e| e.into_inner());
        links.retain(|_, handles| handles.iter().any(|h| !h.is_finished()));
        links.insert(session.id().to_string(), tasks);
        Ok(())
    }

    fn take_tasks(&self) -> Vec<JoinHandle<()>> {
        let mut links = self.links.lock().unwrap_or_else(|e| e.into_inner());
        links.drain().flat_map(|(_, handles)| handles).collect()
    }
}

/// Declares the queryable on `key` and hands every query to `answer`, one after the other,
/// until shutdown. `complete`: whether this node answers for the whole key (create) or only
/// for the sessions it runs (map).
pub(crate) async fn serve_queryable<F, Fut>(
    shared: Arc<Shared>,
    key: String,
    complete: bool,
    answer: F,
) -> Result<JoinHandle<()>, ServerError>
where
    F: Fn(Arc<Shared>, zenoh::query::Query) -> Fut + Send + 'static,
    Fut: std::future::Future<Output = ()> + Send,
{
    let queryable = shared
        .zenoh
        .declare_queryable(key.clone())
        .complete(complete)
        .await
        .map_err(|e| ServerError::Startup(format!("declaring {key}: {e}")))?;
    let mut shutdown = shared.shutdown.clone();
    Ok(tokio::spawn(async move {
        loop {
            let query = tokio::select! {
                query = queryable.recv_async() => match query {
                    Ok(query) => query,
                    Err(_) => break,
                },
                _ = shutdown.wait_for(|stop| *stop) => break,
            };
            answer(shared.clone(), query).await;
        }
    }))
}

/// The protobuf `Error` for a refused request (401 has its own code on the wire).
pub(crate) fn proto_error(error: &ApiError) -> v1::Error {
    let code = match error.status {
        401 => v1::ErrorCode::Unauthenticated,
        _ => error.proto_code(),
    };
    v1::Error {
        code: code as i32,
        message: error.message.clone(),
    }
}

/// A `ServerMessage` carrying `error`, encoded.
pub(crate) fn error_message_bytes(error: &ApiError) -> Vec<u8> {
    v1::ServerMessage {
        message: Some(v1::server_message::Message::Error(proto_error(error))),
    }
    .encode_to_vec()
}

/// The running Zenoh side of the service; [`ZenohHandle::close`] it on shutdown (after the
/// session manager has finished its sessions, so their last updates still go out).
#[derive(Debug)]
pub struct ZenohHandle {
    shared: Arc<Shared>,
    shutdown: watch::Sender<bool>,
    tasks: Vec<JoinHandle<()>>,
    /// The ROS 2 side (`[ros2]`), on the same Zenoh session.
    ros2: Option<Arc<crate::ros2_api::Ros2Bridge>>,
}

/// The tenants this node serves: one per token name, or the public tenant without tokens.
fn tenants(config: &Config) -> Vec<String> {
    let mut names: Vec<String> = config.auth.tokens.iter().map(|t| t.name.clone()).collect();
    names.sort_unstable();
    names.dedup();
    if names.is_empty() {
        names.push(relfusion_proto::zenoh_keys::PUBLIC_TENANT.to_string());
    }
    names
}

/// Opens the Zenoh session from `config` and declares each tenant's create and map
/// queryables and the node status publisher. Sessions created through Zenoh are served until
/// [`ZenohHandle::close`].
pub async fn start(config: &Config, locator: Arc<Locator>) -> Result<ZenohHandle, ServerError> {
    let sessions = locator.sessions().clone();
    // The user/password dictionary lives in the data dir's private tmp folder (emptied at
    // every start) for as long as the Zenoh runtime may re-read it.
    let users_file = sessions.temp_dir().join("zenoh-users");
    let zconfig = setup::zenoh_config(config, &users_file)?;
    let zenoh = open(zconfig, config.zenoh.mode == "client").await?;
    let (shutdown, shutdown_rx) = watch::channel(false);
    let shared = Arc::new(Shared {
        zenoh,
        sessions,
        stats: Arc::default(),
        shutdown: shutdown_rx,
        links: Mutex::default(),
        locator: locator.clone(),
    });
    let ros2 = config.ros2.enabled.then(|| {
        let bridge = Arc::new(crate::ros2_api::Ros2Bridge::new(
            shared.zenoh.clone(),
            &config.ros2,
            config.limits.frame_queue,
            shared.shutdown.clone(),
        ));
        shared.sessions.set_ros2(bridge.clone());
        bridge
    });
    let mut tasks = Vec::new();
    // The same Zenoh session makes this node a member of the cluster.
    tasks.extend(
        locator
            .join(shared.zenoh.clone(), shared.shutdown.clone())
            .await?,
    );
    for tenant in tenants(config) {
        tasks.extend(create::serve(shared.clone(), &tenant).await?);
        tasks.push(map::serve(shared.clone(), &tenant).await?);
    }
    // Last: a node's first status tells clients that its queryables are there.
    tasks.push(status::serve(shared.clone(), config.zenoh.node.clone()).await?);
    let z = &config.zenoh;
    tracing::info!(
        mode = %z.mode,
        listen = ?z.listen,
        connect = ?z.connect,
        node = %z.node,
        auth = config.auth.enabled(),
        "Zenoh endpoints up"
    );
    Ok(ZenohHandle {
        shared,
        shutdown,
        tasks,
        ros2,
    })
}

/// Checks the Zenoh settings of `config` without opening anything (what [`start`] would refuse
/// before connecting).
pub fn check(config: &Config, sessions: &SessionManager) -> Result<(), ServerError> {
    setup::zenoh_config(config, &sessions.temp_dir().join("zenoh-users")).map(|_| ())
}

/// Opens the Zenoh session. A client whose router does not answer yet (containers start in
/// any order) tries again after 1 s, doubling up to 30 s, for as long as it takes; a peer's
/// failure (its listen endpoint taken) is final.
async fn open(
    zconfig: zenoh::Config,
    wait_for_router: bool,
) -> Result<zenoh::Session, ServerError> {
    let mut wait = std::time::Duration::from_secs(1);
    loop {
        match zenoh::open(zconfig.clone()).await {
            Ok(session) => return Ok(session),
            Err(e) if wait_for_router => {
                tracing::warn!("the Zenoh router does not answer ({e}); trying again in {wait:?}");
                tokio::time::sleep(wait).await;
                wait = (wait * 2).min(std::time::Duration::from_secs(30));
            }
            Err(e) => {
                return Err(ServerError::Startup(format!(
                    "opening the Zenoh session: {e}"
                )));
            }
        }
    }
}

impl ZenohHandle {
    /// The Zenoh side's counters.
    pub fn stats(&self) -> ZenohCounts {
        self.shared.stats.counts()
    }

    /// The ROS 2 side's counters (`None` with `[ros2]` off).
    pub fn ros2_stats(&self) -> Option<crate::ros2_api::Ros2Counts> {
        self.ros2.as_ref().map(|r| r.counts())
    }

    /// Stops the queryables and every session's Zenoh tasks (waiting up to 5 s for the last
    /// updates to go out), then closes the Zenoh session.
    pub async fn close(self) {
        let _ = self.shutdown.send(true);
        let mut tasks = self.tasks;
        tasks.extend(self.shared.take_tasks());
        if let Some(ros2) = &self.ros2 {
            tasks.extend(ros2.take_tasks());
        }
        let all = async {
            for task in &mut tasks {
                let _ = task.await;
            }
        };
        if tokio::time::timeout(CLOSE_GRACE, all).await.is_err() {
            tracing::warn!("Zenoh tasks still busy after {CLOSE_GRACE:?}; aborting them");
            for task in &tasks {
                task.abort();
            }
        }
        if let Err(e) = self.shared.zenoh.close().await {
            tracing::warn!("closing the Zenoh session: {e}");
        }
    }
}
