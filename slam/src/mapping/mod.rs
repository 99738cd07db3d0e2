//! Semi-dense mapping: per-keyframe inverse-depth filtering (LSD-SLAM §3, Engel et al. ICCV 2013).

pub mod depth_map;

pub use depth_map::{DepthMap, InverseDepth};
