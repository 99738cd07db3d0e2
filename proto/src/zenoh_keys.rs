//! The Zenoh key space of relfusion, part of the wire contract like the messages (one place, so
//! server, clients and docs agree):
//!
//! | key | who publishes / answers | payload |
//! |---|---|---|
//! | `relfusion/sessions/create` | queryable (server) | query: `SessionConfig`, attachment: bearer token; reply: `CreateSessionReply` |
//! | `relfusion/sessions/<id>/frames` | client | `Frame` |
//! | `relfusion/sessions/<id>/end` | client | `EndOfStream` |
//! | `relfusion/sessions/<id>/poses` | server | `ServerMessage` (`PoseUpdate`, `KeyframeUpdate`, `Error`) |
//! | `relfusion/sessions/<id>/mesh` | server | `MeshUpdate` |
//! | `relfusion/sessions/<id>/finished` | server | `SessionFinished`, once, after the last update |
//! | `relfusion/sessions/<id>/map` | queryable (server) | attachment: bearer token; reply: `MapSnapshot` |
//! | `relfusion/nodes/<node>/status` | server, every 2 s | JSON load and capacity |

/// Prefix of every relfusion key.
pub const ROOT: &str = "relfusion";
/// The session-creating queryable.
pub const CREATE: &str = "relfusion/sessions/create";
/// Every session's map queryable (one declaration serves all sessions of a node).
pub const ANY_MAP: &str = "relfusion/sessions/*/map";

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

/// `relfusion/sessions/<id>/<leaf>`.
pub fn session_key(id: &str, leaf: &str) -> String {
    format!("{ROOT}/sessions/{id}/{leaf}")
}

/// `relfusion/sessions/<id>/*`: every key of one session.
pub fn session_wildcard(id: &str) -> String {
    format!("{ROOT}/sessions/{id}/*")
}

/// `relfusion/nodes/<node>/status`.
pub fn node_status(node: &str) -> String {
    format!("{ROOT}/nodes/{node}/status")
}

/// `(id, leaf)` of a concrete session key `relfusion/sessions/<id>/<leaf>`; `None` for other
/// keys and for keys with wildcards (a query must name one session).
pub fn parse_session_key(key: &str) -> Option<(&str, &str)> {
    let rest = key.strip_prefix(ROOT)?.strip_prefix("/sessions/")?;
    let (id, leaf) = rest.split_once('/')?;
    let concrete = |s: &str| !s.is_empty() && !s.contains(['*', '$', '/', '?', '#']);
    (concrete(id) && concrete(leaf)).then_some((id, leaf))
}

/// Whether `chunk` can be one chunk of a key (a node name in `relfusion/nodes/<node>/status`).
pub fn is_valid_chunk(chunk: &str) -> bool {
    !chunk.is_empty() && !chunk.contains(['*', '$', '/', '?', '#'])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn session_keys_round_trip() {
        let key = session_key("s-0123456789ab", FRAMES);
        assert_eq!(key, "relfusion/sessions/s-0123456789ab/frames");
        assert_eq!(parse_session_key(&key), Some(("s-0123456789ab", FRAMES)));
        assert_eq!(parse_session_key("relfusion/sessions/*/map"), None);
        assert_eq!(parse_session_key("relfusion/sessions/**"), None);
        assert_eq!(parse_session_key(CREATE), None);
        assert_eq!(parse_session_key("relfusion/sessions/s-1/map/x"), None);
        assert_eq!(parse_session_key("other/sessions/s-1/map"), None);
        assert!(is_valid_chunk("node-1"));
        assert!(!is_valid_chunk("a/b") && !is_valid_chunk("*") && !is_valid_chunk(""));
    }
}
