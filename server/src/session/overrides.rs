//! A session's pipeline configuration: the client's partial JSON applied over a base.
//!
//! A stranger's config is input like any other: parameters that size memory or threads
//! (working resolutions, queues, block pools, thread counts), evaluation switches and expert
//! constants are the server's to set. A client sets only the user settings anyone may set
//! (`relfusion_slam::pipeline::user_config`, the one list, with its bounds); anything else is a
//! 400 that names the key, so nothing a client sends multiplies what a session costs beyond
//! what admission reserved for it.

use relfusion_slam::pipeline::{Config as SlamConfig, Scope, UserConfig, UserConfigError};
use serde_json::Value;

use crate::ApiError;
use relfusion_proto::http::FramePolicy;

/// `overrides` (a JSON object, or null) applied over `base`; keys a client may not set,
/// values out of bounds and invalid combinations are a 400 that names them.
pub fn merge_config(base: &SlamConfig, overrides: &Value) -> Result<SlamConfig, ApiError> {
    let refused = |e: UserConfigError| ApiError::bad_request(e.to_string());
    UserConfig::from_json(overrides, Scope::Anyone)
        .map_err(refused)?
        .apply(base)
        .map_err(refused)
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
                json!({"dense": {"densify": {"iterations": 50}}}),
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
            "dense": {"enabled": false},
            "fusion": {"voxels_per_median_depth": 96.0},
        });
        let c = merge_config(&base, &ok).expect("settable");
        assert!(!c.dense.enabled);
        assert_eq!(c.fusion.voxels_per_median_depth, 96.0);
    }
}
