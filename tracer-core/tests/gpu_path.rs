//! The path integrator on the GPU (path.wgsl, bsdf.wgsl) against the CPU's
//! (`render/step.rs` `path`): both draw the same numbers at the same keys
//! and slots, so their images agree within f32 tolerance; the white
//! furnace holds on the GPU; adaptive rounds work with path on both
//! backends; and any split of a frame into rectangles and
//! sample ranges merges into the GPU's whole render bit for bit.
//!
//! Tolerance (CPU f32 against GPU, every scene here): mean absolute
//! difference below 1/1000 and at most 1% of pixels off by more than
//! 2/255 (gpu.rs's bound against the f64 reference). Why it holds: the
//! kernels compute the same f32 formulas; Vulkan's sqrt, division, sin and
//! cos (the CPU takes sin/cos of a turn in f64) differ by a few ulps, which
//! moves a path's vertices by ~1e-7 relative; only where such a difference
//! flips a discrete choice (the lobe, the light, Russian roulette, a
//! silhouette) does one sample of a pixel take another path, and that
//! happens for a handful of samples in a frame. A wrong lobe, weight, pdf or
//! number would move the mean by orders of magnitude more.
//!
//! Needs a wgpu adapter (lavapipe): the prerequisite `gpu`, whose absence
//! fails every test (tests/support/prereq.rs).

mod common;

use common::{diff, gpu};
use tracer_core::adaptive::BlockMask;
use tracer_core::film::WorkRegion;
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::adaptive::render_round;
use tracer_core::render::gpu::GpuRenderer;
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame, Renderer};
use tracer_core::scene::SceneDesc;

/// A Cornell-like set: a floor and a back wall of Lambert, a sphere of
/// `ball` (a `[bsdf.ball]` body), a quad, a sphere and a point light, a sky.
fn scene(ball: &str, extra_camera: &str) -> SceneDesc {
    common::scene(&scene_src(ball, extra_camera))
}

