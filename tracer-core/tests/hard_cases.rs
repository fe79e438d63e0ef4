//! The numerical hard cases of MISSION.md that apply to spheres and planes.
//!
//! Where possible the renderer is checked against an independent analytic
//! evaluation in f64 of the contract's shading formula (a second, simple
//! implementation written here), so acne, leaks and speckles show up as
//! pixels that disagree with the formula, not merely with the renderer's
//! own f64 mode.

mod common;

use common::*;
use glam::DVec3;
use tracer_core::film::RayCounts;
use tracer_core::geometry::PrimId;
use tracer_core::math::Ray;
use tracer_core::render::step::{Static, trace};
use tracer_core::render::{Precision, PreparedFrame};
use tracer_core::scene::{ObjectDesc, RenderSettings, SceneDesc};

/// Shape of the one object an analytic check looks at.
enum Shape {
    Sphere { c: DVec3, r: f64 },
    Plane { n: DVec3, d: f64 },
}

/// Analytic first-hit shading of a scene with a single object and no
/// secondary rays: ambient + unblocked lights, per the contract. For a
/// sphere, a light is blocked exactly when N.L < 0 (the sphere itself is
/// in the way) unless the point is seen from inside.
fn analytic(desc: &SceneDesc, settings: &RenderSettings, px: u32, py: u32) -> Option<[f64; 3]> {
    assert_eq!(desc.objects.len(), 1);
    let shape = match &desc.objects[0] {
        ObjectDesc::Sphere { center, radius, .. } => Shape::Sphere {
            c: DVec3::from_array(center.0),
            r: radius.0,
        },
        ObjectDesc::Plane {
            normal, distance, ..
        } => Shape::Plane {
            n: DVec3::from_array(normal.0),
            d: distance.0,
        },
        ObjectDesc::Mesh(_) => panic!("the analytic reference covers spheres and planes only"),
    };
    let m = &desc.materials[desc.object_materials[0] as usize].1;
    let cam = &desc.camera;
    let pos = DVec3::from_array(cam.position.0);
    let f = (DVec3::from_array(cam.look_at.0) - pos).normalize();
    let r = f.cross(DVec3::from_array(cam.up.0)).normalize();
    let u = r.cross(f);
    let t = (cam.fov_y.0.to_radians() / 2.0).tan();
    let (w, h) = (settings.width as f64, settings.height as f64);
    let (sx, sy) = (px as f64 + 0.5, py as f64 + 0.5);
    let d =
        (f + r * ((2.0 * sx / w - 1.0) * t * w / h) + u * ((1.0 - 2.0 * sy / h) * t)).normalize();

    let (p, n_out) = match shape {
        Shape::Sphere { c, r } => {
            let oc = pos - c;
            let b = oc.dot(d);
            let disc = b * b - (oc.length_squared() - r * r);
            // Leave silhouette pixels out: there a last-bit difference decides hit or miss.
            if disc < 1e-6 * r * r {
                return None;
            }
            let s = disc.sqrt();
            let tt = if -b - s > 0.0 { -b - s } else { -b + s };
            if tt <= 0.0 {
                return None;
            }
            let p = pos + d * tt;
            (p, (p - c).normalize())
        }
        Shape::Plane { n, d: dist } => {
            let denom = n.dot(d);
            let tt = (dist - n.dot(pos)) / denom;
            if !(tt > 0.0) || denom.abs() < 1e-3 {
                return None;
            }
            (pos + d * tt, n)
        }
    };
    let v = -d;
    let n = if n_out.dot(v) >= 0.0 { n_out } else { -n_out };
    let inside = n_out.dot(v) < 0.0;
    let amb = DVec3::from_array(desc.world.ambient.0) * DVec3::from_array(m.ambient.0);
    let mut col = amb;
    for l in &desc.lights {
        let lp = DVec3::from_array(l.position.0);
        let ld = (lp - p).normalize();
        let blocked = match (&desc.objects[0], inside) {
            (ObjectDesc::Sphere { .. }, false) => n.dot(ld) < 0.0,
            _ => false,
        };
        if blocked {
            continue;
        }
        let hv = (ld + v).normalize();
        col += DVec3::from_array(l.diffuse.0) * DVec3::from_array(m.diffuse.0) * n.dot(ld).max(0.0)
            + DVec3::from_array(l.specular.0)
                * DVec3::from_array(m.specular.0)
                * n.dot(hv).max(0.0).powf(m.shininess.0);
    }
    Some(col.to_array())
}

