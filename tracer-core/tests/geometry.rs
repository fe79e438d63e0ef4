//! The geometry tests, written once: one table of rays per primitive kind
//! (sphere, plane, triangle) with the distance each must report, run
//! against every implementation of that test: the scalar one in f64 and
//! f32 (`Sphere`/`Plane`/`Triangle::intersect`), the 4-wide sphere packs
//! and triangle rows (`SpherePack`, `TriangleRay::edges4`), the stream
//! renderer's SIMD lanes (`render::cpu::kernels::closest_hits`), and the
//! world's queries, one ray and a packet at a time (`World::closest_hit`,
//! `World::closest_hits`). A new implementation joins by adding a column.

mod common;

use common::scene;
use glam::{DVec3, Vec3A, Vec4};
use tracer_core::geometry::{Plane, PrimId, Sphere, SpherePack};
use tracer_core::math::{Ray, Real};
use tracer_core::render::cpu::kernels::{Prims, RaySoa, closest_hits};
use tracer_core::render::{Precision, PreparedFrame};
use tracer_core::triangle::{Triangle, TriangleRay};
use tracer_core::world::World;

/// One ray and the answer every implementation must give.
struct Case {
    name: &'static str,
    origin: [f64; 3],
    dir: [f64; 3],
    /// Exclusive limit (`f64::INFINITY`: none).
    t_max: f64,
    /// The ray starts on the primitive (a secondary ray from its surface).
    from_surface: bool,
    /// The distance, or `None` for a miss.
    want: Option<f64>,
    /// Largest error allowed in f32, absolute (f64 answers must be within 1e-9 of it).
    tol32: f64,
}

const INF: f64 = f64::INFINITY;

const fn case(name: &'static str, origin: [f64; 3], dir: [f64; 3], want: Option<f64>) -> Case {
    Case {
        name,
        origin,
        dir,
        t_max: INF,
        from_surface: false,
        want,
        tol32: 1e-5,
    }
}

/// A sphere (radius, centre) and the cases asked of it.
type SphereCases = ((f64, [f64; 3]), Vec<Case>);

/// Sphere of radius `r` at `c` and its cases.
fn sphere_cases() -> Vec<SphereCases> {
    vec![
        (
            (1.0, [0.0, 0.0, 5.0]),
            vec![
                case("near root", [0.0; 3], [0.0, 0.0, 1.0], Some(4.0)),
                case(
                    "far root from inside",
                    [0.0, 0.0, 5.0],
                    [0.0, 0.0, 1.0],
                    Some(1.0),
                ),
                case("behind the origin", [0.0, 0.0, 7.0], [0.0, 0.0, 1.0], None),
                case("beside", [0.0; 3], [0.0, 1.0, 0.0], None),
                Case {
                    t_max: 4.0,
                    ..case("limit is exclusive", [0.0; 3], [0.0, 0.0, 1.0], None)
                },
                Case {
                    t_max: 3.0,
                    ..case("beyond the limit", [0.0; 3], [0.0, 0.0, 1.0], None)
                },
            ],
        ),
        (
            (2.0, [0.0, 0.0, 0.0]),
            vec![
                Case {
                    from_surface: true,
                    ..case(
                        "from the surface inwards",
                        [0.0, 0.0, -2.0],
                        [0.0, 0.0, 1.0],
                        Some(4.0),
                    )
                },
                Case {
                    from_surface: true,
                    ..case(
                        "from the surface outwards",
                        [0.0, 0.0, -2.0],
                        [0.0, 0.0, -1.0],
                        None,
                    )
                },
            ],
        ),
        (
            // Radius 1e-4 seen from 1e5 away: the textbook b^2 - c form
            // cancels to garbage here in f32 (c ~ 1e10 has an ulp of ~1000).
            (1.0e-4, [0.0, 0.0, 1.0e5]),
            vec![
                Case {
                    tol32: 0.02,
                    ..case(
                        "tiny and far",
                        [0.0; 3],
                        [0.0, 0.0, 1.0],
                        Some(1.0e5 - 1.0e-4),
                    )
                },
                case(
                    "just beside tiny and far",
                    [2.0e-4, 0.0, 0.0],
                    [0.0, 0.0, 1.0],
                    None,
                ),
            ],
        ),
    ]
}

/// The plane y = 0 (normal +y) and its cases.
fn plane_cases() -> Vec<Case> {
    vec![
        case(
            "straight down",
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            Some(1.0),
        ),
        case("parallel above", [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], None),
        case("inside the plane", [0.0; 3], [1.0, 0.0, 0.0], None),
        case("away from it", [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], None),
        Case {
            tol32: 1e4,
            ..case("grazing", [0.0, 1.0, 0.0], [1.0, -1e-9, 0.0], Some(1e9))
        },
        Case {
            from_surface: true,
            ..case("from the surface", [0.0; 3], [0.0, 1.0, 0.0], None)
        },
    ]
}

