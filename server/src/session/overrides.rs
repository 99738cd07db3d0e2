//! A session's pipeline configuration: the client's partial JSON merged over a base, with
//! every key a client may set listed here with its bounds.
//!
//! A stranger's config is input like any other: parameters that size memory or threads
//! (working resolutions, queues, block pools, thread counts) and evaluation switches are the
//! server's to set, and a client may change only the parameters of [`SETTABLE`], within their
//! bounds. Anything else is a 400 that names the key, so nothing a client sends multiplies
//! what a session costs beyond what admission reserved for it.

use relfusion_slam::pipeline::Config as SlamConfig;
use serde_json::Value;

use super::types::FramePolicy;
use crate::ApiError;

/// What values a settable key takes.
#[derive(Clone, Copy, Debug)]
enum Bound {
    Bool,
    /// An integer in `[min, max]`.
    Int(i64, i64),
    /// A finite number in `[min, max]`.
    Num(f64, f64),
    /// One of these strings.
    Choice(&'static [&'static str]),
}

/// Every key a client may set (JSON path below the config root), with its bounds: the
/// switches and weights the paper and LSD-SLAM document as per-sequence choices, and the
/// dense layer's energy parameters (eqs. 4-16), bounded where larger values would cost time.
const SETTABLE: &[(&str, Bound)] = &[
    ("pipeline.init", Bound::Choice(&["prior", "random"])),
    ("pipeline.deterministic", Bound::Bool),
    ("pipeline.mapping_thread", Bound::Bool),
    ("pipeline.seed", Bound::Int(0, i64::MAX)),
    ("pipeline.constant_velocity", Bound::Bool),
    ("pipeline.prior_fill", Bound::Bool),
    // Each candidate costs one tracking per keyframe decision; revisits then add no keyframes.
    ("pipeline.reactivation_candidates", Bound::Int(0, 8)),
    ("tracking.affine_lighting", Bound::Bool),
    ("mapping.min_use_grad", Bound::Num(0.0, 100.0)),
    ("mapping.kf_dist_weight", Bound::Num(0.5, 50.0)),
    ("mapping.kf_usage_weight", Bound::Num(0.5, 50.0)),
    ("backend.loop_closure_strictness", Bound::Num(0.5, 100.0)),
    // Compact keyframes held in memory before older ones spill to the store: admission costs
    // them (`memory::SessionCost`), so a client trades memory for store reads within its share.
    ("backend.held_keyframes", Bound::Int(0, 64)),
    ("dense.enabled", Bound::Bool),
    ("dense.compute", Bound::Choice(&["gpu", "cpu"])),
    ("dense.filter.enabled", Bound::Bool),
    ("dense.filter.sigma_s", Bound::Num(1e-3, 1e4)),
    ("dense.filter.sigma_d", Bound::Num(1e-3, 1e4)),
    ("dense.filter.sigma_c", Bound::Num(1e-3, 1e4)),
    ("dense.filter.sigma_u", Bound::Num(1e-3, 1e4)),
    ("dense.filter.gamma", Bound::Num(0.0, 1.0)),
    ("dense.densify.iterations", Bound::Int(0, 200)),
    ("dense.densify.learning_rate", Bound::Num(1e-6, 10.0)),
    ("dense.densify.lambda", Bound::Num(0.0, 1e3)),
    ("dense.densify.alpha", Bound::Num(-10.0, 2.0)),
    ("dense.densify.epsilon", Bound::Num(1e-9, 1.0)),
    ("dense.densify.terms.cnn_grad", Bound::Bool),
    ("dense.densify.terms.semi_dense", Bound::Bool),
    ("dense.densify.terms.charbonnier", Bound::Bool),
    ("dense.densify.terms.cnn_depth", Bound::Bool),
    ("dense.two_view.enabled", Bound::Bool),
    ("dense.two_view.tau_e", Bound::Num(0.0, 1.0)),
    ("fusion.enabled", Bound::Bool),
    ("fusion.compute", Bound::Choice(&["gpu", "cpu"])),
    ("fusion.voxels_per_median_depth", Bound::Num(16.0, 256.0)),
    ("fusion.truncation_voxels", Bound::Num(1.0, 16.0)),
    ("fusion.min_view_cosine", Bound::Num(0.0, 1.0)),
    // TSDF blocks held in memory before the least recently used chunks spill to the store:
    // a client trades memory for store reads. The floor keeps the newest keyframes' volume in
    // at 128 voxels per median depth: at 1024 the chunks went back and forth and the fusion
    // fell behind (docs/tuning.md, "Bounded fusion").
    ("fusion.resident_blocks", Bound::Int(4096, 65536)),
];

