//! Model files' materials on the GPU (issue 34): textures, emission,
//! alpha cut-outs and vertex colours looked up per hit by pbr.wgsl, checked
//! against the CPU's render of the same scene (render/step.rs
//! `material_at`), which tests/textures.rs checks against independent
//! references. Both render in f32; the GPU's texture filter does the
//! CPU's arithmetic on the same decode tables, and the Whitted mapping
//! (`Pbr::whitted`, in f64 on the CPU) is evaluated in f32 on the GPU, so
//! values agree to a few f32 rounding steps; the real assets add the
//! triangle edges where the two traversals may pick different triangles.
//! A missing adapter or asset fails (tests/support/prereq.rs).

mod common;

use common::meshgen::{
    colour_texels, set_quad_node, textured_quad, textured_quad_with, tmpdir, write_png,
};
use common::*;
use tracer_core::film::WorkRegion;
use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::gpu::Strategy;
use tracer_core::render::{Precision, PreparedFrame};
use tracer_core::scene::SceneDesc;

/// An image's linear RGB pixels.
type Image = Vec<[f32; 3]>;

/// The CPU's and the GPU's (stack and wavefront kernels) images of `desc`.
fn cpu_and_gpu(desc: &SceneDesc) -> (Image, [Image; 2]) {
    let (cpu, gpu, _) = cpu_and_gpu_rays(desc);
    (cpu, gpu)
}

/// [`cpu_and_gpu`] with the rays each traced: reflection and refraction
/// counts show whether the GPU spawns the secondary rays a material's
/// textures call for at a hit.
fn cpu_and_gpu_rays(desc: &SceneDesc) -> (Image, [Image; 2], [tracer_core::film::RayCounts; 3]) {
    let s = &desc.render;
    let cpu_film = render_with(desc, s, Precision::F32);
    let mut rays = [cpu_film.rays; 3];
    let cpu = cpu_film.resolve();
    let prepared = PreparedFrame::build(desc, s, 0, Precision::F32).expect("valid settings");
    let gpu = [Strategy::Stack, Strategy::Wavefront].map(|strategy| {
        let g = gpu_with(strategy).expect("an adapter");
        let k = 1 + (strategy == Strategy::Wavefront) as usize;
        let film = g
            .render(
                &prepared,
                WorkRegion::new(
                    0,
                    Rect::full(s.width, s.height),
                    SampleRange::all(s.samples),
                ),
                &|_| {},
            )
            .unwrap_or_else(|e| panic!("GPU render failed: {e}"));
        assert_eq!(film.nonfinite, 0);
        rays[k] = film.rays;
        film.resolve()
    });
    (cpu, gpu, rays)
}

/// Asserts each GPU image within `max` of the CPU's at every pixel (the
/// largest channel difference) and within `mean` on average; returns
/// the worst (max, mean) for the messages.
fn assert_agree(what: &str, desc: &SceneDesc, max: f32, mean: f64) -> (f32, f64) {
    let (cpu, gpus) = cpu_and_gpu(desc);
    assert_finite(&cpu);
    assert!(
        cpu.iter().any(|p| p.iter().any(|&c| c > 0.05)),
        "{what}: the CPU image is black"
    );
    let mut worst = (0.0f32, 0.0f64);
    for (g, kernel) in gpus.iter().zip(["stack", "wavefront"]) {
        let d = diff(&cpu, g, max);
        eprintln!(
            "{what} ({kernel}): max {:.3e}, mean {:.3e}, {} of {} pixels over {max}",
            d.max, d.mean, d.over, d.pixels
        );
        assert!(
            d.over == 0 && d.mean <= mean,
            "{what} ({kernel}): max {} (allowed {max}), mean {} (allowed {mean}), {} pixels over",
            d.max,
            d.mean,
            d.over
        );
        worst = (worst.0.max(d.max), worst.1.max(d.mean));
    }
    worst
}

