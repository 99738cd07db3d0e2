//! Containers start in any order: a relfusiond whose Zenoh router is not up yet starts anyway
//! (HTTP serves at once) and joins the router when it comes up. Fails when relfusiond exits
//! for want of a router, or when its node status never reaches the router's clients.

use relfusion_tests::{Relfusiond, free_port, temp_dir};

use super::client::{ENDPOINTS, node_status, zenoh_client};

#[test]
fn a_node_started_before_its_router_joins_it_when_it_comes_up() {
    let _machine = ENDPOINTS.write().unwrap_or_else(|e| e.into_inner());
    let work = temp_dir("zenoh-late-router");
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    // The deploy files' setting: a client of a router that is not there yet.
    let late = work.join("late.toml");
    std::fs::write(
        &late,
        format!("[zenoh]\nenabled = true\nmode = \"client\"\nnode = \"late\"\nconnect = [\"{endpoint}\"]\n"),
    )
    .expect("config");
    let node = Relfusiond::spawn(
        &work.join("late-data"),
        ["--config", late.to_str().expect("path")],
        &[],
    );
    let health = ureq::get(&format!("{}/healthz", node.url()))
        .call()
        .expect("HTTP serves without the router");
    assert_eq!(health.status().as_u16(), 200);

    // The "router" comes up: another relfusiond listening on the endpoint (a Zenoh peer routes
    // for its clients).
    let router_config = work.join("router.toml");
    std::fs::write(&router_config, "[zenoh]\nnode = \"router\"\n").expect("config");
    let router = Relfusiond::spawn(
        &work.join("router-data"),
        [
            "--config",
            router_config.to_str().expect("path"),
            "--zenoh-listen",
            &endpoint,
        ],
        &[],
    );
    let z = zenoh_client(&endpoint, &router, None);
    let status = node_status(&z, |s| s["node"] == "late");
    assert_eq!(status["node"], "late", "{status}\n{}", node.log());
    drop(z);
    drop(router);
    drop(node);
    let _ = std::fs::remove_dir_all(&work);
}
