//! Meshes generated in code for the mesh tests (meshes.rs, gpu.rs): no
//! model file is needed, so the tests are self-contained.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::DVec3;

pub fn tmpdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tessera-meshtest-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Unit icosphere: an icosahedron subdivided `levels` times, vertices on the
/// sphere, shared between triangles, counter-clockwise seen from outside.
pub fn icosphere(levels: u32) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut v: Vec<DVec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|p| DVec3::from_array(*p).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut mid = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32, v: &mut Vec<DVec3>| {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a as usize] + v[b as usize]) * 0.5).normalize());
                v.len() as u32 - 1
            })
        };
        let mut next = Vec::with_capacity(f.len() * 4);
        for [a, b, c] in f {
            let (ab, bc, ca) = (
                midpoint(a, b, &mut v),
                midpoint(b, c, &mut v),
                midpoint(c, a, &mut v),
            );
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = next;
    }
    (v.iter().map(|p| p.to_array()).collect(), f)
}

/// Writes an OBJ (1-based indices; with `vn` = the positions when `smooth`).
pub fn write_obj(path: &Path, v: &[[f64; 3]], f: &[[u32; 3]], smooth: bool) {
    let mut s = String::new();
    for p in v {
        writeln!(s, "v {} {} {}", p[0], p[1], p[2]).unwrap();
        if smooth {
            writeln!(s, "vn {} {} {}", p[0], p[1], p[2]).unwrap();
        }
    }
    for t in f {
        let [a, b, c] = t.map(|i| i + 1);
        if smooth {
            writeln!(s, "f {a}//{a} {b}//{b} {c}//{c}").unwrap();
        } else {
            writeln!(s, "f {a} {b} {c}").unwrap();
        }
    }
    std::fs::write(path, s).unwrap();
}

/// OBJ text of the pathological mesh: 5000 identical triangles in one spot,
/// zero-area triangles, one huge triangle behind everything (it fills the
/// background of the mesh tests' camera), thin slivers in a fan, and
/// exponential chains that a pure SAH build would split one at a time.
pub fn pathological_obj() -> String {
    let mut s = String::new();
    let mut nv = 0;
    let mut tri = |s: &mut String, p: [[f64; 3]; 3]| {
        for q in p {
            writeln!(s, "v {} {} {}", q[0], q[1], q[2]).unwrap();
        }
        writeln!(s, "f {} {} {}", nv + 1, nv + 2, nv + 3).unwrap();
        nv += 3;
    };
    // 5000 identical triangles in one spot.
    for _ in 0..5000 {
        tri(&mut s, [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]]);
    }
    // Zero-area ones: a point and a segment.
    tri(&mut s, [[0.5, 0.5, 0.5]; 3]);
    tri(&mut s, [[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [2.0, 1.0, 0.0]]);
    // One huge triangle behind everything.
    tri(
        &mut s,
        [[-1e6, -1e6, 30.0], [1e6, -1e6, 30.0], [0.0, 1e6, 30.0]],
    );
    // Thin slivers (1e-7 wide, 3 long) in a fan, and an exponential chain
    // that a SAH build would split one triangle at a time.
    for i in 0..2000 {
        let a = i as f64 * 1e-3;
        tri(
            &mut s,
            [
                [0.0, -0.5, 0.0],
                [3.0 * a.cos(), -0.5 + 3.0 * a.sin(), 1.0],
                [3.0 * a.cos(), -0.5 + 3.0 * a.sin() + 1e-7, 1.0],
            ],
        );
    }
    for i in 0..3000 {
        let x = 1.005f64.powi(i) * 1e-6;
        tri(
            &mut s,
            [[x, -1.0, 2.0], [x + 1e-7, -1.0, 2.0], [x, -1.0 + 1e-7, 2.0]],
        );
    }
    // Triangles at x = 2^i * 1e-20 (1e-20 .. 1e10): a chain for the SAH.
    for i in 0..100 {
        let x = 2f64.powi(i) * 1e-20;
        tri(
            &mut s,
            [
                [x, 1.5, 3.0],
                [x * 1.25, 1.5, 3.0],
                [x, 1.5 + x * 0.25, 3.0],
            ],
        );
    }
    s
}