/// The triangle at z = 5 (both windings are run) and its cases.
const TRIANGLE: [[f64; 3]; 3] = [[-1.0, -1.0, 5.0], [1.0, -1.0, 5.0], [0.0, 1.0, 5.0]];
fn triangle_cases() -> Vec<Case> {
    vec![
        case("through the middle", [0.0; 3], [0.0, 0.0, 1.0], Some(5.0)),
        Case {
            t_max: 5.0,
            ..case("limit is exclusive", [0.0; 3], [0.0, 0.0, 1.0], None)
        },
        case("away from it", [0.0; 3], [0.0, 0.0, -1.0], None),
        case("beside", [2.0, 0.0, 0.0], [0.0, 0.0, 1.0], None),
        case(
            "through an edge's far side",
            [0.0, 1.5, 0.0],
            [0.0, 0.0, 1.0],
            None,
        ),
    ]
}

fn v64(a: [f64; 3]) -> DVec3 {
    DVec3::from_array(a)
}
fn v32(a: [f64; 3]) -> Vec3A {
    Vec3A::new(a[0] as f32, a[1] as f32, a[2] as f32)
}

/// Checks one implementation's answer for `c`.
fn check(what: &str, c: &Case, got: Option<f64>, tol: f64) {
    match (c.want, got) {
        (None, None) => {}
        (Some(w), Some(g)) if (g - w).abs() <= tol => {}
        _ => panic!(
            "{what}, {}: got {got:?}, want {:?} (within {tol})",
            c.name, c.want
        ),
    }
}

/// A world of one primitive (the camera at the origin, so its
/// camera-relative coordinates are the scene's).
fn world<R: Real>(object: &str, precision: Precision) -> World<R> {
    let desc = scene(&format!(
        "[camera]\nposition = [0, 0, 0]\nlook_at = [0, 0, 1]\n[materials.m]\ndiffuse = [1, 1, 1]\n[[objects]]\n{object}\nmaterial = \"m\"\n"
    ));
    let frame = PreparedFrame::build(&desc, &desc.render, 0, precision).unwrap();
    let any: Box<dyn std::any::Any> = match frame {
        PreparedFrame::F32(w) => Box::new(w),
        PreparedFrame::F64(w) => Box::new(w),
    };
    *any.downcast::<World<R>>().expect("the precision asked for")
}

/// The world's answers (one ray, then a packet of two copies), t_max
/// applied: the world has no limit of its own.
fn world_answers<R: Real>(w: &World<R>, c: &Case, ray: Ray<R>, id: PrimId) -> [Option<f64>; 2] {
    let skip = if c.from_surface { id } else { PrimId::NONE };
    let limit = |h: Option<(R, PrimId)>| {
        h.map(|(t, got)| {
            assert_eq!(got, id, "{}", c.name);
            t.to_f64()
        })
        .filter(|&t| t < c.t_max)
    };
    let mut out = [None; 2];
    w.closest_hits(&[ray, ray], skip, &mut out);
    assert_eq!(out[0].map(|h| h.0.to_f64()), out[1].map(|h| h.0.to_f64()));
    [limit(w.closest_hit(&ray, skip)), limit(out[0])]
}

/// The SIMD lanes' answer (8 lanes, all the same ray), t_max applied.
fn kernel_answer(w: &World<f32>, c: &Case, id: PrimId) -> Option<f64> {
    let prims = Prims::new(w);
    let mut rays = RaySoa::default();
    rays.grow(8);
    let (o, d) = (v32(c.origin), v32(c.dir).normalize());
    for l in 0..8 {
        (rays.ox[l], rays.oy[l], rays.oz[l]) = (o.x, o.y, o.z);
        (rays.dx[l], rays.dy[l], rays.dz[l]) = (d.x, d.y, d.z);
        rays.skip[l] = if c.from_surface { id.0 } else { PrimId::NONE.0 };
    }
    let (mut t, mut ids) = (Vec::new(), Vec::new());
    closest_hits::<8>(&prims, &rays, 8, &mut t, &mut ids);
    assert!(
        t.iter().all(|&x| x.to_bits() == t[0].to_bits()),
        "{}",
        c.name
    );
    (ids[0] != PrimId::NONE.0)
        .then(|| {
            assert_eq!(ids[0], id.0, "{}", c.name);
            t[0] as f64
        })
        .filter(|&t| t < c.t_max)
}

/// The world's answers in f64 (within `tol64`) and f32, and the SIMD lanes'.
fn check_worlds(
    c: &Case,
    (w64, r64): (&World<f64>, Ray<f64>),
    (w32, r32): (&World<f32>, Ray<f32>),
    id: PrimId,
    tol64: f64,
) {
    let [one, packet] = world_answers(w64, c, r64, id);
    check("f64 world", c, one, tol64);
    check("f64 world packet", c, packet, tol64);
    let [one, packet] = world_answers(w32, c, r32, id);
    check("f32 world", c, one, c.tol32);
    check("f32 world packet", c, packet, c.tol32);
    check("f32 SIMD lanes", c, kernel_answer(w32, c, id), c.tol32);
}

