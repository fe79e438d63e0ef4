//! The path integrator's contracts beside its images (those are checked
//! against Mitsuba 3 in path_mitsuba.rs): any split of a frame into
//! rectangles and sample ranges merges into the whole render bit for bit
//! (what lets farm frames equal `tessera render`'s), the lens and the
//! shutter work under it, and the scene keys it adds are checked.

mod common;

use tracer_core::film::WorkRegion;
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::{Integrator, SceneDesc};

/// Lambert, mirror, glass and an emitter; a quad, a sphere and a point light; a sky.
const SCENE: &str = r#"
[render]
width = 24
height = 20
samples = 5
max_depth = 8
sampler = "jittered"
integrator = "path"

[camera]
position = [0, 2, -6]
look_at = [0, 0.8, 0]
fov_y = 45

[world]
environment = [0.2, 0.25, 0.3]

[materials.floor]
diffuse = [0.6, 0.6, 0.6]
[materials.chrome]
diffuse = [0.1, 0.1, 0.1]
reflectivity = 0.8
[materials.glass]
transparency = 0.9
ior = 1.5
[materials.lamp]
[bsdf.lamp]
base_colour = [0, 0, 0]
emission = [4, 3, 2]
[bsdf.chrome]
metallic = 1
roughness = 0.3

[[lights]]
type = "quad"
corner = [-1, 4, -1]
edge_u = [2, 0, 0]
edge_v = [0, 0, 2]
diffuse = [3, 3, 3]
[[lights]]
type = "sphere"
center = [3, 2, 1]
radius = 0.3
diffuse = [5, 5, 5]
[[lights]]
position = [-3, 3, -2]
diffuse = [4, 4, 4]

