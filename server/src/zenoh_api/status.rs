//! `relfusion/nodes/<node>/status`: this node's load and capacity as JSON, every 2 s, so a
//! client or scheduler can pick the least loaded node of a Zenoh deployment.

use std::sync::Arc;
use std::time::Duration;

use relfusion_proto::zenoh_keys::node_status;
use serde::Serialize;
use tokio::task::JoinHandle;

use super::{Shared, ZenohCounts};
use crate::ServerError;

/// How often the status is published.
pub const STATUS_PERIOD: Duration = Duration::from_secs(2);

/// The published JSON.
#[derive(Clone, Debug, Serialize)]
pub struct NodeStatus {
    pub node: String,
    pub version: &'static str,
    /// Sessions processing now.
    pub sessions_active: usize,
    /// `limits.max_sessions`.
    pub max_sessions: usize,
    /// Whether new sessions are accepted (false while shutting down).
    pub accepting: bool,
    /// Worker threads of the GPU pool.
    pub gpu_workers: usize,
    /// Real GPUs (0: kernels on the CPU fallback); placement prefers nodes with one.
    pub gpus: usize,
    /// The node's HTTP address for clients (`[zenoh] advertise`), empty if not given.
    pub advertise: String,
    /// Counters of the Zenoh side since start.
    pub zenoh: ZenohCounts,
    /// Counters of the ROS 2 side since start (absent with `[ros2]` off).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ros2: Option<crate::ros2_api::Ros2Counts>,
}

/// The status of this node now.
pub(crate) fn current(shared: &Shared, node: &str) -> NodeStatus {
    let (sessions_active, max_sessions) = shared.sessions.load();
    let load = shared.locator.local_load();
    NodeStatus {
        node: node.to_string(),
        version: env!("CARGO_PKG_VERSION"),
        sessions_active,
        max_sessions,
        accepting: shared.sessions.is_accepting(),
        gpu_workers: shared.sessions.gpu_workers(),
        gpus: load.gpus,
        advertise: load.advertise,
        zenoh: shared.stats.counts(),
        ros2: shared.sessions.ros2().map(|r| r.counts()),
    }
}

/// Declares the publisher and publishes every [`STATUS_PERIOD`] until shutdown.
pub(crate) async fn serve(
    shared: Arc<Shared>,
    node: String,
) -> Result<JoinHandle<()>, ServerError> {
    let key = node_status(&node);
    let publisher = shared
        .zenoh
        .declare_publisher(key.clone())
        .encoding(zenoh::bytes::Encoding::APPLICATION_JSON)
        .await
        .map_err(|e| ServerError::Startup(format!("declaring {key}: {e}")))?;
    let mut shutdown = shared.shutdown.clone();
    Ok(tokio::spawn(async move {
        let mut tick = tokio::time::interval(STATUS_PERIOD);
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = shutdown.wait_for(|stop| *stop) => break,
            }
            let status = current(&shared, &node);
            match serde_json::to_vec(&status) {
                Ok(json) => {
                    if let Err(e) = publisher.put(json).await {
                        tracing::debug!("publishing {key}: {e}");
                    }
                }
                Err(e) => tracing::warn!("serialising the node status: {e}"),
            }
        }
    }))
}
