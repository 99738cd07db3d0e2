//! Files a person opens: point clouds now, meshes with the fusion layer.

pub mod ply;

pub use ply::{ColoredPoint, points_ply_bytes, read_points_ply, write_points_ply};
