//! The Zenoh configuration of the server from the `[zenoh]` section.
//!
//! Everything not set here keeps Zenoh's defaults. Scouting (multicast discovery and gossip) is
//! off unless `zenoh.scouting = true`: explicit endpoints are predictable, and multicast is
//! often unavailable in containers and CI.

use crate::ServerError;
use crate::config::ZenohConfig;
use relfusion_proto::zenoh_keys::is_valid_chunk;

/// The `zenoh::Config` for `config`; a bad mode, endpoint or node name is a config error.
pub fn zenoh_config(config: &ZenohConfig) -> Result<zenoh::Config, ServerError> {
    let bad = |message: String| ServerError::Config {
        path: "[zenoh]".into(),
        message,
    };
    if !is_valid_chunk(&config.node) {
        return Err(bad(format!(
            "zenoh.node {:?} must be one key chunk (no '/', '*', '$', '?', '#')",
            config.node
        )));
    }
    let mut zconfig = zenoh::Config::default();
    let mut set = |key: &str, value: String| {
        zconfig
            .insert_json5(key, &value)
            .map_err(|e| bad(format!("zenoh {key} = {value}: {e}")))
    };
    set("mode", json_string(&config.mode))?;
    if !config.listen.is_empty() {
        set("listen/endpoints", json_list(&config.listen))?;
    }
    if !config.connect.is_empty() {
        set("connect/endpoints", json_list(&config.connect))?;
    }
    set("scouting/multicast/enabled", config.scouting.to_string())?;
    set("scouting/gossip/enabled", config.scouting.to_string())?;
    Ok(zconfig)
}

fn json_string(s: &str) -> String {
    serde_json::Value::String(s.to_string()).to_string()
}

fn json_list(items: &[String]) -> String {
    serde_json::Value::from(items.to_vec()).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_mode_and_scouting_reach_the_zenoh_config() {
        let config = ZenohConfig {
            enabled: true,
            mode: "peer".into(),
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: vec!["tcp/127.0.0.1:7448".into()],
            scouting: false,
            node: "node-1".into(),
        };
        let z = zenoh_config(&config).expect("valid");
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
            z.get_json("scouting/multicast/enabled").expect("multicast"),
            "false"
        );
        assert_eq!(
            z.get_json("scouting/gossip/enabled").expect("gossip"),
            "false"
        );
    }

    #[test]
    fn bad_values_are_config_errors() {
        let base = ZenohConfig {
            node: "n".into(),
            ..ZenohConfig::default()
        };
        for bad in [
            ZenohConfig {
                node: "a/b".into(),
                ..base.clone()
            },
            ZenohConfig {
                listen: vec!["not an endpoint".into()],
                ..base.clone()
            },
        ] {
            assert!(zenoh_config(&bad).is_err(), "{bad:?} accepted");
        }
    }
}
