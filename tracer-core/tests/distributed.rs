//! Distributed ray tracing on the CPU (issue 16): area lights, glossy
//! reflection and translucency, depth of field and motion blur, each
//! against an analytic or independent expectation, the hard cases, and the
//! pins that scenes without the new fields render exactly as before.

mod common;

use common::{examples_dir, render_with, scene};
use tracer_core::film::WorkRegion;
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::{RenderSettings, SceneDesc};

fn render(desc: &SceneDesc, precision: Precision) -> Film {
    render_with(desc, &desc.render, precision)
}

/// The ray direction of raster point (sx, sy) as `docs/scene-format.md`
/// defines it, in f64.
#[allow(clippy::too_many_arguments)]
fn pinhole_dir(
    pos: [f64; 3],
    look: [f64; 3],
    up: [f64; 3],
    fov: f64,
    w: u32,
    h: u32,
    sx: f64,
    sy: f64,
) -> [f64; 3] {
    let f = norm(sub(look, pos));
    let r = norm(cross(f, up));
    let u = cross(r, f);
    let t = (fov.to_radians() / 2.0).tan();
    let a = (2.0 * sx / w as f64 - 1.0) * t * (w as f64 / h as f64);
    let b = (1.0 - 2.0 * sy / h as f64) * t;
    norm([
        f[0] + a * r[0] + b * u[0],
        f[1] + a * r[1] + b * u[1],
        f[2] + a * r[2] + b * u[2],
    ])
}
fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: [f64; 3]) -> [f64; 3] {
    let l = dot(a, a).sqrt();
    a.map(|x| x / l)
}

// ---------------------------------------------------------------- pins

/// Every new field at its default, written out, changes nothing: the scene
/// builds no distributed state and its film is the same bit for bit.
#[test]
fn explicit_defaults_render_bit_identically_to_today() {
    let path = examples_dir().join("resolution.toml");
    let src = std::fs::read_to_string(&path).unwrap();
    let plain = SceneDesc::parse(&src, &path).unwrap();
    let with = src
        .replace(
            "fov_y = 60.0\n",
            "fov_y = 60.0\naperture = 0.0\nshutter = [0.0, 0.0]\nfocus_distance = 3.0\n",
        )
        .replace("ior = 1.0\n", "ior = 1.0\ngloss = 0\ntranslucency = 0.0\n")
        .replace("[[lights]]\n", "[[lights]]\ntype = \"point\"\n")
        .replace(
            "radius = 1.0\nmaterial = \"plastic\"\n",
            "radius = 1.0\nmaterial = \"plastic\"\n[[objects.keyframes]]\nframe = 0\ncenter = [-2.4, 1.0, 1.5]\n",
        );
    assert_ne!(with, src);
    let with = SceneDesc::parse(&with, &path).unwrap();
    let settings = RenderSettings {
        width: 96,
        height: 72,
        ..plain.render
    };
    for precision in [Precision::F32, Precision::F64] {
        let PreparedFrame::F32(w) =
            PreparedFrame::build(&with, &settings, 0, Precision::F32).unwrap()
        else {
            unreachable!()
        };
        assert!(w.dist.is_none(), "no effect is on: no distributed state");
        let a = render_with(&plain, &settings, precision);
        let b = render_with(&with, &settings, precision);
        assert_eq!(a.sums, b.sums, "{precision:?}");
        assert_eq!(a.rays, b.rays);
    }
}

