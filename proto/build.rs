//! Compiles the wire schema with protox (a pure-Rust protobuf compiler), so building needs no
//! system `protoc`.

const FILES: [&str; 4] = [
    "proto/relfusion/v1/geometry.proto",
    "proto/relfusion/v1/frame.proto",
    "proto/relfusion/v1/updates.proto",
    "proto/relfusion/v1/session.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    for file in FILES {
        println!("cargo:rerun-if-changed={file}");
    }
    let fds = protox::compile(FILES, ["proto"])?;
    prost_build::Config::new().compile_fds(fds)?;
    Ok(())
}