/// The emissive-textured quad of tests/textures.rs filling the view, lit
/// too (a white base colour and a light, so the base colour texture, the
/// Whitted mapping and the emission all count).
#[test]
fn gpu_emissive_textured_quad_matches_the_cpu() {
    let dir = tmpdir("gpu-tex-emissive");
    let (tw, th) = (4u32, 3u32);
    write_png(&dir, tw, th, &colour_texels(tw, th));
    let model = textured_quad(
        &dir,
        1.0,
        0.0,
        r#"{"pbrMetallicRoughness":{"baseColorFactor":[0.5,0.5,0.5,1],"baseColorTexture":{"index":0},"metallicFactor":0.3,"roughnessFactor":0.4},
            "emissiveFactor":[1,0.5,0.25],"emissiveTexture":{"index":0}}"#,
        r#"{"wrapS":10497,"wrapT":33648}"#,
    );
    let src = format!(
        "[render]\nwidth = 45\nheight = 37\nsamples = 4\n\
         [camera]\nposition = [0.3, 0.2, 2]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 60\n\
         [world]\nambient = [0.2, 0.2, 0.2]\n\
         [[lights]]\nposition = [1, 2, 3]\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("scene.toml")).unwrap();
    assert_agree("emissive textured quad", &scene, 1e-5, 1e-6);
}

/// The minified checkerboard of tests/textures.rs
/// (`common::minified_checker_scene`): from 2 away each pixel blends the
/// image with its mip level 1 by the footprint's level of detail, from 6
/// away it reads level 2 and 3; the GPU's levels, offsets and λ (f32) are
/// the CPU's.
#[test]
fn gpu_minified_checkerboard_reads_the_cpus_mip_levels() {
    for distance in [2.0, 6.0] {
        let scene = common::minified_checker_scene("gpu-tex-mips", distance, 32);
        assert_agree(&format!("checkerboard from {distance}"), &scene, 1e-5, 1e-6);
    }
}

/// The cut-out quad of tests/textures.rs (`common::cutout_quad`) over a
/// lit plane: camera and shadow rays pass its transparent texels on the
/// GPU as on the CPU.
#[test]
fn gpu_cutout_matches_the_cpu_for_camera_and_shadow_rays() {
    let dir = tmpdir("gpu-tex-cutout");
    let (model, _) = cutout_quad(&dir);
    let scene = quad_over_lit_plane_scene(&dir, &model, 64);
    // Cut and solid texels both seen (the pattern on the quad), and shadows.
    let (cpu, _) = cpu_and_gpu(&scene);
    let red = cpu.iter().filter(|p| **p == [1.0, 0.0, 0.0]).count();
    let blue = cpu.iter().filter(|p| **p == [0.0, 0.0, 1.0]).count();
    assert!(red > 100 && blue == 0, "red {red}, background {blue}");
    assert_agree("cut-out quad", &scene, 1e-5, 1e-6);
}

