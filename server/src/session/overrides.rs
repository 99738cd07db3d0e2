//! A session's pipeline configuration: the client's partial JSON merged over a base.

use relfusion_slam::pipeline::Config as SlamConfig;

use crate::ApiError;

/// `overrides` (a JSON object, or null) deep-merged over `base`; unknown keys and invalid
/// values are a 400 that names them.
pub fn merge_config(
    base: &SlamConfig,
    overrides: &serde_json::Value,
) -> Result<SlamConfig, ApiError> {
    fn merge(into: &mut serde_json::Value, from: &serde_json::Value) {
        match (into, from) {
            (serde_json::Value::Object(a), serde_json::Value::Object(b)) => {
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
}
