//! `[ros2]`: sessions on ROS 2 through rmw_zenoh's wire format (`crate::ros2_api`).

use serde::{Deserialize, Serialize};

/// Largest ROS 2 domain id (ROS 2 allows 0-232 on every platform).
pub const MAX_DOMAIN_ID: u32 = 232;

/// The ROS 2 side of the server. Off by default; on, a session opts in when it is created
/// (`ros2` in `POST /v1/sessions` or in the Zenoh `SessionConfig`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Ros2Config {
    /// Serve ROS 2 (`RELFUSIOND_ROS2=on`); needs `[zenoh]` on: the topics travel on the
    /// server's Zenoh session, to the rmw_zenoh router the robots use.
    pub enabled: bool,
    /// The ROS 2 domain (`ROS_DOMAIN_ID`, `RELFUSIOND_ROS2_DOMAIN_ID`): the first chunk of
    /// every key.
    pub domain_id: u32,
    /// How long creating a session waits for the first message of its `camera_info_topic`.
    pub camera_info_timeout_s: u64,
}

impl Default for Ros2Config {
    fn default() -> Self {
        Ros2Config {
            enabled: false,
            domain_id: 0,
            camera_info_timeout_s: 5,
        }
    }
}

impl Ros2Config {
    /// Checks the values; `zenoh_on`: whether the Zenoh side runs; `tenants`: the token names
    /// (two may not share a ROS 2 namespace).
    pub fn validate(&self, zenoh_on: bool, tenants: &[&str]) -> Result<(), String> {
        if !self.enabled {
            return Ok(());
        }
        if !zenoh_on {
            return Err(
                "ros2.enabled needs Zenoh on ([zenoh] enabled or --zenoh-listen): \
                        ROS 2 topics travel on the server's Zenoh session"
                    .into(),
            );
        }
        if self.domain_id > MAX_DOMAIN_ID {
            return Err(format!(
                "ros2.domain_id must be 0..={MAX_DOMAIN_ID}, got {}",
                self.domain_id
            ));
        }
        if !(1..=60).contains(&self.camera_info_timeout_s) {
            return Err("ros2.camera_info_timeout_s must be 1..=60".into());
        }
        let mut namespaces: Vec<(String, &str)> = tenants
            .iter()
            .map(|t| (crate::ros2_names::tenant_namespace(t), *t))
            .collect();
        namespaces.sort();
        for pair in namespaces.windows(2) {
            if pair[0].0 == pair[1].0 && pair[0].1 != pair[1].1 {
                return Err(format!(
                    "auth.tokens: tenants {:?} and {:?} would share the ROS 2 namespace {} \
                     ('-' becomes '_'); rename one",
                    pair[0].1, pair[1].1, pair[0].0
                ));
            }
        }
        Ok(())
    }

    /// `RELFUSIOND_ROS2` and `RELFUSIOND_ROS2_DOMAIN_ID`.
    pub fn apply_env(&mut self, env: &impl Fn(&str) -> Option<String>) -> Result<(), String> {
        if let Some(v) = env("RELFUSIOND_ROS2") {
            self.enabled = match v.trim() {
                "on" | "true" | "1" => true,
                "off" | "false" | "0" => false,
                other => return Err(format!("RELFUSIOND_ROS2={other:?}: on or off")),
            };
        }
        if let Some(v) = env("RELFUSIOND_ROS2_DOMAIN_ID") {
            self.domain_id = v
                .trim()
                .parse()
                .map_err(|e| format!("RELFUSIOND_ROS2_DOMAIN_ID={v:?}: {e}"))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros2_needs_zenoh_a_domain_and_distinct_tenant_namespaces() {
        let on = Ros2Config {
            enabled: true,
            ..Ros2Config::default()
        };
        assert!(Ros2Config::default().validate(false, &[]).is_ok(), "off");
        assert!(on.validate(false, &[]).is_err());
        assert!(on.validate(true, &["alice", "bob"]).is_ok());
        assert!(on.validate(true, &["a-b", "a_b"]).is_err());
        let far = Ros2Config {
            domain_id: 233,
            ..on.clone()
        };
        assert!(far.validate(true, &[]).is_err());
        let mut from_env = Ros2Config::default();
        let env = |k: &str| match k {
            "RELFUSIOND_ROS2" => Some("on".to_string()),
            "RELFUSIOND_ROS2_DOMAIN_ID" => Some("42".to_string()),
            _ => None,
        };
        from_env.apply_env(&env).expect("valid");
        assert!(from_env.enabled);
        assert_eq!(from_env.domain_id, 42);
    }
}