/// A zero-length shutter at a fractional time renders the static scene at
/// that time: the keyframe interpolation at frame + open.
#[test]
fn zero_length_shutter_renders_the_pose_at_its_time() {
    let base = r#"
[render]
width = 64
height = 48
samples = 1
[camera]
position = [0, 1, -6]
look_at = [0, 1, 0]
SHUTTER
[[camera.keyframes]]
frame = 0
position = [0, 1, -6]
[[camera.keyframes]]
frame = 1
position = [2, 1, -6]
[materials.m]
ambient = [1, 1, 1]
diffuse = [0.5, 0.5, 0.5]
[world]
ambient = [0.2, 0.2, 0.2]
[[lights]]
position = [0, 5, -5]
[[objects]]
type = "sphere"
center = [0, 1, 0]
radius = 1
material = "m"
[[objects.keyframes]]
frame = 0
center = [0, 1, 0]
[[objects.keyframes]]
frame = 1
center = [0, 3, 0]
"#;
    let a = scene(&base.replace("SHUTTER", "shutter = [0.25, 0.25]"));
    let b = scene(
        &base
            .replace("SHUTTER", "")
            .replace("[[camera.keyframes]]\nframe = 0\nposition = [0, 1, -6]\n[[camera.keyframes]]\nframe = 1\nposition = [2, 1, -6]\n", "")
            .replace("position = [0, 1, -6]", "position = [0.5, 1, -6]")
            .replace("[[objects.keyframes]]\nframe = 0\ncenter = [0, 1, 0]\n[[objects.keyframes]]\nframe = 1\ncenter = [0, 3, 0]\n", "")
            .replace("center = [0, 1, 0]", "center = [0, 1.5, 0]"),
    );
    let fa = render(&a, Precision::F64);
    let fb = render(&b, Precision::F64);
    // The same poses up to the rounding of the interpolation.
    let d = common::diff(&fa.resolve(), &fb.resolve(), 1e-6);
    assert!(d.max < 1e-6, "max difference {}", d.max);
}

// ---------------------------------------------------------------- area lights

/// The contract's quad-light term over a plane with only a diffuse term,
/// unshadowed: (1/A) * integral over the quad of cos(theta) at p, which
/// for an axis-aligned rectangle at height h above p has the closed form
/// h/A * [x ln(z + r) + z ln(x + r) - h atan(x z / (h r))] over the corners.
fn quad_irradiance(p: [f64; 2], x0: f64, x1: f64, z0: f64, z1: f64, h: f64) -> f64 {
    let g = |x: f64, z: f64| {
        let r = (x * x + z * z + h * h).sqrt();
        x * (z + r).ln() + z * (x + r).ln() - h * (x * z / (h * r)).atan()
    };
    let (a0, a1, b0, b1) = (x0 - p[0], x1 - p[0], z0 - p[1], z1 - p[1]);
    let integral = g(a1, b1) - g(a0, b1) - g(a1, b0) + g(a0, b0);
    h * integral / ((x1 - x0) * (z1 - z0))
}

#[test]
fn quad_light_over_a_plane_matches_the_closed_form() {
    // Cross-check the closed form by quadrature.
    let (x0, x1, z0, z1, h) = (-1.0, 1.5, -0.5, 1.0, 2.0);
    for p in [[0.0, 0.0], [2.0, -1.0], [-3.0, 4.0]] {
        let n = 800;
        let mut q = 0.0;
        for i in 0..n {
            for j in 0..n {
                let x = x0 + (x1 - x0) * (i as f64 + 0.5) / n as f64 - p[0];
                let z = z0 + (z1 - z0) * (j as f64 + 0.5) / n as f64 - p[1];
                q += h / (x * x + z * z + h * h).sqrt();
            }
        }
        q /= (n * n) as f64;
        let c = quad_irradiance(p, x0, x1, z0, z1, h);
        assert!((q - c).abs() < 1e-5, "closed form {c} vs quadrature {q}");
    }
    // Camera straight down at the floor; the light 2 above it.
    let (w, hgt) = (24u32, 24u32);
    let src = format!(
        r#"
[render]
width = {w}
height = {hgt}
samples = 1
max_depth = 0
[camera]
position = [0, 1, 0]
look_at = [0, 0, 0]
up = [0, 0, 1]
fov_y = 120
[materials.floor]
diffuse = [1, 1, 1]
[[lights]]
type = "quad"
corner = [{x0}, {h}, {z0}]
edge_u = [{eu}, 0, 0]
edge_v = [0, 0, {ev}]
samples = 1024
diffuse = [1, 1, 1]
specular = [0, 0, 0]
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
"#,
        eu = x1 - x0,
        ev = z1 - z0
    );
    let desc = scene(&src);
    for precision in [Precision::F64, Precision::F32] {
        let film = render(&desc, precision);
        let img = film.resolve();
        let mut worst = 0.0f64;
        for y in 0..hgt {
            for x in 0..w {
                let d = pinhole_dir(
                    [0.0, 1.0, 0.0],
                    [0.0; 3],
                    [0.0, 0.0, 1.0],
                    120.0,
                    w,
                    hgt,
                    x as f64 + 0.5,
                    y as f64 + 0.5,
                );
                let t = 1.0 / -d[1];
                let p = [d[0] * t, d[2] * t];
                let want = quad_irradiance(p, x0, x1, z0, z1, h);
                let got = img[(y * w + x) as usize][0] as f64;
                worst = worst.max((got - want).abs());
            }
        }
        // 1024 stratified samples: error well below 1e-3.
        assert!(worst < 2e-3, "{precision:?}: worst error {worst}");
    }
}

