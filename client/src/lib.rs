//! The `relfusion` command line's own library: the lab-bench parts that the SDK
//! (`relfusion-sdk`) leaves out.
//!
//! - [`browser`]: drives Chromium through chromedriver (`relfusion bench viewer`, the viewer's
//!   browser test).

pub mod browser;