fn scene_src(ball: &str, extra_camera: &str) -> String {
    format!(
        r#"
[render]
width = 40
height = 30
samples = 8
max_depth = 8
sampler = "jittered"
integrator = "path"

[camera]
position = [0, 1.6, -5]
look_at = [0, 0.9, 0]
fov_y = 50
{extra_camera}

[world]
environment = [0.15, 0.2, 0.3]

[materials.floor]
diffuse = [0.7, 0.6, 0.5]
[materials.wall]
diffuse = [0.3, 0.5, 0.7]
[materials.ball]
[bsdf.ball]
{ball}
[materials.lamp]
[bsdf.lamp]
base_colour = [0, 0, 0]
emission = [3, 2, 1]

[[lights]]
type = "quad"
corner = [-0.8, 3.5, -0.8]
edge_u = [1.6, 0, 0]
edge_v = [0, 0, 1.6]
diffuse = [4, 4, 4]
[[lights]]
type = "sphere"
center = [2.5, 2, -1]
radius = 0.25
diffuse = [6, 5, 4]
[[lights]]
position = [-2.5, 2.5, -2]
diffuse = [3, 3, 3]

[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
[[objects]]
type = "plane"
normal = [0, 0, -1]
distance = -3
material = "wall"
[[objects]]
type = "sphere"
center = [0, 0.9, 0]
radius = 0.9
material = "ball"
[[objects]]
type = "sphere"
center = [-1.4, 0.3, -1.2]
radius = 0.3
material = "lamp"
"#
    )
}

const LAMBERT: &str = "base_colour = [0.8, 0.8, 0.8]\nmetallic = 0\nroughness = 1\nspecular = 0\n";
const MIRROR: &str = "base_colour = [1, 1, 1]\nmetallic = 1\nroughness = 0\n";
const ROUGH_CONDUCTOR: &str = "base_colour = [0.9, 0.6, 0.3]\nmetallic = 1\nroughness = 0.4\n";
const GLASS: &str =
    "base_colour = [1, 1, 1]\nmetallic = 0\nroughness = 0\ntransmission = 1\nior = 1.5\n";
/// GLASS with `KHR_materials_volume`'s attenuation: a quarter of the red
/// and most of the blue absorbed over 0.5 units inside the ball.
const ABSORBING_GLASS: &str = "base_colour = [1, 1, 1]\nmetallic = 0\nroughness = 0\ntransmission = 1\nior = 1.5\n\
                               attenuation_colour = [0.75, 0.6, 0.2]\nattenuation_distance = 0.5\n";
const PLASTIC: &str = "base_colour = [0.2, 0.5, 0.2]\nmetallic = 0\nroughness = 0.3\n";

fn prepared(desc: &SceneDesc) -> PreparedFrame {
    PreparedFrame::build(desc, &desc.render, 0, Precision::F32).unwrap()
}

fn full(desc: &SceneDesc) -> (Rect, SampleRange) {
    (
        Rect::full(desc.render.width, desc.render.height),
        SampleRange::all(desc.render.samples),
    )
}

fn gpu_film(g: &GpuRenderer, desc: &SceneDesc, rect: Rect, samples: SampleRange) -> Film {
    g.render(&prepared(desc), WorkRegion::new(0, rect, samples), &|_| {})
        .unwrap_or_else(|e| panic!("GPU path render failed: {e}"))
}

fn cpu_film(desc: &SceneDesc) -> Film {
    let (rect, samples) = full(desc);
    CpuRenderer::new(Some(2))
        .unwrap()
        .render(&prepared(desc), WorkRegion::new(0, rect, samples), &|_| {})
        .unwrap()
}

fn mean(img: &[[f32; 3]]) -> f64 {
    img.iter().map(|p| (p[0] + p[1] + p[2]) as f64).sum::<f64>() / (3 * img.len()) as f64
}

/// CPU and GPU path images of `desc` agree within the stated tolerance.
fn check_against_cpu(name: &str, desc: &SceneDesc) {
    check_against_cpu_above(name, desc, 0.02);
}

/// [`check_against_cpu`] of a scene whose mean (linear) is at least `dark`.
fn check_against_cpu_above(name: &str, desc: &SceneDesc, dark: f64) {
    let Some(g) = gpu() else { return };
    let (rect, samples) = full(desc);
    let gf = gpu_film(g, desc, rect, samples);
    let cf = cpu_film(desc);
    assert_eq!(gf.rays.primary, cf.rays.primary, "{name}: primary rays");
    // No sample is non-finite on either backend (a sphere light's cone
    // density once overflowed in f32 far from the light: light.rs
    // `cone_pdf`).
    assert_eq!(
        (gf.nonfinite, cf.nonfinite),
        (0, 0),
        "{name}: non-finite samples (GPU, CPU)"
    );
    let (gi, ci) = (gf.resolve(), cf.resolve());
    let d = diff(&gi, &ci, 2.0 / 255.0);
    eprintln!(
        "{name}: mean CPU {:.5} GPU {:.5}; |diff| mean {:.2e} max {:.3}; {} of {} pixels over 2/255; rays CPU {:?} GPU {:?}",
        mean(&ci),
        mean(&gi),
        d.mean,
        d.max,
        d.over,
        d.pixels,
        cf.rays,
        gf.rays
    );
    assert!(
        mean(&ci) > dark,
        "{name}: the scene is dark ({})",
        mean(&ci)
    );
    assert!(d.mean < 1e-3, "{name}: mean |diff| {}", d.mean);
    assert!(
        d.over * 100 <= d.pixels,
        "{name}: {} of {} pixels differ by more than 2/255",
        d.over,
        d.pixels
    );
    // Secondary rays: the same paths but for the few flipped samples.
    let near = |a: u64, b: u64| a.abs_diff(b) * 100 <= b.max(1);
    assert!(near(gf.rays.shadow, cf.rays.shadow), "{name}: shadow rays");
    assert!(
        near(
            gf.rays.reflection + gf.rays.refraction,
            cf.rays.reflection + cf.rays.refraction
        ),
        "{name}: bounces"
    );
}

#[test]
fn gpu_path_matches_the_cpu_on_lambert_and_every_light_kind() {
    check_against_cpu("lambert", &scene(LAMBERT, ""));
}

#[test]
fn gpu_path_matches_the_cpu_on_a_perfect_mirror() {
    check_against_cpu("mirror", &scene(MIRROR, ""));
}

#[test]
fn gpu_path_matches_the_cpu_on_a_rough_conductor() {
    check_against_cpu("rough conductor", &scene(ROUGH_CONDUCTOR, ""));
}

#[test]
fn gpu_path_matches_the_cpu_on_smooth_glass() {
    check_against_cpu("glass", &scene(GLASS, ""));
}

#[test]
fn gpu_path_matches_the_cpu_inside_an_absorbing_glass_ball() {
    check_against_cpu("absorbing glass", &scene(ABSORBING_GLASS, ""));
}

#[test]
fn gpu_path_matches_the_cpu_on_a_rough_dielectric() {
    check_against_cpu("plastic", &scene(PLASTIC, ""));
}

/// The thesis's Blinn-Phong materials through `Bsdf::from_material`
/// (mirror layer, gloss, transmission), with the lens and motion blur.
#[test]
fn gpu_path_matches_the_cpu_with_whitted_materials_lens_and_motion_blur() {
    check_against_cpu("whitted materials, lens, blur", &lens_and_blur_scene());
}

/// The set with a Blinn-Phong ball (mirror layer, gloss, transmission), a
/// lens and a moving camera.
fn lens_and_blur_scene() -> SceneDesc {
    let src = scene_src(
        "",
        "aperture = 0.1\nfocus_distance = 5\nshutter = [0, 0.5]\n\
         keyframes = [{ frame = 0, position = [0, 1.6, -5] }, { frame = 1, position = [0.4, 1.6, -5] }]",
    )
    .replace("[bsdf.ball]\n", "")
    .replace(
        "[materials.ball]\n",
        "[materials.ball]\ndiffuse = [0.1, 0.1, 0.1]\nreflectivity = 0.6\ntransparency = 0.3\nior = 1.4\n",
    );
    common::scene(&src)
}

/// A white Lambert sphere in a uniform environment returns the
/// environment exactly (path_mitsuba.rs's furnace, on the GPU).
#[test]
fn gpu_white_furnace_returns_the_environment() {
    let Some(g) = gpu() else { return };
    let desc = common::scene(
        r#"
[render]
width = 32
height = 32
samples = 16
max_depth = 6
sampler = "jittered"
integrator = "path"
[camera]
position = [0, 1, -6]
look_at = [0, 1, 0]
fov_y = 40
[world]
environment = [0.5, 0.5, 0.5]
[materials.white]
[bsdf.white]
base_colour = [1, 1, 1]
metallic = 0
roughness = 1
specular = 0
[[objects]]
type = "sphere"
center = [0, 1, 0]
radius = 1.5
material = "white"
"#,
    );
    let (rect, samples) = full(&desc);
    let film = gpu_film(g, &desc, rect, samples);
    assert_eq!(film.nonfinite, 0);
    let img = film.resolve();
    for (i, p) in img.iter().enumerate() {
        for &v in p {
            assert!((v - 0.5).abs() < 1e-5, "pixel {i}: {p:?}, not 0.5");
        }
    }
}

/// Any split of a GPU path-traced frame into rectangles and sample ranges
/// merges into the whole render bit for bit.
#[test]
fn any_split_of_a_gpu_path_traced_frame_merges_bit_for_bit() {
    let Some(g) = gpu() else { return };
    let desc = scene(ROUGH_CONDUCTOR, "");
    let (w, h, n) = (desc.render.width, desc.render.height, desc.render.samples);
    let whole = gpu_film(g, &desc, Rect::full(w, h), SampleRange::all(n));
    assert!(whole.rays.reflection > 0 && whole.rays.shadow > 0);
    let mut merged = Film::new(Rect::full(w, h));
    for (rect, samples) in [
        (Rect::new(0, 0, 13, h), SampleRange::new(0, 3)),
        (Rect::new(0, 0, 13, h), SampleRange::new(3, n)),
        (Rect::new(13, 0, w - 13, 11), SampleRange::all(n)),
        (Rect::new(13, 11, w - 13, h - 11), SampleRange::new(0, 5)),
        (Rect::new(13, 11, w - 13, h - 11), SampleRange::new(5, n)),
    ] {
        merged.merge(&gpu_film(g, &desc, rect, samples)).unwrap();
    }
    assert_eq!(merged.sums, whole.sums);
    assert_eq!(merged.counts, whole.counts);
    assert_eq!(merged.rays, whole.rays);
}

/// Adaptive rounds work with `path` on both backends: a round over every
/// other block gives those blocks exactly the sums of a uniform render of
/// the same samples (CPU and GPU alike), leaves the others empty, carries
/// the sums of squares, and the two backends' rounds agree within the
/// tolerance above.
#[test]
fn adaptive_rounds_of_a_path_scene_agree_on_cpu_and_gpu() {
    let Some(g) = gpu() else { return };
    let desc = scene(PLASTIC, "");
    let p = prepared(&desc);
    let (w, h) = (desc.render.width, desc.render.height);
    let rect = Rect::full(w, h);
    let mut mask = BlockMask::all(rect);
    for (i, a) in mask.active.iter_mut().enumerate() {
        *a = i % 2 == 0;
    }
    let samples = SampleRange::new(2, 8);
    let gpu_round = g.render_round(&p, 0, &mask, samples, &|_| {}).unwrap();
    let cpu = Renderer::Cpu(CpuRenderer::new(Some(2)).unwrap());
    let cpu_round = render_round(&cpu, &p, 0, &mask, samples, &|_| {}).unwrap();
    let gpu_uniform = gpu_film(g, &desc, rect, samples);
    let cpu_uniform = CpuRenderer::new(Some(2))
        .unwrap()
        .render(&p, WorkRegion::new(0, rect, samples), &|_| {})
        .unwrap();
    assert!(gpu_round.squares.is_some() && cpu_round.squares.is_some());
    let mut active = 0;
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            if mask.covers(x, y) {
                active += 1;
                assert_eq!(gpu_round.counts[i], 6);
                assert_eq!(gpu_round.sums[i], gpu_uniform.sums[i], "GPU pixel {x},{y}");
                assert_eq!(cpu_round.sums[i], cpu_uniform.sums[i], "CPU pixel {x},{y}");
            } else {
                assert_eq!((gpu_round.counts[i], cpu_round.counts[i]), (0, 0));
            }
        }
    }
    assert!(active > 0 && active < w * h);
    let d = diff(&gpu_round.resolve(), &cpu_round.resolve(), 2.0 / 255.0);
    assert!(d.mean < 1e-3, "mean |diff| {}", d.mean);
    assert!(d.over * 100 <= d.pixels, "{} pixels over 2/255", d.over);
}

