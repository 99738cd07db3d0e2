//! A live session fed over HTTP and WebSocket: a pose for every frame over SSE and WebSocket,
//! a trajectory with every frame, results (the fused mesh included) downloadable, delete.

use super::client::*;

#[test]
fn live_session_reports_every_frame_over_sse_and_websocket() {
    const FRAMES: usize = 24;
    const OVER_HTTP: usize = 12;
    let seq = TumSequence::open(&synth_sequence("http-live", FRAMES, 11), None).expect("synth");
    let server = spawn("live", None, &[]);
    let id = create_session(&server, &seq, None);
    let events = follow_events(&server, &id);

    for i in 0..OVER_HTTP {
        let accepted = post_frame(&server, &id, &seq, i);
        assert_eq!(accepted.status, 202, "frame {i}: {}", accepted.body);
        assert_eq!(accepted.json()["frame_index"], i as u64);
    }
    let mut socket = ws_connect(&server, &id, None).expect("websocket");
    for i in OVER_HTTP..FRAMES {
        ws_send(&mut socket, ws_frame(&seq, i, frame_bytes(&seq, i)));
    }
    ws_send(
        &mut socket,
        client_message::Message::EndOfStream(EndOfStream {}),
    );
    let mut ws_poses = Vec::new();
    while let Some(message) = ws_next(&mut socket) {
        match message {
            server_message::Message::Pose(pose) => {
                assert_eq!(pose.session_id, id);
                let t = pose
                    .world_from_camera
                    .expect("pose")
                    .translation
                    .expect("t");
                assert!(t.x.is_finite() && t.y.is_finite() && t.z.is_finite());
                ws_poses.push(pose.frame_id);
            }
            server_message::Message::Error(e) => panic!("unexpected error: {e:?}"),
            _ => {}
        }
    }
    for i in OVER_HTTP..FRAMES {
        assert!(
            ws_poses.contains(&(i as u64)),
            "no WS pose for frame {i}: {ws_poses:?}"
        );
    }

    let events = events.join().expect("SSE thread");
    let (last, info) = events.last().expect("events");
    assert_eq!(last, "finished", "{events:?}");
    assert_eq!(info["info"]["state"], "finished", "{info}");
    let sse_poses: Vec<u64> = events
        .iter()
        .filter(|(name, _)| name == "pose")
        .map(|(_, e)| e["frame_id"].as_u64().expect("frame_id"))
        .collect();
    assert_eq!(
        sse_poses,
        (0..FRAMES as u64).collect::<Vec<_>>(),
        "one pose per frame, in order"
    );
    let first = &events.iter().find(|(n, _)| n == "pose").expect("pose").1;
    assert_eq!(first["timestamp"].as_f64(), Some(seq.frames[0].timestamp));
    assert_eq!(
        first["pose"]["q"].as_array().map(Vec::len),
        Some(4),
        "{first}"
    );

    let info = wait_finished(&server, &id, None);
    assert_eq!(info["frames_processed"], FRAMES as u64, "{info}");
    assert_eq!(info["frames_dropped"], 0, "{info}");
    let trajectory = get(&server, &format!("/v1/sessions/{id}/trajectory"), None);
    assert_eq!(trajectory.status, 200);
    let lines = tum_lines(&trajectory.body);
    assert_eq!(lines.len(), FRAMES, "{}", trajectory.body);
    for (line, frame) in lines.iter().zip(&seq.frames) {
        assert_eq!(line.len(), 8);
        assert!((line[0] - frame.timestamp).abs() < 1e-6, "{line:?}");
    }
    let keyframes = get(&server, &format!("/v1/sessions/{id}/keyframes"), None);
    assert!(!tum_lines(&keyframes.body).is_empty(), "{}", keyframes.body);
    let mut cloud = agent()
        .get(format!("{}/v1/sessions/{id}/pointcloud.ply", server.url()))
        .call()
        .expect("pointcloud");
    assert_eq!(cloud.status().as_u16(), 200);
    assert!(
        cloud
            .body_mut()
            .read_to_vec()
            .expect("ply")
            .starts_with(b"ply")
    );
    // The dense layer (no model: edge-aware densification) and the fusion ran: a mesh.
    for (file, magic) in [("mesh.ply", &b"ply"[..]), ("mesh.glb", &b"glTF"[..])] {
        let mut response = agent()
            .get(format!("{}/v1/sessions/{id}/{file}", server.url()))
            .call()
            .unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!(response.status().as_u16(), 200, "{file}");
        let bytes = response.body_mut().read_to_vec().expect(file);
        assert!(
            bytes.starts_with(magic) && bytes.len() > 1000,
            "{file}: {} bytes",
            bytes.len()
        );
    }
    assert!(info["mesh_revision"].as_u64() >= Some(1), "{info}");
    assert!(info["mesh_triangles"].as_u64() > Some(0), "{info}");
    let late = format!(
        "/v1/sessions/{id}/frames?timestamp=9&frame_id={}",
        FRAMES + 5
    );
    send(
        &server,
        "POST",
        &late,
        None,
        "image/png",
        &frame_bytes(&seq, 0),
    )
    .expect_error(409, "conflict", "frame after the end");

    let list = get(&server, "/v1/sessions", None).json();
    assert!(
        list["sessions"]
            .as_array()
            .expect("list")
            .iter()
            .any(|s| s["id"] == id.as_str())
    );
    let metrics = get(&server, "/metrics", None).body;
    let received = metrics
        .lines()
        .find_map(|l| l.strip_prefix("frames_received_total "))
        .and_then(|v| v.trim().parse::<f64>().ok())
        .expect("frames_received_total");
    assert!(received >= FRAMES as f64, "{metrics}");
    assert_eq!(
        send(
            &server,
            "DELETE",
            &format!("/v1/sessions/{id}"),
            None,
            "",
            b""
        )
        .status,
        204
    );
    get(&server, &format!("/v1/sessions/{id}"), None).expect_error(404, "not_found", "deleted");
}
