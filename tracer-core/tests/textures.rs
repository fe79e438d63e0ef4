//! Model files' materials as authored (issue 34): textures sampled by the
//! documented filter, emission seen directly, alpha cut-outs for camera
//! and shadow rays. Each render is checked against an independent
//! computation of what docs/meshes.md ("Materials and textures") states:
//! the camera's projection, the bilinear filter, the footprint's mip
//! level and the sRGB curve, written out again here in f64.

use tracer_core::render::Precision;
use tracer_core::scene::SceneDesc;

mod common;
use common::meshgen::{
    colour_texels, set_quad_node, textured_quad, textured_quad_with, tmpdir, write_png,
};

fn render(scene: &SceneDesc) -> Vec<[f32; 3]> {
    common::render_with(scene, &scene.render, Precision::F32).resolve()
}

/// The sRGB curve (IEC 61966-2-1), in f64.
fn srgb(c: u8) -> f64 {
    let c = c as f64 / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Bilinear lookup with clamp-to-edge of an sRGB texture at (u, v), in f64.
fn bilinear_srgb(w: u32, h: u32, texels: &[[u8; 4]], u: f64, v: f64) -> [f64; 3] {
    let x = u * w as f64 - 0.5;
    let y = v * h as f64 - 0.5;
    let (x0, y0) = (x.floor(), y.floor());
    let (tx, ty) = (x - x0, y - y0);
    let at = |xi: f64, yi: f64, k: usize| {
        let xi = xi.clamp(0.0, w as f64 - 1.0) as u32;
        let yi = yi.clamp(0.0, h as f64 - 1.0) as u32;
        srgb(texels[(yi * w + xi) as usize][k])
    };
    std::array::from_fn(|k| {
        let top = at(x0, y0, k) * (1.0 - tx) + at(x0 + 1.0, y0, k) * tx;
        let bottom = at(x0, y0 + 1.0, k) * (1.0 - tx) + at(x0 + 1.0, y0 + 1.0, k) * tx;
        top * (1.0 - ty) + bottom * ty
    })
}

/// An emissive-textured quad filling the view: every pixel is the
/// texture (decoded from sRGB, bilinearly filtered) at the point its ray
/// meets the quad, computed here from the camera's projection; nothing
/// else adds (black base colour, no specular layer, no light, no ambient).
#[test]
fn an_emissive_textured_quad_filling_the_view_is_the_texture_resampled_through_the_camera() {
    let (tw, th) = (4u32, 3u32);
    let texels = colour_texels(tw, th);
    // tan(fov_y / 2) = 0.45 from 2 away: the view is [-0.9, 0.9]^2 at z = 0.
    let t = common::EMISSIVE_VIEW_TAN;
    let (w, h) = (31u32, 31u32);
    let scene = common::emissive_texture_scene("tex-emissive", (tw, th), &texels, 2.0, w);
    let img = render(&scene);
    let mut worst = 0.0f64;
    for y in 0..h {
        for x in 0..w {
            // The one sample of a pixel goes through its centre.
            let a = 2.0 * (x as f64 + 0.5) / w as f64 - 1.0;
            let b = 1.0 - 2.0 * (y as f64 + 0.5) / h as f64;
            let (px, py) = (2.0 * a * t, 2.0 * b * t);
            let (u, v) = ((px + 1.0) / 2.0, (1.0 - py) / 2.0);
            let want = bilinear_srgb(tw, th, &texels, u, v);
            let got = img[(y * w + x) as usize];
            for k in 0..3 {
                worst = worst.max((got[k] as f64 - want[k]).abs());
            }
        }
    }
    // f32 arithmetic on values at most 1, through the camera's rounding.
    assert!(worst < 2e-5, "largest difference {worst}");
}

/// Mip levels chosen by the pixel's footprint (docs/meshes.md, "Texture
/// filtering"), against the rule written out again here in f64: a cone
/// of one pixel's angle from the camera, its area on the surface over
/// cos, in texels (the quad's 2 x 2 carries 64 x 64), gives the level of
/// detail λ = ½ log2(area); the filter blends the image's bilinear value
/// with level 1's by λ's fraction. Every level below a one-texel
/// checkerboard is its mean, 0.5 in linear values, stored as the nearest
/// sRGB byte. From 2 away λ spans (0.8, 1.25) over the view: pixels
/// near the centre blend the two; from 6 away λ > 2 and every pixel is the mean, where
/// the full-resolution image alone would alias to black or white.
#[test]
fn a_minified_texture_is_filtered_by_the_pixels_footprint_through_its_mip_levels() {
    let n = common::CHECKER_SIDE;
    let texels = common::checker_texels();
    let byte = (255.0 * (1.055 * 0.5f64.powf(1.0 / 2.4) - 0.055)).round() as u8;
    let grey = srgb(byte);
    let t = common::EMISSIVE_VIEW_TAN;
    let size = 32u32;
    for (distance, lods) in [(2.0f64, 0.8..1.25), (6.0, 2.0..3.0)] {
        let scene = common::minified_checker_scene("tex-mips", distance, size);
        let img = render(&scene);
        let spread = 2.0 * t / size as f64;
        let (mut worst, mut checked) = (0.0f64, 0);
        for y in 0..size {
            for x in 0..size {
                let a = 2.0 * (x as f64 + 0.5) / size as f64 - 1.0;
                let b = 1.0 - 2.0 * (y as f64 + 0.5) / size as f64;
                let (px, py) = (distance * a * t, distance * b * t);
                if px.abs() > 0.9 || py.abs() > 0.9 {
                    continue;
                }
                let (u, v) = ((px + 1.0) / 2.0, (1.0 - py) / 2.0);
                let dist = (px * px + py * py + distance * distance).sqrt();
                let cos = distance / dist;
                let lod = 0.5 * ((spread * dist).powi(2) / cos * (n * n) as f64 / 4.0).log2();
                assert!(lods.contains(&lod), "λ {lod} at pixel ({x}, {y})");
                let full = bilinear_srgb(n, n, &texels, u, v);
                let f = lod.min(1.0);
                let got = img[(y * size + x) as usize];
                for k in 0..3 {
                    let want = full[k] * (1.0 - f) + grey * f;
                    worst = worst.max((got[k] as f64 - want).abs());
                }
                checked += 1;
            }
        }
        assert!(checked >= 100, "{checked} pixels checked");
        // λ from f32 positions (about 1e-6 off) moves a blend of values
        // at most 1 apart by as much; the filter is f32. Measured: 5e-7
        // (from 2 away), 2e-8 (6); the image alone is 0.5 off.
        eprintln!("from {distance} away: largest difference {worst:.2e} over {checked} pixels");
        assert!(
            worst < 1e-5,
            "from {distance} away: largest difference {worst}"
        );
    }
}

/// Where the quad [-0.5, 0.5]^2 at z = 1 is solid at (x, y), for
/// [`quad_over_lit_plane`]'s checks: `None` where rounding may decide.
type Solid<'a> = &'a dyn Fn(f64, f64) -> Option<bool>;

/// The white plane z = 0 under the quad of model file `model` (emissive
/// red, at z = 1) of `common::quad_over_lit_plane_scene` at 64x64.
/// Checks every pixel: where `camera_solid` says the
/// camera ray meets the quad solid, the quad's red; elsewhere the plane,
/// lit where the shadow ray (traced here) crosses z = 1 where
/// `shadow_solid` says the quad is not solid, else only the ambient term.
/// Returns (quad seen, plane seen through the quad's square, lit, shadowed).
fn quad_over_lit_plane(
    dir: &std::path::Path,
    model: &str,
    camera_solid: Solid,
    shadow_solid: Solid,
) -> [usize; 4] {
    let light = common::QUAD_LIGHT;
    let (w, h) = (64u32, 64u32);
    let t = 0.5f64; // view [-2, 2]^2 at z = 0 from 4 away
    let scene = common::quad_over_lit_plane_scene(dir, model, w);
    let img = render(&scene);
    let [mut seen_solid, mut seen_cut, mut lit, mut shadowed] = [0; 4];
    for y in 0..h {
        for x in 0..w {
            let a = 2.0 * (x as f64 + 0.5) / w as f64 - 1.0;
            let b = 1.0 - 2.0 * (y as f64 + 0.5) / h as f64;
            let got = img[(y * w + x) as usize];
            // The camera ray meets z = 1 at 3/4 of the way to z = 0.
            let (qx, qy) = (4.0 * a * t * 0.75, 4.0 * b * t * 0.75);
            let Some(solid) = camera_solid(qx, qy) else {
                continue;
            };
            if solid {
                seen_solid += 1;
                assert_eq!(got, [1.0, 0.0, 0.0], "pixel ({x}, {y}) sees the quad");
                continue;
            }
            // Through the quad (or beside it) to the plane.
            let p = [4.0 * a * t, 4.0 * b * t, 0.0];
            if qx.abs() < 0.5 && qy.abs() < 0.5 {
                seen_cut += 1;
            }
            // Its shadow ray meets z = 1 at s = 1 / light_z of the way.
            let s = 1.0 / light[2];
            let (sx, sy) = (p[0] + (light[0] - p[0]) * s, p[1] + (light[1] - p[1]) * s);
            let Some(blocked) = shadow_solid(sx, sy) else {
                continue;
            };
            let d = [light[0] - p[0], light[1] - p[1], light[2] - p[2]];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let want = if blocked {
                shadowed += 1;
                0.25
            } else {
                lit += 1;
                0.25 + 0.5 * d[2] / len
            };
            for k in 0..3 {
                assert!(
                    (got[k] as f64 - want).abs() < 1e-5,
                    "pixel ({x}, {y}): {got:?}, want {want} ({})",
                    if blocked { "shadowed" } else { "lit" }
                );
            }
        }
    }
    [seen_solid, seen_cut, lit, shadowed]
}

/// Whether (x, y) at z = 1 lies on the quad [-0.5, 0.5]^2: `None` within
/// 0.0125 (a twentieth of a 4x4 texture's texel) of its edge.
fn on_square(x: f64, y: f64) -> Option<bool> {
    let outside = (x.abs() - 0.5).max(y.abs() - 0.5);
    (outside.abs() > 0.0125).then_some(outside < 0.0)
}

/// alphaMode MASK: camera rays see the background through the texels
/// whose alpha is below the cutoff and the quad elsewhere; shadow rays
/// towards a light pass through exactly those texels, so the plane
/// behind is lit where the shadow ray, traced here, crosses the quad at
/// a cut texel or misses it, and holds only the ambient term elsewhere.
/// (The quad is double-sided: the shadow rays meet its back.)
#[test]
fn a_cutout_lets_exactly_its_transparent_texels_through_for_camera_and_shadow_rays() {
    let dir = tmpdir("tex-cutout");
    let (model, alpha) = common::cutout_quad(&dir);
    let texel = |x: f64, y: f64| -> Option<bool> {
        let (u, v) = ((x + 0.5) * 4.0, (0.5 - y) * 4.0);
        let outside = (-u).max(u - 4.0).max(-v).max(v - 4.0);
        if outside > 0.0 {
            return (outside > 0.05).then_some(false);
        }
        let edge = (u - u.round()).abs().min((v - v.round()).abs());
        (edge > 0.05).then_some(alpha[(v as usize) * 4 + u as usize] == 1)
    };
    let [solid, cut, lit, shadowed] = quad_over_lit_plane(&dir, &model, &texel, &texel);
    assert!(
        cut > 100 && solid > 100 && lit > 200 && shadowed > 50,
        "cut {cut}, solid {solid}, lit {lit}, shadowed {shadowed}"
    );
}

/// glTF `doubleSided` false (the default): a ray meeting the back face of
/// a single-sided surface passes through it, camera and shadow rays
/// alike, whichever way the node turns the quad (a rotation, or a mirror
/// whose negative determinant reverses the winding that makes the front);
/// a double-sided quad is solid from both sides. The quad lies between
/// the camera (and the light, on the camera's side) and the plane.
#[test]
fn a_single_sided_surface_is_cut_away_from_behind_for_camera_and_shadow_rays() {
    let never = |_: f64, _: f64| Some(false);
    let away = r#"{"mesh":0,"rotation":[1,0,0,0]}"#;
    for (case, z, nodes, double_sided, front_to_camera) in [
        (
            "facing the camera",
            1.0,
            &[r#"{"mesh":0}"#][..],
            false,
            true,
        ),
        ("turned away", -1.0, &[away][..], false, false),
        (
            "mirrored away",
            -1.0,
            &[r#"{"mesh":0,"scale":[1,1,-1]}"#][..],
            false,
            false,
        ),
        // Two nodes place one mesh: stored once, instanced.
        (
            "instanced, turned away",
            -1.0,
            &[away, away][..],
            false,
            false,
        ),
        ("double-sided, turned away", -1.0, &[away][..], true, false),
    ] {
        let dir = tmpdir("single-sided");
        write_png(&dir, 1, 1, &[[255; 4]]);
        let model = textured_quad(
            &dir,
            0.5,
            z,
            &format!(
                r#"{{"pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1],"metallicFactor":0}},
                    "emissiveFactor":[1,0,0],"doubleSided":{double_sided},
                    "extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}"#
            ),
            "{}",
        );
        set_quad_node(&dir, &model, nodes);
        if nodes.len() > 1 {
            let scene = SceneDesc::parse(
                &format!("[camera]\nposition = [0, 0, 4]\nlook_at = [0, 0, 0]\n[[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n"),
                dir.join("scene.toml"),
            )
            .unwrap();
            let world = tracer_core::world::World::<f32>::build(&scene, &scene.render, 0);
            assert_eq!(world.instances.list.len(), nodes.len(), "{case}");
        }
        // The camera sees the front, or the back of a double-sided quad;
        // the shadow rays (going up to the light) meet the side facing
        // away from the camera.
        let camera: Solid = if front_to_camera || double_sided {
            &on_square
        } else {
            &never
        };
        let shadow: Solid = if !front_to_camera || double_sided {
            &on_square
        } else {
            &never
        };
        let [solid, through, lit, shadowed] = quad_over_lit_plane(&dir, &model, camera, shadow);
        let seen = front_to_camera || double_sided;
        let casts = !front_to_camera || double_sided;
        assert!(
            (solid > 300) == seen
                && (through > 300) != seen
                && lit > 300
                && (shadowed > 100) == casts,
            "{case}: quad seen in {solid} pixels, plane through its square in {through}, lit {lit}, shadowed {shadowed}"
        );
    }
}

/// The path integrator takes a model file's material as its glTF BSDF at
/// each hit, and a model scene with no light gets the default sky
/// (docs/scene-format.md, "Default lighting"): a textured Lambert quad
/// (metallic 0, specularFactor 0) facing the camera under a uniform sky of
/// radiance 1 reflects exactly its texture's colour, since every
/// direction leaving a plane meets the sky (no light, so no shadow ray;
/// one BSDF sample of weight = albedo). Without the texture (the factor
/// alone, white) or under the headlight the pixels would differ.
#[test]
fn path_traced_textured_lambert_under_the_default_sky_is_its_texture() {
    let dir = tmpdir("tex-path-sky");
    let texel = [200u8, 120, 40, 255];
    write_png(&dir, 1, 1, &[texel]);
    let model = textured_quad(
        &dir,
        1.0,
        0.0,
        r#"{"pbrMetallicRoughness":{"baseColorTexture":{"index":0},"metallicFactor":0},
            "extensions":{"KHR_materials_specular":{"specularFactor":0}}}"#,
        r#"{"wrapS":33071,"wrapT":33071}"#,
    );
    let src = format!(
        "[render]\nwidth = 16\nheight = 16\nsamples = 4\nintegrator = \"path\"\n\
         [camera]\nposition = [0, 0, 2]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\nlights = true\n"
    );
    let scene = SceneDesc::parse(&src, dir.join("scene.toml")).unwrap();
    assert!(scene.world.default_lighting);
    let img = render(&scene);
    let want = [0, 1, 2].map(|k| srgb(texel[k]));
    for (i, p) in img.iter().enumerate() {
        for k in 0..3 {
            assert!(
                (p[k] as f64 - want[k]).abs() < 1e-5,
                "pixel {i}: {p:?}, want the texel {want:?}"
            );
        }
    }
}

/// The centre pixel value of the quad of [`textured_quad_with`] with a
/// uniform normal texture `texel` (`normalTexture.scale` `scale`,
/// TANGENT `tangent` or none), Lambert white under a far light along
/// `light` of diffuse 0.8, no ambient.
fn normal_mapped_quad(
    tag: &str,
    texel: [u8; 3],
    scale: f64,
    tangent: Option<[f32; 4]>,
    light: [f64; 3],
) -> Vec<[f32; 3]> {
    let dir = tmpdir(tag);
    write_png(&dir, 2, 2, &[[texel[0], texel[1], texel[2], 255]; 4]);
    let model = textured_quad_with(
        &dir,
        1.0,
        0.0,
        &format!(
            r#"{{"pbrMetallicRoughness":{{"metallicFactor":0,"roughnessFactor":1}},
                "normalTexture":{{"index":0,"scale":{scale}}},
                "extensions":{{"KHR_materials_specular":{{"specularFactor":0}}}}}}"#
        ),
        r#"{"magFilter":9728}"#,
        None,
        tangent,
    );
    let far = 1.0e4;
    let src = format!(
        "[render]\nwidth = 9\nheight = 9\nsamples = 1\n\
         [camera]\nposition = [0, 0, 2]\nlook_at = [0, 0, 0]\nup = [0, 1, 0]\nfov_y = 40\n\
         [world]\nambient = [0, 0, 0]\n\
         [[lights]]\nposition = [{}, {}, {}]\ndiffuse = [0.8, 0.8, 0.8]\nspecular = [0, 0, 0]\n\
         [[objects]]\ntype = \"mesh\"\npath = \"{model}\"\n",
        light[0] * far,
        light[1] * far,
        light[2] * far,
    );
    render(&SceneDesc::parse(&src, dir.join("scene.toml")).unwrap())
}

