//! The Zenoh configuration of the server from `[zenoh]` and `[auth]`.
//!
//! Everything not set here keeps Zenoh's defaults. Scouting (multicast discovery and gossip) is
//! off unless `zenoh.scouting = true`: explicit endpoints are predictable, and multicast is
//! often unavailable in containers and CI.
//!
//! With tokens configured (`[auth]`), Zenoh is closed the way HTTP is, with Zenoh's own means:
//! - **authentication**: a peer or client must log in with user/password (Zenoh's `usrpwd`
//!   transport authentication): the user is a token's name, the password the token. A peer
//!   without credentials cannot connect.
//! - **access control**: every other message is denied unless a rule allows it; a user may
//!   publish, subscribe and query only below its own tenant prefix
//!   (`relfusion/tenants/<name>/**`, [`relfusion_proto::zenoh_keys`]) and read the node
//!   status. A wildcard subscription that reaches beyond the prefix (`relfusion/**`) is
//!   refused, and publications of other tenants are never forwarded to it.
//! - nodes (`zenoh.user`) may do everything below `relfusion/**`: they forward sessions.
//!
//! The same rules, printed by [`router_config`], protect a `zenohd` router that nodes and
//! clients join in a cluster (deploy/zenoh). A node in client mode applies none itself: its
//! only link is to that router, which enforces them for everyone (the node's own ACL would
//! deny the router, which is no user).

use std::path::Path;

use relfusion_proto::zenoh_keys::{ROOT, is_valid_chunk, tenant_prefix};
use serde_json::{Value, json};

use crate::config::Config;
use crate::ros2_names;
use crate::{BoxFuture, ServerError};

/// The `zenoh::Config` for the server. `users_file` is where the user/password dictionary is
/// written when auth is on (a private file the caller keeps for the session's lifetime).
pub fn zenoh_config(config: &Config, users_file: &Path) -> Result<zenoh::Config, ServerError> {
    let z = &config.zenoh;
    let bad = |message: String| ServerError::Config {
        path: "[zenoh]".into(),
        message,
    };
    if !is_valid_chunk(&z.node) {
        return Err(bad(format!(
            "zenoh.node {:?} must be one key chunk (no '/', '*', '$', '?', '#')",
            z.node
        )));
    }
    let mut zconfig = zenoh::Config::default();
    let mut set = |key: &str, value: String| {
        zconfig
            .insert_json5(key, &value)
            .map_err(|e| bad(format!("zenoh {key} = {value}: {e}")))
    };
    set("mode", Value::from(z.mode.as_str()).to_string())?;
    if !z.listen.is_empty() {
        set("listen/endpoints", json!(z.listen).to_string())?;
    }
    if !z.connect.is_empty() {
        set("connect/endpoints", json!(z.connect).to_string())?;
    }
    set(
        "transport/link/rx/max_message_size",
        config.zenoh_max_message_bytes().to_string(),
    )?;
    set("scouting/multicast/enabled", z.scouting.to_string())?;
    set("scouting/gossip/enabled", z.scouting.to_string())?;
    if !z.user.is_empty() {
        set(
            "transport/auth/usrpwd/user",
            Value::from(z.user.as_str()).to_string(),
        )?;
        set(
            "transport/auth/usrpwd/password",
            Value::from(z.password.as_str()).to_string(),
        )?;
    }
    if config.auth.enabled() && z.mode != "client" {
        write_users_file(config, users_file)?;
        set(
            "transport/auth/usrpwd/dictionary_file",
            Value::from(users_file.to_string_lossy().as_ref()).to_string(),
        )?;
        set("access_control", access_control(config).to_string())?;
    }
    Ok(zconfig)
}

/// The users dictionary: `user:password` lines, every token's name and token, and the node
/// user.
pub fn users_text(config: &Config) -> String {
    let mut text = String::new();
    for t in &config.auth.tokens {
        text.push_str(&format!("{}:{}\n", t.name, t.token));
    }
    if !config.zenoh.user.is_empty() {
        text.push_str(&format!(
            "{}:{}\n",
            config.zenoh.user, config.zenoh.password
        ));
    }
    text
}