/// Sphere light above a floor, a sphere occluder between: a floor point is
/// in the umbra when the light's cone lies inside the occluder's, fully lit
/// when the cones are disjoint, else in the penumbra.
#[test]
fn sphere_light_penumbra_has_the_width_of_the_cones() {
    let (w, h) = (48u32, 48u32);
    let cam = [4.0, 3.0, 0.5];
    let light = ([0.0, 4.0, 0.0], 0.6);
    let occ = ([0.0, 1.5, 0.0], 0.5);
    let src = |with_occluder: bool| {
        format!(
            r#"
[render]
width = {w}
height = {h}
samples = 1
max_depth = 0
[camera]
position = [4, 3, 0.5]
look_at = [0, 0, 0]
fov_y = 60
[materials.floor]
diffuse = [1, 1, 1]
[materials.occ]
[[lights]]
type = "sphere"
center = [0, 4, 0]
radius = 0.6
samples = 64
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
{}
"#,
            if with_occluder {
                "[[objects]]\ntype = \"sphere\"\ncenter = [0, 1.5, 0]\nradius = 0.5\nmaterial = \"occ\"\n"
            } else {
                ""
            }
        )
    };
    let lit = render(&scene(&src(false)), Precision::F64).resolve();
    let shadowed = render(&scene(&src(true)), Precision::F64).resolve();
    let (mut umbra, mut penumbra, mut full) = (0, 0, 0);
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            let d = pinhole_dir(
                cam,
                [0.0; 3],
                [0.0, 1.0, 0.0],
                60.0,
                w,
                h,
                x as f64 + 0.5,
                y as f64 + 0.5,
            );
            if d[1] >= 0.0 {
                continue;
            }
            let t = 3.0 / -d[1];
            let p = [cam[0] + d[0] * t, 0.0, cam[2] + d[2] * t];
            // The occluder hides the floor point from the camera?
            let to_cam = norm(sub(cam, p));
            let oc = sub(p, occ.0);
            let b = dot(oc, to_cam);
            if b * b - (dot(oc, oc) - occ.1 * occ.1) > 0.0 && -b > 0.0 {
                continue;
            }
            let cone = |c: ([f64; 3], f64)| {
                let v = sub(c.0, p);
                let l = dot(v, v).sqrt();
                (norm(v), (c.1 / l).asin())
            };
            let (al, rl) = cone(light);
            let (ao, ro) = cone(occ);
            let delta = dot(al, ao).clamp(-1.0, 1.0).acos();
            let margin = 0.01;
            let (s, l) = (shadowed[i][0], lit[i][0]);
            if delta + rl <= ro - margin {
                umbra += 1;
                assert_eq!(s, 0.0, "pixel ({x},{y}) should be in the umbra");
            } else if delta >= rl + ro + margin {
                full += 1;
                assert_eq!(s, l, "pixel ({x},{y}) should be fully lit");
            } else if delta + rl >= ro + margin && delta <= rl + ro - margin {
                penumbra += 1;
                assert!(
                    s > 0.0 && s < l,
                    "pixel ({x},{y}) should be in the penumbra: {s} of {l}"
                );
            }
        }
    }
    assert!(
        umbra > 10 && penumbra > 10 && full > 10,
        "{umbra} {penumbra} {full}"
    );
}