/// Renders with one centred sample per pixel and compares every pixel the
/// analytic model covers. Returns how many pixels were checked.
fn check_against_analytic(desc: &SceneDesc, precision: Precision, tol: f64) -> usize {
    let mut settings = desc.render;
    settings.samples = 1;
    settings.max_depth = 0;
    let img = render_with(desc, &settings, precision).resolve();
    let mut checked = 0;
    let mut worst = (0.0f64, 0, 0);
    for py in 0..settings.height {
        for px in 0..settings.width {
            let Some(want) = analytic(desc, &settings, px, py) else {
                continue;
            };
            let got = img[(py * settings.width + px) as usize];
            let err = (0..3)
                .map(|c| (got[c] as f64 - want[c]).abs())
                .fold(0.0, f64::max);
            if err > worst.0 {
                worst = (err, px, py);
            }
            checked += 1;
        }
    }
    assert!(
        worst.0 <= tol,
        "{precision:?}: pixel ({}, {}) differs from the analytic shading by {} (tolerance {tol})",
        worst.1,
        worst.2,
        worst.0
    );
    checked
}

// f32 shading of a hit point is accurate to a few ulps of the colour;
// 2e-4 leaves room for the pow() in the specular term. Acne would show as
// an error of a whole light's contribution (~0.5).
const F32_TOL: f64 = 2e-4;
// The f64 path is checked through the film, which resolves to f32.
const F64_TOL: f64 = 1e-6;

#[test]
fn shadow_rays_from_a_sphere_never_hit_it_again() {
    let s = SPHERE_SELF_SHADOW.scene();
    assert!(check_against_analytic(&s, Precision::F32, F32_TOL) > 1000);
    check_against_analytic(&s, Precision::F64, F64_TOL);
}

#[test]
fn shadow_rays_from_a_plane_never_hit_it_again_even_grazing() {
    let s = GRAZING_PLANE.scene();
    assert!(check_against_analytic(&s, Precision::F32, F32_TOL) > 2000);
    check_against_analytic(&s, Precision::F64, F64_TOL);
}

#[test]
fn inside_a_sphere_lit_from_inside() {
    let s = INSIDE_SPHERE.scene();
    assert!(check_against_analytic(&s, Precision::F32, F32_TOL) > 9000);
    check_against_analytic(&s, Precision::F64, F64_TOL);
}

#[test]
fn tiny_sphere_far_from_the_origin() {
    let s = TINY_FAR_SPHERE.scene();
    assert!(check_against_analytic(&s, Precision::F32, F32_TOL) > 300);
    check_against_analytic(&s, Precision::F64, F64_TOL);
}

#[test]
fn huge_sphere_far_from_the_origin() {
    let s = HUGE_FAR_SPHERE.scene();
    // In f32 the centre (1e6 from the camera) is quantised to 0.06 units, which
    // moves the surface seen from 3 units away and so its shading slightly;
    // acne would be an error of a whole light (~0.5).
    assert!(check_against_analytic(&s, Precision::F32, 5e-3) > 2000);
    check_against_analytic(&s, Precision::F64, F64_TOL);
}

#[test]
fn huge_sphere_as_a_floor_has_no_acne_and_casts_correct_shadows() {
    // A radius-1e6 sphere used as ground, with a small sphere on it. The
    // floor's f32 centre is quantised to 0.06 units, so any method that
    // re-intersects the floor from its own surface speckles here.
    let src = HUGE_SPHERE_FLOOR_SCENE;
    let s = scene(src);
    for p in [Precision::F32, Precision::F64] {
        let img = render(&s, p).resolve();
        assert_huge_sphere_floor_lit_without_acne(&format!("{p:?}"), &img);
    }
}

