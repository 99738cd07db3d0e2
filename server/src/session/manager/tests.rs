//! Session manager behaviour without HTTP: admission, ownership, frame checks, recovery.

use std::path::PathBuf;
use std::sync::Arc;

use serde_json::json;

use super::*;
use crate::config::Config;
use crate::metrics::Metrics;
use crate::session::overrides::upload_config;
use crate::session::persist::{SessionMeta, result_key};
use crate::session::types::{CameraJson, CreateSession, camera_from_json};
use crate::session::{FrameData, SessionEvent};
use crate::storage::{FsStore, ObjectStore};
use relfusion_slam::pipeline::Event;

fn temp_config(tag: &str, max_sessions: usize) -> Config {
    let dir: PathBuf =
        std::env::temp_dir().join(format!("relfusion-manager-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = Config {
        data_dir: dir,
        ..Config::default()
    };
    config.limits.max_sessions = max_sessions;
    config.pool.workers = 1;
    config
}

fn camera() -> CameraJson {
    CameraJson {
        fx: 100.0,
        fy: 100.0,
        cx: 31.5,
        cy: 23.5,
        width: 64,
        height: 48,
        distortion: None,
    }
}

fn request() -> CreateSession {
    CreateSession {
        camera: Some(camera()),
        config: json!({"pipeline": {"deterministic": true}}),
        policy: FramePolicy::Wait,
        ..CreateSession::default()
    }
}

/// A textured PNG of `w`×`h` (smooth blobs, so that tracking has gradients).
fn png(w: u32, h: u32, shift: f32) -> bytes::Bytes {
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        let v = 128.0
            + 60.0 * ((x as f32 + shift) * 0.3).sin() * (y as f32 * 0.25).cos()
            + 40.0 * ((x as f32 + shift) * 0.11 + y as f32 * 0.07).sin();
        let v = v.clamp(0.0, 255.0) as u8;
        image::Rgb([v, v, v])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .expect("encode");
    out.into_inner().into()
}

fn owner(name: &str) -> Owner {
    Owner(Some(name.into()))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn admission_ownership_and_bad_requests() {
    let config = temp_config("admission", 1);
    let m = SessionManager::open(&config, Arc::new(Metrics::new())).expect("open");
    let alice = owner("alice");
    let a = m
        .create(SessionRequest::from_http(request()).expect("valid"), &alice)
        .expect("first session");
    let e = m
        .create(SessionRequest::from_http(request()).expect("valid"), &alice)
        .expect_err("over capacity");
    assert_eq!((e.status, e.code), (503, "resource_exhausted"), "{e}");
    assert!(
        m.get(a.id(), &owner("bob")).is_err(),
        "other owners see 404"
    );
    assert_eq!(m.get(a.id(), &owner("bob")).expect_err("404").status, 404);
    assert_eq!(m.list(&alice).len(), 1);
    assert!(m.list(&owner("bob")).is_empty());

    let mut bad = request();
    bad.config = json!({"tracking": {"no_such_key": 1}});
    m.delete(a.id(), &alice).expect("delete");
    assert_eq!(
        SessionRequest::from_http(bad)
            .and_then(|r| m.create(r, &alice))
            .expect_err("bad config")
            .status,
        400
    );
    let mut bad = request();
    bad.model = Some("midas-xl".into());
    assert_eq!(
        SessionRequest::from_http(bad)
            .and_then(|r| m.create(r, &alice))
            .expect_err("bad model")
            .status,
        400
    );
    let mut bad = request();
    if let Some(c) = bad.camera.as_mut() {
        c.fx = -1.0;
    }
    assert_eq!(
        SessionRequest::from_http(bad)
            .and_then(|r| m.create(r, &alice))
            .expect_err("bad camera")
            .status,
        400
    );
    let no_camera = CreateSession {
        camera: None,
        ..request()
    };
    assert_eq!(
        SessionRequest::from_http(no_camera)
            .expect_err("no camera")
            .status,
        400
    );
    // The slot freed by the delete is available again.
    let b = m
        .create(SessionRequest::from_http(request()).expect("valid"), &alice)
        .expect("slot freed by delete");
    m.delete(b.id(), &alice).expect("delete");
    m.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_are_checked_processed_and_results_persisted() {
    let config = temp_config("frames", 2);
    let m = SessionManager::open(&config, Arc::new(Metrics::new())).expect("open");
    let me = Owner(None);
    let s = m
        .create(SessionRequest::from_http(request()).expect("valid"), &me)
        .expect("create");
    let mut events = s.subscribe();
    let frame = |id: Option<u64>, t: f64, bytes: bytes::Bytes| FrameData {
        frame_id: id,
        timestamp: t,
        bytes,
    };
    let e = s
        .push_frame(frame(None, 0.0, png(32, 24, 0.0)))
        .await
        .expect_err("size mismatch");
    assert!(
        e.message.contains("32x24") && e.message.contains("64x48"),
        "{e}"
    );
    let e = s
        .push_frame(frame(
            None,
            0.0,
            bytes::Bytes::from_static(b"\xFF\xD8\xFFjunk"),
        ))
        .await
        .expect_err("corrupt jpeg");
    assert_eq!(e.status, 400);
    for i in 0..6u64 {
        let id = s
            .push_frame(frame(
                Some(10 + i),
                i as f64 / 30.0,
                png(64, 48, i as f32 * 0.5),
            ))
            .await
            .expect("frame");
        assert_eq!(id, 10 + i);
    }
    let e = s
        .push_frame(frame(Some(12), 1.0, png(64, 48, 0.0)))
        .await
        .expect_err("id not increasing");
    assert!(e.message.contains("strictly increase"), "{e}");
    s.end_of_stream();
    let e = s
        .push_frame(frame(None, 2.0, png(64, 48, 0.0)))
        .await
        .expect_err("after end of stream");
    assert_eq!(e.status, 409);
    let info = s.wait_finished().await;
    assert_eq!(info.state, SessionState::Finished, "{info:?}");
    assert_eq!(info.frames_received, 6);
    assert_eq!(info.frames_processed, 6);
    // Subscribers saw a pose per frame with the client's ids, then Finished.
    let mut pose_ids = Vec::new();
    let mut finished = false;
    while let Ok(e) = events.try_recv() {
        match e {
            SessionEvent::Pipeline(Event::Pose(p)) => pose_ids.push(p.frame_id),
            SessionEvent::Finished { .. } => finished = true,
            _ => {}
        }
    }
    assert_eq!(pose_ids, (10..16).collect::<Vec<_>>());
    assert!(finished);
    let stored = FsStore::open(&config.data_dir).expect("store");
    assert!(
        stored
            .get(&result_key(s.id(), "trajectory.txt"))
            .expect("get")
            .is_some()
    );
    assert!(s.trajectory_tum().expect("trajectory").lines().count() > 1);
    assert!(s.pointcloud_ply().starts_with(b"ply\n"));
    assert!(s.mesh_ply().is_none());
    m.shutdown().await;

    // After a restart the finished session is back, read-only, with the same results.
    let m2 = SessionManager::open(&config, Arc::new(Metrics::new())).expect("reopen");
    let again = m2.get(s.id(), &me).expect("finished session reloaded");
    assert_eq!(again.info().state, SessionState::Finished);
    assert_eq!(again.info().frames_processed, 6);
    assert_eq!(
        again.trajectory_tum().expect("trajectory"),
        s.trajectory_tum().expect("trajectory")
    );
    assert_eq!(
        again
            .push_frame(frame(None, 9.0, png(64, 48, 0.0)))
            .await
            .expect_err("read-only")
            .status,
        409
    );
    m2.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recovery_drops_unacknowledged_uploads_and_fails_interrupted_live_sessions() {
    let config = temp_config("recovery", 2);
    let store = FsStore::open(&config.data_dir).expect("store");
    // An upload folder without meta.json: never acknowledged.
    store
        .put("sessions/s-orphan/upload.partial/rgb.txt", b"")
        .expect("put");
    // A live session that was running when the server died.
    let meta = SessionMeta {
        version: 1,
        id: "s-interrupted".into(),
        owner: Owner(None),
        kind: SessionKind::Live,
        state: SessionState::Running,
        camera: camera_from_json(&camera()).expect("valid"),
        config: Default::default(),
        model: "none".into(),
        policy: FramePolicy::DropOldest,
        created_unix: 1,
        error: None,
        dataset: None,
        total_frames: None,
        counters: Default::default(),
        ended_unix: None,
        notice: None,
        upload_bytes: 0,
        results_bytes: 0,
        map: None,
        node: None,
        scale: None,
    };
    meta.save(&store).expect("save");
    store
        .put(
            &result_key("s-interrupted", "trajectory.txt"),
            b"# checkpoint\n",
        )
        .expect("put");
    let m = SessionManager::open(&config, Arc::new(Metrics::new())).expect("open");
    assert!(store.list("sessions/s-orphan/").expect("list").is_empty());
    let s = m.get("s-interrupted", &Owner(None)).expect("kept");
    let info = s.info();
    assert_eq!(info.state, SessionState::Failed);
    assert!(info.error.as_deref().unwrap_or("").contains("interrupted"));
    assert_eq!(
        s.trajectory_tum().expect("trajectory"),
        "# checkpoint\n",
        "the checkpoint stays downloadable"
    );
    m.shutdown().await;
}

/// A tiny TUM-layout dataset (64×48 PNGs, calibration.txt) packed as a tar under `seq/`.
fn tiny_dataset_tar(frames: usize) -> Vec<u8> {
    let mut b = tar::Builder::new(Vec::new());
    let mut add = |name: &str, data: &[u8]| {
        let mut h = tar::Header::new_gnu();
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        b.append_data(&mut h, format!("seq/{name}"), data)
            .expect("append");
    };
    let mut list = String::from("# timestamp filename\n");
    for i in 0..frames {
        list.push_str(&format!("{}.0 rgb/{i}.png\n", i));
        add(&format!("rgb/{i}.png"), &png(64, 48, i as f32 * 0.5));
    }
    add("rgb.txt", list.as_bytes());
    add("calibration.txt", b"100 100 31.5 23.5\n");
    b.into_inner().expect("tar")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_wait_for_a_slot_and_then_run() {
    let config = temp_config("upload-queue", 1);
    let m = SessionManager::open(&config, Arc::new(Metrics::new())).expect("open");
    let me = Owner(None);
    let live = m
        .create(SessionRequest::from_http(request()).expect("valid"), &me)
        .expect("live session takes the only slot");
    let archive = m.temp_dir().join("a.tar");
    std::fs::write(&archive, tiny_dataset_tar(5)).expect("write archive");
    let up = m
        .create_upload(
            m.reserve_upload(&me, None).expect("ticket"),
            NewUpload {
                archive: &archive,
                kind: ArchiveKind::Tar,
                camera: None,
                config: upload_config(&json!({})).expect("config"),
            },
        )
        .await
        .expect("upload acknowledged");
    let info = up.info();
    assert_eq!(info.state, SessionState::Queued, "{info:?}");
    assert_eq!(info.progress.total, Some(5));
    assert_eq!(info.camera.fx, 100.0, "camera from calibration.txt");
    // Durable before the acknowledgement.
    let store = FsStore::open(&config.data_dir).expect("store");
    let meta = SessionMeta::load(&store, up.id())
        .expect("readable")
        .expect("meta.json written");
    assert!(
        meta.config.pipeline.deterministic,
        "uploads run deterministically"
    );
    assert!(
        store
            .list(&format!("sessions/{}/upload/seq/rgb/", up.id()))
            .expect("list")
            .len()
            == 5
    );
    // A bad archive is a 400 and leaves nothing behind: no session folder appears. (Not a
    // count of objects: the live session and the queued upload write theirs meanwhile, and
    // the live session's worker may write its first object only now, under load.)
    std::fs::write(&archive, b"not a tar").expect("write");
    let session_ids = || {
        let keys = store.list("sessions/").expect("list");
        keys.iter()
            .filter_map(|k| k.split('/').nth(1).map(str::to_owned))
            .filter(|id| id != live.id())
            .collect::<std::collections::BTreeSet<_>>()
    };
    let before = session_ids();
    let e = m
        .create_upload(
            m.reserve_upload(&me, None).expect("ticket"),
            NewUpload {
                archive: &archive,
                kind: ArchiveKind::Tar,
                camera: None,
                config: upload_config(&json!({})).expect("config"),
            },
        )
        .await
        .expect_err("garbage archive");
    assert_eq!(e.status, 400, "{e}");
    assert_eq!(session_ids(), before);

    live.end_of_stream();
    let info = tokio::time::timeout(std::time::Duration::from_secs(60), up.wait_finished())
        .await
        .expect("upload ran once the slot freed");
    assert_eq!(info.state, SessionState::Finished, "{info:?}");
    assert_eq!(info.frames_processed, 5);
    m.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_finishes_live_sessions_and_persists_their_results() {
    let config = temp_config("shutdown", 2);
    let m = SessionManager::open(&config, Arc::new(Metrics::new())).expect("open");
    let me = Owner(None);
    let s = m
        .create(SessionRequest::from_http(request()).expect("valid"), &me)
        .expect("create");
    for i in 0..4u64 {
        s.push_frame(FrameData {
            frame_id: None,
            // 30 frames/s: a camera lost for 2 s would begin a map fragment.
            timestamp: i as f64 / 30.0,
            bytes: png(64, 48, i as f32 * 0.5),
        })
        .await
        .expect("frame");
    }
    m.shutdown().await;
    assert_eq!(s.info().state, SessionState::Finished);
    assert_eq!(s.info().frames_processed, 4, "queued frames are processed");
    assert!(
        m.create(SessionRequest::from_http(request()).expect("valid"), &me)
            .is_err(),
        "no new sessions after shutdown"
    );
    let m2 = SessionManager::open(&config, Arc::new(Metrics::new())).expect("reopen");
    let again = m2.get(s.id(), &me).expect("persisted");
    assert_eq!(again.info().state, SessionState::Finished);
    let tracked = 4 - again.info().frames_lost as usize;
    assert_eq!(
        again.trajectory_tum().expect("trajectory").lines().count(),
        1 + tracked,
        "header + a pose per tracked frame"
    );
    m2.shutdown().await;
}

/// Two nodes' managers on one S3 bucket (s3s-fs): an upload stored by `a` for `b` is neither
/// held nor run by `a`; `b` takes it (a repeat is harmless) and runs it to the end; one that
/// `b` never took is taken back by `a`, after which `b` may no longer take it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_upload_stored_for_another_node_runs_once_there_or_back_here() {
    let s3 = relfusion_tests::s3::S3Server::start("handoff");
    let node = |name: &str| {
        let mut config: Config = toml::from_str(&s3.storage_toml()).expect("storage config");
        let local = temp_config(&format!("handoff-{name}"), 2);
        config.data_dir = local.data_dir;
        config.pool = local.pool;
        config.zenoh.node = name.into();
        SessionManager::open(&config, Arc::new(Metrics::new())).expect("open")
    };
    let (a, b) = (node("a"), node("b"));
    assert!(a.shares_store());
    let me = Owner(None);
    let archive = a.temp_dir().join("a.tar");
    std::fs::write(&archive, tiny_dataset_tar(4)).expect("write archive");
    let upload = || NewUpload {
        archive: &archive,
        kind: ArchiveKind::Tar,
        camera: None,
        config: upload_config(&json!({})).expect("config"),
    };
    let ticket = || a.reserve_upload(&me, None).expect("ticket");

    let info = a
        .create_upload_for("b", ticket(), upload())
        .await
        .expect("stored for b");
    assert_eq!(info.node.as_deref(), Some("b"));
    assert!(!a.holds(&info.id), "a does not run it");
    assert!(a.take_over(&info.id, "a").is_err(), "the store names b");
    b.take_over(&info.id, "b").expect("b takes it");
    b.take_over(&info.id, "b").expect("a repeat is harmless");
    let ran = b.get(&info.id, &me).expect("b holds it");
    let done = tokio::time::timeout(std::time::Duration::from_secs(60), ran.wait_finished())
        .await
        .expect("b ran it");
    assert_eq!(done.state, SessionState::Finished, "{done:?}");
    assert_eq!(done.frames_processed, 4);
    assert_eq!(done.node.as_deref(), Some("b"));

    let info = a
        .create_upload_for("b", ticket(), upload())
        .await
        .expect("stored for b");
    a.take_over(&info.id, "b")
        .expect("b did not answer: a takes it back");
    let err = b.take_over(&info.id, "b").expect_err("a has it now");
    assert!(err.contains("node a's"), "{err}");
    let ran = a.get(&info.id, &me).expect("a holds it");
    let done = tokio::time::timeout(std::time::Duration::from_secs(60), ran.wait_finished())
        .await
        .expect("a ran it");
    assert_eq!(done.state, SessionState::Finished, "{done:?}");
    assert!(!b.holds(&info.id));
    a.shutdown().await;
    b.shutdown().await;
}

/// The operator's `[pipeline] frontend` reaches every new session's config (a client cannot
/// set it), except a session that extends a saved map, which keeps the one front end that can.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_operators_front_end_applies_to_sessions_but_map_extensions() {
    use relfusion_slam::pipeline::Frontend;
    let mut config = temp_config("frontend", 2);
    config.pipeline.frontend = Frontend::Dso;
    let m = SessionManager::open(&config, Arc::new(Metrics::new())).expect("open");
    let base = upload_config(&json!({})).expect("config");
    assert_eq!(base.pipeline.frontend, Frontend::Lsd);
    let frontend = |map: Option<MapMode>| {
        let start = map.map(|mode| MapStart {
            id: "m-000000000000".into(),
            mode,
        });
        m.with_operator_settings(base.clone(), start.as_ref())
            .pipeline
            .frontend
    };
    assert_eq!(frontend(None), Frontend::Dso);
    assert_eq!(frontend(Some(MapMode::Localize)), Frontend::Dso);
    assert_eq!(frontend(Some(MapMode::Extend)), Frontend::Lsd);
    let session = m
        .create(
            SessionRequest::from_http(request()).expect("valid"),
            &owner("alice"),
        )
        .expect("session");
    assert_eq!(session.meta().config.pipeline.frontend, Frontend::Dso);
    // Its odometry is charged: the same request under the LSD front end's operator, with the
    // same share, may map more keyframes.
    let lsd = SessionManager::open(&temp_config("frontend-lsd", 2), Arc::new(Metrics::new()))
        .expect("open");
    let other = lsd
        .create(
            SessionRequest::from_http(request()).expect("valid"),
            &owner("alice"),
        )
        .expect("session");
    let limit = |s: &Session| s.info().max_keyframes.expect("a map limit");
    assert!(
        limit(&session) < limit(&other),
        "{} {}",
        limit(&session),
        limit(&other)
    );
    lsd.shutdown().await;
    let refused = SessionRequest::from_http(CreateSession {
        config: json!({"pipeline": {"frontend": "dso"}}),
        ..request()
    });
    assert!(refused.is_err(), "a client may not choose the front end");
}