/// Hard cases: a quad light cutting through the floor, one lying in the
/// floor's plane (seen edge-on from every floor point), a sphere light
/// half under the floor, a light inside a sphere: finite everywhere, and
/// the cut light lights the floor with its upper half only.
#[test]
fn area_lights_touching_and_cutting_surfaces_stay_finite() {
    let base = r#"
[render]
width = 40
height = 30
samples = 4
max_depth = 3
[camera]
position = [0, 3, -6]
look_at = [0, 0, 0]
[materials.floor]
diffuse = [0.8, 0.8, 0.8]
specular = [0.5, 0.5, 0.5]
shininess = 20
reflectivity = 0.3
[materials.glass]
diffuse = [0.1, 0.1, 0.1]
transparency = 0.9
ior = 1.5
gloss = 10
translucency = 5
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
[[objects]]
type = "sphere"
center = [2, 1, 0]
radius = 1
material = "glass"
LIGHT
"#;
    for light in [
        // Cuts through the floor.
        "[[lights]]\ntype = \"quad\"\ncorner = [-1, -1, 0]\nedge_u = [2, 0, 0]\nedge_v = [0, 2, 0]\nsamples = 16",
        // In the floor's plane: edge-on from every floor point.
        "[[lights]]\ntype = \"quad\"\ncorner = [-1, 0, -1]\nedge_u = [2, 0, 0]\nedge_v = [0, 0, 2]\nsamples = 9",
        // Half under the floor.
        "[[lights]]\ntype = \"sphere\"\ncenter = [-1, 0, 0]\nradius = 0.5\nsamples = 5",
        // Inside the glass sphere, touching its surface.
        "[[lights]]\ntype = \"sphere\"\ncenter = [2, 1, 0]\nradius = 1\nsamples = 4",
    ] {
        let desc = scene(&base.replace("LIGHT", light));
        for precision in [Precision::F32, Precision::F64] {
            let film = render(&desc, precision);
            common::assert_finite(&film.resolve());
        }
    }
    // Edge-on: every floor point sees the light in its own plane, N.L = 0.
    let edge_on = scene(
        &base
            .replace("LIGHT", "[[lights]]\ntype = \"quad\"\ncorner = [-1, 0, -1]\nedge_u = [2, 0, 0]\nedge_v = [0, 0, 2]\nsamples = 9\nspecular = [0, 0, 0]")
            .replace("reflectivity = 0.3", "")
            .replace("max_depth = 3", "max_depth = 0"),
    );
    let img = render(&edge_on, Precision::F64).resolve();
    // Bottom row: floor only, lit by nothing.
    for x in 0..40 {
        let p = img[(29 * 40 + x) as usize];
        assert!(p.iter().all(|&c| c < 1e-6), "{p:?}");
    }
}

/// `samples` changes noise, never the expectation: the mean over an image
/// with 1 and with 16 samples per light agree.
#[test]
fn light_samples_change_noise_not_the_expectation() {
    let src = |n: u32| {
        format!(
            r#"
[render]
width = 64
height = 48
samples = 16
sampler = "jittered"
max_depth = 0
[camera]
position = [0, 3, -6]
look_at = [0, 0, 0]
[materials.floor]
diffuse = [1, 1, 1]
[materials.ball]
diffuse = [0.5, 0.5, 0.5]
[[lights]]
type = "quad"
corner = [-2, 3, -1]
edge_u = [4, 0, 0]
edge_v = [0, 0.5, 2]
samples = {n}
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
[[objects]]
type = "sphere"
center = [0, 0.8, 0]
radius = 0.8
material = "ball"
"#
        )
    };
    let mean = |n| {
        let img = render(&scene(&src(n)), Precision::F64).resolve();
        img.iter().map(|p| p[0] as f64).sum::<f64>() / img.len() as f64
    };
    let (a, b) = (mean(1), mean(16));
    assert!(
        (a - b).abs() < 0.01 * b,
        "mean {a} with 1 sample, {b} with 16"
    );
}

// ---------------------------------------------------------------- cones

/// A mirror plane, viewed with `fov`, reflecting a uniform background
/// through a gloss cone: every direction above the surface returns the
/// background, the others black.
fn glossy_floor(gloss: f64, translucent: bool, camera_y: f64) -> String {
    format!(
        r#"
[render]
width = 16
height = 16
samples = 64
sampler = "jittered"
max_depth = 1
[camera]
position = [0, {camera_y}, -{cz}]
look_at = [0, 0, 0]
up = [0, 0, 1]
fov_y = 1
[world]
background = [0.25, 0.5, 1.0]
[materials.m]
reflectivity = {refl}
transparency = {transp}
ior = 1
gloss = {gloss}
translucency = {gloss}
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "m"
"#,
        cz = (1.0 - camera_y * camera_y).max(0.0).sqrt() * 10.0,
        camera_y = camera_y * 10.0,
        refl = if translucent { 0.0 } else { 1.0 },
        transp = if translucent { 1.0 } else { 0.0 },
    )
}