[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
[[objects]]
type = "sphere"
center = [-1, 1, 0]
radius = 1
material = "chrome"
[[objects]]
type = "sphere"
center = [1.2, 0.6, -0.5]
radius = 0.6
material = "glass"
[[objects]]
type = "sphere"
center = [0.5, 0.3, -2]
radius = 0.3
material = "lamp"
"#;

fn render(desc: &SceneDesc, rect: Rect, samples: SampleRange) -> Film {
    let frame = PreparedFrame::build(desc, &desc.render, 0, Precision::F32).unwrap();
    CpuRenderer::new(Some(2))
        .unwrap()
        .render(&frame, WorkRegion::new(0, rect, samples), &|_| {})
        .unwrap()
}

/// Any split merges to the whole, at 5 spp (pairs drawn independently)
/// and at 9 (3 x 3 strata of each path vertex's pairs, which depend on the
/// frame's count as well as the sample's index).
#[test]
fn any_split_of_a_path_traced_frame_merges_bit_for_bit() {
    for n in [5, 9] {
        let mut desc = common::scene(SCENE);
        desc.render.samples = n;
        split_merges_bit_for_bit(&desc);
    }
}

fn split_merges_bit_for_bit(desc: &SceneDesc) {
    assert_eq!(desc.render.integrator, Integrator::Path);
    let (w, h, n) = (desc.render.width, desc.render.height, desc.render.samples);
    assert_eq!(
        tracer_core::sampling::strata_side(desc.render.sampler, n),
        if n == 9 { 3 } else { 0 }
    );
    let whole = render(desc, Rect::full(w, h), SampleRange::all(n));
    assert_eq!(whole.nonfinite, 0);
    assert!(whole.rays.reflection > 0 && whole.rays.refraction > 0 && whole.rays.shadow > 0);
    // Odd rectangles and sample ranges, merged.
    let mut merged = Film::new(Rect::full(w, h));
    for (rect, samples) in [
        (Rect::new(0, 0, 7, h), SampleRange::new(0, 2)),
        (Rect::new(0, 0, 7, h), SampleRange::new(2, n)),
        (Rect::new(7, 0, w - 7, 9), SampleRange::all(n)),
        (Rect::new(7, 9, w - 7, h - 9), SampleRange::new(0, 3)),
        (Rect::new(7, 9, w - 7, h - 9), SampleRange::new(3, n)),
    ] {
        merged.merge(&render(desc, rect, samples)).unwrap();
    }
    assert_eq!(merged.sums, whole.sums);
    assert_eq!(merged.counts, whole.counts);
    // Light sampling, emitters and the sky all reach the image.
    let img = whole.resolve();
    let mean: f32 = img.iter().map(|p| p[0] + p[1] + p[2]).sum::<f32>() / img.len() as f32;
    assert!(mean > 0.3, "mean {mean}");
}

#[test]
fn whitted_stays_the_default_and_path_changes_the_image() {
    let whitted = common::scene(&SCENE.replace("integrator = \"path\"\n", ""));
    assert_eq!(whitted.render.integrator, Integrator::Whitted);
    let path = common::scene(SCENE);
    let full = |d: &SceneDesc| render(d, Rect::full(24, 20), SampleRange::all(5)).sums;
    assert_ne!(full(&whitted), full(&path));
}

#[test]
fn depth_of_field_and_motion_blur_work_with_path() {
    let desc = common::scene(&SCENE.replace(
        "fov_y = 45\n",
        "fov_y = 45\naperture = 0.2\nfocus_distance = 6\nshutter = [0, 0.5]\n\
         keyframes = [{ frame = 0, position = [0, 2, -6] }, { frame = 1, position = [0.5, 2, -6] }]\n",
    ));
    let pinhole = common::scene(SCENE);
    let lens = render(&desc, Rect::full(24, 20), SampleRange::all(5));
    assert_eq!(lens.nonfinite, 0);
    let still = render(&pinhole, Rect::full(24, 20), SampleRange::all(5));
    assert_ne!(lens.sums, still.sums);
    // Blurred and defocused, the image keeps its brightness (same light,
    // same materials): the means agree within the noise of 480 pixels.
    let mean = |f: &Film| {
        let img = f.resolve();
        img.iter().map(|p| (p[0] + p[1] + p[2]) as f64).sum::<f64>() / img.len() as f64
    };
    let (a, b) = (mean(&lens), mean(&still));
    assert!((a - b).abs() < 0.15 * b, "lens {a} against pinhole {b}");
}

#[test]
fn bsdf_tables_and_the_integrator_are_checked() {
    let err = |src: &str| SceneDesc::parse(src, "t.toml").unwrap_err().to_string();
    let base = "[camera]\nposition = [0, 0, -5]\nlook_at = [0, 0, 0]\n[materials.m]\n";
    assert_eq!(
        err(&format!("{base}[bsdf.n]\nmetallic = 0\n")),
        "t.toml:5:1: bsdf.n: names no material: [materials.n] is missing"
    );
    let e = err(&format!("{base}[bsdf.m]\nroughness = 2\n"));
    assert!(
        e.ends_with("bsdf.m.roughness: must be in [0, 1], got 2"),
        "{e}"
    );
    let e = err(&format!("{base}[bsdf.m]\nior = 0.5\n"));
    assert!(
        e.ends_with("bsdf.m.ior: must be a finite number in [1, 10], got 0.5"),
        "{e}"
    );
    let e = err(&format!(
        "{base}[bsdf.m]\nattenuation_colour = [0, 0.5, 1]\nattenuation_distance = 1\n"
    ));
    assert!(
        e.ends_with(
            "bsdf.m.attenuation_colour: must be in (0, 1] (the share of light kept over attenuation_distance), got [0.0, 0.5, 1.0]"
        ),
        "{e}"
    );
    let e = err(&format!("{base}[bsdf.m]\nattenuation_distance = -2\n"));
    assert!(
        e.ends_with("bsdf.m.attenuation_distance: must be a finite distance above 0, got -2"),
        "{e}"
    );
    let e = err(&format!("{base}[bsdf.m]\nbase_colour = [2, 0, 0]\n"));
    assert!(e.contains("bsdf.m.base_colour: must be in [0, 1]"), "{e}");
    let e = err(&format!("[render]\nintegrator = \"bidir\"\n{base}"));
    assert!(
        e.contains("render.integrator") || e.contains("integrator"),
        "{e}"
    );
    assert!(e.contains("whitted") && e.contains("path"), "{e}");
}

/// A TOML directional light (`type = "directional"`: `diffuse` is the
/// irradiance on a surface facing it) over a Lambert floor seen from
/// above, direct light only: every pixel is albedo / pi x E cos, computed
/// here in f64; under Whitted it is a far point light. Its fields are
/// checked by name.
#[test]
fn a_toml_directional_light_gives_every_point_its_irradiance() {
    let src = r#"
[render]
width = 9
height = 9
samples = 1
max_depth = 2
sampler = "grid"
integrator = "path"
[camera]
position = [0, 4, 0]
look_at = [0, 0, 0]
up = [0, 0, 1]
fov_y = 60
[materials.floor]
diffuse = [0.5, 0.5, 0.5]
[bsdf.floor]
base_colour = [0.5, 0.5, 0.5]
metallic = 0
specular = 0
[[lights]]
type = "directional"
direction = [1, -2, 0.5]
diffuse = [3, 2, 1]
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
"#;
    let desc = common::scene(src);
    let img = common::render_with(&desc, &desc.render, Precision::F64).resolve();
    let cos = 2.0 / (1.0f64 + 4.0 + 0.25).sqrt();
    for (i, p) in img.iter().enumerate() {
        for (k, e) in [3.0, 2.0, 1.0].into_iter().enumerate() {
            let want = 0.5 / std::f64::consts::PI * e * cos;
            let got = p[k] as f64;
            assert!(
                (got - want).abs() <= 1e-6,
                "pixel {i} channel {k}: {got} against {want}"
            );
        }
    }
    let mut whitted = desc.clone();
    whitted.render.integrator = tracer_core::scene::Integrator::Whitted;
    let lit = common::render_with(&whitted, &whitted.render, Precision::F64).resolve();
    assert!(lit.iter().all(|p| p[0] > 0.1), "Whitted: a far point light");

    let err = |from: &str, to: &str| {
        SceneDesc::parse(&src.replace(from, to), "t.toml")
            .unwrap_err()
            .to_string()
    };
    let e = err("direction = [1, -2, 0.5]", "position = [0, 5, 0]");
    assert!(
        e.ends_with("lights[0].position: not a field of a directional light (type = \"directional\" takes direction)"),
        "{e}"
    );
    let e = err("direction = [1, -2, 0.5]", "direction = [0, 0, 0]");
    assert!(e.ends_with("lights[0].direction: must not be zero"), "{e}");
}

/// A TOML spot light (glTF's cone: full inside `inner_cone_angle`, none
/// past `cone_angle`, the squared linear ramp in the cosine between)
/// straight above a Lambert floor, seen from above, direct light only:
/// each pixel's radiance is albedo / pi x I cos / d^2 x the falloff,
/// computed here in f64.
#[test]
fn a_toml_spot_light_lights_its_cone_as_gltf_defines_it() {
    let src = r#"
[render]
width = 33
height = 33
samples = 1
max_depth = 2
sampler = "grid"
integrator = "path"
[camera]
position = [0, 4, 0]
look_at = [0, 0, 0]
up = [0, 0, 1]
fov_y = 90
[materials.floor]
[bsdf.floor]
base_colour = [0.5, 0.5, 0.5]
metallic = 0
specular = 0
[[lights]]
type = "spot"
position = [0, 2, 0]
direction = [0, -1, 0]
cone_angle = 30
inner_cone_angle = 20
diffuse = [8, 8, 8]
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
"#;
    let desc = common::scene(src);
    assert!(
        desc.warnings
            .iter()
            .any(|w| w.contains("lights[0]: a spot light renders as a point light under Whitted")),
        "{:?}",
        desc.warnings
    );
    let img = common::render_with(&desc, &desc.render, Precision::F64).resolve();
    // Row 16 is the image's middle; column c's pixel centre looks at the
    // floor at |x| = |(c + 0.5) / 33 x 8 - 4| (90 degrees from 4 up).
    let expect = |c: usize| {
        let x = (c as f64 + 0.5) / 33.0 * 8.0 - 4.0;
        let d2 = 4.0 + x * x;
        let cos = 2.0 / d2.sqrt();
        let (ci, co) = (20f64.to_radians().cos(), 30f64.to_radians().cos());
        let f = ((cos - co) / (ci - co)).clamp(0.0, 1.0);
        0.5 / std::f64::consts::PI * 8.0 * cos * f * f / d2
    };
    let mut lit = 0;
    for c in 0..33 {
        let got = img[16 * 33 + c][0] as f64;
        let want = expect(c);
        assert!(
            (got - want).abs() <= 1e-5 * want.max(1e-3),
            "column {c}: {got} against {want}"
        );
        lit += usize::from(want > 0.0);
    }
    // The centre fully lit, the ramp and the dark beyond it all crossed.
    assert!((5..33).contains(&lit), "{lit} lit columns");
    assert!(expect(16) > 0.3 && expect(20) > 0.0 && expect(20) < expect(19) && expect(27) == 0.0);

    let err = |extra: &str| {
        SceneDesc::parse(&src.replace("cone_angle = 30\n", extra), "t.toml")
            .unwrap_err()
            .to_string()
    };
    let e = err("cone_angle = 95\n");
    assert!(
        e.ends_with("lights[0].cone_angle: must be in (0, 90] degrees, got 95"),
        "{e}"
    );
    let e = err("cone_angle = 15\n");
    assert!(
        e.ends_with("lights[0].inner_cone_angle: must be in [0, cone_angle = 15) degrees, got 20"),
        "{e}"
    );
    let e = SceneDesc::parse(
        &src.replace("direction = [0, -1, 0]", "direction = [0, 0, 0]"),
        "t.toml",
    )
    .unwrap_err()
    .to_string();
    assert!(e.ends_with("lights[0].direction: must not be zero"), "{e}");
}
