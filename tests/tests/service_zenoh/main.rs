//! The service over Zenoh, end to end: a real `relfusiond` listening on a loopback Zenoh
//! endpoint and real Zenoh sessions as its clients (and, with tokens, as intruders).

mod auth;
mod big_messages;
mod client;
mod intruder;
mod late_router;
mod placement;
mod stream;
