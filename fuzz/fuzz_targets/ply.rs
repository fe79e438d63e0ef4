//! Tessera's PLY reader. The first byte picks the file: 0 the rest as
//! `m.ply` (ASCII or binary, as its header says), 1 the rest gzipped by
//! this target as `m.ply.gz` (the gzip path with PLY content the fuzzer can
//! shape), 2 the rest as `m.ply.gz` itself (hostile gzip streams).
#![no_main]

use std::io::Write as _;

use libfuzzer_sys::fuzz_target;
use tessera_fuzz::{check_mesh, init};
use tracer_core::assets::Bundle;
use tracer_core::mesh::Mesh;

fuzz_target!(|data: &[u8]| {
    init();
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let (name, content) = match mode % 3 {
        0 => ("m.ply", rest.to_vec()),
        1 => {
            let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            gz.write_all(rest).unwrap();
            ("m.ply.gz", gz.finish().unwrap())
        }
        _ => ("m.ply.gz", rest.to_vec()),
    };
    let mut files = Bundle::new();
    files.insert(name, content);
    check_mesh(Mesh::load_from(&files, name, true));
});
