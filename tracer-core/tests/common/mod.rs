//! Helpers shared by the tracer-core integration tests.
#![allow(dead_code)]

pub mod meshgen;
#[path = "../../../tests/support/prereq.rs"]
pub mod prereq;
#[path = "../../../tests/support/sky.rs"]
pub mod sky;

use tracer_core::film::WorkRegion;
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};

/// The test binary's GPU renderer of `strategy`, opened once (one device
/// for the whole binary). A missing adapter fails the test (`None` only
/// if tests/optional.txt made `gpu` optional).
pub fn gpu_with(
    strategy: tracer_core::render::gpu::Strategy,
) -> Option<&'static tracer_core::render::gpu::GpuRenderer> {
    use std::sync::OnceLock;
    use tracer_core::render::gpu::{GpuOptions, GpuRenderer, Strategy};
    static GPU: [OnceLock<Result<GpuRenderer, String>>; 2] = [OnceLock::new(), OnceLock::new()];
    let r = GPU[(strategy == Strategy::Wavefront) as usize].get_or_init(|| {
        let r = GpuRenderer::new(
            std::env::var("TESSERA_TEST_ADAPTER").ok().as_deref(),
            GpuOptions {
                strategy,
                ..GpuOptions::default()
            },
        )
        .map_err(|e| format!("no GPU adapter could be opened: {e}"));
        if let Ok(r) = &r {
            eprintln!("GPU tests use adapter {}", r.adapter());
        }
        r
    });
    prereq::require("gpu", r.as_ref())
}

/// [`gpu_with`] the default (stack) kernel.
pub fn gpu() -> Option<&'static tracer_core::render::gpu::GpuRenderer> {
    gpu_with(tracer_core::render::gpu::Strategy::Stack)
}

pub fn scene(src: &str) -> SceneDesc {
    SceneDesc::parse(src, "test.toml").unwrap_or_else(|e| panic!("test scene does not parse: {e}"))
}

