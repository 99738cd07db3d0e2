//! The `relfusion` command line's own library: the lab-bench parts that the SDK
//! (`relfusion-sdk`) leaves out.
//!
//! - [`browser`]: drives Chromium through chromedriver (`relfusion bench viewer`, the viewer's
//!   browser test).
//! - [`depth_probe`]: the map's depth shape and scale against the sensor's (`bench odometry`,
//!   `bench accuracy`).
//! - [`latency`]: frame-to-pose latency percentiles (`bench serve`, `bench cluster`, `bench long`).
//!
//! The binary has no unit tests of its own (`test = false`): what is worth a unit test lives here,
//! so a test build does not compile the whole command line twice.

pub mod browser;
pub mod depth_probe;
pub mod latency;
