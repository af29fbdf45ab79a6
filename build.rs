//! Compiles the public API (`proto/posematch/v1/posematch.proto`) into Rust with a vendored
//! `protoc`, so a fresh machine needs no system protobuf compiler. The encoded descriptor set is
//! kept for server reflection (`grpcurl list` / `describe` without a proto file).

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // SAFETY: build scripts are single-threaded; prost-build reads PROTOC from the environment.
    unsafe { std::env::set_var("PROTOC", protoc) };
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_prost_build::configure()
        .file_descriptor_set_path(out_dir.join("posematch_descriptor.bin"))
        .compile_protos(&["proto/posematch/v1/posematch.proto"], &["proto"])?;
    println!("cargo:rerun-if-changed=proto");
    Ok(())
}
