//! rmw_zenoh's names on the wire (its design document and `liveliness_utils.cpp`, the same
//! from Jazzy's 0.2 line on): where a topic's messages go, the liveliness tokens the ROS 2
//! graph (`ros2 node list`, `ros2 topic list`) is read from, the attachment every message
//! carries, and relfusion's namespaces in that space.
//!
//! - Topic key: `<domain>/<fully qualified name without its leading '/'>/<DDS type
//!   name>/<type hash>`, e.g.
//!   `0/relfusion/alice/s_0a1b/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_10f3…`.
//! - Liveliness token of a node: `@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>`;
//!   of a publisher (`MP`) or subscription (`MS`):
//!   `@ros2_lv/<domain>/<zid>/<nid>/<eid>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>`,
//!   every `/` inside a name replaced by `%` (an empty namespace or enclave is `%`).
//! - Attachment (33 bytes): sequence number (i64 LE, from 1, per publisher), source time
//!   (i64 LE, ns since the Unix epoch), `0x10` (the GID's length as a LEB128), the GID: the
//!   XXH3-128 of the entity's liveliness key, low half first.
//!
//! A session's namespace is `/relfusion/<tenant>/<session>`: the tenant and session as ROS
//! name tokens (`-` becomes `_`; a leading digit gets a `t` in front). Access control confines
//! each tenant to `*/relfusion/<tenant>/**` ([`crate::zenoh_api::setup`]).

use relfusion_viz::ros2::types::RosType;

/// The liveliness admin space of rmw_zenoh.
pub const ADMIN_SPACE: &str = "@ros2_lv";
/// The root of relfusion's ROS 2 names.
pub const ROOT: &str = "relfusion";
/// The node every session's entities belong to.
pub const NODE: &str = "relfusion";
/// QoS of relfusion's entities: reliable, volatile, keep last 10 (rclcpp's default depth);
/// rmw_zenoh writes only what differs from its defaults (depth 42).
pub const QOS: &str = "::,10:,:,:,,";

/// `name` as one ROS 2 name token: `[A-Za-z_][A-Za-z0-9_]*`.
pub fn token(name: &str) -> String {
    let mut out: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    if out.is_empty() || out.starts_with(|c: char| c.is_ascii_digit()) {
        out.insert(0, 't');
    }
    out
}

/// `/relfusion/<tenant>`: a tenant's ROS 2 namespace.
pub fn tenant_namespace(tenant: &str) -> String {
    format!("/{ROOT}/{}", token(tenant))
}

/// `/relfusion/<tenant>/<session>`: a session's ROS 2 namespace.
pub fn session_namespace(tenant: &str, session_id: &str) -> String {
    format!("{}/{}", tenant_namespace(tenant), token(session_id))
}

/// Why a topic name was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    #[error(
        "{0:?} is not a ROS 2 topic name (tokens of A-Z, a-z, 0-9 and '_', not starting with a digit, separated by single '/')"
    )]
    Invalid(String),
    #[error("{name:?} is outside this tenant's namespace {namespace}")]
    Outside { name: String, namespace: String },
}

/// A topic name resolved in the tenant's namespace (a relative name is put inside it; an
/// absolute one must already be), checked against ROS 2's rules. At most 256 characters.
pub fn resolve_topic(name: &str, tenant: &str) -> Result<String, NameError> {
    let namespace = tenant_namespace(tenant);
    let full = if name.starts_with('/') {
        name.to_string()
    } else {
        format!("{namespace}/{name}")
    };
    let valid_token = |t: &str| {
        !t.is_empty()
            && !t.starts_with(|c: char| c.is_ascii_digit())
            && t.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
    };
    if full.len() > 256 || full.ends_with('/') || !full[1..].split('/').all(valid_token) {
        return Err(NameError::Invalid(name.to_string()));
    }
    if !full.starts_with(&format!("{namespace}/")) {
        return Err(NameError::Outside {
            name: name.to_string(),
            namespace,
        });
    }
    Ok(full)
}

/// The key expression of a topic's messages.
pub fn topic_key(domain: u32, topic: &str, ty: RosType) -> String {
    format!(
        "{domain}/{}/{}/{}",
        topic.trim_start_matches('/'),
        ty.dds_name(),
        ty.hash()
    )
}

/// Every `/` of a name replaced by `%` (a whole empty name is `%`).
pub fn mangle(name: &str) -> String {
    if name.is_empty() {
        "%".into()
    } else {
        name.replace('/', "%")
    }
}

/// One entity of relfusion's node in the ROS 2 graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Entity<'a> {
    Node,
    Publisher { topic: &'a str, ty: RosType },
    Subscription { topic: &'a str, ty: RosType },
}

/// Where an entity lives: the Zenoh session, the context's node and entity ids, the namespace.
#[derive(Clone, Copy, Debug)]
pub struct Place<'a> {
    pub domain: u32,
    pub zid: &'a str,
    pub node_id: u64,
    pub entity_id: u64,
    pub namespace: &'a str,
}

