//! Files a person opens: point clouds now, meshes with the fusion layer.

pub mod ply;

pub use ply::{ColoredPoint, read_points_ply, write_points_ply};