/// A shared glTF asset (a path under shared/) rendered as a scene at
/// `w` x `h`; a missing asset fails (prereq).
pub fn shared_asset(path: &str, w: u32, h: u32) -> SceneDesc {
    let p = prereq::shared(path);
    SceneDesc::load_input(
        &p,
        &tracer_core::scene::ModelSceneOptions {
            width: Some(w),
            height: Some(h),
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{path}: {e}"))
}

pub fn examples_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples")
}

/// Renders the whole image of `desc` with `settings`.
pub fn render_with(desc: &SceneDesc, settings: &RenderSettings, precision: Precision) -> Film {
    let frame = PreparedFrame::build(desc, settings, 0, precision).expect("settings are valid");
    let film = CpuRenderer::new(None)
        .unwrap()
        .render(
            &frame,
            WorkRegion::new(
                0,
                Rect::full(settings.width, settings.height),
                SampleRange::all(settings.samples),
            ),
            &|_| {},
        )
        .unwrap();
    assert_eq!(
        film.nonfinite, 0,
        "a NaN or infinite sample reached the film"
    );
    film
}

pub fn render(desc: &SceneDesc, precision: Precision) -> Film {
    render_with(desc, &desc.render, precision)
}

/// Per-channel absolute differences of two resolved images.
pub struct Diff {
    pub max: f32,
    pub mean: f64,
    /// Pixels whose largest channel difference exceeds the threshold given to [`diff`].
    pub over: usize,
    pub pixels: usize,
}

pub fn diff(a: &[[f32; 3]], b: &[[f32; 3]], threshold: f32) -> Diff {
    assert_eq!(a.len(), b.len());
    let mut d = Diff {
        max: 0.0,
        mean: 0.0,
        over: 0,
        pixels: a.len(),
    };
    for (p, q) in a.iter().zip(b) {
        let m = (0..3).map(|c| (p[c] - q[c]).abs()).fold(0.0f32, f32::max);
        d.max = d.max.max(m);
        d.mean += m as f64;
        if m > threshold {
            d.over += 1;
        }
    }
    d.mean /= a.len() as f64;
    d
}

pub fn assert_finite(img: &[[f32; 3]]) {
    for (i, p) in img.iter().enumerate() {
        assert!(
            p.iter().all(|c| c.is_finite()),
            "pixel {i} is not finite: {p:?}"
        );
    }
}

/// [`HUGE_SPHERE_FLOOR_SCENE`]'s image (`what` names the render): the
/// light is behind the small sphere, so its shadow falls towards the
/// camera, centred on (0, 0, -1.2), which projects to pixel (64, 60), and
/// is ambient only. The floor nearer the camera (rows 86..96, z < -3.3) is
/// outside the shadow and lit at N.L > 0.25: every pixel must be, or it is
/// acne (an acne pixel is ambient only, 0.1).
#[allow(dead_code)] // not every test binary has this case
pub fn assert_huge_sphere_floor_lit_without_acne(what: &str, img: &[[f32; 3]]) {
    let shadow = img[60 * 128 + 64];
    assert!(
        (shadow[0] - 0.1).abs() < 1e-5,
        "{what}: floor in the sphere's shadow = {shadow:?}, want ambient 0.1"
    );
    let lit_min = 0.1 + 0.8 * 0.2;
    for y in 86..96 {
        for x in 0..128 {
            let v = img[y * 128 + x][0];
            assert!(
                v as f64 > lit_min,
                "{what}: floor pixel ({x}, {y}) = {v}: shadow acne"
            );
        }
    }
}

/// A radius-1e6 sphere as the ground with a small sphere on it, lit from behind
/// the small sphere so its shadow falls towards the camera (hard cases, CPU and GPU).
pub const HUGE_SPHERE_FLOOR_SCENE: &str = r#"
[render]
width = 128
height = 96
samples = 1
max_depth = 0
[camera]
position = [0, 2, -6]
look_at = [0, 0.5, 0]
[world]
ambient = [0.1, 0.1, 0.1]
[materials.ground]
ambient = [1, 1, 1]
diffuse = [0.8, 0.8, 0.8]
[[lights]]
position = [0, 3, 6]
[[objects]]
type = "sphere"
center = [0, -1000000, 0]
radius = 1000000
material = "ground"
[[objects]]
type = "sphere"
center = [0, 0.5, 0]
radius = 0.5
material = "ground"
"#;

/// A light lying on the floor plane beside a sphere, and a second light inside
/// a small sphere (hard cases, CPU and GPU).
pub const LIGHT_ON_SURFACE_SCENE: &str = r#"
[render]
width = 128
height = 96
samples = 4
[camera]
position = [0, 2, -5]
look_at = [0, 0.5, 0]
[world]
ambient = [0.1, 0.1, 0.1]
[materials.m]
ambient = [1, 1, 1]
diffuse = [0.8, 0.8, 0.8]
specular = [0.3, 0.3, 0.3]
shininess = 10
[materials.floor]
ambient = [1, 1, 1]
diffuse = [0.8, 0.8, 0.8]
[[lights]]
position = [1.5, 0, 0]
[[lights]]
position = [-1, 0.5, 0.0]
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
[[objects]]
type = "sphere"
center = [0, 0.5, 0]
radius = 0.5
material = "m"
[[objects]]
type = "sphere"
center = [-1, 0.5, 0]
radius = 0.25
material = "m"
"#;

/// A water sphere nested in a glass sphere and two touching glass spheres
/// (`examples/hard/nested-glass.toml`), at the hard-case tests' small size.
pub fn nested_glass_scene() -> (SceneDesc, RenderSettings) {
    let desc = SceneDesc::load(examples_dir().join("hard/nested-glass.toml"))
        .expect("example scene loads");
    let settings = RenderSettings {
        width: 96,
        height: 72,
        samples: 4,
        max_depth: 12,
        ..desc.render
    };
    (desc, settings)
}

/// A hard case with one object, lit by one light, at one centred sample per
/// pixel and no secondary rays: the CPU checks it against an analytic model
/// (hard_cases.rs), the GPU against the CPU's f64 reference (gpu.rs).
pub struct OneObject {
    /// Body of the `[camera]` table.
    pub camera: &'static str,
    /// Body of the `[[objects]]` table, without its material.
    pub object: &'static str,
    pub light: [f64; 3],
    pub size: (u32, u32),
}

impl OneObject {
    pub fn scene(&self) -> SceneDesc {
        scene(&format!(
            r#"
[render]
width = {w}
height = {h}
samples = 1
max_depth = 0
[camera]
{cam}
[world]
ambient = [0.1, 0.1, 0.1]
background = [0.0, 0.0, 0.3]
[materials.m]
ambient = [1.0, 1.0, 1.0]
diffuse = [0.7, 0.6, 0.5]
specular = [0.5, 0.5, 0.5]
shininess = 20.0
[[lights]]
position = [{lx:e}, {ly:e}, {lz:e}]
diffuse = [1.0, 1.0, 1.0]
specular = [1.0, 1.0, 1.0]
[[objects]]
{object}
material = "m"
"#,
            w = self.size.0,
            h = self.size.1,
            cam = self.camera,
            object = self.object,
            lx = self.light[0],
            ly = self.light[1],
            lz = self.light[2],
        ))
    }
}

/// A unit sphere lit from the side: shadow rays leave its own surface.
pub const SPHERE_SELF_SHADOW: OneObject = OneObject {
    camera: "position = [0, 0, -4]\nlook_at = [0, 0, 0]",
    object: "type = \"sphere\"\ncenter = [0, 0, 0]\nradius = 1",
    light: [3.0, 4.0, -5.0],
    size: (96, 96),
};

/// Camera 1e-3 above a plane looking at the horizon: most rays graze it.
pub const GRAZING_PLANE: OneObject = OneObject {
    camera: "position = [0, 0.001, 0]\nlook_at = [0, 0.001, 10]",
    object: "type = \"plane\"\nnormal = [0, 1, 0]\ndistance = 0",
    light: [0.0, 2.0, 5.0],
    size: (128, 64),
};

/// Camera and light inside a sphere: shadow rays from its inner surface
/// cross the interior and must reach the light, not the far wall.
pub const INSIDE_SPHERE: OneObject = OneObject {
    camera: "position = [0, 0, -1]\nlook_at = [0, 0, 1]\nfov_y = 100",
    object: "type = \"sphere\"\ncenter = [0, 0, 0]\nradius = 3",
    light: [0.5, 1.0, 0.0],
    size: (96, 96),
};

/// Radius 1e-4 at 1e5 from the origin, seen from 5e-4 away. Without
/// camera-relative coordinates f32 cannot even place the sphere (its ulp
/// there is 8e-3, 80 radii).
pub const TINY_FAR_SPHERE: OneObject = OneObject {
    camera: "position = [100000.0, 100000.0, 99999.9995]\nlook_at = [100000.0, 100000.0, 100000.0]",
    object: "type = \"sphere\"\ncenter = [100000.0, 100000.0, 100000.0]\nradius = 1e-4",
    light: [100000.0003, 100000.0004, 99999.9995],
    size: (64, 64),
};

/// Radius 1e6, centre 1e5 from the origin, seen from 3 units off its surface.
pub const HUGE_FAR_SPHERE: OneObject = OneObject {
    camera: "position = [100000.0, 1000003.0, 0.0]\nlook_at = [100000.0, 1000000.0, 10.0]",
    object: "type = \"sphere\"\ncenter = [100000.0, 0.0, 0.0]\nradius = 1e6",
    light: [100005.0, 1000010.0, 5.0],
    size: (64, 64),
};

/// A transparent plane (normal +y: "inside" is below) with a red ambient
/// sky plane above and a blue background below. A ray from below that
/// refracts out sees red; under total internal reflection it sees blue.
/// `head` holds the `[render]` and `[camera]` tables.
pub fn glass_plane_scene(head: &str) -> SceneDesc {
    scene(&format!(
        r#"
{head}
[world]
ambient = [1, 1, 1]
background = [0, 0, 1]
[materials.glass]
transparency = 0.9
reflectivity = 0.1
ior = 1.5
[materials.sky]
ambient = [1, 0, 0]
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "glass"
[[objects]]
type = "plane"
normal = [0, -1, 0]
distance = -10
material = "sky"
"#
    ))
}

/// Only the floor, seen from above, under the quad light: no pixel's
/// samples all agree, so a tiny target sends every block to max.
pub const NOISY: &str = r#"
[render]
width = 24
height = 16
max_depth = 0
[camera]
position = [0, 4, -1]
look_at = [0, 0, 0]
fov_y = 40
[world]
ambient = [0.05, 0.05, 0.05]
[materials.floor]
diffuse = [0.8, 0.8, 0.8]
specular = [0, 0, 0]
[[lights]]
type = "quad"
corner = [-1.5, 3, -1.5]
edge_u = [3, 0, 0]
edge_v = [0, 0, 3]
samples = 1
diffuse = [1, 1, 1]
specular = [1, 1, 1]
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
"#;

/// A renderer of a 16x16, 4-sample frame (`render(rect, samples)` gives
/// its error's message) refuses a rectangle outside the image and a sample
/// range outside the frame's, naming them: the CPU's and the GPU's alike.
pub fn assert_bad_regions_refused(render: impl Fn(Rect, SampleRange) -> String) {
    assert_eq!(
        render(Rect::new(8, 8, 9, 1), SampleRange::all(4)),
        "rectangle Rect { x: 8, y: 8, width: 9, height: 1 } is empty or outside the 16x16 image"
    );
    assert_eq!(
        render(Rect::full(16, 16), SampleRange::new(2, 5)),
        "sample range 2..5 is empty or outside 0..4"
    );
}

/// Compares the 8-bit sRGB image `got` (`w` x `h`, RGB) with the golden
/// image `name` in tests/golden/, or writes it there when TESSERA_BLESS is
/// set. Tolerance: a channel may move by 2 levels (f32 rounding
/// differences between compilers and CPUs near a rounding boundary); at
/// most `per_mille` pixels in a thousand (samples that flip to another
/// primitive or path) may move more. `Err` says how many did.
pub fn check_golden(
    name: &str,
    w: u32,
    h: u32,
    got: Vec<u8>,
    per_mille: usize,
) -> Result<(), String> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden");
    let file = dir.join(name);
    if std::env::var_os("TESSERA_BLESS").is_some() {
        std::fs::create_dir_all(&dir).unwrap();
        image::RgbImage::from_raw(w, h, got)
            .unwrap()
            .save(&file)
            .unwrap();
        return Ok(());
    }
    let want = image::open(&file)
        .unwrap_or_else(|e| panic!("{}: {e} (bless with TESSERA_BLESS=1)", file.display()))
        .to_rgb8();
    if want.dimensions() != (w, h) {
        return Err(format!(
            "{name}: golden is {:?}, the render {w}x{h}",
            want.dimensions()
        ));
    }
    let over = got
        .chunks(3)
        .zip(want.as_raw().chunks(3))
        .filter(|(a, b)| a.iter().zip(b.iter()).any(|(x, y)| x.abs_diff(*y) > 2))
        .count();
    if over * 1000 > (w * h) as usize * per_mille {
        return Err(format!(
            "{name}: {over} of {} pixels differ by more than 2/255",
            w * h
        ));
    }
    Ok(())
}

