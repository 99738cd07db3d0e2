//! The user settings: the few parameters of [`Config`] a user should ever touch, each with the
//! values it takes and who may set it. Everything else in [`Config`] is expert level (LSD-SLAM's
//! and the paper's constants, documented where they are defined).
//!
//! The list is written once, below, as paths into [`Config`]'s own fields (a path that names no
//! field does not compile). The server derives what a client may set from it, the README's
//! "User settings" table is checked against it, and [`UserConfig`] parses a partial config
//! (JSON, as a client sends it) into checked values applied over a base config.

use serde_json::Value;

use super::Config;

/// What values a user setting takes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bound {
    Bool,
    /// An integer in `[min, max]`.
    Int(i64, i64),
    /// A finite number in `[min, max]`.
    Num(f64, f64),
    /// One of these strings.
    Choice(&'static [&'static str]),
}

impl Bound {
    fn admits(self, value: &Value) -> bool {
        match (self, value) {
            (Bound::Bool, Value::Bool(_)) => true,
            (Bound::Int(min, max), Value::Number(n)) => {
                n.as_i64().is_some_and(|v| v >= min && v <= max)
            }
            (Bound::Num(min, max), Value::Number(n)) => n
                .as_f64()
                .is_some_and(|v| v.is_finite() && v >= min && v <= max),
            (Bound::Choice(options), Value::String(s)) => options.contains(&s.as_str()),
            _ => false,
        }
    }

    /// The values it takes, in words (for errors and docs).
    pub fn describe(self) -> String {
        match self {
            Bound::Bool => "true or false".to_string(),
            Bound::Int(min, max) => format!("an integer in [{min}, {max}]"),
            Bound::Num(min, max) => format!("a number in [{min}, {max}]"),
            Bound::Choice(options) => format!("one of {options:?}"),
        }
    }
}

/// Who may set a user setting.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scope {
    /// Anyone, a stranger's session included: the setting changes what a session computes,
    /// not how much memory or time it may take beyond what admission reserved.
    Anyone,
    /// Whoever runs the pipeline (`relfusion run --config`): the setting sizes memory
    /// (working resolutions, voxel size), so a server's sessions keep their defaults.
    Operator,
}

/// One user setting: where it lives in [`Config`], its values, who may set it and why a user
/// would.
pub struct UserSetting {
    /// Its path below the config root, e.g. `"dense.enabled"`.
    pub path: &'static str,
    pub bound: Bound,
    pub scope: Scope,
    /// Why a user would touch it (one line).
    pub why: &'static str,
    set: fn(&mut Config, Value) -> serde_json::Result<()>,
}

impl std::fmt::Debug for UserSetting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UserSetting")
            .field("path", &self.path)
            .field("bound", &self.bound)
            .field("scope", &self.scope)
            .finish()
    }
}

/// Writes the list: each entry is `scope bound, "why" => path.to.field;`, the path being
/// [`Config`]'s own fields, so the compiler checks it and the setter is typed.
macro_rules! user_settings {
    ($($scope:ident $bound:expr, $why:literal => $first:ident $(. $rest:ident)*;)*) => {
        /// Every user setting (README, "Configuration").
        pub const USER_SETTINGS: &[UserSetting] = &[$(UserSetting {
            path: concat!(stringify!($first) $(, ".", stringify!($rest))*),
            bound: $bound,
            scope: Scope::$scope,
            why: $why,
            set: |config, value| {
                config.$first$(.$rest)* = serde_json::from_value(value)?;
                Ok(())
            },
        }),*];
    };
}

