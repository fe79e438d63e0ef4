//! Meshes end to end: scene files with `type = "mesh"`, model loading,
//! watertightness, the BVH against brute force, and renders against
//! analytic references. Every mesh is generated here or committed under
//! tests/data (see its README for sources and licences).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tracer_core::film::WorkRegion;

use glam::DVec3;
use tracer_core::assets::Bundle;
use tracer_core::bvh::MAX_DEPTH;
use tracer_core::film::{Film, Rect, SampleRange};
use tracer_core::geometry::PrimId;
use tracer_core::math::{Ray, Real, Vector3};
use tracer_core::mesh::Mesh;
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::sampling::hash_u32;
use tracer_core::scene::SceneDesc;
use tracer_core::world::World;

mod common;
use common::meshgen::{icosphere, pathological_obj, tmpdir, write_obj};
use common::prereq::shared;

const HEADER: &str = r#"
[render]
width = 64
height = 48
samples = 4
max_depth = 3
[camera]
position = [0, 0.5, -5]
look_at = [0, 0, 0]
fov_y = 40
[world]
ambient = [0.1, 0.1, 0.1]
background = [0.05, 0.1, 0.2]
[materials.white]
ambient = [1, 1, 1]
diffuse = [0.7, 0.7, 0.7]
specular = [0.5, 0.5, 0.5]
shininess = 30
[materials.mirror]
diffuse = [0.1, 0.1, 0.1]
reflectivity = 0.6
[[lights]]
position = [-4, 5, -4]
"#;

fn render(scene: &SceneDesc, precision: Precision) -> (Vec<[f32; 3]>, Film) {
    let frame = PreparedFrame::build(scene, &scene.render, 0, precision).unwrap();
    render_frame(&frame)
}

/// The whole frame, on 2 CPU threads: its resolved pixels and its film.
fn render_frame(frame: &PreparedFrame) -> (Vec<[f32; 3]>, Film) {
    let r = frame.settings();
    let film = CpuRenderer::new(Some(2))
        .unwrap()
        .render(
            frame,
            WorkRegion::new(
                0,
                Rect::full(r.width, r.height),
                SampleRange::all(r.samples),
            ),
            &|_| {},
        )
        .unwrap();
    (film.resolve(), film)
}

fn world_of<R: Real>(scene: &SceneDesc) -> World<R> {
    World::build(scene, &scene.render, 0)
}

/// Direction to `target` from `origin`, in the precision's own arithmetic.
fn ray_to<R: Real>(origin: [f64; 3], target: [f64; 3]) -> Ray<R> {
    let o = R::V3::from_array(origin);
    Ray::new(o, (R::V3::from_array(target) - o).normalize())
}

/// Rays from inside and from outside a closed sphere mesh, aimed exactly at
/// its vertices, at points on its edges, and in random directions: none may
/// miss. Returns the number of misses.
fn count_leaks<R: Real>(
    world: &World<R>,
    verts: &[[f64; 3]],
    faces: &[[u32; 3]],
    center: [f64; 3],
    scale: f64,
) -> usize {
    let cam = world.camera_position;
    // Mesh vertices in the world's (camera-relative) frame.
    let at = |p: [f64; 3]| [0, 1, 2].map(|k| p[k] * scale + center[k] - cam[k]);
    let c = at([0.0; 3]);
    let mut targets: Vec<[f64; 3]> = verts.iter().map(|&p| at(p)).collect();
    for f in faces.iter().take(2000) {
        for k in 0..3 {
            let (a, b) = (at(verts[f[k] as usize]), at(verts[f[(k + 1) % 3] as usize]));
            for s in [0.5, 0.25, 1.0 / 3.0] {
                targets.push([0, 1, 2].map(|i| a[i] + (b[i] - a[i]) * s));
            }
        }
    }
    let mut misses = 0;
    for (i, tgt) in targets.iter().enumerate() {
        // From inside: the centre, and a point off-centre.
        for origin in [
            c,
            [c[0] + 0.1 * scale, c[1] - 0.2 * scale, c[2] + 0.05 * scale],
        ] {
            if world
                .closest_hit(&ray_to::<R>(origin, *tgt), PrimId::NONE)
                .is_none()
            {
                misses += 1;
            }
        }
        // From outside, at 3 radii in a pseudo-random direction, through the target.
        let h = hash_u32(i as u32);
        let d = DVec3::new(
            (h & 255) as f64 - 127.5,
            ((h >> 8) & 255) as f64 - 127.5,
            ((h >> 16) & 255) as f64 - 127.5,
        )
        .normalize();
        let dir_out = (DVec3::from_array(*tgt) - DVec3::from_array(c)).normalize();
        // Keep the target well inside the silhouette seen from the origin
        // (at 3 radii the silhouette is at 70.5 degrees from the axis).
        let d = (d * 0.5 + dir_out * 2.0).normalize();
        debug_assert!(d.dot(dir_out) > 0.8);
        let origin = (DVec3::from_array(c) + d * 3.0 * scale).to_array();
        if world
            .closest_hit(&ray_to::<R>(origin, *tgt), PrimId::NONE)
            .is_none()
        {
            misses += 1;
        }
    }
    for i in 0..20_000u32 {
        let h = [hash_u32(i * 3), hash_u32(i * 3 + 1), hash_u32(i * 3 + 2)];
        let d = R::V3::new(
            R::from_f64(h[0] as f64 / u32::MAX as f64 - 0.5),
            R::from_f64(h[1] as f64 / u32::MAX as f64 - 0.5),
            R::from_f64(h[2] as f64 / u32::MAX as f64 - 0.5),
        );
        if !(d.length() > R::ZERO) {
            continue;
        }
        if world
            .closest_hit(&Ray::new(R::V3::from_array(c), d.normalize()), PrimId::NONE)
            .is_none()
        {
            misses += 1;
        }
    }
    misses
}