/// `desc` traced by the path integrator (a model file's own lights in
/// their physical units, or the default sky and sun).
/// examples/distributed.toml path-traced at 480x270, 64 spp: grazing
/// camera rays on the floor see the quad light edge-on, whose density
/// (2e19 and more) squared past f32's range in the power heuristic, and
/// 6 samples of this frame were NaN on the CPU (57 and 30 of a 1080p
/// frame on the H100's CPU and GPU) until both took its ratio form there
/// (step.rs `power_heuristic`, path.wgsl).
#[test]
fn gpu_path_matches_the_cpu_on_grazing_views_of_an_area_light() {
    let desc = SceneDesc::load(common::examples_dir().join("distributed.toml")).unwrap();
    let mut desc = path_traced(desc, 64);
    (desc.render.width, desc.render.height) = (480, 270);
    // A night scene: mean 0.012 in linear light.
    check_against_cpu_above("distributed, 480x270", &desc, 0.01);
}

fn path_traced(mut desc: SceneDesc, samples: u32) -> SceneDesc {
    desc.render.integrator = tracer_core::scene::Integrator::Path;
    desc.render.samples = samples;
    desc
}

/// A real asset's textures (base colour, metallic-roughness, emissive;
/// occlusion has no part in the BSDF) looked up at every path vertex by
/// pbr.wgsl, as `Pbr::bsdf` does on the CPU (issue 34/35).
#[test]
fn gpu_path_matches_the_cpu_on_the_textured_damaged_helmet() {
    let desc = common::shared_asset("scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf", 48, 48);
    check_against_cpu("DamagedHelmet", &path_traced(desc, 2));
}

