//! `GET /v1/cluster`: the nodes of the cluster as this node sees them (members alive, their
//! load and capacity), which is what placement decides from.

use std::sync::Arc;

use axum::Json;
use axum::extract::State;
use serde::Serialize;
use utoipa::ToSchema;

use super::auth::Auth;
use super::error::ErrorBody;
use crate::AppState;

/// One node.
#[derive(Debug, Serialize, ToSchema)]
pub struct ClusterNode {
    pub node: String,
    /// Sessions running now (as last published, every 2 s).
    pub sessions_active: usize,
    pub max_sessions: usize,
    pub accepting: bool,
    /// Real GPUs (0: the CPU fallback).
    pub gpus: usize,
    /// Its HTTP address for clients, if advertised.
    pub advertise: String,
}

/// The cluster.
#[derive(Debug, Serialize, ToSchema)]
pub struct ClusterView {
    /// The node that answered.
    pub node: String,
    /// Whether this node has joined the cluster's Zenoh network (false: a single node).
    pub joined: bool,
    /// Every member alive, this node included, sorted by name.
    pub nodes: Vec<ClusterNode>,
}

/// The nodes of the cluster.
#[utoipa::path(get, path = "/v1/cluster", tag = "service",
    responses(
        (status = 200, description = "The members and their load", body = ClusterView),
        (status = 401, description = "Missing or unknown bearer token", body = ErrorBody),
    ),
    security(("bearer" = [])))]
pub async fn cluster(State(state): State<Arc<AppState>>, Auth(_caller): Auth) -> Json<ClusterView> {
    let locator = &state.locator;
    let nodes = locator
        .members()
        .into_iter()
        .map(|l| ClusterNode {
            node: l.node,
            sessions_active: l.sessions_active,
            max_sessions: l.max_sessions,
            accepting: l.accepting,
            gpus: l.gpus,
            advertise: l.advertise,
        })
        .collect();
    Json(ClusterView {
        node: locator.node().to_string(),
        joined: locator.joined(),
        nodes,
    })
}