/// An OBJ quad (x, y in [-1, 1], z = 0, u along x, v up y) whose MTL has
/// `bump -bm {bm} ramp.png` (and a `norm` map where `norm` is given), a
/// white `Kd`, no ambient, under one far light along `light` of diffuse
/// 0.8; rendered 31x31 from (0, 0, 2): the centre pixel sees (0, 0, 0).
pub fn bumped_obj_quad(tag: &str, bm: f64, norm: Option<[u8; 3]>, light: [f64; 3]) -> SceneDesc {
    let dir = meshgen::tmpdir(tag);
    // The height ramp: 16 texels across, value x / 15 at texel x.
    let ramp = image::RgbaImage::from_fn(16, 4, |x, _| {
        let h = (x * 17) as u8;
        image::Rgba([h, h, h, 255])
    });
    ramp.save(dir.join("ramp.png")).unwrap();
    let mut mtl = format!("newmtl bumpy\nKd 1 1 1\nKa 0 0 0\nKs 0 0 0\nbump -bm {bm} ramp.png\n");
    if let Some(c) = norm {
        meshgen::write_png(&dir, 1, 1, &[[c[0], c[1], c[2], 255]]);
        mtl.push_str("norm tex.png\n");
    }
    std::fs::write(dir.join("quad.mtl"), mtl).unwrap();
    std::fs::write(
        dir.join("quad.obj"),
        "mtllib quad.mtl\nv -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n\
         vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\nusemtl bumpy\n\
         f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n",
    )
    .unwrap();
    let far = 1.0e4;
    let src = format!(
        "[render]\nwidth = 31\nheight = 31\nsamples = 1\n\
         [camera]\nposition = [0, 0, 2]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40\n\
         [world]\nambient = [0, 0, 0]\n\
         [[lights]]\nposition = [{}, {}, {}]\ndiffuse = [0.8, 0.8, 0.8]\nspecular = [0, 0, 0]\n\
         [[objects]]\ntype = \"mesh\"\npath = \"quad.obj\"\n",
        light[0] * far,
        light[1] * far,
        light[2] * far,
    );
    SceneDesc::parse(&src, dir.join("scene.toml")).unwrap()
}