/// Writes `quad.obj` into `dir`: a 3x3 square in the z = 0 plane facing
/// the camera, two triangles (the moving-mesh scenes' object).
pub fn write_quad_obj(dir: &Path) {
    std::fs::write(
        dir.join("quad.obj"),
        "v -1.5 -1.5 0\nv 1.5 -1.5 0\nv 1.5 1.5 0\nv -1.5 1.5 0\nf 1 2 3\nf 1 3 4\n",
    )
    .unwrap();
}

/// The keyframes (TOML) of an object moving along x from `from` at frame
/// 0 to `to` at frame 1.
pub fn keyframes_along_x(from: f64, to: f64) -> String {
    format!(
        "[[objects.keyframes]]\nframe = 0\ntranslate = [{from}, 0, 0]\n[[objects.keyframes]]\nframe = 1\ntranslate = [{to}, 0, 0]\n"
    )
}

/// A glTF file of the quad [-h, h]^2 at z = `z` facing +Z, with texture
/// coordinates (0, 0) at its top-left corner (-h, h) and (1, 1) at its
/// bottom-right one, material `material` (JSON) and the PNG `png` as
/// image 0 (texture 0, sampler `sampler`).
pub fn textured_quad(dir: &Path, h: f32, z: f32, material: &str, sampler: &str) -> String {
    textured_quad_with(dir, h, z, material, sampler, None, None)
}

/// [`textured_quad`] with COLOR_0 (RGBA, one per corner: (-h, -h),
/// (h, -h), (h, h), (-h, h)) where `colours` is given, and TANGENT (the
/// same at every corner) where `tangent` is given.
pub fn textured_quad_with(
    dir: &Path,
    h: f32,
    z: f32,
    material: &str,
    sampler: &str,
    colours: Option<[[f32; 4]; 4]>,
    tangent: Option<[f32; 4]>,
) -> String {
    use base64::Engine as _;
    let mut bin = Vec::new();
    for c in [-h, -h, z, h, -h, z, h, h, z, -h, h, z] {
        bin.extend(c.to_le_bytes());
    }
    for _ in 0..4 {
        for c in [0f32, 0., 1.] {
            bin.extend(c.to_le_bytes());
        }
    }
    for c in [0f32, 1., 1., 1., 1., 0., 0., 0.] {
        bin.extend(c.to_le_bytes());
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        bin.extend(i.to_le_bytes());
    }
    // Padding to 4 bytes, then the colours.
    bin.extend([0u8; 4]);
    for c in colours.iter().flatten().flatten() {
        bin.extend(c.to_le_bytes());
    }
    let (colour_attr, colour_view, colour_accessor) = if colours.is_some() {
        (
            r#","COLOR_0":4"#,
            r#",{"buffer":0,"byteOffset":144,"byteLength":64}"#,
            r#",{"bufferView":4,"componentType":5126,"count":4,"type":"VEC4"}"#,
        )
    } else {
        ("", "", "")
    };
    let (tangent_attr, tangent_view, tangent_accessor) = match tangent {
        Some(t) => {
            let offset = bin.len();
            for _ in 0..4 {
                for c in t {
                    bin.extend(c.to_le_bytes());
                }
            }
            // Its buffer view and accessor, after the colours' where given.
            let k = 4 + colours.is_some() as usize;
            (
                format!(r#","TANGENT":{k}"#),
                format!(r#",{{"buffer":0,"byteOffset":{offset},"byteLength":64}}"#),
                format!(r#",{{"bufferView":{k},"componentType":5126,"count":4,"type":"VEC4"}}"#),
            )
        }
        None => Default::default(),
    };
    let uri = base64::engine::general_purpose::STANDARD.encode(&bin);
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],
        "nodes":[{{"mesh":0}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,"TEXCOORD_0":2{colour_attr}{tangent_attr}}},"indices":3,"material":0}}]}}],
        "materials":[{material}],
        "textures":[{{"source":0,"sampler":0}}],
        "samplers":[{sampler}],
        "images":[{{"uri":"tex.png"}}],
        "extensionsUsed":["KHR_materials_specular"],
        "buffers":[{{"byteLength":{len},"uri":"data:application/octet-stream;base64,{uri}"}}],
        "bufferViews":[{{"buffer":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":48}},
                       {{"buffer":0,"byteOffset":96,"byteLength":32}},{{"buffer":0,"byteOffset":128,"byteLength":12}}{colour_view}{tangent_view}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-1,-1,0],"max":[1,1,0]}},
                     {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC3"}},
                     {{"bufferView":2,"componentType":5126,"count":4,"type":"VEC2"}},
                     {{"bufferView":3,"componentType":5123,"count":6,"type":"SCALAR"}}{colour_accessor}{tangent_accessor}]}}"#,
        len = bin.len(),
    );
    std::fs::write(dir.join("quad.gltf"), json).unwrap();
    "quad.gltf".into()
}