/// Share of the cone of half-angle g around a direction at elevation e
/// that lies above the plane (by solid angle), by quadrature.
fn share_above(e: f64, g: f64) -> f64 {
    let (n_t, n_p) = (2000, 2000);
    let cg = g.cos();
    let mut above = 0.0;
    for i in 0..n_t {
        let c = 1.0 - (i as f64 + 0.5) / n_t as f64 * (1.0 - cg);
        let s = (1.0 - c * c).sqrt();
        for j in 0..n_p {
            let phi = (j as f64 + 0.5) / n_p as f64 * std::f64::consts::TAU;
            // Axis (cos e, sin e, 0); perpendiculars (-sin e, cos e, 0) and z.
            let y = e.sin() * c + e.cos() * s * phi.cos();
            if y > 0.0 {
                above += 1.0;
            }
        }
    }
    above / (n_t * n_p) as f64
}

#[test]
fn gloss_cone_of_a_uniform_environment_gives_its_colour() {
    // Head-on (within the 0.71 degrees of the corner pixels): the whole
    // cone is above the surface, up to 89 degrees.
    for gloss in [1.0, 30.0, 60.0, 89.0] {
        for translucent in [false, true] {
            let desc = scene(&glossy_floor(gloss, translucent, 1.0));
            for precision in [Precision::F32, Precision::F64] {
                let img = render(&desc, precision).resolve();
                for p in &img {
                    for (c, want) in p.iter().zip([0.25, 0.5, 1.0]) {
                        assert!(
                            (c - want).abs() < 1e-5,
                            "gloss {gloss} translucent {translucent}: {p:?}"
                        );
                    }
                }
            }
        }
    }
    // At 30 degrees of elevation, a cone of 60, 89 and 89.9 degrees has
    // part of itself below the surface: that share is black.
    for gloss in [60.0f64, 89.0, 89.9] {
        for translucent in [false, true] {
            let e = 30f64.to_radians();
            let desc = scene(
                &glossy_floor(gloss, translucent, e.sin())
                    .replace("samples = 64", "samples = 1024"),
            );
            let img = render(&desc, Precision::F64).resolve();
            let mean = img.iter().map(|p| p[2] as f64).sum::<f64>() / img.len() as f64;
            let want = share_above(e, gloss.to_radians());
            assert!(
                (mean - want).abs() < 0.01,
                "gloss {gloss} translucent {translucent}: {mean} vs {want}"
            );
        }
    }
}

// ---------------------------------------------------------------- depth of field

fn dof_scene(aperture: f64, focus: f64, depth: f64, radius: f64) -> String {
    format!(
        r#"
[render]
width = 64
height = 64
samples = 256
sampler = "jittered"
max_depth = 0
[camera]
position = [0, 0, 0]
look_at = [0, 0, 1]
fov_y = 20
aperture = {aperture}
focus_distance = {focus}
[world]
ambient = [1, 1, 1]
[materials.white]
ambient = [1, 1, 1]
[[objects]]
type = "sphere"
center = [0, 0, {depth}]
radius = {radius}
material = "white"
"#
    )
}

#[test]
fn focused_point_stays_sharp_and_defocused_spreads_over_the_circle_of_confusion() {
    let px = |focus: f64| 2.0 * focus * (10f64.to_radians()).tan() / 64.0; // pixel size at the focal plane
    // In focus: the same image as the pinhole but for silhouette pixels.
    let sharp = render(&scene(&dof_scene(0.2, 10.0, 10.0, 0.5)), Precision::F64).resolve();
    let pin = render(&scene(&dof_scene(0.0, 10.0, 10.0, 0.5)), Precision::F64).resolve();
    let d = common::diff(&sharp, &pin, 0.3);
    assert!(d.over <= 40, "{} pixels blurred in focus", d.over);
    // Out of focus: a small sphere at 20 seen with focus 10 spreads over
    // the circle of confusion: radius aperture |D - F| / D in the focal
    // plane, plus the sphere's own image.
    let (a, f, dd, rho) = (1.0, 10.0, 20.0, 0.3);
    let blur = render(&scene(&dof_scene(a, f, dd, rho)), Precision::F64).resolve();
    let coc = a * (dd - f) / dd / px(f); // pixels
    let own = rho * f / dd / px(f);
    let centre = 32.0;
    let mut far = 0.0f64;
    let mut energy = 0.0;
    for y in 0..64 {
        for x in 0..64 {
            let v = blur[y * 64 + x][0] as f64;
            energy += v;
            if v > 0.0 {
                let r =
                    ((x as f64 + 0.5 - centre).powi(2) + (y as f64 + 0.5 - centre).powi(2)).sqrt();
                far = far.max(r);
            }
        }
    }
    assert!(
        far <= coc + own + 1.0 && far >= coc + own - 2.5,
        "blur reaches {far} pixels, circle of confusion {coc} + {own}"
    );
    // The light is spread, not lost: the same sum as the pinhole image.
    let pin_small = render(&scene(&dof_scene(0.0, f, dd, rho)), Precision::F64).resolve();
    let e0: f64 = pin_small.iter().map(|p| p[0] as f64).sum();
    assert!((energy - e0).abs() < 0.05 * e0, "energy {energy} vs {e0}");
}