/// AlphaBlendModeTest: MASK cut-outs (camera, bounce and shadow rays pass
/// the cut texels) and BLEND's 1 - alpha as transmission, per texel.
#[test]
fn gpu_path_matches_the_cpu_on_alpha_cutouts_and_blend() {
    let desc = common::shared_asset(
        "scenes/gltf/AlphaBlendModeTest/glTF/AlphaBlendModeTest.gltf",
        64,
        40,
    );
    check_against_cpu("AlphaBlendModeTest", &path_traced(desc, 2));
}

/// The path-traced scene of the quad tests below: model file `model` in
/// `dir` between a point light and a Lambert floor, 48x48, 4 spp, depth 4.
fn quad_between_light_and_floor(dir: &std::path::Path, model: &str) -> SceneDesc {
    let src = format!(
        "[render]\nwidth = 48\nheight = 48\nsamples = 4\nintegrator = \"path\"\nmax_depth = 4\n\
         [camera]\nposition = [0.4, 0.3, 4]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 45\n\
         [world]\nenvironment = [0.1, 0.1, 0.15]\n\
         [materials.white]\ndiffuse = [0.8, 0.8, 0.8]\n\
         [[lights]]\nposition = [0.8, 0.5, 3.5]\ndiffuse = [6, 6, 6]\n\
         [[objects]]\ntype = \"plane\"\nnormal = [0, 0, 1]\ndistance = 0\nmaterial = \"white\"\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"
    );
    SceneDesc::parse(&src, dir.join("scene.toml")).unwrap()
}

