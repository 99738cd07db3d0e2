//! `free_port` lets its port go before relfusiond binds it, so another process can take it in
//! between (a CI run lost the intruder test to that: relfusiond printed its HTTP address, then
//! could not bind its Zenoh endpoint and exited, and the client dialled a dead port for 20 s).
//! The tests' start helper tries another port then; this takes the first port on purpose.

use std::net::TcpListener;

use relfusion_tests::server::on_free_endpoint;

use super::client::*;

#[test]
fn a_peer_whose_zenoh_port_was_taken_starts_on_another() {
    let _machine = ENDPOINTS.read().unwrap_or_else(|e| e.into_inner());
    let work = temp_dir("zenoh-taken-port");
    let mut tried = Vec::new();
    let mut hog = None;
    let (server, endpoint) = on_free_endpoint(|endpoint| {
        if tried.is_empty() {
            let port: u16 = endpoint
                .rsplit(':')
                .next()
                .and_then(|p| p.parse().ok())
                .expect("port");
            hog = Some(TcpListener::bind(("127.0.0.1", port)).expect("take the port first"));
        }
        tried.push(endpoint.to_string());
        Relfusiond::try_spawn_zenoh_peer::<&str>(&work.join("data"), &[], &[], endpoint)
    });
    assert_eq!(tried.len(), 2, "{tried:?}");
    assert_eq!(endpoint, tried[1]);
    assert_ne!(tried[0], tried[1]);
    let z = zenoh_client(&endpoint, &server, None);
    let status = node_status(&z, |_| true);
    assert!(status["sessions_active"].is_u64(), "{status}");
    drop(hog);
}
