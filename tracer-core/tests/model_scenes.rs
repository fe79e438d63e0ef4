//! What scenes take from model files beyond triangles (issue 34): glTF
//! cameras and the automatic camera, `KHR_lights_punctual` lights in
//! Tessera's units, the default lighting, a glTF included from TOML with
//! its camera and lights, and model files as scenes. Files are generated
//! here; each rule is checked against the formula docs/scene-format.md
//! states ("Model files as scenes").

use std::f64::consts::PI;
use std::path::{Path, PathBuf};

use base64::Engine as _;
use tracer_core::render::Precision;
use tracer_core::scene::{LightShape, ModelSceneOptions, PathLightKind, SceneDesc, Vec3};

mod common;
use common::meshgen::tmpdir;

fn render(scene: &SceneDesc) -> Vec<[f32; 3]> {
    common::render_with(scene, &scene.render, Precision::F32).resolve()
}

/// A glTF file: the white (metallic 0, roughness 1) quad [-1, 1]^2 at
/// z = 0 facing +Z, placed by node 0, then the nodes `nodes` (JSON
/// objects, numbered from 1), with `cameras` and `lights` (JSON arrays).
fn quad_gltf(dir: &Path, name: &str, nodes: &[&str], cameras: &str, lights: &str) -> PathBuf {
    let mut bin = Vec::new();
    for c in [-1f32, -1., 0., 1., -1., 0., 1., 1., 0., -1., 1., 0.] {
        bin.extend(c.to_le_bytes());
    }
    for _ in 0..4 {
        for c in [0f32, 0., 1.] {
            bin.extend(c.to_le_bytes());
        }
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        bin.extend(i.to_le_bytes());
    }
    let uri = base64::engine::general_purpose::STANDARD.encode(&bin);
    let node_ids: Vec<String> = (0..=nodes.len()).map(|i| i.to_string()).collect();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[{ids}]}}],
        "nodes":[{{"mesh":0}}{more}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1}},"indices":2,"material":0}}]}}],
        "materials":[{{"name":"white","pbrMetallicRoughness":{{"metallicFactor":0}}}}],
        "cameras":{cameras},
        "extensionsUsed":["KHR_lights_punctual"],
        "extensions":{{"KHR_lights_punctual":{{"lights":{lights}}}}},
        "buffers":[{{"byteLength":{len},"uri":"data:application/octet-stream;base64,{uri}"}}],
        "bufferViews":[{{"buffer":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":48}},{{"buffer":0,"byteOffset":96,"byteLength":12}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-1,-1,0],"max":[1,1,0]}},
                     {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC3"}},
                     {{"bufferView":2,"componentType":5123,"count":6,"type":"SCALAR"}}]}}"#,
        ids = node_ids.join(","),
        more = nodes.iter().map(|n| format!(",{n}")).collect::<String>(),
        len = bin.len(),
    );
    let p = dir.join(name);
    std::fs::write(&p, json).unwrap();
    p
}

/// `KHR_materials_volume` on a transmissive glTF material becomes the
/// absorption inside (sigma = -ln(attenuationColor) / attenuationDistance
/// per channel); without the extension nothing is absorbed.
#[test]
fn khr_materials_volume_becomes_the_absorption_inside() {
    let dir = tmpdir("volume");
    let plain = quad_gltf(&dir, "plain.gltf", &[], "[]", "[]");
    let src = std::fs::read_to_string(&plain).unwrap();
    let material = r#""materials":[{"name":"white","pbrMetallicRoughness":{"metallicFactor":0}}]"#;
    assert!(src.contains(material));
    let volume = src.replace(
        material,
        r#""materials":[{"name":"white","pbrMetallicRoughness":{"metallicFactor":0},
            "extensions":{"KHR_materials_transmission":{"transmissionFactor":1},
                          "KHR_materials_volume":{"thicknessFactor":0.1,"attenuationDistance":2.0,"attenuationColor":[0.5,0.25,1.0]}}}]"#,
    );
    let path = dir.join("volume.gltf");
    std::fs::write(&path, volume).unwrap();
    let absorption = |p: &Path| {
        let desc = model(p, &ModelSceneOptions::default()).unwrap();
        let frame =
            tracer_core::render::PreparedFrame::build(&desc, &desc.render, 0, Precision::F64)
                .unwrap();
        let tracer_core::render::PreparedFrame::F64(w) = frame else {
            unreachable!()
        };
        let i = w
            .materials
            .iter()
            .position(|m| m.pbr != tracer_core::material::NO_PBR)
            .expect("the file's material");
        w.bsdfs[i].absorption.to_array()
    };
    let a = absorption(&path);
    let want = [2f64.ln() / 2.0, 4f64.ln() / 2.0, 0.0];
    for k in 0..3 {
        assert!((a[k] - want[k]).abs() < 1e-6, "{a:?} against {want:?}");
    }
    assert_eq!(absorption(&plain), [0.0; 3]);
}

