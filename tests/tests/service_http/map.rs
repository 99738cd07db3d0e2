//! Joining late, the wire schema and the docs page: `GET /v1/sessions/{id}/map` gives the whole
//! current map (protobuf, or JSON on request) that agrees with the downloads once the session
//! has finished, `/v1/proto` serves the `.proto` sources the server speaks, and `/docs` is
//! Swagger UI served from the binary.

use relfusion_proto::v1::MapSnapshot;

use relfusion_tests::ply_faces;

use super::client::*;

fn map_bytes(server: &Relfusiond, id: &str) -> Vec<u8> {
    let mut response = agent()
        .get(format!("{}/v1/sessions/{id}/map", server.url()))
        .call()
        .expect("map");
    assert_eq!(response.status().as_u16(), 200);
    assert_eq!(
        response
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some("application/x-protobuf")
    );
    response.body_mut().read_to_vec().expect("body")
}

#[test]
fn a_late_client_gets_the_whole_map_and_the_schema() {
    const FRAMES: usize = 24;
    let seq = TumSequence::open(&synth_sequence("http-map", FRAMES, 12), None).expect("synth");
    let server = spawn("map", None, &[]);
    let id = create_session(&server, &seq, None);
    for i in 0..FRAMES / 2 {
        assert_eq!(post_frame(&server, &id, &seq, i).status, 202, "frame {i}");
    }
    // Mid-session: a consistent picture of what is processed so far.
    let mid = MapSnapshot::decode(map_bytes(&server, &id).as_slice()).expect("MapSnapshot");
    assert_eq!(mid.session_id, id);
    assert!(
        mid.trajectory.len() as u64 <= mid.frames_received,
        "{mid:?}"
    );
    assert!(mid.frames_received <= (FRAMES / 2) as u64);
    for i in FRAMES / 2..FRAMES {
        assert_eq!(post_frame(&server, &id, &seq, i).status, 202, "frame {i}");
    }
    let finish = send(
        &server,
        "POST",
        &format!("/v1/sessions/{id}/finish"),
        None,
        "application/json",
        b"",
    );
    assert!(finish.status < 300, "{}", finish.body);
    wait_finished(&server, &id, None);

    // Finished: the snapshot is the final map, equal to the downloads.
    let done = MapSnapshot::decode(map_bytes(&server, &id).as_slice()).expect("MapSnapshot");
    assert_eq!(done.state, "finished");
    assert_eq!(done.frames_processed, FRAMES as u64);
    let trajectory = tum_lines(&get(&server, &format!("/v1/sessions/{id}/trajectory"), None).body);
    assert_eq!(done.trajectory.len(), trajectory.len());
    for (pose, line) in done.trajectory.iter().zip(&trajectory) {
        assert!((pose.timestamp - line[0]).abs() < 1e-6);
        let t = pose
            .world_from_camera
            .as_ref()
            .and_then(|p| p.translation)
            .expect("translation");
        assert!((t.x - line[1]).abs() < 1e-9 && (t.y - line[2]).abs() < 1e-9);
    }
    let keyframes = tum_lines(&get(&server, &format!("/v1/sessions/{id}/keyframes"), None).body);
    assert_eq!(done.keyframes.len(), keyframes.len());
    assert!(
        done.mesh_revision >= 1 && done.block_size > 0.0,
        "{}",
        done.mesh_revision
    );
    let triangles: usize = done.mesh_blocks.iter().map(|b| b.indices.len() / 3).sum();
    let mut ply = agent()
        .get(format!("{}/v1/sessions/{id}/mesh.ply", server.url()))
        .call()
        .expect("mesh.ply");
    let ply = ply.body_mut().read_to_vec().expect("ply");
    assert!(triangles > 0);
    assert_eq!(
        triangles as u64,
        ply_faces(&ply),
        "snapshot vs mesh.ply triangles"
    );

    // JSON on request: the same map.
    let json = reply(
        agent()
            .get(format!("{}/v1/sessions/{id}/map", server.url()))
            .header("Accept", "application/json")
            .call(),
    )
    .json();
    assert_eq!(json["session_id"], id.as_str());
    assert_eq!(
        json["trajectory"].as_array().map(Vec::len),
        Some(trajectory.len())
    );
    assert_eq!(json["mesh_revision"], done.mesh_revision);
    let blocks = json["mesh_blocks"].as_array().expect("blocks");
    assert_eq!(blocks.len(), done.mesh_blocks.len());
    let first = &done.mesh_blocks[0];
    assert_eq!(
        blocks[0]["vertices"].as_array().map(Vec::len),
        Some(first.vertices.len() / 4),
        "one number per float32"
    );
    get(&server, "/v1/sessions/nope/map", None).expect_error(404, "not_found", "unknown session");

    // The schema: every file listed is served byte for byte; nothing else is.
    let list = get(&server, "/v1/proto", None).json();
    let files: Vec<&str> = list["files"]
        .as_array()
        .expect("files")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    assert_eq!(files.len(), relfusion_proto::PROTO_FILES.len());
    for (path, text) in relfusion_proto::PROTO_FILES {
        assert!(files.contains(path));
        let served = get(&server, &format!("/v1/proto/{path}"), None);
        assert_eq!(served.status, 200, "{path}");
        assert_eq!(served.body, *text, "{path}");
        assert!(served.body.contains("package relfusion.v1;"));
    }
    for bad in [
        "relfusion/v1/nope.proto",
        "../Cargo.toml",
        "relfusion%2F..%2F..%2Fbuild.rs",
    ] {
        get(&server, &format!("/v1/proto/{bad}"), None).expect_error(404, "not_found", bad);
    }

    // The API docs page: Swagger UI from the binary itself, over /openapi.json, started by a
    // script of its own (the page's Content-Security-Policy allows no inline script).
    let page = get(&server, "/docs", None);
    assert_eq!(page.status, 200);
    assert!(page.body.contains("/docs/init.js"), "{}", page.body);
    let init = get(&server, "/docs/init.js", None);
    assert!(
        init.status == 200 && init.body.contains("url: \"/openapi.json\""),
        "{}",
        init.body
    );
    let assets = Path::new(env!("CARGO_MANIFEST_DIR")).join("../server/assets/swagger-ui");
    for (file, content_type) in [
        ("swagger-ui-bundle.js", "text/javascript; charset=utf-8"),
        ("swagger-ui.css", "text/css; charset=utf-8"),
    ] {
        assert!(
            page.body.contains(&format!("/docs/{file}")),
            "{file} linked"
        );
        let mut response = agent()
            .get(format!("{}/docs/{file}", server.url()))
            .call()
            .expect(file);
        assert_eq!(response.status().as_u16(), 200, "{file}");
        assert_eq!(
            response
                .headers()
                .get("content-type")
                .and_then(|v| v.to_str().ok()),
            Some(content_type)
        );
        let served = response
            .body_mut()
            .with_config()
            .limit(16 << 20)
            .read_to_vec()
            .expect(file);
        assert_eq!(
            served,
            std::fs::read(assets.join(file)).expect("vendored"),
            "{file}"
        );
    }
    assert_healthy(&server, "map and proto requests");
}