/// Focus on a surface: a plane at the focus distance looks the same with
/// and without a lens; focus and aperture extremes stay finite.
#[test]
fn focus_on_a_surface_and_extreme_lenses_stay_finite() {
    let src = r#"
[render]
width = 32
height = 32
samples = 16
[camera]
position = [0, 0, 0]
look_at = [0, 0, 1]
LENS
[materials.m]
diffuse = [1, 1, 1]
[[lights]]
position = [0, 0, 0]
[[objects]]
type = "plane"
normal = [0, 0, -1]
distance = -5
material = "m"
"#;
    let pin = render(&scene(&src.replace("LENS", "")), Precision::F64).resolve();
    let lens = render(
        &scene(&src.replace("LENS", "aperture = 0.5\nfocus_distance = 5")),
        Precision::F64,
    )
    .resolve();
    // Every lens ray meets the plane at its pinhole point: only the shading
    // (the view direction) differs, the point light at the pinhole.
    let d = common::diff(&pin, &lens, 0.05);
    assert_eq!(d.over, 0, "max difference {}", d.max);
    for lens in [
        "aperture = 1e6\nfocus_distance = 1e-6",
        "aperture = 1e-9\nfocus_distance = 1e9",
        "aperture = 3",
    ] {
        let img = render(&scene(&src.replace("LENS", lens)), Precision::F32).resolve();
        common::assert_finite(&img);
    }
}

// ---------------------------------------------------------------- motion blur

/// A white sphere moving sideways across the shutter in front of a black
/// background: each pixel is the share of the shutter during which its
/// ray meets the sphere.
#[test]
fn moving_sphere_covers_each_pixel_for_its_share_of_the_shutter() {
    let src = r#"
[render]
width = 48
height = 16
samples = 900
sampler = "jittered"
max_depth = 0
[camera]
position = [0, 0, -10]
look_at = [0, 0, 0]
fov_y = 20
shutter = [0.25, 0.75]
[materials.white]
ambient = [1, 1, 1]
[world]
ambient = [1, 1, 1]
[[objects]]
type = "sphere"
center = [0, 0, 0]
radius = 0.5
material = "white"
[[objects.keyframes]]
frame = 0
center = [-3, 0, 0]
[[objects.keyframes]]
frame = 1
center = [3, 0, 0]
"#;
    let desc = scene(src);
    let (w, h) = (48u32, 16u32);
    for precision in [Precision::F64, Precision::F32] {
        let img = render(&desc, precision).resolve();
        let mut worst = 0.0f64;
        for x in 0..w {
            let y = h / 2;
            // The pixel's share over its area, by quadrature over 8x8 points
            // and 400 times of the shutter.
            let mut share = 0.0;
            for k in 0..64 {
                let (sx, sy) = (
                    x as f64 + (k % 8) as f64 / 8.0 + 1.0 / 16.0,
                    y as f64 + (k / 8) as f64 / 8.0 + 1.0 / 16.0,
                );
                let d = pinhole_dir(
                    [0.0, 0.0, -10.0],
                    [0.0; 3],
                    [0.0, 1.0, 0.0],
                    20.0,
                    w,
                    h,
                    sx,
                    sy,
                );
                for j in 0..400 {
                    let t = 0.25 + 0.5 * (j as f64 + 0.5) / 400.0;
                    let c = [-3.0 + 6.0 * t, 0.0, 0.0];
                    let oc = sub([0.0, 0.0, -10.0], c);
                    let b = dot(oc, d);
                    if b * b - (dot(oc, oc) - 0.25) >= 0.0 {
                        share += 1.0;
                    }
                }
            }
            share /= 64.0 * 400.0;
            let got = img[(y * w + x) as usize][0] as f64;
            worst = worst.max((got - share).abs());
        }
        assert!(worst < 0.08, "{precision:?}: worst {worst}");
    }
}