/// The light of [`quad_over_lit_plane_scene`].
pub const QUAD_LIGHT: [f64; 3] = [1.5, 0.0, 3.0];

/// A model file `model` in `dir` (a quad at z = 1) over the white plane
/// z = 0, seen from (0, 0, 4) over [-2, 2]^2 at `size` x `size`, 1 spp, lit
/// by one point light at [`QUAD_LIGHT`] (diffuse 0.5, no specular) and an
/// ambient 0.25, on a blue background: the cut-out and single-sided
/// scenes of tests/textures.rs and tests/gpu_materials.rs.
pub fn quad_over_lit_plane_scene(dir: &std::path::Path, model: &str, size: u32) -> SceneDesc {
    let [lx, ly, lz] = QUAD_LIGHT;
    let src = format!(
        "[render]\nwidth = {size}\nheight = {size}\nsamples = 1\n\
         [camera]\nposition = [0, 0, 4]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = {fov}\n\
         [world]\nambient = [0.25, 0.25, 0.25]\nbackground = [0, 0, 1]\n\
         [materials.white]\nambient = [1, 1, 1]\ndiffuse = [1, 1, 1]\n\
         [[lights]]\nposition = [{lx}, {ly}, {lz}]\ndiffuse = [0.5, 0.5, 0.5]\nspecular = [0, 0, 0]\n\
         [[objects]]\ntype = \"plane\"\nnormal = [0, 0, 1]\ndistance = 0\nmaterial = \"white\"\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n",
        fov = 2.0 * 0.5f64.atan().to_degrees(),
    );
    SceneDesc::parse(&src, dir.join("scene.toml")).unwrap()
}

