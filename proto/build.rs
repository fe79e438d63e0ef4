//! Generates the gRPC code from `tessera/v1/*.proto` with a vendored protoc,
//! so a fresh machine needs no system protobuf compiler.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // SAFETY: build scripts are single-threaded; prost-build reads PROTOC.
    unsafe { std::env::set_var("PROTOC", protoc) };
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    let files = [
        "tessera/v1/common.proto",
        "tessera/v1/jobs.proto",
        "tessera/v1/workers.proto",
    ];
    for f in files {
        println!("cargo:rerun-if-changed={f}");
    }
    tonic_prost_build::configure()
        // A result's films as `Bytes`: decoded as slices of the receive
        // buffer, not copied into vectors (a GPU result is tens of megabytes).
        .bytes(".tessera.v1.SubmitResultRequest.sums")
        .bytes(".tessera.v1.SubmitResultRequest.counts")
        .bytes(".tessera.v1.SubmitResultRequest.squares")
        .file_descriptor_set_path(out.join("tessera_descriptor.bin"))
        .compile_protos(&files, &["."])?;
    Ok(())
}
