//! The service over Zenoh, end to end: a real `relfusiond` listening on a loopback Zenoh
//! endpoint and real Zenoh sessions as its clients (and, with tokens, as intruders), and a
//! ROS 2 robot on rmw_zenoh's wire format played by Python (`ros2`).

mod auth;
mod big_messages;
mod client;
mod intruder;
mod late_router;
mod placement;
mod ros2;
mod stream;
mod taken_port;
