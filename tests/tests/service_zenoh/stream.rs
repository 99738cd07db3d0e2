//! A session over Zenoh, end to end: created through the create queryable (deterministic
//! config, `wait` policy), it gives a pose for every frame published, mesh deltas on `mesh`
//! that add up to the map's mesh, announces its end on `finished`, and its map (the map
//! queryable) holds a trajectory whose ATE equals `relfusion run --deterministic` on the same
//! data.

use std::collections::BTreeSet;

use super::client::*;

#[test]
fn stream_over_zenoh_gives_every_pose_and_the_same_trajectory_as_run() {
    let _machine = ENDPOINTS.read().unwrap_or_else(|e| e.into_inner());
    let seq_dir = synth_sequence("zenoh", FRAMES_N, SEED);
    let seq = TumSequence::open(&seq_dir, None).expect("open sequence");
    let work = temp_dir("zenoh-stream");
    let (server, endpoint) = spawn_server(&work, &[]);
    let z = zenoh_client(&endpoint, &server, None);
    let status = node_status(&z, |_| true);
    assert_eq!(status["accepting"], true, "{status}");
    assert!(
        status["max_sessions"].as_u64().is_some_and(|m| m >= 1),
        "{status}"
    );

    let config = session_config(
        &seq,
        FramePolicy::Wait,
        r#"{"pipeline":{"deterministic":true}}"#,
    );
    let id = create(&z, PUBLIC_TENANT, None, config.encode_to_vec()).expect("session created");
    let updates = subscribe(&z, PUBLIC_TENANT, &id);
    stream_frames(&z, PUBLIC_TENANT, &id, &seq, FRAMES_N);

    let mut posed = BTreeSet::new();
    let mut keyframes = 0;
    // The mesh as a subscriber patches it: block index → block, and the last revision.
    let mut mesh = std::collections::BTreeMap::new();
    let mut revision = 0;
    let finished = loop {
        match next_update(&updates, &server) {
            Ok(message) => match message.message {
                Some(server_message::Message::Pose(p)) => {
                    assert_eq!(p.session_id, id);
                    assert!(posed.insert(p.frame_id), "frame {} posed twice", p.frame_id);
                    assert_eq!(p.timestamp, seq.frames[p.frame_id as usize].timestamp);
                    let pose = p.world_from_camera.expect("pose");
                    assert!(pose.scale > 0.0 && pose.scale.is_finite(), "{pose:?}");
                }
                Some(server_message::Message::Keyframe(k)) => {
                    assert_eq!(k.session_id, id);
                    keyframes += 1;
                }
                Some(server_message::Message::Mesh(m)) => {
                    assert_eq!(m.session_id, id);
                    assert_eq!(m.revision, revision + 1, "mesh revisions have no gap");
                    revision = m.revision;
                    assert!(m.block_size > 0.0);
                    for b in &m.removed_blocks {
                        mesh.remove(&(b.x, b.y, b.z));
                    }
                    for b in m.changed_blocks {
                        let i = b.index.expect("block index");
                        assert_eq!(b.vertices.len(), 12 * (b.colors.len() / 3));
                        assert_eq!(b.normals.len(), b.vertices.len());
                        assert!(!b.indices.is_empty() && b.indices.len() % 3 == 0);
                        mesh.insert((i.x, i.y, i.z), b);
                    }
                }
                Some(server_message::Message::Error(e)) => {
                    panic!("unexpected error: {e:?}\n{}", server.log())
                }
                _ => {}
            },
            Err(finished) => break finished,
        }
    };
    assert_eq!(
        posed,
        (0..FRAMES_N as u64).collect(),
        "a pose for every frame (wait policy drops nothing)"
    );
    assert!(keyframes >= 1, "at least the first keyframe was announced");
    assert_eq!(finished.session_id, id);
    assert_eq!(finished.state, "finished", "{finished:?}");
    assert_eq!(finished.frames_received, FRAMES_N as u64);
    assert_eq!(finished.frames_processed, FRAMES_N as u64);
    assert_eq!(finished.frames_dropped, 0);

    let snapshot = map(&z, PUBLIC_TENANT, None, &id).expect("map of a finished session");
    assert_eq!(snapshot.session_id, id);
    assert_eq!(snapshot.state, "finished");
    assert_eq!(snapshot.frames_processed, FRAMES_N as u64);
    assert_eq!(snapshot.frames_received, FRAMES_N as u64);
    assert!(!snapshot.keyframes.is_empty(), "the map has keyframes");
    assert!(
        keyframes >= 2 * snapshot.keyframes.len(),
        "every keyframe is announced when made and again with its optimised pose \
         ({keyframes} updates, {} keyframes)",
        snapshot.keyframes.len()
    );
    assert!(revision >= 1, "the fused mesh was published on `mesh`");
    assert_eq!(snapshot.mesh_revision, revision);
    let served_mesh: std::collections::BTreeMap<_, _> = snapshot
        .mesh_blocks
        .iter()
        .map(|b| {
            let i = b.index.expect("block index");
            ((i.x, i.y, i.z), b.clone())
        })
        .collect();
    assert!(!served_mesh.is_empty(), "the map has the fused mesh");
    assert!(
        served_mesh == mesh,
        "applying every MeshUpdate gives the map's mesh ({} vs {} blocks)",
        mesh.len(),
        served_mesh.len()
    );
    let served = to_slam(&snapshot.trajectory);
    assert_eq!(served.len(), FRAMES_N, "every frame is in the trajectory");

    let run = run_deterministic(&seq_dir, &work);
    assert_eq!(served.len(), run.len(), "same number of poses");
    let ate_served = ate_rmse(&seq, &served);
    let ate_run = ate_rmse(&seq, &run);
    assert!(
        (ate_served - ate_run).abs() <= 1e-9,
        "ATE over Zenoh {ate_served} vs relfusion run {ate_run}"
    );
    for (a, b) in served.iter().zip(&run) {
        assert_eq!(a.timestamp, b.timestamp);
        let d = (a.world_from_camera.translation - b.world_from_camera.translation).norm();
        assert!(d <= 1e-9, "pose at {} differs by {d}", a.timestamp);
    }
}