/// A normal-mapped quad under one far light is the cosine law with the
/// perturbed normal: every pixel is the light times the diffuse colour
/// times n.l, n the texel's tangent-space normal (2 c / 255 - 1, x and y
/// times `scale`) in the frame (T, B, N), computed here in f64. Without
/// TANGENT, MikkTSpace's frame: T +x along u, B +y (up the image), N +z;
/// with TANGENT (0, 1, 0, w): T +y and B = w (N x T) = -w x. Two scales,
/// so the scale and both tangent-frame axes count.
#[test]
fn a_normal_mapped_quad_under_one_light_follows_the_cosine_law_with_the_perturbed_normal() {
    let tilt = {
        let t = [0.35f64, -0.25, 0.9];
        let l = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
        t.map(|c| c / l)
    };
    let texel = tilt.map(|c| ((c + 1.0) / 2.0 * 255.0).round() as u8);
    let light = [0.7f64, 0.2, 0.5];
    // (tangent, its frame: the world normal of a tangent-space one).
    type Frame = fn([f64; 3]) -> [f64; 3];
    let frames: [(Option<[f32; 4]>, Frame); 3] = [
        (None, |l| l),
        (Some([0.0, 1.0, 0.0, 1.0]), |l| [-l[1], l[0], l[2]]),
        (Some([0.0, 1.0, 0.0, -1.0]), |l| [l[1], l[0], l[2]]),
    ];
    for (k, (tangent, frame)) in frames.into_iter().enumerate() {
        for scale in [1.0f64, 0.5] {
            let img = normal_mapped_quad(
                &format!("normal-map-{k}-{scale}"),
                texel,
                scale,
                tangent,
                light,
            );
            let local: [f64; 3] = std::array::from_fn(|k| {
                let c = texel[k] as f64 / 255.0 * 2.0 - 1.0;
                if k < 2 { c * scale } else { c }
            });
            let n = frame(local);
            let len = n.iter().map(|c| c * c).sum::<f64>().sqrt();
            let l_len = light.iter().map(|c| c * c).sum::<f64>().sqrt();
            let cos = (0..3).map(|k| n[k] / len * light[k] / l_len).sum::<f64>();
            let want = 0.8 * cos;
            let flat = 0.8 * light[2] / l_len;
            assert!(
                (want - flat).abs() > 0.05,
                "the tilt must show: {want} against {flat}"
            );
            for (i, p) in img.iter().enumerate() {
                for c in p {
                    assert!(
                        (*c as f64 - want).abs() < 2e-4,
                        "tangent {tangent:?}, scale {scale}, pixel {i}: {c} against {want} (unmapped {flat})"
                    );
                }
            }
        }
    }
}

