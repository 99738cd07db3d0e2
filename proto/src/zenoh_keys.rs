//! The Zenoh key space of relfusion, part of the wire contract like the messages (one place, so
//! server, clients and docs agree).
//!
//! Every key of a session lives under its owner's tenant prefix, `relfusion/tenants/<tenant>`:
//! `<tenant>` is the name of the bearer token that owns it (the Zenoh user name the client
//! authenticates as), or [`PUBLIC_TENANT`] on a server without tokens. A server with tokens
//! lets each Zenoh user read and write below its own prefix only (Zenoh access control), so
//! one tenant's frames, poses, meshes and session ids never reach another.
//!
//! | key | who publishes / answers | payload |
//! |---|---|---|
//! | `relfusion/tenants/<tenant>/create` | queryable (server) | query: `SessionConfig`, attachment: bearer token; reply: `CreateSessionReply` |
//! | `relfusion/tenants/<tenant>/sessions/<id>/frames` | client | `Frame` |
//! | `relfusion/tenants/<tenant>/sessions/<id>/end` | client | `EndOfStream` |
//! | `relfusion/tenants/<tenant>/sessions/<id>/poses` | server | `ServerMessage` (`PoseUpdate`, `KeyframeUpdate`, `Error`) |
//! | `relfusion/tenants/<tenant>/sessions/<id>/mesh` | server | `MeshUpdate` |
//! | `relfusion/tenants/<tenant>/sessions/<id>/finished` | server | `SessionFinished`, once, after the last update |
//! | `relfusion/tenants/<tenant>/sessions/<id>/map` | queryable (server) | attachment: bearer token; reply: `MapSnapshot` |
//! | `relfusion/nodes/<node>/status` | server, every 2 s | JSON load and capacity |

/// Prefix of every relfusion key.
pub const ROOT: &str = "relfusion";
/// The tenant of a server without tokens (everyone is one anonymous owner).
pub const PUBLIC_TENANT: &str = "public";

/// Client → server: protobuf `Frame`s.
pub const FRAMES: &str = "frames";
/// Client → server: protobuf `EndOfStream`.
pub const END: &str = "end";
/// Server → clients: protobuf `ServerMessage`s.
pub const POSES: &str = "poses";
/// Server → clients: protobuf `MeshUpdate`s.
pub const MESH: &str = "mesh";
/// Server → clients: protobuf `SessionFinished`.
pub const FINISHED: &str = "finished";
/// Queryable: protobuf `MapSnapshot`.
pub const MAP: &str = "map";

/// `relfusion/tenants/<tenant>`: everything of one tenant.
pub fn tenant_prefix(tenant: &str) -> String {
    format!("{ROOT}/tenants/{tenant}")
}

/// `relfusion/tenants/<tenant>/create`: the session-creating queryable of a tenant.
pub fn create_key(tenant: &str) -> String {
    format!("{}/create", tenant_prefix(tenant))
}

/// `relfusion/tenants/<tenant>/sessions/*/map`: every map queryable of a tenant (one
/// declaration serves all its sessions on a node).
pub fn any_map(tenant: &str) -> String {
    format!("{}/sessions/*/{MAP}", tenant_prefix(tenant))
}

/// `relfusion/tenants/<tenant>/sessions/<id>/<leaf>`.
pub fn session_key(tenant: &str, id: &str, leaf: &str) -> String {
    format!("{}/sessions/{id}/{leaf}", tenant_prefix(tenant))
}

/// `relfusion/tenants/<tenant>/sessions/<id>/*`: every key of one session.
pub fn session_wildcard(tenant: &str, id: &str) -> String {
    format!("{}/sessions/{id}/*", tenant_prefix(tenant))
}

/// `relfusion/nodes/<node>/status`.
pub fn node_status(node: &str) -> String {
    format!("{ROOT}/nodes/{node}/status")
}

/// A concrete session key's parts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SessionKey<'a> {
    pub tenant: &'a str,
    pub id: &'a str,
    pub leaf: &'a str,
}

/// The parts of a concrete session key `relfusion/tenants/<tenant>/sessions/<id>/<leaf>`;
/// `None` for other keys and for keys with wildcards (a query must name one session).
pub fn parse_session_key(key: &str) -> Option<SessionKey<'_>> {
    let rest = key.strip_prefix(ROOT)?.strip_prefix("/tenants/")?;
    let (tenant, rest) = rest.split_once('/')?;
    let rest = rest.strip_prefix("sessions/")?;
    let (id, leaf) = rest.split_once('/')?;
    [tenant, id, leaf]
        .iter()
        .all(|c| is_valid_chunk(c))
        .then_some(SessionKey { tenant, id, leaf })
}

/// Whether `chunk` can be one chunk of a key (a node name, a tenant, a session id).
pub fn is_valid_chunk(chunk: &str) -> bool {
    !chunk.is_empty() && !chunk.contains(['*', '$', '/', '?', '#'])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn session_keys_round_trip() {
        let key = session_key("alice", "s-0123456789ab", FRAMES);
        assert_eq!(
            key,
            "relfusion/tenants/alice/sessions/s-0123456789ab/frames"
        );
        assert_eq!(
            parse_session_key(&key),
            Some(SessionKey {
                tenant: "alice",
                id: "s-0123456789ab",
                leaf: FRAMES
            })
        );
        assert_eq!(parse_session_key(&any_map("alice")), None);
        assert_eq!(
            parse_session_key("relfusion/tenants/*/sessions/s-1/map"),
            None
        );
        assert_eq!(
            parse_session_key("relfusion/tenants/alice/sessions/**"),
            None
        );
        assert_eq!(parse_session_key(&create_key("alice")), None);
        assert_eq!(
            parse_session_key("relfusion/tenants/a/sessions/s-1/map/x"),
            None
        );
        assert_eq!(parse_session_key("other/tenants/a/sessions/s-1/map"), None);
        assert!(session_wildcard("bob", "s-1").starts_with(&tenant_prefix("bob")));
        assert!(is_valid_chunk("node-1"));
        assert!(!is_valid_chunk("a/b") && !is_valid_chunk("*") && !is_valid_chunk(""));
    }
}