/// Writes [`users_text`] with mode 0600: it holds the tokens.
fn write_users_file(config: &Config, path: &Path) -> Result<(), ServerError> {
    let text = users_text(config);
    let io = |e: std::io::Error| {
        ServerError::Startup(format!(
            "writing the Zenoh users file {}: {e}",
            path.display()
        ))
    };
    use std::io::Write as _;
    use std::os::unix::fs::OpenOptionsExt as _;
    let _ = std::fs::remove_file(path);
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
        .map_err(io)?;
    file.write_all(text.as_bytes()).map_err(io)
}

/// The access-control section (see the module docs): default deny, each token's user below
/// its tenant prefix, nodes everywhere below `relfusion/**`.
pub fn access_control(config: &Config) -> Value {
    let mut rules = vec![
        json!({
            "id": "node-status-read",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["declare_subscriber"],
            "key_exprs": [format!("{ROOT}/nodes/**")],
        }),
        json!({
            "id": "node-status-deliver",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put"],
            "key_exprs": [format!("{ROOT}/nodes/**")],
        }),
        json!({
            "id": "nodes",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ["put", "delete", "declare_subscriber", "query", "declare_queryable",
                         "reply", "liveliness_token", "declare_liveliness_subscriber",
                         "liveliness_query"],
            "key_exprs": node_keys(config),
        }),
    ];
    let mut subjects = Vec::new();
    let mut policies = Vec::new();
    let mut names: Vec<&str> = config.auth.tokens.iter().map(|t| t.name.as_str()).collect();
    names.sort_unstable();
    names.dedup();
    for name in names {
        let prefix = format!("{}/**", tenant_prefix(name));
        rules.push(json!({
            "id": format!("tenant-{name}-in"),
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put", "declare_subscriber", "query"],
            "key_exprs": [prefix],
        }));
        rules.push(json!({
            "id": format!("tenant-{name}-out"),
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put", "reply", "declare_subscriber", "declare_queryable"],
            "key_exprs": [prefix],
        }));
        let mut tenant_rules = vec![
            json!(format!("tenant-{name}-in")),
            json!(format!("tenant-{name}-out")),
            json!("node-status-read"),
            json!("node-status-deliver"),
        ];
        if config.ros2.enabled {
            rules.extend(ros2_rules(name));
            tenant_rules.push(json!(format!("tenant-{name}-ros2-in")));
            tenant_rules.push(json!(format!("tenant-{name}-ros2-out")));
        }
        subjects.push(json!({ "id": format!("user-{name}"), "usernames": [name] }));
        policies.push(json!({
            "rules": tenant_rules,
            "subjects": [format!("user-{name}")],
        }));
    }
    if !config.zenoh.user.is_empty() {
        subjects.push(json!({ "id": "nodes", "usernames": [config.zenoh.user] }));
        policies.push(json!({ "rules": ["nodes"], "subjects": ["nodes"] }));
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

/// What nodes may do everything on: relfusion's keys and, with `[ros2]` on, the ROS 2 topics
/// and liveliness tokens of every domain.
fn node_keys(config: &Config) -> Vec<String> {
    let mut keys = vec![format!("{ROOT}/**")];
    if config.ros2.enabled {
        keys.push(format!("*/{}/**", ros2_names::ROOT));
        keys.push(format!("{}/**", ros2_names::ADMIN_SPACE));
    }
    keys
}

/// A tenant's ROS 2 rules: its topics (`<domain>/relfusion/<tenant>/**`) like its relfusion
/// keys, and the liveliness tokens of entities in its namespace (`/relfusion/<tenant>` and
/// below), so a robot of the tenant can join the graph and see its own part of it — not
/// another tenant's. A liveliness subscription or query must name the namespace: rmw_zenoh's
/// whole-domain graph subscription (`@ros2_lv/<domain>/**`) reaches beyond it and is refused.
fn ros2_rules(name: &str) -> [Value; 2] {
    let ns = ros2_names::mangle(&ros2_names::tenant_namespace(name));
    let topics = format!("*/{}", &ros2_names::tenant_namespace(name)[1..]) + "/**";
    let tokens = [
        format!("{}/*/*/*/*/*/*/{ns}/**", ros2_names::ADMIN_SPACE),
        format!("{}/*/*/*/*/*/*/{ns}%$*/**", ros2_names::ADMIN_SPACE),
    ];
    let mut keys = vec![topics];
    keys.extend(tokens);
    [
        json!({
            "id": format!("tenant-{name}-ros2-in"),
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put", "declare_subscriber", "liveliness_token",
                         "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": keys,
        }),
        json!({
            "id": format!("tenant-{name}-ros2-out"),
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put", "declare_subscriber", "liveliness_token",
                         "declare_liveliness_subscriber", "reply"],
            "key_exprs": keys,
        }),
    ]
}

/// A `zenohd` configuration (JSON5) for a cluster router with this server's protection:
/// listening on `listen`, user/password authentication from `users_file`, and the access
/// rules of [`access_control`]. `relfusiond --print-zenoh-router-config` prints it.
pub fn router_config(config: &Config, listen: &str, users_file: &str) -> String {
    let mut router = json!({
        "mode": "router",
        "listen": { "endpoints": [listen] },
        "scouting": { "multicast": { "enabled": false }, "gossip": { "enabled": true } },
        "transport": { "link": { "rx": { "max_message_size": config.zenoh_max_message_bytes() } } },
    });
    if config.auth.enabled() {
        router["transport"]["auth"] = json!({ "usrpwd": { "dictionary_file": users_file } });
        router["access_control"] = access_control(config);
    }
    serde_json::to_string_pretty(&router).unwrap_or_default()
}

/// Runs a Zenoh router on `listen` with the protection of [`router_config`] (what `zenohd`
/// would run with it), until `shutdown`: the meeting point of a cluster's nodes when no
/// `zenohd` is deployed (`relfusiond --zenoh-router ENDPOINT`). It serves no sessions.
///
/// Boxed like [`crate::run`], so that `relfusiond` does not compile Zenoh's router again.
pub fn run_router(
    config: &Config,
    listen: &str,
    shutdown: BoxFuture<()>,
) -> BoxFuture<Result<(), ServerError>> {
    Box::pin(router_until(config.clone(), listen.to_owned(), shutdown))
}

async fn router_until(
    config: Config,
    listen: String,
    shutdown: BoxFuture<()>,
) -> Result<(), ServerError> {
    let (config, listen) = (&config, listen.as_str());
    let folder = tempfile::tempdir()
        .map_err(|e| ServerError::Startup(format!("a folder for the router's users: {e}")))?;
    let users = folder.path().join("users");
    if config.auth.enabled() {
        write_users_file(config, &users)?;
    }
    let text = router_config(config, listen, &users.to_string_lossy());
    let zconfig = zenoh::Config::from_json5(&text)
        .map_err(|e| ServerError::Startup(format!("the router configuration: {e}")))?;
    let router = zenoh::open(zconfig)
        .await
        .map_err(|e| ServerError::Startup(format!("starting the Zenoh router on {listen}: {e}")))?;
    println!("zenoh router on {listen}");
    shutdown.await;
    if let Err(e) = router.close().await {
        tracing::warn!("closing the Zenoh router: {e}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TokenEntry;

    fn config(tokens: &[(&str, &str)]) -> Config {
        let mut c = Config::default();
        c.zenoh.enabled = true;
        c.zenoh.mode = "peer".into();
        c.zenoh.listen = vec!["tcp/127.0.0.1:7447".into()];
        c.zenoh.connect = vec!["tcp/127.0.0.1:7448".into()];
        c.zenoh.node = "node-1".into();
        c.auth.tokens = tokens
            .iter()
            .map(|(n, t)| TokenEntry {
                name: n.to_string(),
                token: t.to_string(),
            })
            .collect();
        c
    }

    fn users_file(tag: &str) -> std::path::PathBuf {
        std::env::temp_dir().join(format!(
            "relfusion-zenoh-users-{tag}-{}",
            std::process::id()
        ))
    }

    #[test]
    fn endpoints_mode_and_scouting_reach_the_zenoh_config() {
        let z = zenoh_config(&config(&[]), &users_file("open")).expect("valid");
        assert_eq!(z.get_json("mode").expect("mode"), "\"peer\"");
        assert!(
            z.get_json("listen/endpoints")
                .expect("listen")
                .contains("tcp/127.0.0.1:7447")
        );
        assert!(
            z.get_json("connect/endpoints")
                .expect("connect")
                .contains("tcp/127.0.0.1:7448")
        );
        assert_eq!(
            z.get_json("scouting/multicast/enabled").expect("m"),
            "false"
        );
        assert_eq!(z.get_json("access_control/enabled").expect("acl"), "false");
        assert_eq!(
            z.get_json("transport/link/rx/max_message_size")
                .expect("size"),
            (16 << 20).to_string(),
            "8 MiB frames: 16 MiB messages, not Zenoh's 1 GiB"
        );
    }

    #[test]
    fn a_client_of_a_router_leaves_access_control_to_the_router() {
        let mut c = config(&[("alice", "a1")]);
        c.zenoh.mode = "client".into();
        let z = zenoh_config(&c, &users_file("client")).expect("valid");
        assert_eq!(z.get_json("access_control/enabled").expect("acl"), "false");
        let router = router_config(&c, "tcp/127.0.0.1:7447", "/etc/zenoh/users");
        assert!(
            router.contains("relfusion/tenants/alice/**"),
            "the router enforces it"
        );
    }

    #[test]
    fn tokens_turn_on_authentication_and_per_tenant_access_control() {
        let path = users_file("auth");
        let z = zenoh_config(&config(&[("alice", "a1"), ("bob", "b2")]), &path).expect("valid");
        assert_eq!(z.get_json("access_control/enabled").expect("acl"), "true");
        assert_eq!(
            z.get_json("access_control/default_permission")
                .expect("default"),
            "\"deny\""
        );
        let acl = z.get_json("access_control/rules").expect("rules");
        assert!(
            acl.contains("relfusion/tenants/alice/**") && acl.contains("relfusion/tenants/bob/**")
        );
        let users = std::fs::read_to_string(&path).expect("users file");
        assert_eq!(users, "alice:a1\nbob:b2\n");
        use std::os::unix::fs::PermissionsExt as _;
        let mode = std::fs::metadata(&path).expect("meta").permissions().mode();
        assert_eq!(mode & 0o077, 0, "the users file is private");
        let _ = std::fs::remove_file(path);
        let router = router_config(&config(&[("alice", "a1")]), "tcp/0.0.0.0:7447", "/etc/u");
        let parsed: Value = serde_json::from_str(&router).expect("JSON");
        assert_eq!(parsed["access_control"]["default_permission"], "deny");
        assert_eq!(
            parsed["transport"]["link"]["rx"]["max_message_size"],
            16 << 20
        );
        assert_eq!(
            parsed["transport"]["auth"]["usrpwd"]["dictionary_file"],
            "/etc/u"
        );
        let mut zc = zenoh::Config::default();
        zc.insert_json5("access_control", &parsed["access_control"].to_string())
            .expect("zenoh accepts the rules");
    }

    #[test]
    fn ros2_confines_each_tenant_to_its_namespace() {
        let mut c = config(&[("alice", "a1"), ("bob-2", "b2")]);
        let off = access_control(&c).to_string();
        assert!(!off.contains("@ros2_lv"), "no ROS 2 rules with [ros2] off");
        c.ros2.enabled = true;
        let acl = access_control(&c);
        let rule = |id: &str| {
            acl["rules"]
                .as_array()
                .and_then(|r| r.iter().find(|r| r["id"] == id))
                .cloned()
                .unwrap_or_else(|| panic!("no rule {id}"))
        };
        let alice = rule("tenant-alice-ros2-in");
        assert_eq!(alice["key_exprs"][0], "*/relfusion/alice/**");
        assert_eq!(
            alice["key_exprs"][2],
            "@ros2_lv/*/*/*/*/*/*/%relfusion%alice%$*/**"
        );
        assert_eq!(
            rule("tenant-bob-2-ros2-out")["key_exprs"][0],
            "*/relfusion/bob_2/**"
        );
        let mut zc = zenoh::Config::default();
        zc.insert_json5("access_control", &acl.to_string())
            .expect("zenoh accepts the rules");
    }

    #[test]
    fn bad_values_are_config_errors() {
        let mut bad_node = config(&[]);
        bad_node.zenoh.node = "a/b".into();
        assert!(zenoh_config(&bad_node, &users_file("bad1")).is_err());
        let mut bad_endpoint = config(&[]);
        bad_endpoint.zenoh.listen = vec!["not an endpoint".into()];
        assert!(zenoh_config(&bad_endpoint, &users_file("bad2")).is_err());
    }
}