/// A moving camera with a still scene and a still camera with the scene
/// moving the other way see the same thing.
#[test]
fn camera_motion_blur_mirrors_object_motion() {
    let cam_moves = r#"
[render]
width = 40
height = 20
samples = 64
max_depth = 0
[camera]
position = [0, 0, -10]
look_at = [0, 0, 0]
fov_y = 20
shutter = [0, 1]
[[camera.keyframes]]
frame = 0
position = [1, 0, -10]
look_at = [1, 0, 0]
[[camera.keyframes]]
frame = 1
position = [-1, 0, -10]
look_at = [-1, 0, 0]
[materials.white]
ambient = [1, 1, 1]
[world]
ambient = [1, 1, 1]
[[objects]]
type = "sphere"
center = [0, 0, 0]
radius = 0.5
material = "white"
"#;
    let ball_moves = r#"
[render]
width = 40
height = 20
samples = 64
max_depth = 0
[camera]
position = [0, 0, -10]
look_at = [0, 0, 0]
fov_y = 20
shutter = [0, 1]
[materials.white]
ambient = [1, 1, 1]
[world]
ambient = [1, 1, 1]
[[objects]]
type = "sphere"
center = [0, 0, 0]
radius = 0.5
material = "white"
[[objects.keyframes]]
frame = 0
center = [-1, 0, 0]
[[objects.keyframes]]
frame = 1
center = [1, 0, 0]
"#;
    let a = render(&scene(cam_moves), Precision::F64).resolve();
    let b = render(&scene(ball_moves), Precision::F64).resolve();
    // The same up to rounding (a silhouette sample may flip).
    let d = common::diff(&a, &b, 0.02);
    assert!(d.over <= 2, "{} pixels differ, max {}", d.over, d.max);
    assert!(a.iter().any(|p| p[0] > 0.0 && p[0] < 1.0), "blurred");
}

/// A mesh translated by keyframes: static at a zero-length shutter (the
/// same image as the mesh placed there), blurred over a long one, its
/// pixels covered all the time white, never black, between otherwise.
#[test]
fn moving_mesh_blurs_between_its_positions() {
    let dir = common::meshgen::tmpdir("dist-mesh");
    common::meshgen::write_quad_obj(&dir);
    let src = |shutter: &str, keys: bool, translate: &str| {
        format!(
            r#"
[render]
width = 48
height = 16
samples = 64
sampler = "jittered"
max_depth = 0
[camera]
position = [0, 0, -10]
look_at = [0, 0, 0]
fov_y = 20
shutter = {shutter}
[materials.white]
ambient = [1, 1, 1]
[world]
ambient = [1, 1, 1]
[[objects]]
type = "mesh"
path = "quad.obj"
material = "white"
translate = {translate}
{}
"#,
            if keys {
                common::meshgen::keyframes_along_x(-1.0, 1.0)
            } else {
                String::new()
            }
        )
    };
    let load = |s: String| SceneDesc::parse(&s, dir.join("s.toml")).unwrap();
    let still = render(&load(src("[0.5, 0.5]", true, "[7, 7, 7]")), Precision::F64);
    let placed = render(&load(src("[0, 0]", false, "[0, 0, 0]")), Precision::F64);
    assert_eq!(still.sums, placed.sums);
    let blurred = render(&load(src("[0, 1]", true, "[0, 0, 0]")), Precision::F64).resolve();
    // The square (3 wide) moves from -1 to 1: |x| < 0.5 is always covered;
    // the image spans |x| < 5.3.
    let row = 8 * 48;
    let px = |x: usize| blurred[row + x][0];
    assert_eq!(px(24), 1.0, "the middle is always covered");
    assert_eq!(px(0), 0.0, "the edge is never covered");
    assert!((1..48).any(|x| px(x) > 0.1 && px(x) < 0.9), "blurred edges");
    common::assert_finite(&blurred);
}