fn bound_of(path: &str) -> Option<Bound> {
    SETTABLE.iter().find(|(p, _)| *p == path).map(|&(_, b)| b)
}

/// Checks every leaf of the client's `overrides` against [`SETTABLE`].
fn check_settable(overrides: &Value, path: &mut Vec<String>) -> Result<(), ApiError> {
    if let Value::Object(map) = overrides {
        let joined = path.join(".");
        // An object is either a section to descend into or a key's whole value.
        if path.is_empty() || bound_of(&joined).is_none() {
            for (key, value) in map {
                path.push(key.clone());
                check_settable(value, path)?;
                path.pop();
            }
            return Ok(());
        }
    }
    let key = path.join(".");
    let Some(bound) = bound_of(&key) else {
        return Err(ApiError::bad_request(format!(
            "config.{key} cannot be set by a client (the server sets it); settable keys: {}",
            SETTABLE
                .iter()
                .map(|(p, _)| *p)
                .collect::<Vec<_>>()
                .join(", ")
        )));
    };
    let ok = match (bound, overrides) {
        (Bound::Bool, Value::Bool(_)) => true,
        (Bound::Int(min, max), Value::Number(n)) => {
            n.as_i64().is_some_and(|v| v >= min && v <= max)
        }
        (Bound::Num(min, max), Value::Number(n)) => n
            .as_f64()
            .is_some_and(|v| v.is_finite() && v >= min && v <= max),
        (Bound::Choice(options), Value::String(s)) => options.contains(&s.as_str()),
        _ => false,
    };
    if ok {
        return Ok(());
    }
    let expected = match bound {
        Bound::Bool => "true or false".to_string(),
        Bound::Int(min, max) => format!("an integer in [{min}, {max}]"),
        Bound::Num(min, max) => format!("a number in [{min}, {max}]"),
        Bound::Choice(options) => format!("one of {options:?}"),
    };
    Err(ApiError::bad_request(format!(
        "config.{key} must be {expected}, got {overrides}"
    )))
}

/// `overrides` (a JSON object, or null) deep-merged over `base`; keys a client may not set,
/// values out of bounds and invalid combinations are a 400 that names them.
pub fn merge_config(base: &SlamConfig, overrides: &Value) -> Result<SlamConfig, ApiError> {
    fn merge(into: &mut Value, from: &Value) {
        match (into, from) {
            (Value::Object(a), Value::Object(b)) => {
                for (k, v) in b {
                    match a.get_mut(k) {
                        Some(slot) => merge(slot, v),
                        None => {
                            a.insert(k.clone(), v.clone());
                        }
                    }
                }
            }
            (slot, v) => *slot = v.clone(),
        }
    }
    if overrides.is_null() {
        return Ok(base.clone());
    }
    if !overrides.is_object() {
        return Err(ApiError::bad_request("config must be a JSON object"));
    }
    check_settable(overrides, &mut Vec::new())?;
    let mut value = serde_json::to_value(base)
        .map_err(|e| ApiError::internal(format!("serialising the default config: {e}")))?;
    merge(&mut value, overrides);
    let config: SlamConfig =
        serde_json::from_value(value).map_err(|e| ApiError::bad_request(format!("config: {e}")))?;
    config
        .validate()
        .map_err(|e| ApiError::bad_request(e.to_string()))?;
    Ok(config)
}