/// An MTL bump map displaces the surface along its normal by `-bm` times
/// the height (docs/meshes.md, "Bump maps"): on the quad of
/// [`bumped_obj_quad`] the ramp rises 16/15 per unit of u, u spans 2 units
/// of x, so the displaced surface z = bm (16/15) x / 2 has the normal
/// (-s, 0, 1) / |.| with s = bm 8 / 15, and the centre pixel is 0.8 n.l,
/// computed here in f64, for both signs of `-bm` and two lights. A `norm`
/// map given beside it wins (the texel's normal, flat here).
#[test]
fn an_obj_bump_map_tilts_the_normal_as_the_displaced_surface_does() {
    let centre = |img: &[[f32; 3]]| img[15 * 31 + 15];
    for (k, (bm, light)) in [
        (0.25, [1.0, 0.0, 1.0]),
        (-0.5, [1.0, 0.0, 1.0]),
        (0.75, [-0.6, 0.3, 1.0]),
    ]
    .into_iter()
    .enumerate()
    {
        let img = render(&common::bumped_obj_quad(
            &format!("bump-{k}"),
            bm,
            None,
            light,
        ));
        let s = bm * 8.0 / 15.0;
        let n = [-s, 0.0, 1.0];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let want = 0.8 * dot(n, light) / (dot(n, n) * dot(light, light)).sqrt();
        let got = centre(&img);
        for c in got {
            assert!(
                (c as f64 - want).abs() < 1e-5,
                "bm {bm}, light {light:?}: {got:?}, want {want}"
            );
        }
    }
    // `norm` (the flat normal (0, 0, 1) as 128, 128, 255) takes the place
    // of the bump map: the plain cosine law.
    let light = [1.0, 0.0, 1.0];
    let img = render(&common::bumped_obj_quad(
        "bump-norm",
        0.75,
        Some([128, 128, 255]),
        light,
    ));
    let got = centre(&img);
    // x and y are 128 / 255 * 2 - 1 = 1 / 255, z is 1.
    let xy = 128.0f64 / 255.0 * 2.0 - 1.0;
    let n = [xy, xy, 1.0];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    let want = 0.8 * (n[0] + n[2]) / len / 2f64.sqrt();
    for c in got {
        assert!((c as f64 - want).abs() < 1e-4, "norm: {got:?}, want {want}");
    }
}