user_settings! {
    // The window's keyframes and points are not in the admission's memory model yet.
    Operator Bound::Choice(&["lsd", "dso"]),
        "poses from LSD-SLAM's tracking or from the DSO-class window (issue 35)"
        => pipeline.frontend;
    Anyone Bound::Choice(&["prior", "random"]),
        "first keyframe's depth from the depth prior, or LSD-SLAM's random start"
        => pipeline.init;
    Anyone Bound::Bool, "back end in step with the frames: reproducible results"
        => pipeline.deterministic;
    Anyone Bound::Bool, "map on its own thread, as a live camera needs"
        => pipeline.mapping_thread;
    Anyone Bound::Int(0, i64::MAX), "seed of the random depth initialisation"
        => pipeline.seed;
    // Each candidate costs one tracking per keyframe decision; revisits then add no keyframes.
    Anyone Bound::Int(0, 8), "old keyframes re-used when the camera returns (long sessions)"
        => pipeline.reactivation_candidates;
    Anyone Bound::Bool, "off for cameras with fixed exposure"
        => tracking.affine_lighting;
    Anyone Bound::Num(0.0, 100.0), "lower for low-texture scenes"
        => mapping.min_use_grad;
    Anyone Bound::Num(0.5, 50.0), "how often keyframes are taken (distance)"
        => mapping.kf_dist_weight;
    Anyone Bound::Num(0.5, 50.0), "how often keyframes are taken (overlap)"
        => mapping.kf_usage_weight;
    Anyone Bound::Num(0.5, 100.0), "how readily keyframes far apart are linked"
        => backend.loop_closure_strictness;
    // Admission costs held keyframes (`memory::SessionCost` in the server), so a client trades
    // memory for store reads within its share.
    Anyone Bound::Int(0, 64), "old keyframes kept in memory before they spill to the store"
        => backend.held_keyframes;
    Anyone Bound::Bool, "a metric depth prior holds the map's scale"
        => backend.metric_scale.enabled;
    Anyone Bound::Bool, "the dense layer (paper §III-B..E)"
        => dense.enabled;
    Anyone Bound::Choice(&["gpu", "cpu"]), "where the dense layer runs"
        => dense.compute;
    Operator Bound::Int(8, 4096), "the dense layer's working width"
        => dense.width;
    Operator Bound::Int(8, 4096), "the dense layer's working height"
        => dense.height;
    Anyone Bound::Bool, "the fused mesh (paper §III-F)"
        => fusion.enabled;
    Anyone Bound::Choice(&["gpu", "cpu"]), "where the fusion runs"
        => fusion.compute;
    Anyone Bound::Num(16.0, 256.0), "the mesh's resolution, relative to the scene's depth"
        => fusion.voxels_per_median_depth;
    Operator Bound::Num(1e-4, 1.0), "the mesh's resolution in the map's units, instead"
        => fusion.voxel_size;
    // The floor keeps the newest keyframes' volume in at 128 voxels per median depth: at 1024
    // the chunks went back and forth and the fusion fell behind (docs/tuning.md, "Bounded
    // fusion").
    Anyone Bound::Int(4096, 65536), "TSDF blocks kept in memory before they spill to the store"
        => fusion.resident_blocks;
}

/// Why a partial config was refused.
#[derive(Debug, thiserror::Error)]
pub enum UserConfigError {
    #[error("config must be a JSON object")]
    NotAnObject,
    /// The key is expert level or the operator's: the message lists what may be set.
    #[error(
        "config.{key} cannot be set here (it is expert level or the server's); settable keys: {settable}"
    )]
    NotSettable { key: String, settable: String },
    #[error("config.{key} must be {expected}, got {got}")]
    OutOfBounds {
        key: String,
        expected: String,
        got: String,
    },
    /// The values are each in bounds but the config they make is not valid.
    #[error(transparent)]
    Invalid(#[from] crate::Error),
}

/// A partial config of user settings, each checked against its bound: what a client of the
/// server sends, applied over the server's base config.
#[derive(Debug, Default)]
pub struct UserConfig {
    values: Vec<(&'static UserSetting, Value)>,
}

impl UserConfig {
    /// The settings `scope` may set.
    pub fn settable(scope: Scope) -> impl Iterator<Item = &'static UserSetting> {
        USER_SETTINGS
            .iter()
            .filter(move |s| scope == Scope::Operator || s.scope == Scope::Anyone)
    }

    /// Parses `json` (nested objects, as in a config file; null = nothing set), refusing any
    /// key `scope` may not set and any value out of its bound.
    pub fn from_json(json: &Value, scope: Scope) -> Result<Self, UserConfigError> {
        let mut config = UserConfig::default();
        match json {
            Value::Null => Ok(config),
            Value::Object(_) => {
                config.collect(json, &mut Vec::new(), scope)?;
                Ok(config)
            }
            _ => Err(UserConfigError::NotAnObject),
        }
    }

    /// Descends into sections until a path names a setting.
    fn collect(
        &mut self,
        json: &Value,
        path: &mut Vec<String>,
        scope: Scope,
    ) -> Result<(), UserConfigError> {
        let key = path.join(".");
        let setting = Self::settable(scope).find(|s| s.path == key);
        match (setting, json) {
            (Some(setting), value) if setting.bound.admits(value) => {
                self.values.push((setting, value.clone()));
                Ok(())
            }
            (Some(setting), value) => Err(UserConfigError::OutOfBounds {
                key,
                expected: setting.bound.describe(),
                got: value.to_string(),
            }),
            (None, Value::Object(map)) => {
                for (name, value) in map {
                    path.push(name.clone());
                    self.collect(value, path, scope)?;
                    path.pop();
                }
                Ok(())
            }
            (None, _) => Err(UserConfigError::NotSettable {
                key,
                settable: Self::settable(scope)
                    .map(|s| s.path)
                    .collect::<Vec<_>>()
                    .join(", "),
            }),
        }
    }