/// Single-sided quads (glTF `doubleSided` false) over a lit plane, one
/// facing the camera (its back to the light's shadow rays) and one turned
/// away by a mirror: back faces are cut away on the GPU as on the CPU,
/// for camera and shadow rays.
#[test]
fn gpu_single_sided_quads_match_the_cpu_from_front_and_back() {
    for (case, z, nodes) in [
        ("facing the camera", 1.0, [r#"{"mesh":0}"#]),
        ("mirrored away", -1.0, [r#"{"mesh":0,"scale":[1,1,-1]}"#]),
    ] {
        let dir = tmpdir("gpu-single-sided");
        write_png(&dir, 1, 1, &[[255; 4]]);
        let model = textured_quad(
            &dir,
            0.5,
            z,
            r#"{"pbrMetallicRoughness":{"baseColorFactor":[0.2,0.6,0.3,1],"metallicFactor":0},
                "emissiveFactor":[1,0,0]}"#,
            "{}",
        );
        set_quad_node(&dir, &model, &nodes);
        let scene = quad_over_lit_plane_scene(&dir, &model, 48);
        assert_agree(case, &scene, 1e-5, 1e-6);
    }
}

/// A moving mesh's model materials keep only their factors on the GPU
/// (distributed effects): a single-sided glTF quad on one, whose back
/// faces the CPU cuts away, is refused by name; the same quad
/// double-sided renders as on the CPU.
#[test]
fn gpu_refuses_a_moving_single_sided_mesh_and_renders_a_double_sided_one() {
    for double_sided in [false, true] {
        let dir = tmpdir("gpu-moving-sided");
        write_png(&dir, 1, 1, &[[255; 4]]);
        let model = textured_quad(
            &dir,
            0.5,
            0.0,
            &format!(
                r#"{{"pbrMetallicRoughness":{{"baseColorFactor":[0.8,0.3,0.2,1],"metallicFactor":0}},
                    "doubleSided":{double_sided}}}"#
            ),
            "{}",
        );
        let src = format!(
            "[render]\nwidth = 24\nheight = 24\nsamples = 4\n\
             [camera]\nposition = [0, 0, 3]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40\nshutter = [0, 1]\n\
             [world]\nambient = [0.3, 0.3, 0.3]\n\
             [[lights]]\nposition = [0, 1, 3]\n\
             [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n{}",
            common::meshgen::keyframes_along_x(-0.3, 0.3)
        );
        let scene = SceneDesc::parse(&src, dir.join("scene.toml")).unwrap();
        let prepared = PreparedFrame::build(&scene, &scene.render, 0, Precision::F32).unwrap();
        let got = gpu_with(Strategy::Stack).expect("an adapter").render(
            &prepared,
            WorkRegion::new(0, Rect::full(24, 24), SampleRange::all(4)),
            &|_| {},
        );
        if double_sided {
            assert!(got.is_ok(), "{:?}", got.err());
            assert_agree("moving double-sided quad", &scene, 1e-5, 1e-6);
        } else {
            let Err(e) = got else {
                panic!("a moving single-sided mesh was not refused")
            };
            let e = e.to_string();
            assert!(
                e.contains("single-sided surfaces (glTF doubleSided false) on a moving mesh"),
                "{e}"
            );
        }
    }
}

/// OBJ bump maps (tests/textures.rs checks the CPU against the displaced
/// surface's normal) and a `norm` map beside one, on the GPU as on the CPU.
#[test]
fn gpu_obj_bump_and_norm_maps_match_the_cpu() {
    let light = [-0.6, 0.3, 1.0];
    for (tag, norm) in [("gpu-bump", None), ("gpu-bump-norm", Some([150, 110, 240]))] {
        let scene = bumped_obj_quad(tag, 0.75, norm, light);
        assert_agree(tag, &scene, 1e-5, 1e-6);
    }
}

/// COLOR_0 multiplies the base colour, interpolated over the triangles.
#[test]
fn gpu_vertex_colours_match_the_cpu() {
    let dir = tmpdir("gpu-vertex-colours");
    write_png(
        &dir,
        2,
        2,
        &[
            [255, 255, 255, 255],
            [128, 200, 64, 255],
            [30, 60, 90, 255],
            [255, 0, 128, 255],
        ],
    );
    let model = textured_quad_with(
        &dir,
        1.0,
        0.0,
        r#"{"pbrMetallicRoughness":{"baseColorTexture":{"index":0},"metallicFactor":0}}"#,
        r#"{}"#,
        Some([
            [1.0, 0.0, 0.0, 1.0],
            [0.0, 1.0, 0.0, 1.0],
            [0.0, 0.0, 1.0, 1.0],
            [1.0, 1.0, 1.0, 1.0],
        ]),
        None,
    );
    let src = format!(
        "[render]\nwidth = 40\nheight = 40\nsamples = 1\n\
         [camera]\nposition = [0, 0, 2.5]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 50\n\
         [world]\nambient = [0.3, 0.3, 0.3]\n\
         [[lights]]\nposition = [0, 1, 3]\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("scene.toml")).unwrap();
    let (cpu, _) = cpu_and_gpu(&scene);
    // The corners' colours differ: red dominates at the bottom-left corner.
    let bl = cpu[(34 * 40 + 5) as usize];
    assert!(bl[0] > 2.0 * bl[1] && bl[0] > 2.0 * bl[2], "{bl:?}");
    assert_agree("vertex colours", &scene, 1e-5, 1e-6);
}

/// The real assets of shared/scenes on the GPU against the CPU, at a
/// small size, 1 spp. Pixels where the two traversals may meet different
/// triangles (edges, grazing hits) may differ by a whole texel value, and
/// the sharpest highlights (Phong exponents up to 320,000 from roughness
/// 0.05: the GPU's pow is exp2(y log2 x), whose error y multiplies) by
/// more, so the bound is 1e-2 on 98% of the pixels and 2e-3 on the mean.
#[test]
fn gpu_renders_the_shared_gltf_assets_as_the_cpu_does() {
    for (path, w, h) in [
        ("scenes/gltf/DamagedHelmet/glTF/DamagedHelmet.gltf", 96, 96),
        (
            "scenes/gltf/AlphaBlendModeTest/glTF/AlphaBlendModeTest.gltf",
            96,
            64,
        ),
        (
            "scenes/gltf/EmissiveStrengthTest/glTF/EmissiveStrengthTest.gltf",
            96,
            48,
        ),
        (
            "scenes/gltf/TextureTransformTest/glTF/TextureTransformTest.gltf",
            80,
            80,
        ),
        (
            "scenes/gltf/TextureSettingsTest/glTF/TextureSettingsTest.gltf",
            96,
            64,
        ),
        ("scenes/gltf/SpecularTest/glTF/SpecularTest.gltf", 96, 48),
    ] {
        let scene = shared_asset(path, w, h);
        let (cpu, gpus, rays) = cpu_and_gpu_rays(&scene);
        for (k, (g, kernel)) in gpus.iter().zip(["stack", "wavefront"]).enumerate() {
            // The same secondary rays, within the few hits where the two
            // traversals part (DamagedHelmet's mirror-smooth texels once
            // spawned none on the GPU: HAS_REFLECTION was off).
            let (c, r) = (rays[0], rays[k + 1]);
            for (what, a, b) in [
                ("reflection", c.reflection, r.reflection),
                ("refraction", c.refraction, r.refraction),
            ] {
                assert!(
                    a.abs_diff(b) * 100 <= a.max(1),
                    "{path} ({kernel}): {what} rays CPU {a} GPU {b}"
                );
            }
            assert_asset_close(&format!("{path} ({kernel})"), &cpu, g);
        }
    }
}

/// A real asset's GPU image against the CPU's: within 1e-2 on 98% of the
/// pixels and 2e-3 on the mean (`gpu_renders_the_shared_gltf_assets_as_the_cpu_does`
/// says why).
fn assert_asset_close(what: &str, cpu: &Image, gpu: &Image) {
    let d = diff(cpu, gpu, 1e-2);
    eprintln!(
        "{what}: max {:.3e}, mean {:.3e}, {} of {} pixels over 1e-2",
        d.max, d.mean, d.over, d.pixels
    );
    assert!(
        d.over * 50 <= d.pixels && d.mean < 2e-3,
        "{what}: max {}, mean {}, {} of {} pixels over 1e-2",
        d.max,
        d.mean,
        d.over,
        d.pixels
    );
}

/// The texel-pack cache (layout::TexelPack): another tile or frame of the
/// same world packs and uploads no texel, and renders as before; a world
/// of other images packs and uploads its own. A renderer of its own, so
/// that no other test's scene comes between the renders counted.
#[test]
fn a_second_tile_of_a_textured_scene_reuses_the_packed_texels() {
    use tracer_core::render::gpu::{GpuOptions, GpuRenderer};
    let g = GpuRenderer::new(
        std::env::var("TESSERA_TEST_ADAPTER").ok().as_deref(),
        GpuOptions::default(),
    )
    .unwrap_or_else(|e| panic!("no GPU adapter could be opened: {e}"));
    let textured = |tag: &str, texels: &[[u8; 4]]| {
        let dir = tmpdir(tag);
        write_png(&dir, 4, 3, texels);
        let model = textured_quad(
            &dir,
            1.0,
            0.0,
            r#"{"pbrMetallicRoughness":{"baseColorTexture":{"index":0},"metallicFactor":0}}"#,
            r#"{}"#,
        );
        let src = format!(
            "[render]\nwidth = 24\nheight = 16\nsamples = 1\n\
             [camera]\nposition = [0, 0, 2]\nlook_at = [0, 0, 0]\n\
             [[lights]]\nposition = [1, 2, 3]\n\
             [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"
        );
        SceneDesc::parse(&src, dir.join("scene.toml")).unwrap()
    };
    let a = textured("texel-cache-a", &colour_texels(4, 3));
    let b = textured("texel-cache-b", &[[40, 200, 90, 255]; 12]);
    let render = |desc: &SceneDesc, frame: u32, rect: Rect| {
        let p = PreparedFrame::build(desc, &desc.render, frame, Precision::F32).unwrap();
        g.render(
            &p,
            WorkRegion::new(frame, rect, SampleRange::all(1)),
            &|_| {},
        )
        .unwrap_or_else(|e| panic!("GPU render failed: {e}"))
    };
    let (left, right) = (Rect::new(0, 0, 12, 16), Rect::new(12, 0, 12, 16));
    let first = render(&a, 0, left);
    assert_eq!(g.texel_work(), (1, 1), "the first tile packs and uploads");
    let second = render(&a, 0, right);
    let again = render(&a, 0, left);
    // A new frame of the same scene (the farm's next frame): the same images.
    let next_frame = render(&a, 1, right);
    assert_eq!(
        g.texel_work(),
        (1, 1),
        "other tiles and frames of the same world reuse the texels"
    );
    assert_eq!(again.sums, first.sums, "a reused pack renders as the first");
    assert_eq!(next_frame.sums, second.sums);
    assert_ne!(first.sums, second.sums);
    let other = render(&b, 0, left);
    assert_eq!(
        g.texel_work(),
        (2, 2),
        "other images are packed and uploaded"
    );
    assert_ne!(other.sums, first.sums);
    let back = render(&a, 0, left);
    assert_eq!(g.texel_work(), (3, 3), "one scene is kept at a time");
    assert_eq!(back.sums, first.sums);
}

/// A normal map (glTF normalTexture with a scale, MikkTSpace tangents) on
/// the GPU as on the CPU: pbr.wgsl `normal_mapped` against render/step.rs
/// `shading_normal`, a varied texture bilinearly filtered, under a light
/// with a specular highlight (the tilted normal moves both terms).
#[test]
fn gpu_normal_map_matches_the_cpu() {
    let dir = tmpdir("gpu-normal-map");
    let texels: Vec<[u8; 4]> = (0..12u8)
        .map(|i| [100 + 9 * i, 160 - 7 * i, 230 - (i % 3) * 20, 255])
        .collect();
    write_png(&dir, 4, 3, &texels);
    let model = textured_quad(
        &dir,
        1.0,
        0.0,
        r#"{"pbrMetallicRoughness":{"baseColorFactor":[0.8,0.7,0.6,1],"metallicFactor":0.2,"roughnessFactor":0.5},
            "normalTexture":{"index":0,"scale":0.8}}"#,
        r#"{}"#,
    );
    let src = format!(
        "[render]\nwidth = 40\nheight = 32\nsamples = 1\n\
         [camera]\nposition = [0.4, -0.3, 2.2]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 55\n\
         [world]\nambient = [0.1, 0.1, 0.1]\n\
         [[lights]]\nposition = [1, 1.5, 2.5]\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("scene.toml")).unwrap();
    assert_agree("normal-mapped quad", &scene, 1e-5, 1e-6);
}

/// Textured instances on the GPU (instances.wgsl `placed_triangle`): the
/// three DamagedHelmets of `common::three_helmets`, one mesh stored once
/// with its vertex attributes, traced in two levels, textured, normal
/// mapped (a mirrored copy's tangent frame flipped) and emissive as on
/// the CPU, within the shared assets' bounds above.
#[test]
fn gpu_textured_instances_match_the_cpu() {
    let dir = common::meshgen::tmpdir("gpu-three-helmets");
    let scene = common::three_helmets(&dir, false, 120, 48);
    let (cpu, gpus, _) = cpu_and_gpu_rays(&scene);
    for (g, kernel) in gpus.iter().zip(["stack", "wavefront"]) {
        assert_asset_close(&format!("three helmets ({kernel})"), &cpu, g);
    }
}
