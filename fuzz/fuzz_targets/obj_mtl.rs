//! The OBJ loader (tobj, and the MTL rewriting before it). The input is an
//! OBJ file, then a NUL byte, then the MTL library it may name (as `m.mtl`
//! or `cornell_box.mtl`, the seeds' names).
#![no_main]

use libfuzzer_sys::fuzz_target;
use tessera_fuzz::{check_mesh, init};
use tracer_core::assets::Bundle;
use tracer_core::mesh::Mesh;

fuzz_target!(|data: &[u8]| {
    init();
    let (obj, mtl) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, &[][..]),
    };
    let mut files = Bundle::new();
    files.insert("m.obj", obj);
    files.insert("m.mtl", mtl);
    files.insert("cornell_box.mtl", mtl);
    // Materials needed (a missing library is a warning) or overridden.
    let need_materials = obj.len() % 2 == 0;
    check_mesh(Mesh::load_from(&files, "m.obj", need_materials));
});