#[test]
fn light_on_a_surface_and_inside_a_sphere() {
    // Light lying exactly on the floor plane, and a sphere beside it.
    let src = LIGHT_ON_SURFACE_SCENE;
    let s = scene(src);
    let f32img = render(&s, Precision::F32).resolve();
    let f64img = render(&s, Precision::F64).resolve();
    assert_finite(&f32img);
    let d = diff(&f32img, &f64img, 1e-3);
    // Silhouette samples may flip between hit and miss in the last bit: a few pixels.
    assert!(
        d.over * 1000 <= d.pixels,
        "{} of {} pixels differ by > 1e-3 between f32 and f64",
        d.over,
        d.pixels
    );
    assert!(d.mean < 1e-4, "mean f32/f64 difference {}", d.mean);
    // The second light sits at the centre of the small sphere: it lights nothing outside
    // it. The floor's N.L with the first light (on the floor) is 0. So the floor
    // receives only ambient: exactly 0.1 everywhere it is seen.
    let floor_px = f64img[95 * 128 + 2]; // bottom-left corner: floor
    assert!(
        (floor_px[0] - 0.1).abs() < 1e-6,
        "floor corner = {floor_px:?}"
    );
    // The big sphere's side facing the first light is lit.
    let lit = f64img.iter().filter(|p| p[0] > 0.3).count();
    assert!(
        lit > 15,
        "the sphere beside the light on the floor is not lit ({lit} pixels)"
    );
}

fn trace_from_below(angle_from_normal_deg: f64) -> ([f64; 3], RayCounts) {
    let s = glass_plane_scene("[camera]\nposition = [0, -1, 0]\nlook_at = [0, 0, 1]");
    let PreparedFrame::F64(world) = PreparedFrame::build(&s, &s.render, 0, Precision::F64).unwrap()
    else {
        unreachable!()
    };
    let a = angle_from_normal_deg.to_radians();
    // World origin is the camera at (0, -1, 0): start the ray there, aimed up at the plane.
    let ray = Ray::<f64>::new(DVec3::ZERO, DVec3::new(0.0, a.cos(), a.sin()));
    let mut rays = RayCounts::default();
    let c = trace(&world, &Static, &ray, 0, (), PrimId::NONE, &mut rays);
    (c.to_array(), rays)
}

#[test]
fn total_internal_reflection_at_and_past_the_critical_angle() {
    let critical = (1.0f64 / 1.5).asin().to_degrees(); // 41.81 degrees
    // Before the critical angle: 0.9 of red (refracted to the sky) + 0.1 of blue.
    let (c, rays) = trace_from_below(critical - 0.01);
    assert_eq!(rays.refraction, 1);
    assert!(
        (c[0] - 0.9).abs() < 1e-9 && (c[2] - 0.1).abs() < 1e-9,
        "below critical: {c:?}"
    );
    // Just past it: no refraction at all, the whole 0.9 + 0.1 reflects to the blue below.
    let (c, rays) = trace_from_below(critical + 0.01);
    assert_eq!(rays.refraction, 0);
    assert_eq!(c, [0.0, 0.0, 1.0], "past critical: {c:?}");
    // Exactly at it the refracted ray is tangent: finite, no NaN, whatever it sees.
    let (c, _) = trace_from_below(critical);
    assert!(
        c.iter().all(|v| v.is_finite() && *v >= 0.0),
        "at critical: {c:?}"
    );
}

#[test]
fn nested_and_touching_glass_spheres() {
    let (s, settings) = nested_glass_scene();
    let a = render_with(&s, &settings, Precision::F32).resolve();
    let b = render_with(&s, &settings, Precision::F64).resolve();
    assert_finite(&a);
    // Speckles from self-intersection would be isolated pixels far off the
    // reference. Silhouettes seen through several refractions may flip a
    // sample: allow 1% of pixels over 1/255, none over 0.25.
    let d = diff(&a, &b, 1.0 / 255.0);
    assert!(
        d.over * 100 <= d.pixels,
        "{} of {} pixels differ by > 1/255",
        d.over,
        d.pixels
    );
    assert!(d.max < 0.25, "largest f32/f64 difference {}", d.max);
}

#[test]
fn tangent_and_grazing_rays_on_a_sphere_do_not_produce_nan() {
    use tracer_core::geometry::Sphere;
    let s = Sphere::<f32> {
        center: glam::Vec3A::new(0.0, 0.0, 10.0),
        radius: 1.0,
        material: 0,
    };
    for i in 0..10_000 {
        // Rays whose distance from the centre sweeps 1 +- 1e-6 (tangent).
        let off = 1.0 - 1e-6 + 2e-6 * i as f32 / 10_000.0;
        let r = Ray::<f32>::new(glam::Vec3A::new(off, 0.0, 0.0), glam::Vec3A::Z);
        if let Some(t) = s.intersect(&r, f32::INFINITY, false) {
            assert!(
                t.is_finite() && (t - 10.0).abs() < 0.01,
                "tangent ray {off}: t = {t}"
            );
        }
    }
}