/// A textured, vertex-coloured cut-out quad between a point light and a
/// Lambert floor: the quad's cut texels let camera rays through to the
/// floor and next-event shadow rays through to the light, and its solid
/// texels shade with the texture times the vertex colour.
#[test]
fn gpu_path_matches_the_cpu_on_a_textured_vertex_coloured_cutout() {
    use common::meshgen::{textured_quad_with, tmpdir, write_png};
    let dir = tmpdir("gpu-path-cutout");
    let alpha = [1, 0, 1, 1, 0, 0, 1, 0, 1, 1, 0, 1, 0, 1, 1, 0];
    let texels: Vec<[u8; 4]> = alpha
        .iter()
        .enumerate()
        .map(|(i, &a)| [255 - 12 * i as u8, 60 + 10 * i as u8, 200, a * 255])
        .collect();
    write_png(&dir, 4, 4, &texels);
    let model = textured_quad_with(
        &dir,
        0.6,
        0.8,
        r#"{"pbrMetallicRoughness":{"baseColorTexture":{"index":0},"metallicFactor":0,"roughnessFactor":0.7},
            "alphaMode":"MASK","doubleSided":true}"#,
        r#"{"magFilter":9728,"wrapS":33071,"wrapT":33071}"#,
        Some([
            [1.0, 0.2, 0.2, 1.0],
            [0.2, 1.0, 0.2, 1.0],
            [0.2, 0.2, 1.0, 1.0],
            [1.0, 1.0, 1.0, 1.0],
        ]),
        None,
    );
    let desc = quad_between_light_and_floor(&dir, &model);
    check_against_cpu("textured cut-out quad", &desc);
}

