//! `SceneDesc::parse_from` on arbitrary text, over a bundle holding the
//! repository's example models (so scenes that name them load real meshes).
#![no_main]

use libfuzzer_sys::fuzz_target;
use tessera_fuzz::{check_scene, init};
use tracer_core::assets::Bundle;
use tracer_core::scene::SceneDesc;

const TRI_PLY: &[u8] = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";

fn bundle() -> Bundle {
    let mut b = Bundle::new();
    let models: [(&str, &[u8]); 4] = [
        (
            "cornell_box.obj",
            include_bytes!("../../examples/models/cornell_box.obj"),
        ),
        (
            "cornell_box.mtl",
            include_bytes!("../../examples/models/cornell_box.mtl"),
        ),
        ("Box.gltf", include_bytes!("../../examples/models/Box.gltf")),
        ("tri.ply", TRI_PLY),
    ];
    for (name, data) in models {
        b.insert(format!("models/{name}"), data);
        b.insert(name, data);
    }
    b
}

fuzz_target!(|data: &[u8]| {
    init();
    thread_local!(static FILES: Bundle = bundle());
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    FILES.with(|files| check_scene(SceneDesc::parse_from(text, "fuzz.toml", files)));
});