#[test]
fn closed_sphere_mesh_never_leaks_through_edges_or_vertices() {
    let dir = tmpdir("leak");
    let (v, f) = icosphere(4);
    write_obj(&dir.join("ball.obj"), &v, &f, false);
    // Off the origin and rotated, so coordinates are not round numbers.
    let center = [0.3, -0.2, 1.7];
    let scale = 1.3;
    let src = format!(
        "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"ball.obj\"\ntranslate = {center:?}\nscale = {scale}\nmaterial = \"white\"\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("leak.toml")).unwrap();
    let w32 = world_of::<f32>(&scene);
    let w64 = world_of::<f64>(&scene);
    assert_eq!(w32.triangle_count(), f.len());
    assert!(w32.accel.is_some());
    assert_eq!(count_leaks(&w32, &v, &f, center, scale), 0, "f32 leaks");
    assert_eq!(count_leaks(&w64, &v, &f, center, scale), 0, "f64 leaks");
    // Same rays without the tree: the triangle test alone is watertight.
    let mut brute = w32.clone();
    brute.set_accel(Some(false));
    assert_eq!(
        count_leaks(&brute, &v, &f, center, scale),
        0,
        "f32 brute-force leaks"
    );
}

#[test]
fn bvh_equals_brute_force_for_random_rays_in_f32_and_f64() {
    let dir = tmpdir("brute");
    let (v, f) = icosphere(3);
    write_obj(&dir.join("ball.obj"), &v, &f, true);
    // A triangle soup of random slivers and big triangles, plus spheres and a plane.
    let mut soup = String::new();
    for i in 0..3000u32 {
        let r = |k: u32| (hash_u32(i * 16 + k) as f64 / u32::MAX as f64 - 0.5) * 4.0;
        let c = [r(0), r(1), r(2)];
        let size = if i % 10 == 0 { 1.5 } else { 0.1 };
        for k in 0..3 {
            writeln!(
                soup,
                "v {} {} {}",
                c[0] + r(3 + 3 * k) * size,
                c[1] + r(4 + 3 * k) * size,
                c[2] + r(5 + 3 * k) * size
            )
            .unwrap();
        }
        writeln!(soup, "f {} {} {}", 3 * i + 1, 3 * i + 2, 3 * i + 3).unwrap();
    }
    std::fs::write(dir.join("soup.obj"), soup).unwrap();
    let mut src = format!(
        "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"ball.obj\"\nmaterial = \"white\"\nrotate = {{ axis = [1, 1, 0], degrees = 30 }}\n\
         [[objects]]\ntype = \"mesh\"\npath = \"soup.obj\"\nmaterial = \"mirror\"\n\
         [[objects]]\ntype = \"plane\"\nnormal = [0, 1, 0]\ndistance = -2\nmaterial = \"white\"\n"
    );
    // Without spheres the f32 tree tests its leaves' triangles 4 at a time
    // (`Bvh::packets`); with them, one by one: check both.
    let meshes_only = SceneDesc::parse(&src, dir.join("brute.toml")).unwrap();
    for i in 0..20 {
        write!(src, "[[objects]]\ntype = \"sphere\"\ncenter = [{}, {}, 0.5]\nradius = 0.3\nmaterial = \"white\"\n", i % 5 - 2, i / 5 - 2).unwrap();
    }
    let scene = SceneDesc::parse(&src, dir.join("brute.toml")).unwrap();
    fn check<R: Real>(scene: &SceneDesc) {
        let tree = world_of::<R>(scene);
        assert!(tree.accel.is_some());
        let packed = !tree.accel.as_ref().unwrap().packets.is_empty();
        assert_eq!(
            packed,
            tree.spheres.is_empty() && std::mem::size_of::<R>() == 4
        );
        let mut brute = tree.clone();
        brute.set_accel(Some(false));
        let mut hits = 0;
        for i in 0..30_000u32 {
            let u = |k: u32| R::from_f64(hash_u32(i * 8 + k) as f64 / u32::MAX as f64 - 0.5);
            let o = R::V3::new(
                u(0) * R::from_f64(8.0),
                u(1) * R::from_f64(8.0),
                u(2) * R::from_f64(8.0) + R::from_f64(5.0),
            );
            let d = R::V3::new(u(3), u(4), u(5));
            if !(d.length() > R::ZERO) {
                continue;
            }
            let ray = Ray::new(o, d.normalize());
            let a = tree.closest_hit(&ray, PrimId::NONE);
            let b = brute.closest_hit(&ray, PrimId::NONE);
            // Same distance, bit for bit (same tests), and the same
            // primitive: ties go to the lower id in both (`PrimId::nearer`).
            assert_eq!(a, b, "ray {i}");
            hits += a.is_some() as u32;
            if let Some((t, id)) = a {
                // Shadow rays: occluded before the hit iff anything is nearer.
                let short = t * R::from_f64(0.999);
                assert_eq!(
                    tree.occluded(&ray, short, PrimId::NONE),
                    brute.occluded(&ray, short, PrimId::NONE),
                    "ray {i}"
                );
                assert!(tree.occluded(&ray, t * R::from_f64(1.001), PrimId::NONE));
                // A ray starting on the hit primitive never hits it again.
                assert_eq!(tree.closest_hit(&ray, id), brute.closest_hit(&ray, id));
            }
        }
        assert!(hits > 15_000, "too few hits ({hits}) to test much");
    }
    check::<f32>(&scene);
    check::<f64>(&scene);
    check::<f32>(&meshes_only);
    check::<f64>(&meshes_only);
}

/// Mean absolute difference over channels, and the fraction of pixels that
/// differ by more than `tol` in some channel.
fn compare(a: &[[f32; 3]], b: &[[f32; 3]], tol: f32) -> (f32, f32) {
    let mut sum = 0.0;
    let mut off = 0;
    for (p, q) in a.iter().zip(b) {
        let d = (0..3).map(|k| (p[k].min(1.0) - q[k].min(1.0)).abs());
        let m = d.clone().fold(0.0f32, f32::max);
        sum += d.sum::<f32>();
        off += (m > tol) as usize;
    }
    (sum / (3 * a.len()) as f32, off as f32 / a.len() as f32)
}

#[test]
fn smooth_mesh_sphere_renders_like_the_analytic_sphere() {
    let dir = tmpdir("smooth");
    let (v, f) = icosphere(5); // 20480 triangles
    write_obj(&dir.join("ball.obj"), &v, &f, true);
    let rest =
        "[[objects]]\ntype = \"plane\"\nnormal = [0, 1, 0]\ndistance = -1\nmaterial = \"mirror\"\n";
    let mesh = SceneDesc::parse(
        &format!("{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"ball.obj\"\nmaterial = \"white\"\n{rest}"),
        dir.join("m.toml"),
    )
    .unwrap();
    let sphere = SceneDesc::parse(
        &format!("{HEADER}\n[[objects]]\ntype = \"sphere\"\ncenter = [0, 0, 0]\nradius = 1\nmaterial = \"white\"\n{rest}"),
        dir.join("s.toml"),
    )
    .unwrap();
    // The same ball without its normals, shaded flat.
    write_obj(&dir.join("facets.obj"), &v, &f, false);
    let facets = SceneDesc::parse(
        &format!("{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"facets.obj\"\nmaterial = \"white\"\n{rest}"),
        dir.join("f.toml"),
    )
    .unwrap();
    for precision in [Precision::F32, Precision::F64] {
        let (a, fa) = render(&mesh, precision);
        let (b, _) = render(&sphere, precision);
        assert_eq!(fa.nonfinite, 0);
        let (mean, off) = compare(&a, &b, 0.05);
        // Tolerance: the inscribed polyhedron is up to 0.1% smaller, which
        // moves silhouette pixels; shading within 0.05 nearly everywhere.
        assert!(
            mean < 0.004 && off < 0.03,
            "{precision:?}: mean {mean}, {off} of pixels off by > 0.05"
        );
        // Its vertex normals are used: the flat-shaded facets are
        // measurably farther from the sphere (their highlights step).
        let (flat, _) = compare(&render(&facets, precision).0, &b, 0.05);
        assert!(
            flat > 2.0 * mean,
            "{precision:?}: smooth {mean} against flat {flat}"
        );
    }
}

#[test]
fn mesh_floor_renders_like_the_plane_it_tessellates() {
    // A 40x40 grid of quads (3200 triangles) vs. the analytic plane: shadow
    // rays and reflections start on triangles (self-skip and neighbours).
    let dir = tmpdir("floor");
    let n = 40;
    let mut v = Vec::new();
    let mut f = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            // 2000 units across: its far edge is within a pixel of the horizon.
            v.push([
                -1000.0 + 2000.0 * i as f64 / n as f64,
                0.0,
                -1000.0 + 2000.0 * j as f64 / n as f64,
            ]);
        }
    }
    for j in 0..n {
        for i in 0..n {
            let a = (j * (n + 1) + i) as u32;
            let (b, c, d) = (a + 1, a + n as u32 + 2, a + n as u32 + 1);
            f.push([a, d, c]);
            f.push([a, c, b]); // counter-clockwise seen from above: normal +y
        }
    }
    write_obj(&dir.join("floor.obj"), &v, &f, false);
    let ball =
        "[[objects]]\ntype = \"sphere\"\ncenter = [0, 0, 0]\nradius = 0.8\nmaterial = \"white\"\n";
    let mesh = SceneDesc::parse(
        &format!("{HEADER}\n{ball}[[objects]]\ntype = \"mesh\"\npath = \"floor.obj\"\ntranslate = [0, -0.8, 0]\nmaterial = \"mirror\"\n"),
        dir.join("m.toml"),
    )
    .unwrap();
    let plane = SceneDesc::parse(
        &format!("{HEADER}\n{ball}[[objects]]\ntype = \"plane\"\nnormal = [0, 1, 0]\ndistance = -0.8\nmaterial = \"mirror\"\n"),
        dir.join("p.toml"),
    )
    .unwrap();
    let (a, fa) = render(&mesh, Precision::F32);
    let (b, _) = render(&plane, Precision::F32);
    assert_eq!(fa.nonfinite, 0);
    let (mean, off) = compare(&a, &b, 0.02);
    assert!(
        mean < 0.002 && off < 0.01,
        "mean {mean}, {off} of pixels off"
    );
}

