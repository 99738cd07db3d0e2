//! relfusion wire schema, version 1 (protobuf package `relfusion.v1`).
//!
//! The `.proto` sources in `proto/relfusion/v1/` are the contract; the Rust types in [`v1`] are
//! generated from them at build time with protox + prost (no system `protoc`). Clients in other
//! languages can take the sources from [`PROTO_FILES`] (the server also serves them).
//!
//! The HTTP API's JSON is the second contract, defined once in [`http`].
//!
//! Conventions are documented in the sources: poses are `world_from_camera` Sim(3) transforms
//! (camera-to-world, scale-last), inverse depth and mesh geometry are packed little-endian
//! `float32`, lengths are map units.

/// Generated message types of `relfusion.v1`.
pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/relfusion.v1.rs"));
}

pub use prost::Message;

pub mod http;
pub mod zenoh_keys;

/// The schema sources as `(path relative to the proto root, contents)`, in dependency order.
pub const PROTO_FILES: &[(&str, &str)] = &[
    (
        "relfusion/v1/geometry.proto",
        include_str!("../proto/relfusion/v1/geometry.proto"),
    ),
    (
        "relfusion/v1/frame.proto",
        include_str!("../proto/relfusion/v1/frame.proto"),
    ),
    (
        "relfusion/v1/updates.proto",
        include_str!("../proto/relfusion/v1/updates.proto"),
    ),
    (
        "relfusion/v1/session.proto",
        include_str!("../proto/relfusion/v1/session.proto"),
    ),
];