/// A perspective camera with tan(yfov / 2) = 0.5 and aspect ratio 1.
const CAMERA: &str = r#"[{"type":"perspective","name":"front","perspective":{"yfov":0.9272952180016122,"aspectRatio":1.0,"znear":0.1}},
                         {"type":"orthographic","name":"flat","orthographic":{"xmag":1,"ymag":1,"znear":0.1,"zfar":10}}]"#;

fn scene(dir: &Path, src: &str) -> Result<SceneDesc, String> {
    SceneDesc::parse(src, dir.join("scene.toml")).map_err(|e| e.to_string())
}

fn model(path: &Path, options: &ModelSceneOptions) -> Result<SceneDesc, String> {
    SceneDesc::load_input(path, options).map_err(|e| e.to_string())
}

/// The value of the centre pixel of an odd-sized image: its one sample
/// (grid, 1 spp) goes exactly through the image's centre.
fn centre(img: &[[f32; 3]], w: u32, h: u32) -> [f32; 3] {
    img[(h / 2 * w + w / 2) as usize]
}

#[test]
fn a_gltf_camera_renders_the_quad_where_the_projection_puts_it() {
    let dir = tmpdir("model-camera");
    // Camera at z = 3 looking down -Z: the quad's edges (x = +-1 at
    // distance 3) lie at tan = 1/3, i.e. 2/3 of the way from the centre to
    // the image's edge (tan(fov/2) = 0.5).
    let p = quad_gltf(
        &dir,
        "cam.gltf",
        &[r#"{"camera":0,"translation":[0,0,3]}"#],
        CAMERA,
        "[]",
    );
    let s = model(
        &p,
        &ModelSceneOptions {
            width: Some(61),
            ..Default::default()
        },
    )
    .unwrap();
    // aspectRatio 1 and only --width given: the height follows.
    assert_eq!((s.render.width, s.render.height), (61, 61));
    assert_eq!(s.camera.position, Vec3([0.0, 0.0, 3.0]));
    assert_eq!(s.camera.look_at, Vec3([0.0, 0.0, 2.0]));
    // yfov is stored as f32 in the file.
    assert!((s.camera.fov_y.0 - 2.0 * 0.5f64.atan().to_degrees()).abs() < 1e-5);
    let img = render(&SceneDesc {
        render: tracer_core::scene::RenderSettings {
            samples: 1,
            ..s.render
        },
        ..s
    });
    // Quad edges at pixel 61 * (1 -+ 2/3) / 2 = 10.17 and 50.83.
    for y in 0..61u32 {
        for x in 0..61u32 {
            let v = img[(y * 61 + x) as usize][0];
            let inside = |c: u32| (12..=49).contains(&c);
            let outside = |c: u32| c <= 9 || c >= 51;
            if inside(x) && inside(y) {
                assert!(v > 0.1, "({x}, {y}) should show the quad: {v}");
            } else if outside(x) || outside(y) {
                assert_eq!(v, 0.0, "({x}, {y}) should be background");
            }
        }
    }
    // By name, by index; an orthographic camera and a missing one are refused.
    let by_name = ModelSceneOptions {
        camera: Some("front".into()),
        ..Default::default()
    };
    assert_eq!(
        model(&p, &by_name).unwrap().camera.position,
        Vec3([0.0, 0.0, 3.0])
    );
    let e = model(
        &p,
        &ModelSceneOptions {
            camera: Some("1".into()),
            ..Default::default()
        },
    )
    .unwrap_err();
    assert_eq!(
        e,
        format!(
            "{}: --camera 1: no camera 1 is placed by the file's default scene (its cameras: 0 \"front\" (perspective))",
            p.display()
        )
    );
    let p2 = quad_gltf(
        &dir,
        "ortho.gltf",
        &[
            r#"{"camera":1,"translation":[0,0,3]}"#,
            r#"{"camera":0,"translation":[0,0,4]}"#,
        ],
        CAMERA,
        "[]",
    );
    let e = model(
        &p2,
        &ModelSceneOptions {
            camera: Some("flat".into()),
            ..Default::default()
        },
    )
    .unwrap_err();
    assert_eq!(
        e,
        format!(
            "{}: --camera flat: camera 1 \"flat\" is orthographic, which Tessera's camera model (a pinhole, docs/scene-format.md) cannot render: pick a perspective camera (its cameras: 1 \"flat\" (orthographic), 0 \"front\" (perspective)) or \"auto\"",
            p2.display()
        )
    );
    // The default skips the orthographic first camera, and says so.
    let s = model(&p2, &ModelSceneOptions::default()).unwrap();
    assert_eq!(s.camera.position, Vec3([0.0, 0.0, 4.0]));
    assert_eq!(
        s.warnings,
        [format!(
            "{}: its first camera, 1 \"flat\" (orthographic), cannot be rendered (Tessera's camera is a pinhole); camera 0 \"front\" (perspective) is used",
            p2.display()
        )]
    );
}

#[test]
fn the_automatic_camera_frames_the_bounding_sphere_as_documented() {
    let dir = tmpdir("model-auto");
    let p = quad_gltf(&dir, "q.gltf", &[], "[]", "[]");
    let s = model(&p, &ModelSceneOptions::default()).unwrap();
    // Box [-1,1]^2 x {0}: centre 0, r = sqrt(2); 800x600 is wider than
    // tall, so the vertical half-angle 22.5 degrees decides.
    let d = 2f64.sqrt() / 22.5f64.to_radians().sin();
    assert_eq!((s.render.width, s.render.height), (800, 600));
    assert_eq!(s.camera.look_at, Vec3([0.0, 0.0, 0.0]));
    assert_eq!(s.camera.position, Vec3([0.0, 0.0, d]));
    assert_eq!(s.camera.fov_y.0, 45.0);
    // A tall image: the horizontal half-angle decides.
    let tall = ModelSceneOptions {
        width: Some(30),
        height: Some(90),
        ..Default::default()
    };
    let s = model(&p, &tall).unwrap();
    let a = (22.5f64.to_radians().tan() / 3.0).atan();
    assert!((s.camera.position.0[2] - 2f64.sqrt() / a.sin()).abs() < 1e-12);
    // The bounding sphere touches the narrow edges: the quad's corners lie
    // inside the picture, its edge midpoints well inside.
    let s = model(
        &p,
        &ModelSceneOptions {
            width: Some(41),
            height: Some(41),
            ..Default::default()
        },
    )
    .unwrap();
    let img = render(&SceneDesc {
        render: tracer_core::scene::RenderSettings {
            samples: 1,
            ..s.render
        },
        ..s
    });
    assert!(img[20 * 41 + 20][0] > 0.1, "centre lit");
    assert!(img.iter().all(|p| p[0] >= 0.0));
    let lit = img.iter().filter(|p| p[0] > 0.0).count();
    // The quad's area over the view's: (2 / (2 d tan 22.5))^2 of 41^2.
    let d = 2f64.sqrt() / 22.5f64.to_radians().sin();
    let share = (2.0 / (2.0 * d * 22.5f64.to_radians().tan())).powi(2);
    let expected = share * 41.0 * 41.0;
    assert!(
        (lit as f64 - expected).abs() < 4.0 * 41.0,
        "{lit} pixels lit, {expected:.0} expected"
    );
}

/// A point light of `intensity` at the camera, on the quad's axis: the
/// centre pixel is intensity / (pi d_ref^2) (diffuse 1 plus specular 0.04
/// with N.H = 1), d_ref^2 = |p - c|^2 + r^2 = 9 + 2.
#[test]
fn punctual_lights_give_radiance_in_the_documented_units() {
    let dir = tmpdir("model-lights");
    let at = |light: usize| {
        format!(
            r#"{{"extensions":{{"KHR_lights_punctual":{{"light":{light}}}}},"translation":[0,0,3]}}"#
        )
    };
    let lights = r#"[{"type":"point","name":"bulb","intensity":10,"color":[1,0.5,0.25]},
                     {"type":"directional","name":"sun","intensity":2},
                     {"type":"spot","name":"spot","intensity":10,"spot":{"innerConeAngle":0.1,"outerConeAngle":0.3}}]"#;
    let cam = r#"{"camera":0,"translation":[0,0,3]}"#;
    // Under path: the centre pixel of each light's render (direct light).
    let mut path_centre = Vec::new();
    for (light, want) in [
        (
            0usize,
            [10.0 / (PI * 11.0), 5.0 / (PI * 11.0), 2.5 / (PI * 11.0)],
        ),
        (1, [2.0 / PI; 3]),
        (2, [10.0 / (PI * 11.0); 3]),
    ] {
        let l = at(light);
        let p = quad_gltf(&dir, &format!("l{light}.gltf"), &[cam, &l], CAMERA, lights);
        let s = model(
            &p,
            &ModelSceneOptions {
                width: Some(21),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(s.lights.len(), 1, "the file's light, no default lighting");
        assert_eq!(s.world.ambient, Vec3([0.0; 3]));
        let l = &s.lights[0];
        assert_eq!(l.shape, LightShape::Point);
        for k in 0..3 {
            assert!(
                (l.diffuse.0[k] - want[k]).abs() < 1e-12,
                "{:?} {want:?}",
                l.diffuse
            );
        }
        assert_eq!(l.specular, l.diffuse);
        if light == 1 {
            // Against its direction (-Z), 1000 radii from the box's centre.
            assert_eq!(l.position, Vec3([0.0, 0.0, 1000.0 * 2f64.sqrt()]));
        } else {
            assert_eq!(l.position, Vec3([0.0, 0.0, 3.0]));
        }
        // Physical units for the path integrator: candela, and lux times
        // the square of the directional light's distance.
        let physical = match light {
            0 => [10.0, 5.0, 2.5],
            1 => [2.0 * 2.0e6; 3], // D = 1000 r, r = sqrt 2
            _ => [10.0; 3],
        };
        // Under path, the spot keeps its cone and the sun is directional.
        let kind = match l.path_kind {
            None => "point",
            Some(PathLightKind::Spot {
                direction,
                cos_inner,
                cos_outer,
            }) => {
                assert_eq!(direction, Vec3([0.0, 0.0, -1.0]));
                // The angles as the file's f32s.
                assert!((cos_inner - 0.1f64.cos()).abs() < 1e-8, "{cos_inner}");
                assert!((cos_outer - 0.3f64.cos()).abs() < 1e-8, "{cos_outer}");
                "spot"
            }
            Some(PathLightKind::Directional {
                direction,
                irradiance,
                radius,
            }) => {
                assert_eq!(direction, Vec3([0.0, 0.0, -1.0]));
                assert_eq!(irradiance, Vec3([2.0; 3]));
                assert_eq!(radius, 2f64.sqrt());
                "directional"
            }
        };
        assert_eq!(kind, ["point", "directional", "spot"][light]);
        let got = l.path_radiance.expect("a model light's physical units").0;
        for k in 0..3 {
            assert!(
                (got[k] - physical[k]).abs() < 1e-9 * physical[k],
                "{got:?} {physical:?}"
            );
        }
        let traced = render(&SceneDesc {
            render: tracer_core::scene::RenderSettings {
                samples: 1,
                max_depth: 2,
                integrator: tracer_core::scene::Integrator::Path,
                ..s.render
            },
            ..s.clone()
        });
        path_centre.push(centre(&traced, 21, 21));
        let img = render(&SceneDesc {
            render: tracer_core::scene::RenderSettings {
                samples: 1,
                ..s.render
            },
            ..s.clone()
        });
        let c = centre(&img, 21, 21);
        for k in 0..3 {
            let expect = want[k] * 1.04;
            assert!(
                (c[k] as f64 - expect).abs() < 1e-5 * expect,
                "light {light} channel {k}: {} against {expect}",
                c[k]
            );
        }
        let spot_warning = s.warnings.iter().any(|w| {
            w.ends_with("light 2 \"spot\" (spot) (cone 5.7..17.2 degrees) renders as a point light under Whitted, shining every way (its cone is the path integrator's only)")
        });
        assert_eq!(spot_warning, light == 2, "{:?}", s.warnings);
        let falloff = s
            .warnings
            .iter()
            .any(|w| w.contains("1 point or spot light(s) render without inverse-square falloff"));
        assert_eq!(falloff, light != 1, "{:?}", s.warnings);
    }
    // Path: the same BRDF at normal incidence under each light, so the
    // centre pixels are in the ratio of the irradiances: I / d^2 = 10/9
    // (times the colour) for the point and spot lights at d = 3, 2 lux
    // for the sun.
    let irradiance = [
        [10.0 / 9.0, 5.0 / 9.0, 2.5 / 9.0],
        [2.0; 3],
        [10.0 / 9.0; 3],
    ];
    for (light, e) in irradiance.iter().enumerate() {
        for k in 0..3 {
            let (got, want) = (
                path_centre[light][k] as f64 / path_centre[1][k] as f64,
                e[k] / 2.0,
            );
            assert!(
                path_centre[1][k] > 0.0 && (got - want).abs() < 1e-4 * want,
                "path, light {light} channel {k}: {got} of the sun's, want {want} ({path_centre:?})"
            );
        }
    }
}

#[test]
fn a_file_without_lights_gets_the_default_lighting() {
    let dir = tmpdir("model-default-light");
    let p = quad_gltf(
        &dir,
        "dark.gltf",
        &[r#"{"camera":0,"translation":[0,0,3]}"#],
        CAMERA,
        "[]",
    );
    let s = model(
        &p,
        &ModelSceneOptions {
            width: Some(21),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(s.world.ambient, Vec3([0.2; 3]));
    assert_eq!(s.lights.len(), 1);
    assert_eq!(s.lights[0].position, s.camera.position);
    assert_eq!(s.lights[0].diffuse, Vec3([0.8; 3]));
    let img = render(&SceneDesc {
        render: tracer_core::scene::RenderSettings {
            samples: 1,
            ..s.render
        },
        ..s
    });
    // ambient 0.2 * 1 + headlight 0.8 * (1 + 0.04) at the centre.
    let c = centre(&img, 21, 21)[0] as f64;
    assert!((c - (0.2 + 0.8 * 1.04)).abs() < 1e-5, "{c}");
}

#[test]
fn a_toml_scene_includes_a_gltf_with_its_camera_and_lights_and_overrides_them() {
    let dir = tmpdir("model-include");
    let lights = r#"[{"type":"point","name":"key","intensity":10},{"type":"point","name":"fill","intensity":1}]"#;
    let key = r#"{"extensions":{"KHR_lights_punctual":{"light":0}},"translation":[0,0,3]}"#;
    let fill = r#"{"extensions":{"KHR_lights_punctual":{"light":1}},"translation":[0,2,0]}"#;
    quad_gltf(
        &dir,
        "lamp.gltf",
        &[r#"{"camera":0,"translation":[0,0,3]}"#, key, fill],
        CAMERA,
        lights,
    );
    let object = "[[objects]]\ntype = \"mesh\"\npath = \"lamp.gltf\"\n";
    // Camera and lights from the file, placed by the object's transform.
    let s = scene(
        &dir,
        &format!("[render]\nheight = 30\n{object}camera = \"front\"\nlights = true\ntranslate = [5, 0, 0]\n"),
    )
    .unwrap();
    assert_eq!((s.render.width, s.render.height), (30, 30), "aspectRatio 1");
    assert_eq!(s.camera.position, Vec3([5.0, 0.0, 3.0]));
    assert_eq!(s.lights.len(), 2);
    assert_eq!(s.lights[0].position, Vec3([5.0, 0.0, 3.0]));
    assert_eq!(s.lights[1].position, Vec3([5.0, 2.0, 0.0]));
    // Overrides: the scene's own [camera] and lights instead.
    let own =
        "[camera]\nposition = [0, 0, 9]\nlook_at = [0, 0, 0]\n[[lights]]\nposition = [1, 1, 1]\n";
    let s = scene(&dir, &format!("{own}{object}lights = [\"fill\"]\n")).unwrap();
    assert_eq!(s.camera.position, Vec3([0.0, 0.0, 9.0]));
    assert_eq!(s.lights.len(), 2);
    assert_eq!(
        s.lights[0].position,
        Vec3([1.0, 1.0, 1.0]),
        "the scene's first"
    );
    assert_eq!(s.lights[1].position, Vec3([0.0, 2.0, 0.0]));
    let s = scene(&dir, &format!("{own}{object}")).unwrap();
    assert_eq!(
        s.lights.len(),
        1,
        "lights = false by default: TOML scenes as before"
    );
    assert_eq!(s.world.ambient, Vec3([0.0; 3]));
    // Refusals name the object and what is wrong.
    let e = scene(&dir, &format!("{own}{object}camera = 0\n")).unwrap_err();
    assert!(
        e.ends_with("objects[0] (mesh).camera: the scene's [camera] table gives the camera already: remove one of the two"),
        "{e}"
    );
    let e = scene(
        &dir,
        &format!("{object}camera = \"auto\"\nlights = [\"lamp\"]\n"),
    )
    .unwrap_err();
    assert!(
        e.ends_with("objects[0] (mesh).lights: no light named \"lamp\" in the file's default scene (its lights: \"key\", \"fill\")"),
        "{e}"
    );
    let e = scene(&dir, object).unwrap_err();
    assert!(
        e.ends_with("scene.toml:1:1: missing table [camera] (or `camera = ...` on a mesh object: one of its glTF cameras, or \"auto\")"),
        "{e}"
    );
    let e = scene(
        &dir,
        &format!("{object}camera = \"auto\"\n{object}camera = \"auto\"\n"),
    )
    .unwrap_err();
    assert!(
        e.ends_with("objects[1] (mesh).camera: objects[0] gives the scene's camera already: only one object may"),
        "{e}"
    );
}

#[test]
fn a_ply_is_refused_as_a_scene_with_the_toml_to_write() {
    let dir = tmpdir("model-ply");
    let p = dir.join("bunny.ply");
    std::fs::write(&p, "ply\n").unwrap();
    let e = model(&p, &ModelSceneOptions::default()).unwrap_err();
    assert!(
        e.starts_with(&format!(
            "{}: a PLY file is a mesh without camera, lights or materials, so it is not a scene by itself: wrap it in a TOML scene",
            p.display()
        )),
        "{e}"
    );
    // The TOML it shows is a scene that renders.
    let toml: String = e
        .lines()
        .skip_while(|l| !l.starts_with("[[objects]]"))
        .take_while(|l| !l.is_empty())
        .map(|l| format!("{l}\n"))
        .collect();
    common::meshgen::write_obj(
        &dir.join("tri.obj"),
        &[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        &[[0, 1, 2]],
        false,
    );
    let s = scene(&dir, &toml.replace("bunny.ply", "tri.obj")).unwrap();
    assert_eq!(s.lights.len(), 1, "default lighting");
}

/// The real assets of ../shared/scenes, rendered from their files with no
/// TOML (automatic camera or the file's own, default lighting), each
/// pinned by its own golden image in tests/golden/ (`asset-*.png`; see
/// tests/examples.rs for re-blessing): Whitted at 4 spp for every asset,
/// the path integrator at 16 spp for those whose look depends on it
/// (textures, cut-outs and blending, emission, Sibenik's interior). The
/// path images are noisy but deterministic (the same seeds); their
/// tolerance allows 1% of pixels to take another path, Whitted's 0.1%.
#[test]
fn shared_assets_match_their_golden_images() {
    use tracer_core::film::to_srgb8;
    use tracer_core::scene::Integrator;
    let assets = [
        (
            "DamagedHelmet",
            "gltf/DamagedHelmet/glTF/DamagedHelmet.gltf",
            true,
        ),
        (
            "AlphaBlendModeTest",
            "gltf/AlphaBlendModeTest/glTF/AlphaBlendModeTest.gltf",
            true,
        ),
        (
            "TextureTransformTest",
            "gltf/TextureTransformTest/glTF/TextureTransformTest.gltf",
            false,
        ),
        (
            "TextureSettingsTest",
            "gltf/TextureSettingsTest/glTF/TextureSettingsTest.gltf",
            false,
        ),
        (
            "EmissiveStrengthTest",
            "gltf/EmissiveStrengthTest/glTF/EmissiveStrengthTest.gltf",
            true,
        ),
        (
            "SpecularTest",
            "gltf/SpecularTest/glTF/SpecularTest.gltf",
            false,
        ),
        ("Cameras", "gltf/Cameras/glTF/Cameras.gltf", false),
        ("Sibenik", "obj/Sibenik_Cathedral/sibenik.obj.gz", true),
    ];
    let mut failures = vec![];
    for (name, file, path_too) in assets {
        let integrators: &[(Integrator, u32, &str, usize)] = if path_too {
            &[
                (Integrator::Whitted, 4, "whitted", 1),
                (Integrator::Path, 16, "path", 10),
            ]
        } else {
            &[(Integrator::Whitted, 4, "whitted", 1)]
        };
        for &(integrator, samples, tag, per_mille) in integrators {
            // Cameras.gltf's camera has aspect ratio 1.
            let (w, h) = if name == "Cameras" {
                (120, 120)
            } else {
                (160, 120)
            };
            let mut desc = common::shared_asset(&format!("scenes/{file}"), w, h);
            desc.render.integrator = integrator;
            desc.render.samples = samples;
            let (w, h) = (desc.render.width, desc.render.height);
            let got = to_srgb8(&render(&desc));
            if let Err(e) =
                common::check_golden(&format!("asset-{name}-{tag}.png"), w, h, got, per_mille)
            {
                failures.push(e);
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