/// Hard cases of the cones and motion together: a moving glass sphere
/// (refraction, total internal reflection into a gloss cone near 90
/// degrees, a translucency cone) with a sphere light inside it, nested and
/// touching glass. Finite in f32 and f64, and f32 tracks f64.
#[test]
fn moving_glass_with_cones_and_tir_stays_finite() {
    let src = r#"
[render]
width = 48
height = 36
samples = 4
max_depth = 6
[camera]
position = [0, 1, -5]
look_at = [0, 0.8, 0]
shutter = [0, 1]
aperture = 0.05
[world]
ambient = [0.1, 0.1, 0.1]
background = [0.3, 0.4, 0.6]
[materials.glass]
diffuse = [0.02, 0.02, 0.02]
specular = [0.9, 0.9, 0.9]
shininess = 80
reflectivity = 0.1
transparency = 0.9
ior = 2.4
gloss = 89.9
translucency = 30
[materials.floor]
diffuse = [0.7, 0.7, 0.7]
reflectivity = 0.2
gloss = 45
[[lights]]
type = "sphere"
center = [0, 0.8, 0]
radius = 0.3
samples = 4
[[lights]]
type = "quad"
corner = [-1, 3, -1]
edge_u = [2, 0, 0]
edge_v = [0, 0, 2]
samples = 2
[[objects]]
type = "plane"
normal = [0, 1, 0]
distance = 0
material = "floor"
[[objects]]
type = "sphere"
center = [0, 0.8, 0]
radius = 0.8
material = "glass"
[[objects.keyframes]]
frame = 0
center = [-0.5, 0.8, 0]
[[objects.keyframes]]
frame = 1
center = [0.5, 0.8, 0]
[[objects]]
type = "sphere"
center = [0, 0.8, 0]
radius = 0.4
material = "glass"
[[objects]]
type = "sphere"
center = [1.6, 0.8, 0]
radius = 0.8
material = "glass"
"#;
    let desc = scene(src);
    let a = render(&desc, Precision::F32).resolve();
    let b = render(&desc, Precision::F64).resolve();
    common::assert_finite(&a);
    common::assert_finite(&b);
    let d = common::diff(&a, &b, 2.0 / 255.0);
    assert!(d.mean < 5e-3, "mean f32/f64 difference {}", d.mean);
}

// ---------------------------------------------------------------- determinism

/// The distributed example renders the same sums whatever the tiles and
/// sample ranges: random numbers depend on (pixel, sample, frame, dimension) only.
#[test]
fn distributed_renders_are_independent_of_tiles_and_sample_ranges() {
    let desc = SceneDesc::load(examples_dir().join("distributed.toml")).unwrap();
    let settings = RenderSettings {
        width: 40,
        height: 30,
        samples: 6,
        ..desc.render
    };
    let frame = PreparedFrame::build(&desc, &settings, 0, Precision::F32).unwrap();
    let r1 = CpuRenderer::new(Some(1)).unwrap();
    let r2 = CpuRenderer::new(Some(2)).unwrap();
    let whole = r2
        .render(
            &frame,
            WorkRegion::new(0, Rect::full(40, 30), SampleRange::all(6)),
            &|_| {},
        )
        .unwrap();
    let mut parts = Film::new(Rect::full(40, 30));
    for rect in [
        Rect::new(0, 0, 17, 30),
        Rect::new(17, 0, 23, 11),
        Rect::new(17, 11, 23, 19),
    ] {
        for range in [
            SampleRange::new(0, 1),
            SampleRange::new(1, 4),
            SampleRange::new(4, 6),
        ] {
            parts
                .merge(
                    &r1.render(&frame, WorkRegion::new(0, rect, range), &|_| {})
                        .unwrap(),
                )
                .unwrap();
        }
    }
    assert_eq!(whole.sums, parts.sums);
    assert_eq!(whole.counts, parts.counts);
    assert_eq!(whole.nonfinite, 0);
}

/// Every example with distributed effects, in f32 and f64: finite, and f32
/// close to the f64 reference (the same random numbers on both).
#[test]
fn distributed_examples_are_finite_and_f32_tracks_f64() {
    for name in ["distributed.toml", "resolution-quad.toml"] {
        let desc = SceneDesc::load(examples_dir().join(name)).unwrap();
        let settings = RenderSettings {
            width: 80,
            height: 60,
            samples: 4,
            ..desc.render
        };
        let a = render_with(&desc, &settings, Precision::F32).resolve();
        let b = render_with(&desc, &settings, Precision::F64).resolve();
        common::assert_finite(&a);
        let d = common::diff(&a, &b, 2.0 / 255.0);
        assert!(d.mean < 2e-3, "{name}: mean {}", d.mean);
    }
}
