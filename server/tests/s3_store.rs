//! The S3 store ([`S3Store`], the `object_store` crate) against a real S3-compatible server
//! (s3s-fs, started here): the store's contract — atomic put, get, sorted prefix listing,
//! prefix deletion, refused keys — holds as it does for the filesystem store, and a folder (a
//! saved map, an upload) round-trips through it; a wrong endpoint or credential stops the
//! store at open.

use relfusion_server::config::S3Config;
use relfusion_server::storage::ObjectStore;
use relfusion_server::storage::s3::S3Store;
use relfusion_tests::s3::S3Server;

fn config(server: &S3Server) -> S3Config {
    let toml: toml::Value = toml::from_str(&server.storage_toml()).expect("toml");
    toml["storage"]["s3"]
        .clone()
        .try_into()
        .expect("the [storage.s3] the server gives")
}

#[test]
fn the_s3_store_keeps_the_store_contract() {
    let server = S3Server::start("store");
    let mut cfg = config(&server);
    cfg.prefix = "deployment-1".into();
    let store = S3Store::open(&cfg).expect("open");
    assert!(store.shared() && store.local_path("sessions/a").is_none());

    store.put("sessions/a/meta.json", b"{}").expect("put");
    store.put("sessions/a/results/t.txt", b"x").expect("put");
    store.put("sessions/b/meta.json", b"[]").expect("put");
    store
        .put("sessions/b/meta.json", b"[1]")
        .expect("overwrite");
    assert_eq!(
        store.get("sessions/b/meta.json").expect("get").as_deref(),
        Some(&b"[1]"[..])
    );
    assert_eq!(store.get("sessions/zz/meta.json").expect("get"), None);
    assert_eq!(
        store.list("sessions/a/").expect("list"),
        vec!["sessions/a/meta.json", "sessions/a/results/t.txt"]
    );
    assert_eq!(store.list("sessions/").expect("list").len(), 3);
    assert_eq!(
        store.list("sessions/a/res").expect("list").len(),
        1,
        "a partial prefix"
    );
    assert!(store.list("nothing/").expect("list").is_empty());
    assert!(
        server.objects("deployment-1/sessions") == 3,
        "below the prefix"
    );
    store.delete_prefix("sessions/a/").expect("delete");
    assert_eq!(
        store.list("sessions/").expect("list"),
        vec!["sessions/b/meta.json"]
    );
    for bad in ["../evil", "/etc/evil", "a/../../evil", "", "a/./b"] {
        assert!(store.put(bad, b"x").is_err(), "{bad:?} refused");
    }

    // A folder of files (a map) through the store.
    let folder = std::env::temp_dir().join(format!("relfusion-s3-folder-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&folder);
    let stored = relfusion_server::folders::store(&store, "maps/m-1/map", |dir| {
        std::fs::create_dir_all(dir.join("keyframes")).map_err(|e| e.to_string())?;
        std::fs::write(dir.join("map.json"), b"{\"v\":1}").map_err(|e| e.to_string())?;
        std::fs::write(dir.join("keyframes/0.npy"), vec![7u8; 70_000]).map_err(|e| e.to_string())
    })
    .expect("store a folder");
    assert_eq!(stored, 70_007);
    let fetched = relfusion_server::folders::fetch(&store, "maps/m-1/map").expect("fetch");
    assert_eq!(
        std::fs::read(fetched.path().join("keyframes/0.npy")).expect("file"),
        vec![7u8; 70_000]
    );
    let _ = std::fs::remove_dir_all(&folder);

    let mut wrong = config(&server);
    wrong.secret_access_key = "not-the-secret".into();
    assert!(
        S3Store::open(&wrong).is_err(),
        "a wrong secret is refused at open"
    );
    let mut nowhere = config(&server);
    nowhere.endpoint = format!("http://127.0.0.1:{}", relfusion_tests::free_port());
    nowhere.timeout_s = 2;
    assert!(
        S3Store::open(&nowhere).is_err(),
        "no server: refused at open"
    );
}