    /// `base` with these settings applied, validated as a whole.
    pub fn apply(&self, base: &Config) -> Result<Config, UserConfigError> {
        let mut config = base.clone();
        for (setting, value) in &self.values {
            (setting.set)(&mut config, value.clone()).map_err(|e| {
                UserConfigError::OutOfBounds {
                    key: setting.path.to_string(),
                    expected: setting.bound.describe(),
                    got: format!("{value} ({e})"),
                }
            })?;
        }
        config.validate()?;
        Ok(config)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn every_setting_sets_its_own_field_and_nothing_else() {
        for setting in USER_SETTINGS {
            let base = Config::default();
            let mut before = serde_json::to_value(&base).expect("serialise");
            let value = match setting.bound {
                Bound::Bool => {
                    let now = pointer(&before, setting.path).as_bool().expect("bool");
                    json!(!now)
                }
                Bound::Int(min, max) => json!(if min < 3 && 3 <= max { 3 } else { max }),
                Bound::Num(min, max) => json!((min + max) / 2.0),
                Bound::Choice(options) => {
                    let now = pointer(&before, setting.path).clone();
                    json!(options.iter().find(|o| json!(o) != now).expect("a choice"))
                }
            };
            let mut config = base.clone();
            (setting.set)(&mut config, value.clone()).expect(setting.path);
            let after = serde_json::to_value(&config).expect("serialise");
            *pointer_mut(&mut before, setting.path) = value;
            assert_eq!(after, before, "{}", setting.path);
        }
    }

    fn pointer<'a>(v: &'a Value, path: &str) -> &'a Value {
        v.pointer(&format!("/{}", path.replace('.', "/")))
            .expect(path)
    }

    fn pointer_mut<'a>(v: &'a mut Value, path: &str) -> &'a mut Value {
        v.pointer_mut(&format!("/{}", path.replace('.', "/")))
            .expect(path)
    }

    #[test]
    fn a_partial_config_applies_over_the_base_and_keeps_the_rest() {
        let mut base = Config::default();
        base.pipeline.deterministic = true;
        let user = UserConfig::from_json(
            &json!({"pipeline": {"seed": 5}, "fusion": {"voxels_per_median_depth": 96.0}}),
            Scope::Anyone,
        )
        .expect("parse");
        let c = user.apply(&base).expect("apply");
        assert_eq!(c.pipeline.seed, 5);
        assert_eq!(c.fusion.voxels_per_median_depth, 96.0);
        assert!(c.pipeline.deterministic, "keys not given keep the base's");
        assert_eq!(c.tracking, base.tracking);
        let none = UserConfig::from_json(&Value::Null, Scope::Anyone).expect("null");
        assert_eq!(none.apply(&base).expect("apply"), base);
    }

    #[test]
    fn expert_operator_unknown_and_out_of_bound_keys_are_refused_by_name() {
        for (bad, names) in [
            (json!({"pipeline": {"seeed": 5}}), "pipeline.seeed"),
            (json!({"nonsense": 1}), "nonsense"),
            (json!({"pipeline": {"seed": "five"}}), "pipeline.seed"),
            (
                json!({"pipeline": {"prior_init_var": 1.0}}),
                "pipeline.prior_init_var",
            ),
            (json!({"dense": {"width": 640}}), "dense.width"),
            (json!({"fusion": {"voxel_size": 0.01}}), "fusion.voxel_size"),
            (
                json!({"dense": {"densify": {"iterations": 50}}}),
                "dense.densify.iterations",
            ),
            (json!({"pipeline": {"init": "oracle"}}), "pipeline.init"),
            (
                json!({"mapping": {"kf_dist_weight": "inf"}}),
                "mapping.kf_dist_weight",
            ),
            (json!({"pipeline": 3}), "pipeline"),
        ] {
            let e = UserConfig::from_json(&bad, Scope::Anyone).expect_err("accepted");
            assert!(e.to_string().contains(names), "{bad}: {e}");
        }
        assert!(matches!(
            UserConfig::from_json(&json!([1, 2]), Scope::Anyone),
            Err(UserConfigError::NotAnObject)
        ));
        let operator = json!({"dense": {"width": 640, "height": 480}});
        let c = UserConfig::from_json(&operator, Scope::Operator)
            .expect("the operator sets resolutions")
            .apply(&Config::default())
            .expect("apply");
        assert_eq!((c.dense.width, c.dense.height), (640, 480));
    }

    /// The README's "User settings" table, one row per setting.
    fn readme_table() -> String {
        let mut table =
            String::from("| key | values | who may set it | what for |\n|---|---|---|---|\n");
        for s in USER_SETTINGS {
            let who = match s.scope {
                Scope::Anyone => "anyone",
                Scope::Operator => "the operator",
            };
            table.push_str(&format!(
                "| `{}` | {} | {who} | {} |\n",
                s.path,
                s.bound.describe(),
                s.why
            ));
        }
        table
    }

    #[test]
    fn the_readme_lists_exactly_these_settings() {
        let readme = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../README.md"))
            .expect("README.md");
        let table = readme_table();
        assert!(
            readme.contains(&table),
            "README.md's \"User settings\" table differs from USER_SETTINGS; it should read:\n{table}"
        );
    }

    #[test]
    fn values_in_bounds_that_make_an_invalid_config_are_refused() {
        // Each is in its bound; together with the base they must still pass `validate`.
        let mut base = Config::default();
        base.dense.width = 7;
        let user =
            UserConfig::from_json(&json!({"pipeline": {"seed": 1}}), Scope::Anyone).expect("parse");
        assert!(matches!(
            user.apply(&base),
            Err(UserConfigError::Invalid(_))
        ));
    }
}