/// Gives `dir`/`model` (a [`textured_quad`]) the nodes `nodes` (JSON
/// objects placing mesh 0: a rotation, a scale; all in the scene) in
/// place of its one bare `{"mesh":0}`.
pub fn set_quad_node(dir: &Path, model: &str, nodes: &[&str]) {
    let file = dir.join(model);
    let json = std::fs::read_to_string(&file).unwrap();
    let (bare, scene) = (r#""nodes":[{"mesh":0}]"#, r#""scenes":[{"nodes":[0]}]"#);
    assert!(
        json.contains(bare) && json.contains(scene),
        "{model}: no bare node"
    );
    let listed: Vec<String> = (0..nodes.len()).map(|i| i.to_string()).collect();
    let json = json
        .replace(bare, &format!(r#""nodes":[{}]"#, nodes.join(",")))
        .replace(
            scene,
            &format!(r#""scenes":[{{"nodes":[{}]}}]"#, listed.join(",")),
        );
    std::fs::write(&file, json).unwrap();
}

pub fn write_png(dir: &Path, w: u32, h: u32, texels: &[[u8; 4]]) {
    let img = image::RgbaImage::from_fn(w, h, |x, y| image::Rgba(texels[(y * w + x) as usize]));
    img.save(dir.join("tex.png")).unwrap();
}

/// `w` x `h` opaque texels of distinct colours (at most 13 texels).
pub fn colour_texels(w: u32, h: u32) -> Vec<[u8; 4]> {
    (0..w * h)
        .map(|i| {
            [
                (i * 21 + 3) as u8,
                (250 - i * 19) as u8,
                ((i * 97) % 251) as u8,
                255,
            ]
        })
        .collect()
}

/// Writes a glTF file with one `KHR_lights_punctual` light (`light`: its
/// JSON object) on a node at `position` whose -Z axis (the direction glTF
/// lights shine in) is the unit `direction` (not +Z), and, as a model file
/// needs triangles, one of no area at the origin (dropped at build).
pub fn write_gltf_light(path: &Path, light: &str, position: [f64; 3], direction: [f64; 3]) {
    // The rotation taking -Z to `direction`: axis (-Z) x d, w = 1 + (-Z).d.
    let d = DVec3::from_array(direction).normalize();
    let a = DVec3::new(0.0, 0.0, -1.0);
    let axis = a.cross(d);
    let q = glam::DVec4::new(axis.x, axis.y, axis.z, 1.0 + a.dot(d)).normalize();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,1]}}],
        "nodes":[{{"extensions":{{"KHR_lights_punctual":{{"light":0}}}},"translation":{:?},"rotation":{:?}}},{{"mesh":0}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
        "buffers":[{{"byteLength":36,"uri":"data:application/octet-stream;base64,{zeros}"}}],
        "bufferViews":[{{"buffer":0,"byteLength":36}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[0,0,0]}}],
        "extensionsUsed":["KHR_lights_punctual"],
        "extensions":{{"KHR_lights_punctual":{{"lights":[{light}]}}}}}}"#,
        position,
        [q.x, q.y, q.z, q.w],
        zeros = "A".repeat(48),
    );
    std::fs::write(path, json).unwrap();
}