/// A textured mesh placed by several nodes is stored once (its triangles,
/// vertex attributes and tree in its own space) and renders as the same
/// file with the mesh copied per node, within rounding: DamagedHelmet
/// three times, one turned and scaled, one mirrored (which flips its
/// tangent frame's bitangent), under textures, its normal map and its
/// emission. Pixels where the instanced and copied triangles (rounded in
/// object and world space) part may differ; the mean stays at rounding.
#[test]
fn a_textured_mesh_placed_by_three_nodes_is_stored_once_and_renders_as_copies() {
    let dir = common::meshgen::tmpdir("three-helmets");
    let (inst, copies) = (
        common::three_helmets(&dir, false, 120, 48),
        common::three_helmets(&dir, true, 120, 48),
    );
    let prepared =
        tracer_core::render::PreparedFrame::build(&inst, &inst.render, 0, Precision::F32).unwrap();
    let tracer_core::render::PreparedFrame::F32(w) = &prepared else {
        unreachable!()
    };
    assert_eq!((w.instances.list.len(), w.instances.meshes.len()), (3, 1));
    let stored = w.instances.meshes[0].triangles.len();
    assert!(w.triangle_count() == 0, "the helmet is not copied");
    assert_eq!(w.attrs.tri.len(), stored, "its attributes are stored once");
    let s = &inst.render;
    let (a, b) = (
        common::render_with(&inst, s, Precision::F32).resolve(),
        common::render_with(&copies, &copies.render, Precision::F32).resolve(),
    );
    // The helmets fill much of the view (two black images would agree too).
    let covered = a.iter().filter(|p| **p != a[0]).count();
    assert!(covered > a.len() / 5, "{covered} pixels covered");
    let d = common::diff(&a, &b, 2.0 / 255.0);
    eprintln!(
        "instanced vs copied helmets: mean {:.2e}, max {:.3}, {} of {} pixels over 2/255",
        d.mean, d.max, d.over, d.pixels
    );
    assert!(
        d.mean < 1e-4 && d.over * 100 <= covered,
        "mean {}, {} of {} pixels over 2/255",
        d.mean,
        d.over,
        d.pixels
    );
}