#[test]
fn pathological_meshes_build_within_the_stack_and_render_without_nan() {
    let dir = tmpdir("patho");
    let s = pathological_obj();
    std::fs::write(dir.join("bad.obj"), s).unwrap();
    let src = format!(
        "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"bad.obj\"\nmaterial = \"mirror\"\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("p.toml")).unwrap();
    for precision in [Precision::F32, Precision::F64] {
        let frame = PreparedFrame::build(&scene, &scene.render, 0, precision).unwrap();
        let stats = match &frame {
            PreparedFrame::F32(w) => {
                // The point and the segment, and slivers whose width rounds away in f32.
                assert!(w.degenerate_triangles >= 2);
                w.accel.as_ref().unwrap().stats
            }
            PreparedFrame::F64(w) => w.accel.as_ref().unwrap().stats,
        };
        assert!(stats.depth < MAX_DEPTH, "{stats:?}");
        let (img, film) = render(&scene, precision);
        assert_eq!(film.nonfinite, 0);
        assert!(img.iter().flatten().all(|c| c.is_finite()));
        // The huge triangle fills the background: no pixel sees the sky colour.
        assert!(img.iter().all(|p| *p != [0.05, 0.1, 0.2]));
    }
}

#[test]
fn transforms_place_vertices_as_documented() {
    let dir = tmpdir("xf");
    std::fs::write(dir.join("t.obj"), "v 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n").unwrap();
    let src = format!(
        "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"t.obj\"\nmaterial = \"white\"\nscale = [2, 3, 4]\n\
         rotate_euler = [0, 0, 90]\nrotate = {{ axis = [0, 2, 0], degrees = 90 }}\ntranslate = [10, 20, 30]\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("t.toml")).unwrap();
    let w = world_of::<f64>(&scene);
    let cam = DVec3::from_array(w.camera_position);
    let got: Vec<[f64; 3]> = w
        .triangle(0)
        .vertices()
        .iter()
        .map(|p| (*p + cam).to_array())
        .collect();
    // scale, then z 90 (x->y, y->-x), then y 90 (x->-z, z->x), then translate.
    let want = [[10.0, 22.0, 30.0], [10.0, 20.0, 33.0], [14.0, 20.0, 30.0]];
    for (g, w) in got.iter().zip(want) {
        assert!(
            (DVec3::from_array(*g) - DVec3::from_array(w)).length() < 1e-12,
            "{got:?}"
        );
    }
    // A mirroring scale keeps the geometric normal outward (winding flipped back).
    let mirrored = SceneDesc::parse(
        &src.replace("scale = [2, 3, 4]", "scale = [-1, 1, 1]"),
        dir.join("t.toml"),
    )
    .unwrap();
    let wm = world_of::<f64>(&mirrored);
    let plain = SceneDesc::parse(
        &src.replace("scale = [2, 3, 4]", "scale = 1"),
        dir.join("t.toml"),
    )
    .unwrap();
    let wp = world_of::<f64>(&plain);
    let c = |w: &World<f64>| {
        let v = w.triangle(0).vertices();
        (v[0] + v[1] + v[2]) * (1.0 / 3.0)
    };
    // Outward = away from the model origin (which maps to the translation).
    let origin = DVec3::new(10.0, 20.0, 30.0) - cam;
    assert!(wm.triangle(0).normal().dot(c(&wm) - origin) > 0.0);
    assert!(wp.triangle(0).normal().dot(c(&wp) - origin) > 0.0);
}

fn scene_err(src: &str, dir: &Path) -> String {
    SceneDesc::parse(src, dir.join("bad.toml"))
        .unwrap_err()
        .to_string()
}

#[test]
fn bad_mesh_objects_are_rejected_with_file_line_and_problem() {
    let dir = tmpdir("errors");
    std::fs::write(dir.join("ok.obj"), "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    std::fs::write(
        dir.join("broken.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n",
    )
    .unwrap();
    std::fs::write(dir.join("broken.gltf"), "{ \"asset\": { \"version\": \"2.0\" }, \"buffers\": [ { \"byteLength\": 12, \"uri\": \"data:application/octet-stream;base64,AAAA\" } ] }").unwrap();
    let obj = |extra: &str| {
        format!(
            "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"ok.obj\"\nmaterial = \"white\"\n{extra}"
        )
    };
    let line = HEADER.lines().count() + 2; // the [[objects]] header line
    let e = scene_err(&obj("").replace("ok.obj", "missing.obj"), &dir);
    assert!(
        e.starts_with(&format!("{}:{}:", dir.join("bad.toml").display(), line + 2)),
        "{e}"
    );
    assert!(
        e.contains("objects[0] (mesh).path: cannot load model: ")
            && e.contains("missing.obj: cannot read model file"),
        "{e}"
    );
    let e = scene_err(&obj("").replace("ok.obj", "broken.obj"), &dir);
    assert!(
        e.contains("objects[0] (mesh).path: cannot load model: ")
            && e.contains("broken.obj: invalid OBJ: line 4: face parse error: \"x\" is not a vertex reference (v, v/vt, v//vn or v/vt/vn)"),
        "{e}"
    );
    let e = scene_err(&obj("").replace("ok.obj", "broken.gltf"), &dir);
    assert!(
        e.contains("broken.gltf: invalid glTF: buffer 0 has 3 bytes, the file declares 12"),
        "{e}"
    );
    let e = scene_err(&obj("scale = 0"), &dir);
    assert!(
        e.contains("objects[0] (mesh).scale: must be finite and non-zero"),
        "{e}"
    );
    let e = scene_err(&obj("rotate = { axis = [0, 0, 0], degrees = 3 }"), &dir);
    assert!(
        e.contains("objects[0] (mesh).rotate: axis must be a finite, non-zero vector"),
        "{e}"
    );
    let e = scene_err(&obj("rotate = { axis = [0, 1, 0], degree = 3 }"), &dir);
    assert!(e.contains("unknown field `degree`"), "{e}");
    let e = scene_err(&obj("colour = 1"), &dir);
    assert!(e.contains("unknown field `colour`"), "{e}");
    let e = scene_err(
        &obj("").replace("material = \"white\"", "material = \"chalk\""),
        &dir,
    );
    assert!(
        e.contains("objects[0] (mesh).material: unknown material \"chalk\""),
        "{e}"
    );
    let e = scene_err(&obj("scale = [1, 2]"), &dir);
    assert!(e.contains("scale") || e.contains("three numbers"), "{e}");
}

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../examples/models")
        .join(name)
}

#[test]
fn committed_models_load_with_their_materials() {
    // Cornell box (MIT, see examples/models/README.md): 18 quads -> 36 triangles + MTL colours.
    let m = tracer_core::mesh::Mesh::load(&data("cornell_box.obj"), true).unwrap();
    assert_eq!(m.triangles.len(), 36);
    let names: Vec<&str> = m.materials.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["white", "red", "green", "blue", "light"]);
    assert_eq!(m.materials[1].1.diffuse.0, [1.0, 0.0, 0.0]);
    assert_eq!(m.materials[4].1.ambient.0, [20.0, 20.0, 20.0]);
    // Box.gltf (CC BY 4.0, Cesium): 12 triangles with normals, a red PBR material, a node matrix.
    let b = tracer_core::mesh::Mesh::load(&data("Box.gltf"), true).unwrap();
    assert_eq!(b.triangles.len(), 12);
    assert_eq!(b.normals.len(), b.positions.len());
    // baseColorFactor [0.8, 0, 0]; metallic and roughness default to 1: a rough red metal, no mirror.
    let mat = &b.materials[b.triangle_materials[0] as usize].1;
    let d = mat.diffuse.0;
    assert!(
        (d[0] - 0.8).abs() < 1e-6 && d[1] == 0.0 && d[2] == 0.0,
        "{mat:?}"
    );
    assert_eq!(mat.reflectivity.0, 0.0);
    assert!(
        (mat.specular.0[0] - 0.8).abs() < 1e-6 && mat.specular.0[1] == 0.0,
        "{mat:?}"
    );
    // The node's matrix swaps y and z (y-up from z-up): the box stays the unit cube.
    for p in &b.positions {
        assert!(p.iter().all(|c| (c.abs() - 0.5).abs() < 1e-6), "{p:?}");
    }
}

/// examples/cornell.toml (a model file) at `size` x `size`, `samples` spp.
fn cornell(size: u32, samples: u32) -> SceneDesc {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/cornell.toml");
    let mut scene = SceneDesc::load(&path).unwrap();
    scene.render.width = size;
    scene.render.height = size;
    scene.render.samples = samples;
    scene
}

#[test]
fn cornell_example_renders_its_coloured_walls() {
    let scene = cornell(48, 1);
    let (img, film) = render(&scene, Precision::F32);
    assert_eq!(film.nonfinite, 0);
    let px = |x: usize, y: usize| img[y * 48 + x];
    // Camera looks down +z, so +x is to the left: the red wall (x = 552)
    // is on the left, the green one (x = 0) on the right, as in the original.
    let (left, right) = (px(3, 24), px(44, 24));
    assert!(
        left[0] > 0.1 && left[0] > 4.0 * left[1] && left[0] > 4.0 * left[2],
        "left wall {left:?}"
    );
    assert!(
        right[1] > 0.1 && right[1] > 4.0 * right[0] && right[1] > 4.0 * right[2],
        "right wall {right:?}"
    );
    // The light panel glows (Ka 20 x ambient 0.05), the back wall is lit grey-white.
    let back = px(24, 12);
    assert!(
        back.iter().all(|&c| c > 0.2) && (back[0] - back[2]).abs() < 0.1,
        "back wall {back:?}"
    );
    // The front face of the tall block faces away from the light: only ambient (Ka 0).
    // The tall block's front face: Ka 0, and the light grazes it (it lies
    // almost in the face's plane), so it stays nearly black.
    assert!(
        px(24, 30).iter().all(|&c| c < 0.05),
        "block front {:?}",
        px(24, 30)
    );
}

/// A scene rendered once (`PreparedFrame::build_owned`, what `tessera
/// render` uses) frees its models before the tree's build and renders the
/// same film, bit for bit, as one built from a kept description.
#[test]
fn a_scene_built_once_frees_its_models_and_renders_the_same() {
    let scene = cornell(32, 2);
    let (kept, _) = render(&scene, Precision::F32);
    let owned = scene.clone();
    let weak: Vec<_> = owned
        .models()
        .iter()
        .flatten()
        .map(Arc::downgrade)
        .collect();
    assert!(!weak.is_empty(), "the Cornell box is a model file");
    drop(scene);
    let settings = owned.render;
    let frame = PreparedFrame::build_owned(owned, &settings, 0, Precision::F32).unwrap();
    assert!(
        weak.iter().all(|w| w.upgrade().is_none()),
        "no model outlives the build"
    );
    assert!(render_frame(&frame).0 == kept, "the same film");
}

/// A big world (at least `GIVE_UP_TRIANGLES_FROM` `f32` triangles) holds
/// them as corners into shared vertices alone, its tree built over those
/// and tested without packets: every ray finds the hit the brute-force
/// test of every triangle finds, bit for bit, its shadow rays agree, and
/// its vertex normals shade it smoothly. A 370 x 370 wavy grid with
/// normals: 273,800 triangles.
#[test]
fn a_big_world_hits_as_the_brute_force_from_its_corners() {
    let dir = tmpdir("big-world");
    let n = 370u32;
    let mut v = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            let (x, z) = (
                i as f64 / n as f64 * 4.0 - 2.0,
                j as f64 / n as f64 * 4.0 - 2.0,
            );
            v.push([x, 0.2 * (3.0 * x).sin() * (2.0 * z).cos() - 1.0, z]);
        }
    }
    let at = |i: u32, j: u32| j * (n + 1) + i;
    let mut f = Vec::new();
    for j in 0..n {
        for i in 0..n {
            f.push([at(i, j), at(i, j + 1), at(i + 1, j)]);
            f.push([at(i + 1, j), at(i, j + 1), at(i + 1, j + 1)]);
        }
    }
    // Normals: write_obj's `vn` repeats the vertex; the grid's own go here.
    let mut obj = String::new();
    for p in &v {
        writeln!(obj, "v {} {} {}", p[0], p[1], p[2]).unwrap();
        let (x, z) = (p[0], p[2]);
        let (dx, dz) = (
            0.6 * (3.0 * x).cos() * (2.0 * z).cos(),
            -0.4 * (3.0 * x).sin() * (2.0 * z).sin(),
        );
        writeln!(obj, "vn {} 1 {}", -dx, -dz).unwrap();
    }
    for t in &f {
        let [a, b, c] = t.map(|i| i + 1);
        writeln!(obj, "f {a}//{a} {b}//{b} {c}//{c}").unwrap();
    }
    std::fs::write(dir.join("grid.obj"), obj).unwrap();
    let scene = SceneDesc::parse(
        &format!(
            "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"grid.obj\"\nmaterial = \"white\"\n"
        ),
        dir.join("grid.toml"),
    )
    .unwrap();
    let world = world_of::<f32>(&scene);
    assert!(world.triangle_count() >= tracer_core::world::GIVE_UP_TRIANGLES_FROM);
    let tree = world.accel.as_ref().expect("a tree");
    assert!(tree.packets.is_empty(), "a big world's tree has no packets");
    assert!(
        world.gathered_triangles().is_none(),
        "nor gathered triangles"
    );
    let mut brute = world.clone();
    brute.set_accel(Some(false));
    assert!(brute.accel.is_none());
    let mut hits = 0;
    for i in 0..600u32 {
        let u = |k: u32| hash_u32(i * 8 + k) as f64 / u32::MAX as f64;
        // From above the grid, down at it, in the camera-relative world.
        let o = [u(0) * 4.0 - 2.0, 1.5 + u(1), u(2) * 4.0 - 2.0 + 5.0];
        // (The grid lies at y = -1.5 there, z from 3 to 7.)
        let target = [u(3) * 4.0 - 2.0, -1.5, u(4) * 4.0 - 2.0 + 5.0];
        let ray = ray_to::<f32>(o, target);
        let a = world.closest_hit(&ray, PrimId::NONE);
        assert_eq!(a, brute.closest_hit(&ray, PrimId::NONE), "ray {i}");
        if let Some((t, id)) = a {
            hits += 1;
            assert_eq!(
                world.occluded(&ray, t * 0.999, PrimId::NONE),
                brute.occluded(&ray, t * 0.999, PrimId::NONE),
                "ray {i}"
            );
            let p = ray.at(t);
            let n = world.triangle_normal(id.index());
            let v = -ray.dir;
            let n = if n.dot(v) < 0.0 { -n } else { n };
            // Smooth: the interpolated normal, not the facet's.
            let s = world.shading_normal(id, p, n, v);
            assert!(
                s != n && (s.length() - 1.0).abs() < 1e-5,
                "ray {i}: {s} {n}"
            );
        }
    }
    assert!(hits > 500, "too few hits ({hits}) to test much");
}