/// The cut-out quad of the MASK tests, written into `dir`: [-0.5, 0.5]^2
/// at z = 1, emissive red, double-sided, cut by a 4x4 NEAREST texture whose
/// alpha is 0 or 255 by the returned pattern (row by row). Returns the
/// model file's name and the pattern.
pub fn cutout_quad(dir: &std::path::Path) -> (String, [u8; 16]) {
    let alpha = [1, 0, 1, 1, 0, 0, 1, 0, 1, 1, 0, 1, 0, 1, 1, 0];
    let texels: Vec<[u8; 4]> = alpha.iter().map(|&a| [255, 255, 255, a * 255]).collect();
    meshgen::write_png(dir, 4, 4, &texels);
    let model = meshgen::textured_quad(
        dir,
        0.5,
        1.0,
        r#"{"pbrMetallicRoughness":{"baseColorFactor":[0,0,0,1],"baseColorTexture":{"index":0},"metallicFactor":0},
            "emissiveFactor":[1,0,0],"alphaMode":"MASK","doubleSided":true,
            "extensions":{"KHR_materials_specular":{"specularFactor":0}}}"#,
        r#"{"magFilter":9728,"wrapS":33071,"wrapT":33071}"#,
    );
    (model, alpha)
}

/// Texels of the minified-checker scene's texture (a side).
pub const CHECKER_SIDE: u32 = 64;
/// tan(fov_y / 2) of [`emissive_texture_scene`]'s camera.
pub const EMISSIVE_VIEW_TAN: f64 = 0.45;

/// A `CHECKER_SIDE`-texel square checkerboard of black and white texels,
/// black at (0, 0).
pub fn checker_texels() -> Vec<[u8; 4]> {
    let n = CHECKER_SIDE;
    (0..n * n)
        .map(|i| {
            let c = if (i % n + i / n).is_multiple_of(2) {
                0
            } else {
                255
            };
            [c, c, c, 255]
        })
        .collect()
}