/// The liveliness token of `entity` at `place` (see the module docs).
pub fn liveliness_key(place: &Place<'_>, entity: Entity<'_>) -> String {
    let (kind, entity_id) = match entity {
        Entity::Node => ("NN", place.node_id),
        Entity::Publisher { .. } => ("MP", place.entity_id),
        Entity::Subscription { .. } => ("MS", place.entity_id),
    };
    let mut key = format!(
        "{ADMIN_SPACE}/{}/{}/{}/{entity_id}/{kind}/%/{}/{NODE}",
        place.domain,
        place.zid,
        place.node_id,
        mangle(place.namespace)
    );
    if let Entity::Publisher { topic, ty } | Entity::Subscription { topic, ty } = entity {
        key.push_str(&format!(
            "/{}/{}/{}/{QOS}",
            mangle(topic),
            ty.dds_name(),
            ty.hash()
        ));
    }
    key
}

/// An entity's GID: the XXH3-128 of its liveliness key, low 64 bits first (both halves
/// little-endian).
pub fn gid(liveliness_key: &str) -> [u8; 16] {
    xxhash_rust::xxh3::xxh3_128(liveliness_key.as_bytes()).to_le_bytes()
}

/// The attachment of a message (see the module docs).
pub fn attachment(sequence: i64, source_time_ns: i64, gid: &[u8; 16]) -> [u8; 33] {
    let mut out = [0u8; 33];
    out[..8].copy_from_slice(&sequence.to_le_bytes());
    out[8..16].copy_from_slice(&source_time_ns.to_le_bytes());
    out[16] = 16;
    out[17..].copy_from_slice(gid);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use relfusion_viz::ros2::types::{POSE_STAMPED, RosType};

    #[test]
    fn keys_and_tokens_are_rmw_zenohs() {
        // The design document's publisher token, rebuilt from its parts.
        let string = RosType("std_msgs/msg/String");
        assert_eq!(
            topic_key(0, "/chatter", string),
            "0/chatter/std_msgs::msg::dds_::String_/\
             RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        let place = Place {
            domain: 0,
            zid: "8b20917502ee955ac4476e0266340d5c",
            node_id: 0,
            entity_id: 10,
            namespace: "/",
        };
        let mp = liveliness_key(
            &place,
            Entity::Publisher {
                topic: "/chatter",
                ty: string,
            },
        );
        assert_eq!(
            mp.replace("/relfusion/", "/talker/")
                .replace(QOS, "::,7:,:,:,,"),
            "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/\
             std_msgs::msg::dds_::String_/\
             RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
        );
        let nn = liveliness_key(
            &Place {
                namespace: "/relfusion/alice/s_0a",
                entity_id: 3,
                ..place
            },
            Entity::Node,
        );
        assert_eq!(
            nn,
            "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%relfusion%alice%s_0a/relfusion"
        );
        let _ = POSE_STAMPED;
    }

    #[test]
    fn gids_are_xxh3_128_and_attachments_33_bytes() {
        // XXH3-128 of the empty input (the reference implementation's test vector).
        let empty = gid("");
        assert_eq!(
            u128::from_le_bytes(empty),
            0x99aa06d3014798d86001c324468d497f
        );
        let a = attachment(1, 2, &empty);
        assert_eq!(a[0], 1);
        assert_eq!(a[8], 2);
        assert_eq!(a[16], 0x10);
        assert_eq!(&a[17..], &empty);
    }

    #[test]
    fn names_stay_in_the_tenants_namespace() {
        assert_eq!(token("s-0a1b"), "s_0a1b");
        assert_eq!(token("7up"), "t7up");
        assert_eq!(
            session_namespace("alice-2", "s-00ff"),
            "/relfusion/alice_2/s_00ff"
        );
        assert_eq!(
            resolve_topic("camera/image_raw", "alice").as_deref(),
            Ok("/relfusion/alice/camera/image_raw")
        );
        assert_eq!(
            resolve_topic("/relfusion/alice/cam/compressed", "alice").as_deref(),
            Ok("/relfusion/alice/cam/compressed")
        );
        assert!(matches!(
            resolve_topic("/relfusion/bob/cam", "alice"),
            Err(NameError::Outside { .. })
        ));
        assert!(matches!(
            resolve_topic("/relfusion/alice2/cam", "alice"),
            Err(NameError::Outside { .. })
        ));
        for bad in ["", "a//b", "a/", "1cam", "a b", "a/../b", "ä"] {
            assert!(
                matches!(resolve_topic(bad, "alice"), Err(NameError::Invalid(_))),
                "{bad:?}"
            );
        }
    }
}
