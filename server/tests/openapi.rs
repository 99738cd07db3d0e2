//! The OpenAPI document is pinned: any change of a route, parameter or schema shows up as a diff
//! of `tests/snapshots/openapi.json`. After an intended change, regenerate it with
//! `UPDATE_SNAPSHOTS=1 cargo test -p relfusion-server --test openapi` and review the diff.

use std::path::PathBuf;

#[test]
fn openapi_document_matches_the_snapshot() {
    let spec = relfusion_server::http::openapi::spec_json();
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/snapshots/openapi.json");
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() {
        std::fs::write(&path, format!("{spec}\n")).expect("write snapshot");
        return;
    }
    let expected = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e}; create it with UPDATE_SNAPSHOTS=1 cargo test -p relfusion-server --test openapi",
            path.display()
        )
    });
    if expected.trim_end() != spec.trim_end() {
        let first_difference = expected
            .lines()
            .zip(spec.lines())
            .position(|(a, b)| a != b)
            .unwrap_or_else(|| expected.lines().count().min(spec.lines().count()));
        panic!(
            "the OpenAPI document changed (first difference at line {}):\n  snapshot: {:?}\n  now:      {:?}\n\
             if intended, run UPDATE_SNAPSHOTS=1 cargo test -p relfusion-server --test openapi",
            first_difference + 1,
            expected.lines().nth(first_difference),
            spec.lines().nth(first_difference)
        );
    }
}

#[test]
fn openapi_document_lists_every_route() {
    let spec: serde_json::Value =
        serde_json::from_str(&relfusion_server::http::openapi::spec_json()).expect("valid JSON");
    let paths = spec["paths"].as_object().expect("paths");
    for route in [
        "/v1/sessions",
        "/v1/sessions/{id}",
        "/v1/sessions/{id}/frames",
        "/v1/sessions/{id}/finish",
        "/v1/sessions/{id}/stream",
        "/v1/sessions/{id}/events",
        "/v1/uploads",
        "/v1/sessions/{id}/trajectory",
        "/v1/sessions/{id}/keyframes",
        "/v1/sessions/{id}/pointcloud.ply",
        "/v1/sessions/{id}/mesh.ply",
        "/v1/sessions/{id}/mesh.glb",
        "/healthz",
        "/readyz",
        "/metrics",
        "/openapi.json",
        "/v1/version",
    ] {
        assert!(
            paths.contains_key(route),
            "{route} missing from the OpenAPI document"
        );
    }
    assert!(spec["components"]["securitySchemes"]["bearer"].is_object());
    assert!(spec["components"]["schemas"]["CreateSession"].is_object());
}