/// The emissive quad [-1, 1]^2 at z = 0 under the `w` x `h` texture
/// `texels` (sRGB, clamped), seen head on from `distance` on +z at `size`
/// x `size` pixels, one sample each through its centre (tan(fov_y / 2) =
/// `EMISSIVE_VIEW_TAN`): nothing but the emission adds (black base colour, no
/// specular layer, a black light, no ambient).
pub fn emissive_texture_scene(
    tag: &str,
    (w, h): (u32, u32),
    texels: &[[u8; 4]],
    distance: f64,
    size: u32,
) -> SceneDesc {
    let dir = meshgen::tmpdir(tag);
    meshgen::write_png(&dir, w, h, texels);
    let model = meshgen::textured_quad(
        &dir,
        1.0,
        0.0,
        r#"{"pbrMetallicRoughness":{"baseColorFactor":[0,0,0,1],"metallicFactor":0},
            "emissiveFactor":[1,1,1],"emissiveTexture":{"index":0},
            "extensions":{"KHR_materials_specular":{"specularFactor":0}}}"#,
        r#"{"wrapS":33071,"wrapT":33071}"#,
    );
    let fov = 2.0 * EMISSIVE_VIEW_TAN.atan().to_degrees();
    let src = format!(
        "[render]\nwidth = {size}\nheight = {size}\nsamples = 1\n\
         [camera]\nposition = [0, 0, {distance}]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = {fov}\n\
         [[lights]]\nposition = [0, 0, 5]\ndiffuse = [0, 0, 0]\nspecular = [0, 0, 0]\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"
    );
    SceneDesc::parse(&src, dir.join("scene.toml")).unwrap()
}

/// [`emissive_texture_scene`] under a `CHECKER_SIDE`-texel checkerboard
/// ([`checker_texels`]), whose texture is minified (a pixel covers about
/// 1.8 texels per unit of distance / 2 at 32 pixels), so every pixel
/// reads mip levels.
pub fn minified_checker_scene(tag: &str, distance: f64, size: u32) -> SceneDesc {
    let n = CHECKER_SIDE;
    emissive_texture_scene(tag, (n, n), &checker_texels(), distance, size)
}

/// DamagedHelmet (textures of every kind, a normal map, tangents by
/// MikkTSpace) placed by three nodes, the third mirrored, as a scene of
/// `w` x `h`: written into `dir` with the asset's buffer and images
/// beside it. `copied`: each node gets a mesh entry of its own over the
/// same accessors, which the loader copies (the one-level form); else
/// the three nodes share mesh 0, which is stored once and instanced.
pub fn three_helmets(dir: &std::path::Path, copied: bool, w: u32, h: u32) -> SceneDesc {
    let src = prereq::shared("scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf");
    let folder = src.parent().unwrap();
    for f in std::fs::read_dir(folder).unwrap() {
        let f = f.unwrap().path();
        if f.extension().is_some_and(|e| e != "gltf") {
            std::fs::copy(&f, dir.join(f.file_name().unwrap())).unwrap();
        }
    }
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&src).unwrap()).unwrap();
    let mesh = json["meshes"][0].clone();
    let turn = [0.70710677, 0.0, 0.0, 0.70710677];
    let nodes = serde_json::json!([
        {"mesh": 0, "rotation": turn, "translation": [-2.2, 0.0, 0.0]},
        {"mesh": if copied { 1 } else { 0 }, "rotation": [0.5, 0.5, -0.5, 0.5],
         "translation": [0.0, 0.3, -0.5], "scale": [0.9, 0.9, 0.9]},
        {"mesh": if copied { 2 } else { 0 }, "rotation": turn,
         "translation": [2.2, 0.0, 0.0], "scale": [-1.0, 1.0, 1.0]},
    ]);
    json["nodes"] = nodes;
    json["scenes"][0]["nodes"] = serde_json::json!([0, 1, 2]);
    json["meshes"] = serde_json::json!(if copied {
        vec![mesh.clone(), mesh.clone(), mesh]
    } else {
        vec![mesh]
    });
    let path = dir.join(if copied {
        "copied.gltf"
    } else {
        "instanced.gltf"
    });
    std::fs::write(&path, json.to_string()).unwrap();
    let mut desc = SceneDesc::load_input(
        &path,
        &tracer_core::scene::ModelSceneOptions {
            width: Some(w),
            height: Some(h),
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    // Closer than the automatic camera, which frames the row's bounding
    // sphere: the helmets fill the width.
    desc.camera.position = tracer_core::scene::Vec3([0.0, 0.1, 4.0]);
    desc.camera.look_at = tracer_core::scene::Vec3([0.0, 0.1, 0.0]);
    desc
}