/// A single-sided glossy quad turned away from the camera by a mirror,
/// between a point light and a Lambert floor: camera and bounce rays
/// meeting its back pass through, next-event shadow rays from the floor
/// meet its front and are blocked, on the GPU as on the CPU.
#[test]
fn gpu_path_matches_the_cpu_on_a_single_sided_quad_seen_from_behind() {
    use common::meshgen::{set_quad_node, textured_quad, tmpdir, write_png};
    let dir = tmpdir("gpu-path-single-sided");
    write_png(&dir, 1, 1, &[[255; 4]]);
    let model = textured_quad(
        &dir,
        0.6,
        -0.8,
        r#"{"pbrMetallicRoughness":{"baseColorFactor":[0.9,0.5,0.2,1],"metallicFactor":0.3,"roughnessFactor":0.4}}"#,
        "{}",
    );
    set_quad_node(&dir, &model, &[r#"{"mesh":0,"scale":[1,1,-1]}"#]);
    let desc = quad_between_light_and_floor(&dir, &model);
    check_against_cpu("single-sided quad from behind", &desc);
}

/// A quad emitting a two-colour texture lights the floor in front of it
/// and nothing else does: the GPU's light samples on its triangles read
/// the emissive texel at the sampled point, as the CPU's do (with the
/// emissive factor alone the floor would be lit white).
#[test]
fn gpu_path_matches_the_cpu_under_a_textured_emitter() {
    use common::meshgen::{textured_quad_with, tmpdir, write_png};
    let dir = tmpdir("gpu-path-textured-emitter");
    let texels: Vec<[u8; 4]> = (0..16)
        .map(|i| {
            if i % 4 < 2 {
                [255, 40, 10, 255]
            } else {
                [10, 60, 255, 255]
            }
        })
        .collect();
    write_png(&dir, 4, 4, &texels);
    let model = textured_quad_with(
        &dir,
        0.6,
        0.8,
        r#"{"emissiveFactor":[1,1,1],"emissiveTexture":{"index":0},
            "pbrMetallicRoughness":{"baseColorFactor":[0,0,0,1],"metallicFactor":0}}"#,
        r#"{"magFilter":9728,"wrapS":33071,"wrapT":33071}"#,
        None,
        None,
    );
    let src = format!(
        "[render]\nwidth = 48\nheight = 48\nsamples = 4\nintegrator = \"path\"\nmax_depth = 3\n\
         [camera]\nposition = [0, 1.2, 4]\nlook_at = [0, -0.6, 1.4]\nup = [0, 1, 0]\nfov_y = 50\n\
         [world]\nenvironment = [0, 0, 0]\n\
         [materials.white]\ndiffuse = [0.8, 0.8, 0.8]\n\
         [[objects]]\ntype = \"plane\"\nnormal = [0, 1, 0]\ndistance = -0.7\nmaterial = \"white\"\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"
    );
    let desc = SceneDesc::parse(&src, dir.join("scene.toml")).unwrap();
    check_against_cpu("textured emitter", &desc);
}

/// The Cornell-like set with an emissive OBJ quad (two triangles facing
/// down, `[bsdf.lamp]` emission) above the ball: the GPU samples the
/// triangles as lights, picking them after the lights by bisection, as
/// the CPU does (`tracer_core::emitters`), with the lights
/// (`with_lights`) or as the only emitters. `instances`: the quad is
/// instead placed three times by a TOML `instances` list, stored once,
/// its six placed triangles the lights.
fn emissive_mesh_scene(tag: &str, with_lights: bool, instances: bool) -> SceneDesc {
    let dir = common::meshgen::tmpdir(tag);
    std::fs::write(
        dir.join("lamp.obj"),
        "v -0.3 2.6 -0.3\nv 0.3 2.6 -0.3\nv 0.3 2.6 0.3\nv -0.3 2.6 0.3\nf 1 2 3\nf 1 3 4\n",
    )
    .unwrap();
    let mut src = scene_src(LAMBERT, "");
    if !with_lights {
        let (a, b) = (
            src.find("[[lights]]").unwrap(),
            src.find("[[objects]]").unwrap(),
        );
        src.replace_range(a..b, "");
    }
    let placed = if instances {
        "instances = [{ translate = [-1.2, 0, 0.5] }, { translate = [1.2, -0.3, 0], scale = 0.8 }, \
         { translate = [0, 0.2, -0.6], rotate_euler = [0, 45, 0] }]\n"
    } else {
        ""
    };
    let src = format!(
        "{src}\n[[objects]]\ntype = \"mesh\"\npath = {:?}\nmaterial = \"lamp\"\n{placed}",
        dir.join("lamp.obj")
    );
    let desc = common::scene(&src);
    let frame = prepared(&desc);
    let PreparedFrame::F32(w) = &frame else {
        unreachable!()
    };
    let path = w.dist.as_ref().and_then(|d| d.path.as_ref()).unwrap();
    let kinds: Vec<u32> = path.emitters.iter().map(|e| e.id.kind()).collect();
    if instances {
        assert_eq!(
            kinds,
            [tracer_core::geometry::PrimId::INSTANCE_TRIANGLE; 6],
            "the three placed quads' triangles are lights"
        );
        assert!(w.triangle_count() == 0, "the quad is stored once");
    } else {
        assert_eq!(kinds.len(), 2, "the quad's two triangles are lights");
    }
    desc
}

#[test]
fn gpu_path_matches_the_cpu_with_emissive_triangles_and_lights() {
    check_against_cpu(
        "emissive mesh",
        &emissive_mesh_scene("emitters-lights", true, false),
    );
}

/// Instanced emitters (instances.wgsl): light samples on placed
/// triangles, and BSDF samples that hit them weighed against those
/// samples' density (path.wgsl, `KIND_INSTANCE_TRIANGLE`).
#[test]
fn gpu_path_matches_the_cpu_with_instanced_emissive_triangles() {
    check_against_cpu(
        "instanced emissive mesh",
        &emissive_mesh_scene("emitters-instanced", false, true),
    );
}

#[test]
fn gpu_path_matches_the_cpu_with_emissive_triangles_alone() {
    check_against_cpu(
        "emissive mesh alone",
        &emissive_mesh_scene("emitters-alone", false, false),
    );
}

/// A model file's spot light (its cone: glTF's smooth falloff) and
/// directional light, the path integrator's own light kinds, beside the
/// scene's quad, sphere and point lights: the GPU draws the same samples.
#[test]
fn gpu_path_matches_the_cpu_with_spot_and_directional_lights() {
    let dir = common::meshgen::tmpdir("gpu-path-spot");
    let spot = r#"{"type":"spot","color":[1,0.9,0.8],"intensity":12,"spot":{"innerConeAngle":0.3,"outerConeAngle":0.5}}"#;
    let sun = r#"{"type":"directional","color":[0.9,0.9,1],"intensity":1.5}"#;
    common::meshgen::write_gltf_light(
        &dir.join("spot.gltf"),
        spot,
        [0.5, 3.0, -1.0],
        [-0.1, -1.0, 0.2],
    );
    common::meshgen::write_gltf_light(&dir.join("sun.gltf"), sun, [0.0; 3], [0.5, -0.7, 0.5]);
    let mut src = scene_src(LAMBERT, "");
    for f in ["spot.gltf", "sun.gltf"] {
        src += &format!(
            "\n[[objects]]\ntype = \"mesh\"\npath = {:?}\nlights = true\n",
            dir.join(f)
        );
    }
    let desc = common::scene(&src);
    let frame = prepared(&desc);
    let PreparedFrame::F32(w) = &frame else {
        unreachable!()
    };
    let kinds: Vec<_> = w
        .dist
        .as_ref()
        .unwrap()
        .lights
        .iter()
        .map(|l| l.geom)
        .collect();
    assert!(
        matches!(
            kinds[3..],
            [
                tracer_core::light::LightGeom::Spot { .. },
                tracer_core::light::LightGeom::Directional { .. }
            ]
        ),
        "{kinds:?}"
    );
    check_against_cpu("spot and directional", &desc);
    std::fs::remove_dir_all(&dir).ok();
}

/// The scene with an environment image (`sky.exr`: a gradient sky, a dark
/// ground and a small bright sun, turned 40 degrees) in place of its sky;
/// with `with_lights`, its lights and an emissive quad mesh (light-sampled
/// triangles, selected after the image), else the image alone.
fn environment_image_scene(tag: &str, ball: &str, with_lights: bool) -> SceneDesc {
    let dir = common::meshgen::tmpdir(tag);
    let (w, h) = (24u32, 12u32);
    let texels = common::sky::texels(w, h, (7, 3), [40.0, 32.0, 20.0]);
    let sky = image::Rgb32FImage::from_fn(w, h, |x, y| image::Rgb(texels[(y * w + x) as usize]));
    sky.save(dir.join("sky.exr")).unwrap();
    let mut src = scene_src(ball, "");
    if !with_lights {
        let (a, b) = (
            src.find("[[lights]]").unwrap(),
            src.find("[[objects]]").unwrap(),
        );
        src.replace_range(a..b, "");
    }
    if with_lights {
        std::fs::write(
            dir.join("lamp.obj"),
            "v -0.3 2.6 -0.3\nv 0.3 2.6 -0.3\nv 0.3 2.6 0.3\nv -0.3 2.6 0.3\nf 1 2 3\nf 1 3 4\n",
        )
        .unwrap();
        src.push_str(&format!(
            "\n[[objects]]\ntype = \"mesh\"\npath = {:?}\nmaterial = \"lamp\"\n",
            dir.join("lamp.obj")
        ));
    }
    let src = src.replace(
        "environment = [0.15, 0.2, 0.3]",
        &format!(
            "environment = {:?}\nenvironment_rotation = 40",
            dir.join("sky.exr")
        ),
    );
    let desc = common::scene(&src);
    let frame = prepared(&desc);
    let PreparedFrame::F32(w) = &frame else {
        unreachable!()
    };
    let path = w.dist.as_ref().and_then(|d| d.path.as_ref()).unwrap();
    assert!(path.env_prob > 0.0, "the image is light-sampled");
    assert_eq!(path.emitters.len(), if with_lights { 2 } else { 0 });
    desc
}

/// An environment image, selected between the scene's lights and the
/// emissive triangles: the GPU picks the same light, draws the same
/// directions from the image, and weighs BSDF samples that leave the
/// scene by the same density.
#[test]
fn gpu_path_matches_the_cpu_under_an_environment_image_and_every_light() {
    check_against_cpu(
        "environment image and lights",
        &environment_image_scene("env-lights", LAMBERT, true),
    );
}

/// The image alone, seen in a rough conductor and directly by the camera.
/// Tiles of one frame upload its words (the image) once.
#[test]
fn gpu_path_matches_the_cpu_under_an_environment_image_alone() {
    let desc = environment_image_scene("env-alone", ROUGH_CONDUCTOR, false);
    check_against_cpu("environment image alone", &desc);
    // A renderer of its own: the binary's shared one serves other tests' scenes between tiles.
    let g = GpuRenderer::new(
        std::env::var("TESSERA_TEST_ADAPTER").ok().as_deref(),
        Default::default(),
    )
    .unwrap_or_else(|e| panic!("no GPU adapter could be opened: {e}"));
    let frame = prepared(&desc);
    for (x, y) in [(0, 0), (20, 0), (0, 15), (20, 15)] {
        g.render(
            &frame,
            WorkRegion::new(0, Rect::new(x, y, 20, 15), SampleRange::all(2)),
            &|_| {},
        )
        .expect("a tile");
    }
    assert_eq!(g.dist_uploads(), 1, "the words of 4 tiles of one frame");
}

/// The wavefront driver (path_wave.wgsl: one segment of every path a
/// dispatch, paths that go on queued for the next) runs the stack
/// driver's step in the same order: the same sums, bit for bit, and the
/// same rays, with lens and motion blur, absorbing glass, emissive
/// triangles, an environment image and every light.
#[test]
fn the_wavefront_path_driver_renders_the_stack_drivers_sums() {
    use tracer_core::render::gpu::{GpuOptions, Strategy};
    let Some(g) = gpu() else { return };
    let wave = GpuRenderer::new(
        Some(&g.adapter().index.to_string()),
        GpuOptions {
            strategy: Strategy::Wavefront,
            // Several dispatches a frame, each its own queues' run.
            dispatch_pixel_samples: 3000,
            ..GpuOptions::default()
        },
    )
    .unwrap();
    let scenes = [
        ("lens and blur", lens_and_blur_scene()),
        ("absorbing glass", scene(ABSORBING_GLASS, "")),
        (
            "emitters",
            emissive_mesh_scene("wave-emitters", true, false),
        ),
        (
            "instanced emitters",
            emissive_mesh_scene("wave-emitters-instanced", true, true),
        ),
        (
            "environment image",
            environment_image_scene("wave-env", ROUGH_CONDUCTOR, true),
        ),
    ];
    for (name, desc) in &scenes {
        let (rect, samples) = full(desc);
        let stack = gpu_film(g, desc, rect, samples);
        let waved = gpu_film(&wave, desc, rect, samples);
        assert!(
            wave.last_stats().dispatches > 3 * stack_dispatches(desc),
            "{name}: the wavefront ran ({} dispatches)",
            wave.last_stats().dispatches
        );
        assert_eq!(waved.rays, stack.rays, "{name}: rays");
        assert_eq!(
            waved.nonfinite, stack.nonfinite,
            "{name}: non-finite samples"
        );
        assert_eq!(waved.sums, stack.sums, "{name}: sums");
        assert!(mean(&stack.resolve()) > 0.02, "{name}: lit");
    }
}

/// Dispatches of the stack kernel for `desc` at the wavefront test's budget.
fn stack_dispatches(desc: &SceneDesc) -> u32 {
    let (rect, samples) = full(desc);
    (rect.area() as u64 * samples.len() as u64).div_ceil(3000) as u32
}