/// A small world keeps its triangles' unit normals (computed once, after
/// the tree's reordering): each equals, bit for bit, the normal computed
/// from the triangle at a hit, as a big world does.
#[test]
fn kept_triangle_normals_are_the_computed_ones() {
    let world = world_of::<f32>(&cornell(32, 1));
    assert!(world.triangle_count() > 0);
    assert!(world.triangle_count() < tracer_core::world::GIVE_UP_TRIANGLES_FROM);
    for i in 0..world.triangle_count() {
        assert_eq!(
            world.triangle_normal(i).to_array().map(f64::to_bits),
            world.triangle(i).normal().to_array().map(f64::to_bits),
            "triangle {i}"
        );
    }
}

#[test]
fn sphere_scenes_render_identically_with_and_without_the_bvh() {
    // The complexity scenes (9 spheres and a floor) with a BVH forced on,
    // against the plain sphere loop: the very same film, bit for bit.
    for name in ["chrome-9", "glass-9", "emerald-9"] {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join(format!("../examples/complexity/{name}.toml"));
        let mut scene = SceneDesc::load(&path).unwrap();
        scene.render.width = 80;
        scene.render.height = 60;
        for precision in [Precision::F32, Precision::F64] {
            let frame = PreparedFrame::build(&scene, &scene.render, 0, precision).unwrap();
            let (with, without) = match frame {
                PreparedFrame::F32(mut w) => {
                    let brute = w.clone();
                    w.set_accel(Some(true));
                    assert!(w.accel.is_some() && brute.accel.is_none());
                    (PreparedFrame::F32(w), PreparedFrame::F32(brute))
                }
                PreparedFrame::F64(mut w) => {
                    let mut brute = w.clone();
                    brute.set_accel(Some(false));
                    w.set_accel(Some(true));
                    (PreparedFrame::F64(w), PreparedFrame::F64(brute))
                }
            };
            let r = CpuRenderer::new(Some(2)).unwrap();
            let all = (Rect::full(80, 60), SampleRange::all(scene.render.samples));
            let a = r
                .render(&with, WorkRegion::new(0, all.0, all.1), &|_| {})
                .unwrap();
            let b = r
                .render(&without, WorkRegion::new(0, all.0, all.1), &|_| {})
                .unwrap();
            assert!(
                a.sums == b.sums && a.counts == b.counts,
                "{name} {precision:?}: films differ"
            );
            assert_eq!(a.rays.total(), b.rays.total());
        }
    }
}

/// A flat grid of `n` x `n` unit quads (two coplanar triangles each, both
/// diagonals alternating) at z = `z`, centred on the z axis.
fn grid(n: u32, z: f64) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    let h = n as f64 / 2.0;
    let v = (0..=n)
        .flat_map(|y| (0..=n).map(move |x| [x as f64 - h, y as f64 - h, z]))
        .collect();
    let at = |x: u32, y: u32| y * (n + 1) + x;
    let f = (0..n)
        .flat_map(|y| (0..n).map(move |x| (x, y)))
        .flat_map(|(x, y)| {
            if (x + y) % 2 == 0 {
                [
                    [at(x, y), at(x + 1, y), at(x + 1, y + 1)],
                    [at(x, y), at(x + 1, y + 1), at(x, y + 1)],
                ]
            } else {
                [
                    [at(x, y), at(x + 1, y), at(x, y + 1)],
                    [at(x + 1, y), at(x + 1, y + 1), at(x, y + 1)],
                ]
            }
        })
        .collect();
    (v, f)
}

/// Packets of rays (`World::closest_hits`, and the tree's packet walk with
/// the SSE, AVX2 and AVX-512 node tests where the CPU has them; shadow rays
/// through `World::occluded_many` and `bvh::occluded_hits`) give
/// every ray the single-ray answer, bit for bit: coherent camera-like
/// packets (some aimed exactly at the shared vertices and edges of a flat
/// grid, where coplanar triangles tie), packets of parallel rays along an
/// axis (direction components 0 and -0, origins on the grid's lines),
/// packets whose rays point into different octants, partial packets, and
/// packets leaving a surface.
#[test]
fn packets_of_rays_answer_as_single_rays_bit_for_bit() {
    use tracer_core::bvh::{PACKET, closest_hits_at, occluded_hits, occluded_hits_at};
    use tracer_core::simd::SimdLevel;
    use tracer_core::triangle::TriangleRay;

    let dir = tmpdir("packets");
    let (v, f) = icosphere(3);
    write_obj(&dir.join("ball.obj"), &v, &f, true);
    // Two overlapping coplanar grids, one shifted by a third of a cell (as
    // in models with coincident faces): rays meeting both often get the same
    // distance from two triangles with different boxes, in different leaves.
    let (mut v, mut f) = grid(8, 2.0);
    let (v2, f2) = grid(7, 2.0);
    let base = v.len() as u32;
    v.extend(
        v2.iter()
            .map(|p| [p[0] + 1.0 / 3.0, p[1] + 1.0 / 3.0, p[2]]),
    );
    f.extend(f2.iter().map(|t| t.map(|i| i + base)));
    write_obj(&dir.join("grid.obj"), &v, &f, false);
    let mut src = format!(
        "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"ball.obj\"\nmaterial = \"white\"\nscale = 0.8\ntranslate = [1.5, 1.0, 0.5]\n\
         [[objects]]\ntype = \"mesh\"\npath = \"grid.obj\"\nmaterial = \"white\"\n\
         [[objects]]\ntype = \"plane\"\nnormal = [0, 0, -1]\ndistance = -3\nmaterial = \"white\"\n"
    );
    let meshes_only = SceneDesc::parse(&src, dir.join("packets.toml")).unwrap();
    for i in 0..12 {
        write!(src, "[[objects]]\ntype = \"sphere\"\ncenter = [{}, {}, 1.0]\nradius = 0.4\nmaterial = \"white\"\n", i % 4 - 2, i / 4 - 1).unwrap();
    }
    let with_spheres = SceneDesc::parse(&src, dir.join("packets.toml")).unwrap();

    for (label, scene) in [
        ("meshes", &meshes_only),
        ("meshes and spheres", &with_spheres),
    ] {
        let world: World<f32> = world_of(scene);
        let tree = world.accel.as_ref().expect("a tree");
        let h = |k: u32| hash_u32(k) as f64 / u32::MAX as f64 - 0.5;
        let (mut rays_tested, mut ties) = (0, 0);
        let (mut blocked_seen, mut open_seen) = (0, 0);
        let mut levels_run = 0u32;
        for p in 0..600u32 {
            let n = if p % 7 == 0 {
                1 + p as usize % PACKET
            } else {
                PACKET
            };
            let origin = [h(p * 8) * 0.5, h(p * 8 + 1) * 0.5, -4.0];
            // A 4x4 block of targets on the grid's plane, 1/8 apart: on grid
            // vertices (exact ties) for every third packet; around x = 0 or
            // y = 0 (mixed octants) for every fifth.
            let (cx, cy) = if p % 5 == 0 {
                (0.0, 0.0)
            } else {
                (
                    (h(p * 8 + 2) * 8.0).round() / 2.0,
                    (h(p * 8 + 3) * 8.0).round() / 2.0,
                )
            };
            let jitter = if p % 3 == 0 { 0.0 } else { 0.1 };
            let packet: Vec<Ray<f32>> = (0..n as u32)
                .map(|j| {
                    if p % 11 == 1 {
                        // Parallel rays along the z axis (direction components
                        // exactly 0 or -0), from origins on the grid's lines.
                        let d = glam::Vec3A::new(
                            if p % 2 == 0 { 0.0 } else { -0.0 },
                            if p % 4 < 2 { 0.0 } else { -0.0 },
                            1.0,
                        );
                        return Ray::new(
                            glam::Vec3A::new(
                                cx as f32 + (j % 4) as f32 * 0.5,
                                cy as f32 + (j / 4) as f32 * 0.5,
                                -4.0,
                            ),
                            d,
                        );
                    }
                    let t = [
                        cx + (j % 4) as f64 * 0.125 - 0.1875 + jitter * h(p * 64 + j),
                        cy + (j / 4) as f64 * 0.125 - 0.1875 + jitter * h(p * 64 + j + 16),
                        2.0,
                    ];
                    let o = if p % 3 == 0 { [0.0, 0.0, -4.0] } else { origin };
                    ray_to::<f32>(o, t)
                })
                .collect();
            let want: Vec<_> = packet
                .iter()
                .map(|r| world.closest_hit(r, PrimId::NONE))
                .collect();
            let mut got = vec![None; n];
            world.closest_hits(&packet, PrimId::NONE, &mut got);
            assert_eq!(got, want, "{label}: packet {p}");
            // The tree's walk itself, both node tests, with a prior hit to beat.
            let tree_want: Vec<_> = packet
                .iter()
                .map(|r| {
                    tracer_core::bvh::closest_hit(&world, tree, r, 5.0, PrimId(7), PrimId::NONE)
                })
                .collect();
            for level in [SimdLevel::Baseline, SimdLevel::Avx2, SimdLevel::Avx512] {
                let (mut best, mut found) = (vec![5.0f32; n], vec![PrimId(7); n]);
                if !closest_hits_at(
                    level,
                    &world,
                    tree,
                    &packet,
                    &mut best,
                    &mut found,
                    PrimId::NONE,
                ) {
                    assert!(!level.is_available());
                    continue;
                }
                levels_run |= 1 << level as u32;
                let got: Vec<_> = best
                    .iter()
                    .zip(&found)
                    .map(|(&t, &id)| Some((t, id)))
                    .collect();
                let want: Vec<_> = tree_want
                    .iter()
                    .map(|w| Some(w.unwrap_or((5.0, PrimId(7)))))
                    .collect();
                assert_eq!(got, want, "{label}: packet {p}, tree walk at {level:?}");
            }
            // Rays leaving the nearest hit of the first ray, in a narrow cone.
            if let Some((t, id)) = want[0] {
                let from = packet[0].at(t);
                let leaving: Vec<Ray<f32>> = (0..n as u32)
                    .map(|j| {
                        Ray::new(
                            from,
                            glam::Vec3A::new(
                                h(p * 32 + j) as f32 * 0.3,
                                h(p * 32 + j + 16) as f32 * 0.3,
                                -1.0,
                            )
                            .normalize(),
                        )
                    })
                    .collect();
                let want: Vec<_> = leaving.iter().map(|r| world.closest_hit(r, id)).collect();
                let mut got = vec![None; n];
                world.closest_hits(&leaving, id, &mut got);
                assert_eq!(got, want, "{label}: packet {p} leaving {id:?}");
            }
            // Shadow rays from the hits to a point light: each from its own
            // primitive, some blocked by the ball or the spheres.
            let (mut shadow, mut t_max, mut skips) = (Vec::new(), Vec::new(), Vec::new());
            for (r, w) in packet.iter().zip(&want) {
                if let Some((t, id)) = *w {
                    let from = r.at(t) - r.dir * 1e-3;
                    let light = glam::Vec3A::new(2.0 + h(p * 4) as f32, 2.0, -3.0);
                    shadow.push(Ray::new(from, (light - from).normalize()));
                    t_max.push((light - from).length());
                    skips.push(id);
                }
            }
            if !shadow.is_empty() {
                let want: Vec<bool> = shadow
                    .iter()
                    .zip(&t_max)
                    .zip(&skips)
                    .map(|((r, &t), &id)| world.occluded(r, t, id))
                    .collect();
                let mut got = vec![false; shadow.len()];
                world.occluded_many(&shadow, &t_max, &skips, &mut got);
                assert_eq!(got, want, "{label}: packet {p}, shadow rays");
                let tree_want = shadow.iter().zip(&t_max).zip(&skips).enumerate().fold(
                    0u32,
                    |m, (j, ((r, &t), &id))| {
                        m | (tracer_core::bvh::occluded(&world, tree, r, t, id) as u32) << j
                    },
                );
                assert_eq!(
                    occluded_hits(&world, tree, &shadow, &t_max, &skips),
                    tree_want,
                    "{label}: packet {p}, shadow rays, tree walk"
                );
                for level in [SimdLevel::Baseline, SimdLevel::Avx2, SimdLevel::Avx512] {
                    if let Some(got) =
                        occluded_hits_at(level, &world, tree, &shadow, &t_max, &skips)
                    {
                        assert_eq!(
                            got, tree_want,
                            "{label}: packet {p}, shadow rays, tree walk at {level:?}"
                        );
                    }
                }
                blocked_seen += want.iter().filter(|&&b| b).count();
                open_seen += want.iter().filter(|&&b| !b).count();
            }
            // Rays where two triangles give the very same distance.
            for r in &packet {
                let tr = TriangleRay::new(r);
                let mut d: Vec<u32> = world
                    .triangles()
                    .filter_map(|t| t.intersect(&tr, f32::INFINITY))
                    .map(f32::to_bits)
                    .collect();
                d.sort_unstable();
                ties += d.windows(2).any(|w| w[0] == w[1]) as u32;
            }
            rays_tested += n;
        }
        assert!(rays_tested > 8000);
        // Every level this CPU has was checked (the baseline everywhere).
        let have = SimdLevel::available()
            .iter()
            .fold(0u32, |m, &l| m | 1 << l as u32);
        assert_eq!(levels_run, have, "{label}");
        assert!(
            blocked_seen > 200 && open_seen > 500,
            "{label}: shadow rays blocked {blocked_seen}, open {open_seen}"
        );
        assert!(
            ties > 1000,
            "{label}: only {ties} rays meet two triangles at the same distance; the tie rule is not exercised"
        );
    }
}

