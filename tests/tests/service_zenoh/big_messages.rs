//! Issue 34, item 7: Zenoh reassembled messages up to its default 1 GiB before the access
//! rules saw them, so a tenant's 800 MiB `put` to a key it may not use grew the node by as
//! much, for good. Now a node reassembles at most `zenoh.max_message_mb` (twice the largest
//! frame, 16 MiB by default) and drops the rest as it arrives.

use relfusion_tests::attacks::peak_rss;

use super::client::*;

#[test]
fn a_tenants_huge_zenoh_messages_cost_the_node_no_memory() {
    let _machine = ENDPOINTS.read().unwrap_or_else(|e| e.into_inner());
    let work = temp_dir("zenoh-big-messages");
    let (server, endpoint) = spawn_server(&work, &[("RELFUSIOND_TOKENS", "alice:tok-a,bob:tok-b")]);
    let alice = zenoh_client(&endpoint, &server, Some(("alice", "tok-a")));
    node_status(&alice, |_| true);
    let bob = zenoh_client(&endpoint, &server, Some(("bob", "tok-b")));
    let before = peak_rss(server.pid());
    for key in [
        "relfusion/tenants/alice/sessions/s-0/frames",
        "relfusion/tenants/bob/sessions/s-0/frames",
    ] {
        let _ = bob
            .put(key, vec![7u8; 200 << 20])
            .congestion_control(CongestionControl::Block)
            .wait();
    }
    // Give the node time to take in (and drop) every fragment.
    std::thread::sleep(Duration::from_secs(3));
    let grown = peak_rss(server.pid()).saturating_sub(before) >> 20;
    println!("two 200 MiB Zenoh puts: node peak RSS +{grown} MiB");
    assert!(
        grown < 100,
        "the node reassembled the messages: +{grown} MiB"
    );
    let health = ureq::get(format!("{}/healthz", server.url()))
        .call()
        .expect("healthz")
        .body_mut()
        .read_to_string()
        .expect("body");
    assert_eq!(health, "ok");
    node_status(&alice, |_| true);
}
