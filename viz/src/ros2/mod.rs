//! ROS 2 messages without ROS: the CDR encoding ([`cdr`]), the standard message types with
//! their REP-2011 type hashes ([`types`]), writers and readers of the messages relfusion
//! speaks ([`msgs`]), a session as ROS 2 topics ([`log`]), and as a ROS 2 bag in MCAP
//! ([`mcap`]). The service puts them on Zenoh
//! the way rmw_zenoh does (`relfusion-server`'s `ros2_api`).

pub mod cdr;
pub mod log;
pub mod mcap;
pub mod msgs;
pub mod types;

pub use log::{Ros2Log, Ros2Sink, Topic};