/// The CPU renderer's camera-ray and shadow-ray packets give the films of
/// single rays: a mesh scene (two lights) rendered tile by tile equals, sum
/// for sum, the same pixels traced one ray at a time with the recursive
/// `trace`.
#[test]
fn camera_ray_packets_render_the_films_of_single_rays() {
    use tracer_core::render::cpu::render_tile_recursive;
    use tracer_core::render::step::{Static, trace};
    use tracer_core::sampling::{pixel_seed, sample_offset};

    let dir = tmpdir("packet-film");
    let (v, f) = icosphere(3);
    write_obj(&dir.join("ball.obj"), &v, &f, true);
    let (v, f) = grid(6, 0.0);
    write_obj(&dir.join("grid.obj"), &v, &f, false);
    let src = format!(
        "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"ball.obj\"\nmaterial = \"mirror\"\n\
         [[objects]]\ntype = \"mesh\"\npath = \"grid.obj\"\nmaterial = \"white\"\nrotate_euler = [90, 0, 0]\ntranslate = [0, -1, 0]\n\
         [[lights]]\nposition = [3, 4, -2]\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("film.toml")).unwrap();
    let world: World<f32> = world_of(&scene);
    assert!(world.accel.is_some());
    let (w, h, spp) = (
        scene.render.width,
        scene.render.height,
        scene.render.samples,
    );
    // Tiles of odd sizes, so packets are cut at tile edges.
    for tile in [
        Rect {
            x: 0,
            y: 0,
            width: w,
            height: h,
        },
        Rect {
            x: 5,
            y: 3,
            width: 13,
            height: 7,
        },
    ] {
        let got = render_tile_recursive(&world, 0, tile, SampleRange::all(spp));
        let mut want = Film::new(tile);
        let mut i = 0;
        for y in tile.y..tile.y + tile.height {
            for x in tile.x..tile.x + tile.width {
                for sample in 0..spp {
                    let (u, v) =
                        sample_offset(world.settings.sampler, spp, pixel_seed(x, y, 0), sample);
                    let ray = world.camera.ray(x as f32 + u, y as f32 + v);
                    want.rays.primary += 1;
                    let c = trace(&world, &Static, &ray, 0, (), PrimId::NONE, &mut want.rays);
                    want.add_sample::<f32>(i, [c.x, c.y, c.z]);
                }
                i += 1;
            }
        }
        assert_eq!(got.sums, want.sums, "tile {tile:?}");
        assert_eq!(got.counts, want.counts);
        assert_eq!(got.rays, want.rays);
    }
}

// Issue 14: files peers load whose differences are choices, not defects.

fn load_err(path: &Path) -> String {
    tracer_core::mesh::Mesh::load(path, true)
        .unwrap_err()
        .to_string()
}

#[test]
fn ply_headers_and_ascii_bodies_with_lone_cr_line_ends_load_like_lf() {
    use tracer_core::mesh::Mesh;
    let dir = tmpdir("ply-cr");
    let head = "ply\nformat ascii 1.0\ncomment made on a Mac\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
    let body = "0 0 0\n1 0 0\n1 1 0\n0 1 0 9 9\n4 0 1 2 3\n";
    std::fs::write(dir.join("lf.ply"), format!("{head}{body}")).unwrap();
    let lf = Mesh::load(&dir.join("lf.ply"), true).unwrap();
    assert_eq!(lf.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    for (name, head_end, body_end) in [
        ("cr.ply", "\r", "\r"),
        ("cr-head.ply", "\r", "\n"),
        ("crlf.ply", "\r\n", "\r\n"),
    ] {
        let text = format!(
            "{}{}",
            head.replace('\n', head_end),
            body.replace('\n', body_end)
        );
        std::fs::write(dir.join(name), text).unwrap();
        assert_eq!(Mesh::load(&dir.join(name), true).unwrap(), lf, "{name}");
    }
    // Binary after a CR-only header: the body's first byte is 0x0A and
    // belongs to the first vertex, not to the header's line end.
    let first = f32::from_le_bytes([0x0A, 0x00, 0x80, 0x3F]);
    let vertices = [[first, 0.0, 0.0], [1.0, 2.0, 0.0], [0.0, 1.0, 0.0]];
    for (name, end) in [
        ("bin-cr.ply", "\r"),
        ("bin-crlf.ply", "\r\n"),
        ("bin-lf.ply", "\n"),
    ] {
        let mut data = "ply\nformat binary_little_endian 1.0\ncomment caf\u{e9}\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n"
            .replace('\n', end)
            .into_bytes();
        for v in vertices {
            for c in v {
                data.extend(c.to_le_bytes());
            }
        }
        data.push(3);
        for i in [0u32, 1, 2] {
            data.extend(i.to_le_bytes());
        }
        std::fs::write(dir.join(name), data).unwrap();
        let m = Mesh::load(&dir.join(name), true).unwrap();
        assert_eq!(m.positions, vertices, "{name}");
        assert_eq!(m.triangles, vec![[0, 1, 2]], "{name}");
    }
    // Still refused: a header that never ends.
    std::fs::write(
        dir.join("open.ply"),
        "ply\rformat ascii 1.0\relement vertex 0\r",
    )
    .unwrap();
    assert!(
        load_err(&dir.join("open.ply"))
            .ends_with("open.ply: invalid PLY header: file ends before end_header"),
        "{}",
        load_err(&dir.join("open.ply"))
    );
}

#[test]
fn obj_polylines_and_points_are_never_faces() {
    use tracer_core::mesh::Mesh;
    let dir = tmpdir("obj-lines");
    std::fs::write(
        dir.join("m.mtl"),
        "newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n",
    )
    .unwrap();
    // One quad (two triangles) in red; polylines of 2, 4 and 5 vertices and
    // points between and after, one `l` in blue that must not become a face.
    let obj = "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nvt 0 0\n\
               usemtl red\nf 1 2 3 4\nl 1 2\n  l 1 2 3 4\nl 1/1 2/1 3/1 4/1 5/1\np 1 2 3\n\
               usemtl blue\nl 2 3 4 5\np 5\nline 1 2 3\n";
    std::fs::write(dir.join("lines.obj"), obj).unwrap();
    let m = Mesh::load(&dir.join("lines.obj"), true).unwrap();
    assert_eq!(m.triangles.len(), 2, "{:?}", m.triangles);
    let used: Vec<&str> = m
        .triangle_materials
        .iter()
        .map(|&i| m.materials[i as usize].0.as_str())
        .collect();
    assert_eq!(used, ["red", "red"]);
    assert!(m.warnings.is_empty(), "{:?}", m.warnings);
    // Only lines and points: nothing to render, said so.
    std::fs::write(
        dir.join("wire.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3 1\np 1 2 3\n",
    )
    .unwrap();
    assert!(
        load_err(&dir.join("wire.obj")).ends_with("wire.obj: contains no triangles"),
        "{}",
        load_err(&dir.join("wire.obj"))
    );
    // Faces after the blanked lines still get their errors.
    std::fs::write(
        dir.join("bad.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3\nf 1 2 9\n",
    )
    .unwrap();
    assert!(
        load_err(&dir.join("bad.obj"))
            .contains("bad.obj: invalid OBJ: face vertex index out of bounds"),
        "{}",
        load_err(&dir.join("bad.obj"))
    );
}

/// A glTF of one triangle (positions, then a float per vertex for a custom
/// attribute) with `.bin` beside it; `patch` edits the JSON.
fn write_gltf(dir: &Path, name: &str, patch: impl FnOnce(&mut String)) -> PathBuf {
    let mut bin = Vec::new();
    for c in [0f32, 0., 0., 1., 0., 0., 0., 1., 0., 7., 8., 9.] {
        bin.extend(c.to_le_bytes());
    }
    std::fs::write(dir.join("tri.bin"), &bin).unwrap();
    let mut json = r#"{"asset":{"version":"2.0"},
      "buffers":[{"byteLength":48,"uri":"tri.bin"}],
      "bufferViews":[{"buffer":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":12}],
      "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]},
                   {"bufferView":1,"componentType":5126,"count":3,"type":"SCALAR"}],
      "materials":[{"name":"paint","pbrMetallicRoughness":{"baseColorFactor":[0.2,0.4,0.6,1],"metallicFactor":0}}],
      "meshes":[{"primitives":[{"attributes":{"POSITION":0},"material":0}]}],
      "nodes":[{"mesh":0}],"scenes":[{"nodes":[0]}],"scene":0}"#
        .to_string();
    patch(&mut json);
    let p = dir.join(name);
    std::fs::write(&p, json).unwrap();
    p
}

#[test]
fn gltf_extras_empty_textures_custom_attributes_and_missing_bounds_load() {
    use tracer_core::mesh::Mesh;
    let dir = tmpdir("gltf-lenient");
    let plain = Mesh::load(&write_gltf(&dir, "plain.gltf", |_| {}), true).unwrap();
    assert_eq!(plain.triangles, vec![[0, 1, 2]]);
    assert_eq!(plain.materials[0].0, "paint");
    type Patch = fn(&mut String);
    let cases: [(&str, Patch); 5] = [
        // `extras` may hold any JSON value, not only objects.
        ("extras.gltf", |j| {
            *j = j
                .replace(
                    r#""version":"2.0"}"#,
                    r#""version":"2.0","extras":"exported by hand"}"#,
                )
                .replace(r#"{"mesh":0}"#, r#"{"mesh":0,"extras":[1,2]}"#)
                .replace(r#""name":"paint""#, r#""name":"paint","extras":42"#);
        }),
        // A texture without an image (its material still has its colour).
        ("empty-texture.gltf", |j| {
            *j = j
                .replace(
                    r#""metallicFactor":0}"#,
                    r#""metallicFactor":0,"baseColorTexture":{"index":0}}"#,
                )
                .replace(r#""meshes":"#, r#""textures":[{}],"meshes":"#);
        }),
        // An application-specific attribute (`_` prefix) is not read.
        ("custom-attribute.gltf", |j| {
            *j = j.replace(r#""POSITION":0}"#, r#""POSITION":0,"_TEMPERATURE":1}"#);
        }),
        // POSITION without min and max: the bounds come from the vertices.
        ("no-bounds.gltf", |j| {
            *j = j.replace(r#","min":[0,0,0],"max":[1,1,0]"#, "")
        }),
        ("bad-bounds.gltf", |j| {
            *j = j.replace(r#""max":[1,1,0]"#, r#""max":[1]"#)
        }),
    ];
    for (name, patch) in cases {
        let m = Mesh::load(&write_gltf(&dir, name, patch), true)
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(m, plain, "{name}");
    }
    // Other validation errors stay errors, with the crate's wording.
    let p = write_gltf(&dir, "bad-index.gltf", |j| {
        *j = j.replace(r#""material":0"#, r#""material":3"#)
    });
    assert_eq!(
        load_err(&p),
        "bad-index.gltf: invalid glTF: invalid glTF: meshes[0].primitives[0].material: Index out of bounds;"
    );
    let p = write_gltf(&dir, "bad-semantic.gltf", |j| {
        *j = j.replace(r#""POSITION":0}"#, r#""POSITION":0,"TEMPERATURE":1}"#)
    });
    assert!(
        load_err(&p).contains("bad-semantic.gltf: invalid glTF:"),
        "{}",
        load_err(&p)
    );
}

#[test]
fn compressed_gltf_is_refused_naming_the_extension() {
    let dir = tmpdir("gltf-compressed");
    for (ext, what) in [
        ("KHR_draco_mesh_compression", "Draco mesh compression"),
        ("EXT_meshopt_compression", "meshoptimizer compression"),
    ] {
        let name = format!("{ext}.gltf");
        let p = write_gltf(&dir, &name, |j| {
            *j = j.replace(
                r#""asset":"#,
                &format!(r#""extensionsUsed":["{ext}"],"extensionsRequired":["KHR_materials_unlit","{ext}"],"asset":"#),
            );
        });
        assert_eq!(
            load_err(&p),
            format!(
                "{name}: requires the extension {ext} ({what}), which Tessera does not decode: export the model without it"
            )
        );
        // Used but not required: the file carries uncompressed data too.
        let p = write_gltf(&dir, &name, |j| {
            *j = j.replace(
                r#""asset":"#,
                &format!(r#""extensionsUsed":["{ext}"],"asset":"#),
            );
        });
        assert_eq!(
            tracer_core::mesh::Mesh::load(&p, true)
                .unwrap()
                .triangles
                .len(),
            1
        );
    }
}

#[test]
fn gltf_requiring_appearance_extensions_renders_with_a_warning() {
    let dir = tmpdir("gltf-required");
    let require = |ext: &'static str| {
        move |j: &mut String| {
            *j = j.replace(
                r#""asset":"#,
                &format!(r#""extensionsUsed":["{ext}"],"extensionsRequired":["{ext}"],"asset":"#),
            );
        }
    };
    let p = write_gltf(&dir, "webgl.gltf", require("KHR_technique_webgl"));
    let m = tracer_core::mesh::Mesh::load(&p, true).unwrap();
    assert_eq!(m.triangles.len(), 1);
    assert_eq!(
        m.warnings,
        [
            "requires the extension KHR_technique_webgl, which Tessera does not read (it changes materials, textures or lights, not geometry): rendered without it"
        ]
    );
    let p = write_gltf(&dir, "unlit.gltf", require("KHR_materials_unlit"));
    assert_eq!(
        tracer_core::mesh::Mesh::load(&p, true)
            .unwrap()
            .warnings
            .len(),
        1
    );
    // Quantized attributes are read (issue 34), with no warning.
    let p = write_gltf(&dir, "quantized.gltf", require("KHR_mesh_quantization"));
    assert!(
        tracer_core::mesh::Mesh::load(&p, true)
            .unwrap()
            .warnings
            .is_empty()
    );
    // Extensions that change geometry stay refused, by name.
    let p = write_gltf(&dir, "made-up.gltf", require("EXT_made_up_geometry"));
    assert_eq!(
        load_err(&p),
        "made-up.gltf: requires the extension EXT_made_up_geometry, which Tessera does not read"
    );
}

#[test]
fn obj_encodings_unnamed_usemtl_and_partial_vertex_colours_load() {
    use tracer_core::mesh::Mesh;
    let dir = tmpdir("obj-lenient");
    let quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";
    std::fs::write(dir.join("plain.obj"), quad).unwrap();
    let plain = Mesh::load(&dir.join("plain.obj"), true).unwrap();
    assert_eq!(plain.triangles.len(), 2);
    // UTF-16 in either byte order, and UTF-8 with a byte-order mark.
    let be: Vec<u8> = [0xFE, 0xFF]
        .into_iter()
        .chain(quad.encode_utf16().flat_map(u16::to_be_bytes))
        .collect();
    let le: Vec<u8> = [0xFF, 0xFE]
        .into_iter()
        .chain(quad.encode_utf16().flat_map(u16::to_le_bytes))
        .collect();
    let bom: Vec<u8> = b"\xEF\xBB\xBF"
        .iter()
        .chain(quad.as_bytes())
        .copied()
        .collect();
    for (name, data) in [("be.obj", be), ("le.obj", le), ("bom.obj", bom)] {
        std::fs::write(dir.join(name), data).unwrap();
        assert_eq!(Mesh::load(&dir.join(name), true).unwrap(), plain, "{name}");
    }
    // A Latin-1 material name (not UTF-8) in the OBJ and its MTL still matches.
    std::fs::write(dir.join("latin.mtl"), b"newmtl Terraind\xe4k\nKd 0 1 0\n").unwrap();
    let mut obj = b"mtllib latin.mtl\nusemtl Terraind\xe4k\n".to_vec();
    obj.extend_from_slice(quad.as_bytes());
    std::fs::write(dir.join("latin.obj"), obj).unwrap();
    let m = Mesh::load(&dir.join("latin.obj"), true).unwrap();
    assert_eq!(m.materials.len(), 1, "{:?}", m.materials);
    assert_eq!(m.materials[0].0, "Terraind\u{fffd}k");
    assert_eq!(m.materials[0].1.diffuse.0, [0.0, 1.0, 0.0]);
    // `usemtl` with no name: the default material from there on.
    std::fs::write(dir.join("m.mtl"), "newmtl red\nKd 1 0 0\n").unwrap();
    std::fs::write(
        dir.join("unnamed.obj"),
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nusemtl red\nf 1 2 3\nusemtl \nf 1 2 3 4\n",
    )
    .unwrap();
    let m = Mesh::load(&dir.join("unnamed.obj"), true).unwrap();
    let used: Vec<&str> = m
        .triangle_materials
        .iter()
        .map(|&i| m.materials[i as usize].0.as_str())
        .collect();
    assert_eq!(used, ["red", "default", "default"]);
    // Colours on some vertices only: the positions load, the colours are not read.
    std::fs::write(
        dir.join("colours.obj"),
        "v 0 0 0\nv 1 0 0 1 0 0\nv 1 1 0\nv 0 1 0 0.5 0.5 0.5\nf 1 2 3 4\n",
    )
    .unwrap();
    assert_eq!(Mesh::load(&dir.join("colours.obj"), true).unwrap(), plain);
    // A statement continued on the next lines with `\`.
    std::fs::write(
        dir.join("continued.obj"),
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 \\\r\n 0\nf 1 2 \\\n3 \\\n4\n",
    )
    .unwrap();
    assert_eq!(Mesh::load(&dir.join("continued.obj"), true).unwrap(), plain);
}

#[test]
fn meshes_named_by_absolute_path_find_their_side_files() {
    let dir = tmpdir("absolute");
    std::fs::create_dir_all(dir.join("models")).unwrap();
    std::fs::write(dir.join("models/m.mtl"), "newmtl red\nKd 1 0 0\n").unwrap();
    std::fs::write(
        dir.join("models/q.obj"),
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n",
    )
    .unwrap();
    write_gltf(&dir.join("models"), "t.gltf", |_| {});
    let scene_dir = tmpdir("absolute-scene");
    for model in ["q.obj", "t.gltf"] {
        let path = dir.join("models").join(model);
        assert!(path.is_absolute());
        let src = format!(
            "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = {:?}\n",
            path.display().to_string()
        );
        let scene = SceneDesc::parse(&src, scene_dir.join("s.toml"))
            .unwrap_or_else(|e| panic!("{model}: {e}"));
        let world = world_of::<f32>(&scene);
        assert_eq!(world.triangle_shading.len(), 1, "{model}");
    }
}

// Inputs found by the fuzz targets (fuzz/, scripts/fuzz), minimised: each
// must be a clear error naming the file, never a panic (caught or not), an
// abort or a hang.

/// Loads `name` through the real loaders from a bundle of `files`, as the
/// coordinator and the fuzz targets do.
fn load_bundle(files: &[(&str, &[u8])], name: &str) -> Result<Mesh, String> {
    let mut bundle = Bundle::new();
    for (n, data) in files {
        bundle.insert(*n, *data);
    }
    Mesh::load_from(&bundle, name, true).map_err(|e| e.to_string())
}

#[test]
fn fuzz_gltf_position_accessor_that_does_not_exist() {
    // gltf-json 1.4.1's validation indexes `accessors` by the POSITION
    // attribute before it reports the index out of range: it panicked.
    let doc =
        br#"{"asset":{"version":"2.0"},"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}]}"#;
    assert_eq!(
        load_bundle(&[("m.gltf", doc)], "m.gltf").unwrap_err(),
        r#"m.gltf: invalid glTF: meshes[0].primitives[0].attributes["POSITION"]: accessor 0 does not exist (the file has 0 accessors)"#
    );
}

#[test]
fn fuzz_gltf_attribute_accessor_of_the_wrong_type() {
    // gltf 1.4.1's reader asserts that NORMAL's accessor holds [f32; 3]
    // (accessor/util.rs) and reaches unreachable!() on float indices.
    let gltf = |normal: &str, indices: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":36,"uri":"data:application/octet-stream;base64,{}"}}],
            "bufferViews":[{{"buffer":0,"byteLength":36}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
                         {{"bufferView":0,"componentType":5123,"count":3,"type":"SCALAR"}},
                         {{"bufferView":0,"componentType":5126,"count":3,"type":"SCALAR"}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":{normal}}}{indices}}}]}}]}}"#,
            "AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA"
        )
    };
    assert_eq!(
        load_bundle(&[("n.gltf", gltf("1", "").as_bytes())], "n.gltf").unwrap_err(),
        "n.gltf: mesh 0 primitive 0: NORMAL accessor 1 holds SCALAR of unsigned short, expected VEC3 of float, or (KHR_mesh_quantization) of normalized byte or short"
    );
    assert_eq!(
        load_bundle(
            &[("i.gltf", gltf("0", r#","indices":2"#).as_bytes())],
            "i.gltf"
        )
        .unwrap_err(),
        "i.gltf: mesh 0 primitive 0: indices accessor 2 holds SCALAR of float, expected SCALAR of unsigned byte, short or int"
    );
    let ok = load_bundle(
        &[("ok.gltf", gltf("0", r#","indices":1"#).as_bytes())],
        "ok.gltf",
    );
    assert_eq!(ok.unwrap().triangles.len(), 1);
}

#[test]
fn fuzz_glb_header_length_shorter_than_the_header() {
    // gltf 1.4.1 computed the GLB's content length as `length - 12`: an
    // overflow (a panic with overflow checks, else a wrapped length).
    let glb = b"glTF\x02\x00\x00\x00\x04\x00\x00\x00\x08\x00\x00\x00JSON{}      ";
    assert_eq!(
        load_bundle(&[("m.glb", glb)], "m.glb").unwrap_err(),
        "m.glb: invalid glTF: the GLB header declares a length of 4 bytes, less than its own 12"
    );
}

#[test]
fn fuzz_gltf_accessor_of_no_elements() {
    // gltf 1.4.1's reader computes `count - 1` for an accessor's (and a
    // sparse part's) last element: an overflow for count 0.
    let gltf = |accessor: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":36,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA"}}],
            "bufferViews":[{{"buffer":0,"byteLength":36}}],"accessors":[{accessor}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}]}}"#
        )
    };
    let empty = gltf(
        r#"{"bufferView":0,"componentType":5126,"count":0,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}"#,
    );
    assert_eq!(
        load_bundle(&[("e.gltf", empty.as_bytes())], "e.gltf").unwrap_err(),
        "e.gltf: mesh 0 primitive 0: accessor 0: count 0 (an accessor has at least 1 element)"
    );
    let sparse = gltf(
        r#"{"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0],
            "sparse":{"count":0,"indices":{"bufferView":0,"componentType":5125},"values":{"bufferView":0}}}"#,
    );
    assert_eq!(
        load_bundle(&[("s.gltf", sparse.as_bytes())], "s.gltf").unwrap_err(),
        "s.gltf: mesh 0 primitive 0: accessor 0: sparse count 0 (at least 1 value)"
    );
}

#[test]
fn fuzz_obj_face_texture_or_normal_index_far_out_of_range() {
    // tobj 4.0.5 resolved `-7` with 3 texture coordinates (or a huge
    // index) to near usize::MAX, then overflowed computing `vt * 2 + 1`.
    let obj =
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\nf 1/1/1 2/2/1 3/-7/1\n";
    assert_eq!(
        load_bundle(&[("t.obj", obj)], "t.obj").unwrap_err(),
        "t.obj: invalid OBJ: line 8: face texture coordinate index -7 is out of range (3 defined before this line)"
    );
    let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//6148914691236517206\n";
    assert_eq!(
        load_bundle(&[("n.obj", obj)], "n.obj").unwrap_err(),
        "n.obj: invalid OBJ: line 5: face normal index 6148914691236517206 is out of range (1 defined in the file)"
    );
    // Relative and absolute indices in range, and 0 (none), still load.
    let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf -3/-1/-1 2/1/0 3/0/1\n";
    assert_eq!(
        load_bundle(&[("ok.obj", obj)], "ok.obj")
            .unwrap()
            .triangles
            .len(),
        1
    );
}

// Loader gaps of issue 34: each refusal names what the file is, and
// quantized files load.

/// A glTF of one triangle whose POSITION is `accessor` (JSON, over buffer
/// view 0 of `bytes`), required extensions `required`, placed by `node`.
fn gltf_of(bytes: &[u8], view: &str, accessor: &str, required: &str, node: &str) -> String {
    use base64::Engine as _;
    let uri = base64::engine::general_purpose::STANDARD.encode(bytes);
    format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":[{required}],"extensionsRequired":[{required}],
        "buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{uri}"}}],
        "bufferViews":[{view}],"accessors":[{accessor}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
        "nodes":[{node}],"scenes":[{{"nodes":[0]}}],"scene":0}}"#,
        bytes.len()
    )
}

#[test]
fn quantized_gltf_positions_are_dequantized_as_the_extension_says() {
    // Normalized shorts (4-byte aligned: stride 8), scaled back by the node.
    let mut b = Vec::new();
    for v in [[0i16, 0, 0], [32767, 0, 0], [0, -32768, 16384]] {
        for c in v {
            b.extend(c.to_le_bytes());
        }
        b.extend([0, 0]);
    }
    let doc = gltf_of(
        &b,
        r#"{"buffer":0,"byteLength":24,"byteStride":8}"#,
        r#"{"bufferView":0,"componentType":5122,"normalized":true,"count":3,"type":"VEC3"}"#,
        r#""KHR_mesh_quantization""#,
        r#"{"mesh":0,"scale":[2,2,2]}"#,
    );
    let m = load_bundle(&[("q.gltf", doc.as_bytes())], "q.gltf").unwrap();
    assert_eq!(m.warnings, Vec::<String>::new());
    let want = [
        [0.0, 0.0, 0.0],
        [2.0, 0.0, 0.0],
        [0.0, -2.0, 2.0 * (16384.0f32 / 32767.0)],
    ];
    for (p, w) in m.positions.iter().zip(want) {
        for k in 0..3 {
            assert!((p[k] - w[k]).abs() < 1e-6, "{p:?} {w:?}");
        }
    }
    // Unnormalized unsigned bytes: the integers themselves.
    let b = [0u8, 0, 0, 0, 3, 0, 0, 0, 0, 5, 7, 0];
    let doc = gltf_of(
        &b,
        r#"{"buffer":0,"byteLength":12,"byteStride":4}"#,
        r#"{"bufferView":0,"componentType":5121,"count":3,"type":"VEC3"}"#,
        r#""KHR_mesh_quantization""#,
        r#"{"mesh":0}"#,
    );
    let m = load_bundle(&[("u.gltf", doc.as_bytes())], "u.gltf").unwrap();
    assert_eq!(
        m.positions,
        vec![[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 5.0, 7.0]]
    );
    // Types the extension does not allow are named.
    let doc = gltf_of(
        &[0; 36],
        r#"{"buffer":0,"byteLength":36}"#,
        r#"{"bufferView":0,"componentType":5125,"count":3,"type":"VEC3"}"#,
        "",
        r#"{"mesh":0}"#,
    );
    assert_eq!(
        load_bundle(&[("i.gltf", doc.as_bytes())], "i.gltf").unwrap_err(),
        "i.gltf: mesh 0 primitive 0: POSITION accessor 0 holds VEC3 of unsigned int, expected VEC3 of float, or (KHR_mesh_quantization) of byte, unsigned byte, short or unsigned short"
    );
}

#[test]
fn gltf_1_0_and_draco_are_refused_by_name() {
    let v1 = br#"{"asset":{"version":"1.0"},"meshes":{"m":{"primitives":[]}},"scene":"s"}"#;
    let message = "is glTF 1.0 (asset.version \"1.0\"), which Tessera does not read: it reads glTF 2.0; convert the file (for example with gltf-pipeline, or by importing it into Blender and exporting glTF 2.0)";
    assert_eq!(
        load_bundle(&[("old.gltf", v1)], "old.gltf").unwrap_err(),
        format!("old.gltf: {message}")
    );
    // Also when nothing in it fails to parse as 2.0.
    let bare = br#"{"asset":{"version":"1.0"}}"#;
    assert_eq!(
        load_bundle(&[("bare.gltf", bare)], "bare.gltf").unwrap_err(),
        format!("bare.gltf: {message}")
    );
    let glb1 =
        b"glTF\x01\x00\x00\x00\x20\x00\x00\x00\x08\x00\x00\x00\x00\x00\x00\x00{\"asset\":{}}";
    assert_eq!(
        load_bundle(&[("old.glb", glb1)], "old.glb").unwrap_err(),
        "old.glb: is glTF 1.0 (binary glTF, GLB version 1), which Tessera does not read: it reads glTF 2.0; convert the file (for example with gltf-pipeline, or by importing it into Blender and exporting glTF 2.0)"
    );
    // Draco used, not required (as BoxDraco's exporter wrote it): the
    // accessors have no data, and the message says why.
    let draco = br#"{"asset":{"version":"2.0"},"extensionsUsed":["KHR_draco_mesh_compression"],
        "accessors":[{"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}],
        "meshes":[{"primitives":[{"attributes":{"POSITION":0},
            "extensions":{"KHR_draco_mesh_compression":{"bufferView":0,"attributes":{"POSITION":0}}}}]}]}"#;
    assert_eq!(
        load_bundle(&[("d.gltf", draco)], "d.gltf").unwrap_err(),
        "d.gltf: uses the extension KHR_draco_mesh_compression (Draco mesh compression), which Tessera does not decode, and has no uncompressed data in its place (accessors[0].bufferView: Missing data): export the model without it"
    );
}

#[test]
fn obj_number_errors_name_their_line() {
    for (obj, want) in [
        (
            "v 0 0 0\nv 3.1+e2 0 0\nv 0 1 0\nf 1 2 3\n",
            "n.obj: invalid OBJ: line 2: position parse error: \"3.1+e2\" is not a number",
        ),
        (
            "# MSVC\nv 0 0 0\nv 1 0 0\nv 0 1.#INF 0\nf 1 2 3\n",
            "n.obj: invalid OBJ: line 4: position parse error: \"1.#INF\" is not a number",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 x\nf 1 2 3\n",
            "n.obj: invalid OBJ: line 4: normal parse error: \"x\" is not a number",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0.5\nf 1 2 3\n",
            "n.obj: invalid OBJ: line 4: texcoord parse error: 2 numbers expected, found 1",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2.5 3\n",
            "n.obj: invalid OBJ: line 5: face parse error: \"2.5\" is not a vertex reference (v, v/vt, v//vn or v/vt/vn)",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf\n",
            "n.obj: invalid OBJ: line 5: face without vertices",
        ),
    ] {
        assert_eq!(
            load_bundle(&[("n.obj", obj.as_bytes())], "n.obj").unwrap_err(),
            want,
            "{obj:?}"
        );
    }
}

#[test]
fn fuzz_gltf_sparse_views_with_a_stride_shorter_than_their_elements() {
    // gltf 1.4.1 steps through sparse indices and values by their view's
    // byteStride and panicked reading a 12-byte element from a 4- or
    // 5-byte step (or a 2-byte index from a 1-byte one).
    let doc = |indices_stride: &str, values_stride: &str| {
        format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":36,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAA"}}],
            "bufferViews":[{{"buffer":0,"byteLength":36}},{{"buffer":0,"byteLength":36{values_stride}}},{{"buffer":0,"byteLength":8{indices_stride}}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0],
               "sparse":{{"count":2,"indices":{{"bufferView":2,"componentType":5123}},"values":{{"bufferView":1}}}}}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}]}}"#
        )
    };
    for stride in [4, 5] {
        let d = doc("", &format!(r#","byteStride":{stride}"#));
        assert_eq!(
            load_bundle(&[("s.gltf", d.as_bytes())], "s.gltf").unwrap_err(),
            format!(
                "s.gltf: mesh 0 primitive 0: accessor 0: sparse values: buffer view 1 has byteStride {stride}, smaller than its 12-byte elements (sparse data is tightly packed: no byteStride)"
            )
        );
    }
    // byteStride below 4 is refused by the format's validation already;
    // an index view's stride of 4 still holds its 2-byte indices.
    let ok = doc(r#","byteStride":4"#, "");
    assert!(load_bundle(&[("ok.gltf", ok.as_bytes())], "ok.gltf").is_ok());
    let plain = doc("", "");
    assert_eq!(
        load_bundle(&[("p.gltf", plain.as_bytes())], "p.gltf")
            .unwrap()
            .triangles
            .len(),
        1
    );
}

#[test]
fn a_gzipped_obj_loads_with_its_mtl_beside_it() {
    let m = Mesh::load(&shared("scenes/obj/Sibenik_Cathedral/sibenik.obj.gz"), true).unwrap();
    assert_eq!(m.triangles.len(), 75_284);
    assert!(m.materials.len() > 10, "{} materials", m.materials.len());
    assert!(m.warnings.is_empty(), "{:?}", m.warnings);
    // The same as the plain OBJ it unpacks to.
    let dir = tmpdir("obj-gz");
    let obj = b"mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n";
    std::fs::write(dir.join("m.mtl"), "newmtl red\nKd 1 0 0\n").unwrap();
    std::fs::write(dir.join("t.obj"), obj).unwrap();
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    std::io::Write::write_all(&mut gz, obj).unwrap();
    std::fs::write(dir.join("t.obj.gz"), gz.finish().unwrap()).unwrap();
    assert_eq!(
        Mesh::load(&dir.join("t.obj.gz"), true).unwrap(),
        Mesh::load(&dir.join("t.obj"), true).unwrap()
    );
    std::fs::write(dir.join("bad.obj.gz"), b"not gzip").unwrap();
    assert!(
        load_err(&dir.join("bad.obj.gz")).starts_with("bad.obj.gz: invalid gzip data:"),
        "{}",
        load_err(&dir.join("bad.obj.gz"))
    );
}

/// A TOML `instances` list: one smooth ball placed 9 times (turned,
/// scaled, one mirrored) and stored once. Its two-level tree answers as
/// brute force over the same instances, bit for bit; and its images equal
/// those of 9 mesh objects (the one-level path, copies rounded in world
/// space) within rounding, in f32 and f64.
#[test]
fn instances_equal_brute_force_and_copied_objects() {
    let dir = tmpdir("instances");
    let (v, f) = icosphere(3);
    write_obj(&dir.join("ball.obj"), &v, &f, true);
    let placements: Vec<String> = (0..9)
        .map(|i| {
            let (x, y) = ((i % 3) as f64 * 1.4 - 1.4, (i / 3) as f64 * 1.1 - 1.0);
            let scale = if i == 4 {
                "[-0.5, 0.5, 0.5]".to_string()
            } else {
                format!("{}", 0.35 + 0.03 * i as f64)
            };
            format!(
                "translate = [{x}, {y}, 0.3]\nrotate_euler = [{}, {}, 0]\nscale = {scale}",
                10 * i,
                25 * i
            )
        })
        .collect();
    let rest = "[[objects]]\ntype = \"sphere\"\ncenter = [1.5, 1.2, -1]\nradius = 0.3\nmaterial = \"white\"\n\
                [[objects]]\ntype = \"plane\"\nnormal = [0, 1, 0]\ndistance = -2\nmaterial = \"mirror\"\n";
    let mut inst = format!(
        "{HEADER}\n[[objects]]\ntype = \"mesh\"\npath = \"ball.obj\"\nmaterial = \"white\"\ninstances = [\n"
    );
    for p in &placements {
        writeln!(inst, "  {{ {} }},", p.replace('\n', ", ")).unwrap();
    }
    inst.push_str("]\n");
    inst.push_str(rest);
    let mut copies = HEADER.to_string();
    for p in &placements {
        write!(
            copies,
            "[[objects]]\ntype = \"mesh\"\npath = \"ball.obj\"\nmaterial = \"white\"\n{p}\n"
        )
        .unwrap();
    }
    copies.push_str(rest);
    let inst = SceneDesc::parse(&inst, dir.join("inst.toml")).unwrap();
    let copies = SceneDesc::parse(&copies, dir.join("copies.toml")).unwrap();

    fn check<R: Real>(scene: &SceneDesc) {
        let tree = world_of::<R>(scene);
        assert_eq!(tree.instances.list.len(), 9);
        assert_eq!(tree.instances.meshes.len(), 1);
        assert!(
            tree.triangle_count() == 0,
            "the ball is stored once, not copied"
        );
        let mut brute = tree.clone();
        brute.set_accel(Some(false));
        let mut hits = 0;
        for i in 0..20_000u32 {
            let u = |k: u32| R::from_f64(hash_u32(i * 8 + k) as f64 / u32::MAX as f64 - 0.5);
            let o = R::V3::new(
                u(0) * R::from_f64(6.0),
                u(1) * R::from_f64(6.0),
                R::from_f64(-4.0),
            );
            let d = R::V3::new(u(3), u(4), R::from_f64(1.0));
            let ray = Ray::new(o, d.normalize());
            let a = tree.closest_hit(&ray, PrimId::NONE);
            assert_eq!(a, brute.closest_hit(&ray, PrimId::NONE), "ray {i}");
            if let Some((t, id)) = a {
                hits += (id.kind() == PrimId::INSTANCE_TRIANGLE) as u32;
                let short = t * R::from_f64(0.999);
                assert!(!tree.occluded(&ray, short, PrimId::NONE), "ray {i}");
                assert!(tree.occluded(&ray, t * R::from_f64(1.001), PrimId::NONE));
                // Leaving the hit triangle, a ray does not meet it again.
                assert_eq!(tree.closest_hit(&ray, id), brute.closest_hit(&ray, id));
            }
        }
        assert!(hits > 1_000, "too few instance hits ({hits})");
    }
    check::<f32>(&inst);
    check::<f64>(&inst);
    for precision in [Precision::F32, Precision::F64] {
        let (a, fa) = render(&inst, precision);
        let (b, _) = render(&copies, precision);
        assert_eq!(fa.nonfinite, 0);
        let (mean, off) = compare(&a, &b, 0.02);
        // Rounding in object instead of world space moves a few silhouette
        // samples; shading agrees to 0.02 nearly everywhere.
        assert!(
            mean < 0.002 && off < 0.01,
            "{precision:?}: mean {mean}, {off} of pixels off by > 0.02"
        );
    }
}