#[test]
fn spheres_answer_the_table_in_every_implementation() {
    let id = PrimId::new(PrimId::SPHERE, 0);
    for ((r, center), cases) in sphere_cases() {
        let s64 = Sphere::<f64> {
            center: v64(center),
            radius: r,
            material: 0,
        };
        let s32 = Sphere::<f32> {
            center: v32(center),
            radius: r as f32,
            material: 0,
        };
        let pack = SpherePack::pack(&[s32])[0];
        let object = format!("type = \"sphere\"\ncenter = {center:?}\nradius = {r:e}");
        let (w64, w32) = (
            world::<f64>(&object, Precision::F64),
            world::<f32>(&object, Precision::F32),
        );
        for c in &cases {
            let r64 = Ray::new(v64(c.origin), v64(c.dir).normalize());
            let r32 = Ray::new(v32(c.origin), v32(c.dir).normalize());
            let t32 = c.t_max as f32;
            check(
                "f64 scalar",
                c,
                s64.intersect(&r64, c.t_max, c.from_surface),
                1e-9,
            );
            let got = s32.intersect(&r32, t32, c.from_surface).map(f64::from);
            check("f32 scalar", c, got, c.tol32);
            let o = [r32.origin.x, r32.origin.y, r32.origin.z].map(Vec4::splat);
            let d = [r32.dir.x, r32.dir.y, r32.dir.z].map(Vec4::splat);
            let lane = if c.from_surface { 0 } else { usize::MAX };
            let t = pack.intersect(o, d, t32, lane).x;
            check(
                "f32 pack",
                c,
                (t < f32::INFINITY).then_some(t as f64),
                c.tol32,
            );
            check_worlds(c, (&w64, r64), (&w32, r32), id, 1e-9);
        }
    }
}

#[test]
fn planes_answer_the_table_in_every_implementation() {
    let id = PrimId::new(PrimId::PLANE, 0);
    let p64 = Plane::<f64> {
        normal: DVec3::Y,
        distance: 0.0,
        material: 0,
    };
    let p32 = Plane::<f32> {
        normal: Vec3A::Y,
        distance: 0.0,
        material: 0,
    };
    let object = "type = \"plane\"\nnormal = [0, 1, 0]\ndistance = 0";
    let (w64, w32) = (
        world::<f64>(object, Precision::F64),
        world::<f32>(object, Precision::F32),
    );
    for c in &plane_cases() {
        let r64 = Ray::new(v64(c.origin), v64(c.dir).normalize());
        let r32 = Ray::new(v32(c.origin), v32(c.dir).normalize());
        check(
            "f64 scalar",
            c,
            p64.intersect(&r64, c.t_max, c.from_surface),
            1e-9 * c.tol32 / 1e-5,
        );
        let got = p32
            .intersect(&r32, c.t_max as f32, c.from_surface)
            .map(f64::from);
        check("f32 scalar", c, got, c.tol32);
        check_worlds(c, (&w64, r64), (&w32, r32), id, 1e-9 * c.tol32 / 1e-5);
    }
}

#[test]
fn triangles_answer_the_table_in_every_implementation_and_winding() {
    let [a, b, c3] = TRIANGLE;
    for (winding, vs) in [("ccw", [a, b, c3]), ("cw", [a, c3, b])] {
        let t64 = Triangle::new(vs.map(v64));
        let t32 = Triangle::new(vs.map(v32));
        for c in &triangle_cases() {
            let r64 = TriangleRay::new(&Ray::new(v64(c.origin), v64(c.dir).normalize()));
            let r32 = TriangleRay::new(&Ray::new(v32(c.origin), v32(c.dir).normalize()));
            let t_max = c.t_max as f32;
            check(
                &format!("f64 scalar {winding}"),
                c,
                t64.intersect(&r64, c.t_max),
                1e-9,
            );
            let scalar = t32.intersect(&r32, t_max);
            check(
                &format!("f32 scalar {winding}"),
                c,
                scalar.map(f64::from),
                c.tol32,
            );
            #[cfg(target_arch = "x86_64")]
            {
                // The 4-wide rows, the triangle in lane 2, finished as the tree's leaves do.
                let mut rows = tracer_core::triangle::Triangle4::default();
                rows.set(2, &t32);
                let e = r32.edges4(&rows, 0b0100);
                let got = if (e.exact >> 2) & 1 != 0 {
                    t32.intersect(&r32, t_max)
                } else if (e.candidates >> 2) & 1 != 0 {
                    tracer_core::triangle::finish(e.t_scaled[2], e.det[2], t_max)
                        .filter(|&t| t < t_max)
                } else {
                    None
                };
                assert_eq!(
                    got.map(f32::to_bits),
                    scalar.map(f32::to_bits),
                    "4-wide {winding}, {}",
                    c.name
                );
            }
        }
    }
}
