//! The glTF loader (the `gltf` crate and the checks before its reader):
//! `.glb` for inputs with the GLB magic, `.gltf` otherwise. The input is
//! also there as `m.bin`, for a buffer URI that names a file.
#![no_main]

use libfuzzer_sys::fuzz_target;
use tessera_fuzz::{check_mesh, init};
use tracer_core::assets::Bundle;
use tracer_core::mesh::Mesh;

fuzz_target!(|data: &[u8]| {
    init();
    let name = if data.starts_with(b"glTF") {
        "m.glb"
    } else {
        "m.gltf"
    };
    let mut files = Bundle::new();
    files.insert(name, data);
    files.insert("m.bin", data);
    check_mesh(Mesh::load_from(&files, name, true));
});
