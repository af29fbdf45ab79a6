//! Compiles the public API (`proto/posematch/v1/posematch.proto`) into Rust with a vendored
//! `protoc`, so a fresh machine needs no system protobuf compiler. The encoded descriptor set is
//! kept for server reflection (`grpcurl list` / `describe` without a proto file), for the HTTP
//! API's OpenAPI document, and for pbjson, which generates the proto3 canonical JSON mapping
//! (serde) of every message: the HTTP/JSON API speaks the same messages as gRPC, so the proto
//! stays the one contract.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // SAFETY: build scripts are single-threaded; prost-build reads PROTOC from the environment.
    unsafe { std::env::set_var("PROTOC", protoc) };
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    let descriptor_path = out_dir.join("posematch_descriptor.bin");
    tonic_prost_build::configure()
        .file_descriptor_set_path(&descriptor_path)
        .compile_protos(&["proto/posematch/v1/posematch.proto"], &["proto"])?;
    let descriptors = std::fs::read(&descriptor_path)?;
    pbjson_build::Builder::new()
        .register_descriptors(&descriptors)?
        .build(&[".posematch.v1"])?;
    println!("cargo:rerun-if-changed=proto");
    Ok(())
}