/// A live session's configuration: `overrides` over the live defaults for `policy`.
pub fn live_config(overrides: &Value, policy: FramePolicy) -> Result<SlamConfig, ApiError> {
    let mut base = SlamConfig::default();
    // A live camera does not wait: tracking gives every frame its pose at frame rate and the
    // mapping thread observes the frames it has time for (skipped, never queued). A replay
    // that waits for room loses nothing, and maps every frame in step.
    base.pipeline.mapping_thread = policy == FramePolicy::DropOldest;
    merge_config(&base, overrides)
}

/// An upload's configuration: `overrides` over deterministic defaults (a re-run after a
/// crash must give the result the interrupted run would have given).
pub fn upload_config(overrides: &Value) -> Result<SlamConfig, ApiError> {
    let mut base = SlamConfig::default();
    base.pipeline.deterministic = true;
    merge_config(&base, overrides)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn partial_json_merges_over_the_base_and_unknown_keys_are_400() {
        let mut base = SlamConfig::default();
        base.pipeline.deterministic = true;
        let c = merge_config(&base, &json!({"pipeline": {"seed": 5}})).expect("merge");
        assert_eq!(c.pipeline.seed, 5);
        assert!(
            c.pipeline.deterministic,
            "keys not given keep the base's value"
        );
        assert_eq!(c.tracking, base.tracking);
        assert_eq!(
            merge_config(&base, &serde_json::Value::Null).expect("null"),
            base
        );
        for bad in [
            json!({"pipeline": {"seeed": 5}}),
            json!({"nonsense": 1}),
            json!({"pipeline": {"seed": "five"}}),
            json!({"pipeline": {"prior_init_var": -1.0}}),
            json!([1, 2]),
        ] {
            let e = merge_config(&base, &bad).expect_err("invalid config accepted");
            assert_eq!(e.status, 400, "{bad}: {e}");
        }
    }

    #[test]
    fn memory_sizing_keys_are_the_servers_and_settable_ones_are_bounded() {
        let base = SlamConfig::default();
        for (bad, names) in [
            (
                json!({"fusion": {"max_blocks": 4_000_000_000u64}}),
                "fusion.max_blocks",
            ),
            (json!({"fusion": {"voxel_size": 1e-9}}), "fusion.voxel_size"),
            (
                json!({"fusion": {"keyframe_memory_mb": 1e9}}),
                "fusion.keyframe_memory_mb",
            ),
            (json!({"dense": {"width": 8192}}), "dense.width"),
            (json!({"dense": {"queue": 100000}}), "dense.queue"),
            (json!({"mapping": {"threads": 64}}), "mapping.threads"),
            (json!({"dense": {"keep_stages": true}}), "dense.keep_stages"),
            (
                json!({"dense": {"densify": {"iterations": 100000}}}),
                "dense.densify.iterations",
            ),
            (
                json!({"fusion": {"voxels_per_median_depth": 4096}}),
                "fusion.voxels_per_median_depth",
            ),
            (
                json!({"mapping": {"kf_dist_weight": "inf"}}),
                "mapping.kf_dist_weight",
            ),
            (json!({"pipeline": {"init": "oracle"}}), "pipeline.init"),
        ] {
            let e = merge_config(&base, &bad).expect_err("accepted");
            assert_eq!(e.status, 400, "{bad}: {e}");
            assert!(e.message.contains(names), "{bad}: {e}");
        }
        let ok = json!({
            "pipeline": {"deterministic": true, "init": "random"},
            "dense": {"densify": {"iterations": 50, "terms": {"cnn_depth": true}}},
            "fusion": {"voxels_per_median_depth": 96.0},
        });
        let c = merge_config(&base, &ok).expect("settable");
        assert_eq!(c.dense.densify.iterations, 50);
        assert_eq!(c.fusion.voxels_per_median_depth, 96.0);
    }
}
