//! The path integrator against an independent oracle, Mitsuba 3
//! (`scalar_rgb`, its `path` integrator). One description ([`Case`])
//! writes both scenes: Tessera's TOML (materials given by `[bsdf.NAME]`)
//! and a Mitsuba dict, rendered by `python3` (the `mitsuba` package,
//! installed by scripts/test; its absence fails the test).
//!
//! Each case compares converged images within the Monte Carlo noise floor
//! measured in the same test: Mitsuba renders twice (seeds 1 and 2) and
//! the RMSE between those two renders is the floor. Tessera renders with
//! the same samples per pixel, so an unbiased Tessera image lies about
//! that far from Mitsuba's first render too. Two checks per case:
//! - per pixel: RMSE(Tessera, Mitsuba 1) <= 1.5 RMSE(Mitsuba 2, Mitsuba 1)
//!   (1.5: the estimators differ, so their variances do too) + the case's
//!   bias allowance;
//! - the image mean (which averages the noise away, so it sees bias that
//!   per-pixel noise hides): |mean(T) - mean(M1)| <= 4 standard errors of
//!   that difference (estimated from the two Mitsuba renders) + the bias
//!   allowance times the mean.
//!
//! The bias allowance is 0 where both renderers integrate the same
//! function and stated per case where definitions differ.

mod common;

use std::fmt::Write as _;
use std::process::Command;
use tracer_core::film::WorkRegion;

use tracer_core::film::{Rect, SampleRange};
use tracer_core::render::{CpuRenderer, Precision, PreparedFrame};
use tracer_core::scene::SceneDesc;

type V = [f64; 3];

#[derive(Clone, Copy)]
enum Mat {
    /// Lambert only (glTF dielectric with specular factor 0).
    Lambert(V),
    /// glTF metal, white (F = 1, as Mitsuba's `material = none`), of this roughness.
    Metal(f64),
    /// Smooth glass (transmission 1) of this ior.
    Glass(f64),
    /// Smooth glass of this ior around a volume that keeps `colour` of
    /// the light over `distance` (`KHR_materials_volume`'s attenuation;
    /// Mitsuba: a `dielectric` whose interior is a purely absorbing
    /// `homogeneous` medium, sigma_t = -ln(colour) / distance (as an RGB
    /// in [0, 1] times `scale`), albedo 0, rendered by `volpath`).
    AbsorbingGlass { ior: f64, colour: V, distance: f64 },
    /// A model file's Lambert material (glTF metallic 0, specularFactor 0)
    /// whose base colour is the case's texture (Mitsuba: a `bitmap`);
    /// only on a [`Shape::Quad`].
    Textured,
}

#[derive(Clone, Copy)]
enum Shape {
    Sphere {
        c: V,
        r: f64,
    },
    /// { p : p.n = d } for unit `n` facing the camera (Mitsuba: a square of
    /// side 2e4 there: its edge lies below a pixel's size from the camera).
    Plane {
        n: V,
        d: f64,
    },
    /// The parallelogram with texture coordinates (0, 0) at `corner`, u
    /// growing along `eu` and v along `ev` (to (1, 1)), facing `eu x ev`:
    /// for Tessera a glTF file, for Mitsuba a `rectangle`, whose uv is
    /// ((x + 1) / 2, (y + 1) / 2) of its local square.
    Quad {
        corner: V,
        eu: V,
        ev: V,
    },
}

#[derive(Clone, Copy)]
enum Light {
    Point {
        p: V,
        intensity: V,
    },
    /// Radiance `l` from a parallelogram (Mitsuba: from its `edge_u x
    /// edge_v` side only: the cases put nothing on the other side).
    Quad {
        corner: V,
        eu: V,
        ev: V,
        l: V,
    },
    /// Radiance `l` from the `edge_u x edge_v` side of a parallelogram of
    /// two emissive triangles: for Tessera an OBJ mesh whose material is
    /// `[bsdf] emission` (black otherwise), light-sampled as triangles;
    /// for Mitsuba the same `rectangle` area emitter as [`Light::Quad`].
    Mesh {
        corner: V,
        eu: V,
        ev: V,
        l: V,
    },
    /// A model file's `KHR_lights_punctual` spot light at `p` shining
    /// along `dir`, `intensity` candela on its axis, outer cone angle
    /// `outer` degrees, its inner cone 0.001 in cosine inside it: glTF's
    /// falloff (squared, linear in the cosine) and Mitsuba's `spot`
    /// (linear in the angle, from `beam_width` to `cutoff_angle` set to
    /// the same cones) then differ only within a ring of 0.12 degrees.
    Spot {
        p: V,
        dir: V,
        intensity: V,
        outer: f64,
    },
    /// A model file's directional light along `dir` of `irradiance` lux
    /// (Mitsuba's `directional`).
    Directional {
        dir: V,
        irradiance: V,
    },
    /// A glTF parallelogram (uv as [`Shape::Quad`]'s) emitting the case's
    /// texture from its `eu x ev` side (`emissiveTexture`, factor 1):
    /// light-sampled as two triangles by their mean texel, radiance the
    /// texel at the sampled point; Mitsuba: an area emitter whose
    /// radiance is a `bitmap`.
    TexturedQuad {
        corner: V,
        eu: V,
        ev: V,
    },
}

/// The inner cone angle (radians) of a [`Light::Spot`] of outer angle
/// `outer` degrees.
fn spot_inner(outer: f64) -> f64 {
    (outer.to_radians().cos() + 0.001).acos()
}

/// A light's colour as glTF's colour and intensity (colour at most 1).
fn colour_intensity(c: V) -> (V, f64) {
    let i = c[0].max(c[1]).max(c[2]);
    (c.map(|x| x / i), i)
}

struct Case {
    name: &'static str,
    size: u32,
    spp: u32,
    max_depth: u32,
    eye: V,
    look_at: V,
    fov_y: f64,
    environment: V,
    objects: Vec<(Shape, Mat)>,
    lights: Vec<Light>,
    /// Relative bias the definitions allow (see each case).
    bias: f64,
    /// The PNG of [`Mat::Textured`]: width, height, sRGB RGBA texels.
    texture: Option<(u32, u32, Vec<[u8; 4]>)>,
    /// An environment image (`env.exr`: width, height, linear RGB texels)
    /// in place of `environment` (Mitsuba: an `envmap` of the same file).
    env_image: Option<(u32, u32, Vec<[f32; 3]>)>,
}

fn rgb(v: V) -> String {
    format!("[{}, {}, {}]", v[0], v[1], v[2])
}

fn py_rgb(v: V) -> String {
    format!("{{'type': 'rgb', 'value': {}}}", rgb(v))
}

fn cross(a: V, b: V) -> V {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(a: V) -> V {
    let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    a.map(|x| x / l)
}

impl Case {
    /// The case's files (the texture, the glTF quads) in a fresh directory.
    fn files(&self) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "tessera-mitsuba-{}-{}",
            self.name,
            std::process::id()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        if let Some((w, h, texels)) = &self.texture {
            let img =
                image::RgbaImage::from_fn(*w, *h, |x, y| image::Rgba(texels[(y * w + x) as usize]));
            img.save(dir.join("tex.png")).unwrap();
        }
        if let Some((w, h, texels)) = &self.env_image {
            let img = image::Rgb32FImage::from_fn(*w, *h, |x, y| {
                image::Rgb(texels[(y * w + x) as usize])
            });
            img.save(dir.join("env.exr")).unwrap();
        }
        for (i, (shape, _)) in self.objects.iter().enumerate() {
            if let Shape::Quad { corner, eu, ev } = *shape {
                write_gltf_quad(
                    &dir.join(format!("o{i}.gltf")),
                    corner,
                    eu,
                    ev,
                    LAMBERT_TEXTURED,
                );
            }
        }
        for (i, l) in self.lights.iter().enumerate() {
            if let Light::Mesh { corner, eu, ev, .. } = *l {
                // Counter-clockwise seen from eu x ev: that side is outward.
                let p = |a: f64, b: f64| -> V {
                    std::array::from_fn(|k| corner[k] + a * eu[k] + b * ev[k])
                };
                let mut obj = String::new();
                for q in [p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)] {
                    writeln!(obj, "v {} {} {}", q[0], q[1], q[2]).unwrap();
                }
                obj.push_str("f 1 2 3\nf 1 3 4\n");
                std::fs::write(dir.join(format!("l{i}.obj")), obj).unwrap();
            }
            let path = dir.join(format!("l{i}.gltf"));
            match *l {
                Light::Spot {
                    p,
                    dir,
                    intensity,
                    outer,
                } => {
                    let (c, i) = colour_intensity(intensity);
                    let light = format!(
                        r#"{{"type":"spot","color":{c:?},"intensity":{i},"spot":{{"innerConeAngle":{},"outerConeAngle":{}}}}}"#,
                        spot_inner(outer),
                        outer.to_radians()
                    );
                    common::meshgen::write_gltf_light(&path, &light, p, dir);
                }
                Light::Directional { dir, irradiance } => {
                    let (c, i) = colour_intensity(irradiance);
                    let light =
                        format!(r#"{{"type":"directional","color":{c:?},"intensity":{i}}}"#);
                    common::meshgen::write_gltf_light(&path, &light, [0.0; 3], dir);
                }
                Light::TexturedQuad { corner, eu, ev } => {
                    write_gltf_quad(&path, corner, eu, ev, EMISSIVE_TEXTURED)
                }
                _ => {}
            }
        }
        dir
    }

    fn toml(&self, dir: &std::path::Path) -> String {
        let mut s = String::new();
        writeln!(
            s,
            "[render]\nwidth = {0}\nheight = {0}\nsamples = {1}\nmax_depth = {2}\n\
             sampler = \"jittered\"\nintegrator = \"path\"\n\n\
             [camera]\nposition = {3}\nlook_at = {4}\nfov_y = {5}\n\n\
             [world]\nenvironment = {6}\n",
            self.size,
            self.spp,
            self.max_depth,
            rgb(self.eye),
            rgb(self.look_at),
            self.fov_y,
            match self.env_image {
                Some(_) => format!("{:?}", dir.join("env.exr")),
                None => rgb(self.environment),
            }
        )
        .unwrap();
        for (i, (shape, mat)) in self.objects.iter().enumerate() {
            if let Shape::Quad { .. } = shape {
                assert!(
                    matches!(mat, Mat::Textured),
                    "a quad is a textured glTF file"
                );
                let path = dir.join(format!("o{i}.gltf"));
                writeln!(s, "[[objects]]\ntype = \"mesh\"\npath = {path:?}\n").unwrap();
                continue;
            }
            writeln!(s, "[materials.m{i}]\ndiffuse = [0.5, 0.5, 0.5]\n").unwrap();
            let b = match *mat {
                Mat::Lambert(c) => format!("base_colour = {}\nmetallic = 0\nspecular = 0", rgb(c)),
                Mat::Metal(r) => format!("metallic = 1\nroughness = {r}"),
                Mat::Glass(ior) => {
                    format!("metallic = 0\nroughness = 0\ntransmission = 1\nior = {ior}")
                }
                Mat::AbsorbingGlass {
                    ior,
                    colour,
                    distance,
                } => format!(
                    "metallic = 0\nroughness = 0\ntransmission = 1\nior = {ior}\n\
                     attenuation_colour = {}\nattenuation_distance = {distance}",
                    rgb(colour)
                ),
                Mat::Textured => panic!("a textured material is a glTF quad's"),
            };
            writeln!(s, "[bsdf.m{i}]\n{b}\n").unwrap();
            match *shape {
                Shape::Sphere { c, r } => writeln!(
                    s,
                    "[[objects]]\ntype = \"sphere\"\ncenter = {}\nradius = {r}\nmaterial = \"m{i}\"\n",
                    rgb(c)
                ),
                Shape::Plane { n, d } => writeln!(
                    s,
                    "[[objects]]\ntype = \"plane\"\nnormal = {}\ndistance = {d}\nmaterial = \"m{i}\"\n",
                    rgb(n)
                ),
                Shape::Quad { .. } => unreachable!(),
            }
            .unwrap();
        }
        for (i, l) in self.lights.iter().enumerate() {
            match *l {
                Light::Point { p, intensity } => writeln!(
                    s,
                    "[[lights]]\nposition = {}\ndiffuse = {}\n",
                    rgb(p),
                    rgb(intensity)
                ),
                Light::Quad { corner, eu, ev, l } => writeln!(
                    s,
                    "[[lights]]\ntype = \"quad\"\ncorner = {}\nedge_u = {}\nedge_v = {}\ndiffuse = {}\n",
                    rgb(corner),
                    rgb(eu),
                    rgb(ev),
                    rgb(l)
                ),
                Light::Mesh { l, .. } => writeln!(
                    s,
                    "[materials.l{i}]\n[bsdf.l{i}]\nbase_colour = [0, 0, 0]\nmetallic = 0\nspecular = 0\n\
                     emission = {}\n\n[[objects]]\ntype = \"mesh\"\npath = {:?}\nmaterial = \"l{i}\"\n",
                    rgb(l),
                    dir.join(format!("l{i}.obj"))
                ),
                Light::TexturedQuad { .. } => writeln!(
                    s,
                    "[[objects]]\ntype = \"mesh\"\npath = {:?}\n",
                    dir.join(format!("l{i}.gltf"))
                ),
                Light::Spot { .. } | Light::Directional { .. } => writeln!(
                    s,
                    "[[objects]]\ntype = \"mesh\"\npath = {:?}\nlights = true\n",
                    dir.join(format!("l{i}.gltf"))
                ),
            }
            .unwrap();
        }
        s
    }

    fn mitsuba(&self, dir: &std::path::Path) -> String {
        let mut s = String::new();
        // Media need the volumetric path tracer (the same estimator on surfaces).
        let integrator = if self
            .objects
            .iter()
            .any(|(_, m)| matches!(m, Mat::AbsorbingGlass { .. }))
        {
            "volpath"
        } else {
            "path"
        };
        writeln!(
            s,
            "{{'type': 'scene', 'integrator': {{'type': '{integrator}', 'max_depth': {depth}}},\n\
             'sensor': {{'type': 'perspective', 'fov': {fov}, 'fov_axis': 'y',\n\
               'to_world': T().look_at(origin={eye}, target={look}, up=[0, 1, 0]),\n\
               'film': {{'type': 'hdrfilm', 'width': {size}, 'height': {size}, 'pixel_format': 'rgb', 'rfilter': {{'type': 'box'}}}},\n\
               'sampler': {{'type': 'independent', 'sample_count': {spp}}}}},\n\
             'env': {env},",
            depth = self.max_depth,
            fov = self.fov_y,
            eye = rgb(self.eye),
            look = rgb(self.look_at),
            size = self.size,
            spp = self.spp,
            env = match self.env_image {
                Some(_) => format!(
                    "{{'type': 'envmap', 'filename': {:?}}}",
                    dir.join("env.exr").to_str().unwrap()
                ),
                None => format!("{{'type': 'constant', 'radiance': {}}}", py_rgb(self.environment)),
            }
        )
        .unwrap();
        for (i, (shape, mat)) in self.objects.iter().enumerate() {
            let bsdf = match *mat {
                Mat::Lambert(c) => format!("{{'type': 'diffuse', 'reflectance': {}}}", py_rgb(c)),
                Mat::Metal(0.0) => "{'type': 'conductor', 'material': 'none'}".into(),
                Mat::Metal(r) => format!(
                    "{{'type': 'roughconductor', 'material': 'none', 'distribution': 'ggx', 'alpha': {}}}",
                    r * r
                ),
                Mat::Glass(ior) | Mat::AbsorbingGlass { ior, .. } => {
                    format!("{{'type': 'dielectric', 'int_ior': {ior}, 'ext_ior': 1.0}}")
                }
                Mat::Textured => format!(
                    "{{'type': 'diffuse', 'reflectance': {{'type': 'bitmap', 'filename': {:?}, \
                     'filter_type': 'bilinear', 'wrap_mode': 'repeat'}}}}",
                    dir.join("tex.png").to_str().unwrap()
                ),
            };
            let shape = match *shape {
                Shape::Sphere { c, r } => {
                    format!("'type': 'sphere', 'center': {}, 'radius': {r}", rgb(c))
                }
                Shape::Plane { n, d } => {
                    let c = n.map(|x| x * d);
                    let t = [c[0] + n[0], c[1] + n[1], c[2] + n[2]];
                    let up = if n[1].abs() > 0.9 {
                        [0.0, 0.0, 1.0]
                    } else {
                        [0.0, 1.0, 0.0]
                    };
                    format!(
                        "'type': 'rectangle', 'to_world': T().look_at(origin={}, target={}, up={}) @ T().scale([1e4, 1e4, 1])",
                        rgb(c),
                        rgb(t),
                        rgb(up)
                    )
                }
                Shape::Quad { corner, eu, ev } => format!(
                    "'type': 'rectangle', 'to_world': T([{}, [0, 0, 0, 1]])",
                    parallelogram(corner, eu, ev)
                ),
            };
            let interior = match *mat {
                Mat::AbsorbingGlass {
                    colour, distance, ..
                } => {
                    // Mitsuba takes an RGB in [0, 1] and a scale.
                    let sigma = colour.map(|c| -c.ln() / distance);
                    let scale = sigma.iter().fold(0.0f64, |a, &b| a.max(b));
                    format!(
                        ", 'interior': {{'type': 'homogeneous', 'albedo': 0.0, 'scale': {scale}, 'sigma_t': {}}}",
                        py_rgb(sigma.map(|x| x / scale))
                    )
                }
                _ => String::new(),
            };
            writeln!(s, "'o{i}': {{{shape}, 'bsdf': {bsdf}{interior}}},").unwrap();
        }
        for (i, l) in self.lights.iter().enumerate() {
            match *l {
                Light::Point { p, intensity } => writeln!(
                    s,
                    "'l{i}': {{'type': 'point', 'position': {}, 'intensity': {}}},",
                    rgb(p),
                    py_rgb(intensity)
                ),
                Light::Spot {
                    p,
                    dir,
                    intensity,
                    outer,
                } => {
                    let t = [p[0] + dir[0], p[1] + dir[1], p[2] + dir[2]];
                    let up = if dir[1].abs() > 0.9 {
                        [0.0, 0.0, 1.0]
                    } else {
                        [0.0, 1.0, 0.0]
                    };
                    writeln!(
                        s,
                        "'l{i}': {{'type': 'spot', 'to_world': T().look_at(origin={}, target={}, up={}), \
                         'intensity': {}, 'cutoff_angle': {outer}, 'beam_width': {}}},",
                        rgb(p),
                        rgb(t),
                        rgb(up),
                        py_rgb(intensity),
                        spot_inner(outer).to_degrees()
                    )
                }
                Light::Directional { dir, irradiance } => writeln!(
                    s,
                    "'l{i}': {{'type': 'directional', 'direction': {}, 'irradiance': {}}},",
                    rgb(dir),
                    py_rgb(irradiance)
                ),
                Light::TexturedQuad { corner, eu, ev } => writeln!(
                    s,
                    "'l{i}': {{'type': 'rectangle', 'to_world': T([{}, [0, 0, 0, 1]]), \
                     'bsdf': {{'type': 'diffuse', 'reflectance': {}}}, \
                     'emitter': {{'type': 'area', 'radiance': {{'type': 'bitmap', 'filename': {:?}, \
                     'filter_type': 'bilinear', 'wrap_mode': 'repeat'}}}}}},",
                    parallelogram(corner, eu, ev),
                    py_rgb([0.0; 3]),
                    dir.join("tex.png").to_str().unwrap()
                ),
                Light::Quad { corner, eu, ev, l } | Light::Mesh { corner, eu, ev, l } => {
                    writeln!(
                        s,
                        "'l{i}': {{'type': 'rectangle', 'to_world': T([{}, [0, 0, 0, 1]]), \
                         'bsdf': {{'type': 'diffuse', 'reflectance': {}}}, \
                         'emitter': {{'type': 'area', 'radiance': {}}}}},",
                        parallelogram(corner, eu, ev),
                        py_rgb([0.0; 3]),
                        py_rgb(l)
                    )
                }
            }
            .unwrap();
        }
        s.push('}');
        s
    }

    fn tessera(&self) -> Vec<[f32; 3]> {
        self.tessera_with(self.spp, |_| {})
    }

    /// Tessera's render at `spp` samples per pixel, its prepared frame
    /// changed by `edit` first.
    fn tessera_with(&self, spp: u32, edit: impl FnOnce(&mut PreparedFrame)) -> Vec<[f32; 3]> {
        let dir = self.files();
        let toml = self.toml(&dir);
        let mut desc = SceneDesc::parse(&toml, dir.join("mitsuba-case.toml"))
            .unwrap_or_else(|e| panic!("{}: {e}\n{toml}", self.name));
        desc.render.samples = spp;
        let s = desc.render;
        let mut frame = PreparedFrame::build(&desc, &s, 0, Precision::F32).unwrap();
        // Loaded: the files are not needed again (`mitsuba_renders` makes its own).
        std::fs::remove_dir_all(&dir).ok();
        edit(&mut frame);
        let film = CpuRenderer::new(None)
            .unwrap()
            .render(
                &frame,
                WorkRegion::new(
                    0,
                    Rect::full(s.width, s.height),
                    SampleRange::all(s.samples),
                ),
                &|_| {},
            )
            .unwrap();
        assert_eq!(film.nonfinite, 0, "{}: non-finite samples", self.name);
        film.resolve()
    }

    /// Mitsuba's renders with seeds 1 and 2.
    fn mitsuba_renders(&self) -> [Vec<[f32; 3]>; 2] {
        let dir = self.files();
        let script = format!(
            "import struct, sys\n\
             import mitsuba as mi\n\
             mi.set_variant('scalar_rgb')\n\
             T = mi.ScalarTransform4f\n\
             scene = mi.load_dict({})\n\
             for seed in (1, 2):\n\
             \x20   a = mi.render(scene, seed=seed).array\n\
             \x20   open(sys.argv[1] + '/m%d.f32' % seed, 'wb').write(struct.pack('<%df' % len(a), *a))\n",
            self.mitsuba(&dir)
        );
        let out = Command::new("python3")
            .arg("-c")
            .arg(&script)
            .arg(&dir)
            .output()
            .expect("python3 runs (the Mitsuba oracle needs it)");
        assert!(
            out.status.success(),
            "{}: Mitsuba 3 failed (pip install mitsuba; scripts/test does):\n{}\n{script}",
            self.name,
            String::from_utf8_lossy(&out.stderr)
        );
        let read = |seed: u32| -> Vec<[f32; 3]> {
            let b = std::fs::read(dir.join(format!("m{seed}.f32"))).unwrap();
            let f: Vec<f32> = b
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                .collect();
            assert_eq!(f.len(), (self.size * self.size * 3) as usize);
            f.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        };
        let r = [read(1), read(2)];
        std::fs::remove_dir_all(&dir).ok();
        r
    }

    fn check(&self) {
        let t = self.tessera();
        let [m1, m2] = self.mitsuba_renders();
        let floor = rmse(&m2, &m1);
        let err = rmse(&t, &m1);
        let (mt, mm) = (mean(&t), mean(&m1));
        // Standard error of a difference of two image means: the floor
        // is that of a difference of two pixels' values.
        let se = floor / ((t.len() * 3) as f64).sqrt();
        eprintln!(
            "{}: RMSE {err:.5} (floor {floor:.5}); mean {mt:.5} vs Mitsuba {mm:.5} (standard error {se:.5}, bias allowed {:.5})",
            self.name,
            self.bias * mm
        );
        assert!(mm > 0.01, "{}: the reference image is black", self.name);
        assert!(
            err <= 1.5 * floor + self.bias * mm,
            "{}: RMSE against Mitsuba {err} over 1.5 x the noise floor {floor} + bias {}",
            self.name,
            self.bias * mm
        );
        assert!(
            (mt - mm).abs() <= 4.0 * se + self.bias * mm,
            "{}: image mean {mt} against Mitsuba's {mm}: more than 4 standard errors ({se}) + bias {}",
            self.name,
            self.bias * mm
        );
    }
}

fn rmse(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let s: f64 = a
        .iter()
        .zip(b)
        .flat_map(|(p, q)| (0..3).map(move |k| (p[k] as f64 - q[k] as f64).powi(2)))
        .sum();
    (s / (a.len() * 3) as f64).sqrt()
}

fn mean(a: &[[f32; 3]]) -> f64 {
    a.iter()
        .flat_map(|p| p.iter().map(|&v| v as f64))
        .sum::<f64>()
        / (a.len() * 3) as f64
}

/// The rows of the affine map taking Mitsuba's square [-1, 1]^2 (and its
/// +z) onto the parallelogram at `corner` with edges `eu`, `ev` (its
/// normal along eu x ev).
fn parallelogram(corner: V, eu: V, ev: V) -> String {
    let n = norm(cross(eu, ev));
    let c: Vec<f64> = (0..3).map(|k| corner[k] + 0.5 * (eu[k] + ev[k])).collect();
    let rows: Vec<String> = (0..3)
        .map(|k| format!("[{}, {}, {}, {}]", 0.5 * eu[k], 0.5 * ev[k], n[k], c[k]))
        .collect();
    rows.join(", ")
}

/// [`write_gltf_quad`]'s material for [`Mat::Textured`]: white Lambert
/// (metallic 0, specularFactor 0) times image `tex.png`.
const LAMBERT_TEXTURED: &str = r#"{"pbrMetallicRoughness":{"baseColorTexture":{"index":0},"metallicFactor":0},
    "extensions":{"KHR_materials_specular":{"specularFactor":0}}}"#;

/// [`Light::TexturedQuad`]'s material: black, reflecting nothing,
/// emitting `emissiveFactor` 1 times image `tex.png`.
const EMISSIVE_TEXTURED: &str = r#"{"pbrMetallicRoughness":{"baseColorFactor":[0,0,0,1],"metallicFactor":0},
    "emissiveFactor":[1,1,1],"emissiveTexture":{"index":0},
    "extensions":{"KHR_materials_specular":{"specularFactor":0}}}"#;

/// A glTF file of one parallelogram ([`Shape::Quad`], [`Light::TexturedQuad`])
/// of the JSON `material`, whose texture 0 is image `tex.png` (the
/// default sampler: repeat, bilinear).
fn write_gltf_quad(path: &std::path::Path, corner: V, eu: V, ev: V, material: &str) {
    let n = norm(cross(eu, ev));
    let p = |a: f64, b: f64| -> V { std::array::from_fn(|k| corner[k] + a * eu[k] + b * ev[k]) };
    let mut bin = Vec::new();
    for q in [p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)] {
        bin.extend(q.iter().flat_map(|&c| (c as f32).to_le_bytes()));
    }
    for _ in 0..4 {
        bin.extend(n.iter().flat_map(|&c| (c as f32).to_le_bytes()));
    }
    for c in [0f32, 0., 1., 0., 1., 1., 0., 1.] {
        bin.extend(c.to_le_bytes());
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        bin.extend(i.to_le_bytes());
    }
    let bin_path = path.with_extension("bin");
    std::fs::write(&bin_path, &bin).unwrap();
    let (lo, hi): (Vec<f64>, Vec<f64>) = (0..3)
        .map(|k| {
            let c =
                [p(0.0, 0.0), p(1.0, 0.0), p(1.0, 1.0), p(0.0, 1.0)].map(|q| q[k] as f32 as f64);
            (
                c.iter().cloned().fold(f64::INFINITY, f64::min),
                c.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
            )
        })
        .unzip();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],
        "nodes":[{{"mesh":0}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,"TEXCOORD_0":2}},"indices":3,"material":0}}]}}],
        "materials":[{material}],
        "textures":[{{"source":0}}],
        "images":[{{"uri":"tex.png"}}],
        "extensionsUsed":["KHR_materials_specular"],
        "buffers":[{{"byteLength":{len},"uri":{uri:?}}}],
        "bufferViews":[{{"buffer":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":48}},
                       {{"buffer":0,"byteOffset":96,"byteLength":32}},{{"buffer":0,"byteOffset":128,"byteLength":12}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":{lo:?},"max":{hi:?}}},
                     {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC3"}},
                     {{"bufferView":2,"componentType":5126,"count":4,"type":"VEC2"}},
                     {{"bufferView":3,"componentType":5123,"count":6,"type":"SCALAR"}}]}}"#,
        len = bin.len(),
        uri = bin_path.file_name().unwrap().to_str().unwrap(),
    );
    std::fs::write(path, json).unwrap();
}

const FLOOR_Y: Shape = Shape::Plane {
    n: [0.0, 1.0, 0.0],
    d: 0.0,
};

fn base(name: &'static str) -> Case {
    Case {
        name,
        size: 32,
        spp: 64,
        max_depth: 6,
        eye: [0.0, 2.0, -6.0],
        look_at: [0.0, 0.8, 0.0],
        fov_y: 40.0,
        environment: [0.0; 3],
        objects: Vec::new(),
        lights: Vec::new(),
        bias: 0.0,
        texture: None,
        env_image: None,
    }
}

/// A quad light of radiance `l` above the origin facing down.
fn ceiling_light(l: f64) -> Light {
    Light::Quad {
        corner: [-1.0, 4.0, -1.0],
        eu: [2.0, 0.0, 0.0],
        ev: [0.0, 0.0, 2.0],
        l: [l; 3],
    }
}

#[test]
fn lambert_surfaces_under_a_point_light_and_the_sky_match_mitsuba() {
    let mut c = base("lambert");
    c.environment = [0.3, 0.4, 0.5];
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.7, 0.7, 0.7])),
        (
            Shape::Sphere {
                c: [-0.8, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Lambert([0.8, 0.2, 0.2]),
        ),
        (
            Shape::Sphere {
                c: [1.2, 0.5, -0.5],
                r: 0.5,
            },
            Mat::Lambert([0.2, 0.8, 0.3]),
        ),
    ];
    c.lights = vec![Light::Point {
        p: [2.0, 4.0, -2.0],
        intensity: [8.0, 8.0, 8.0],
    }];
    c.check();
}

/// A sky image: a gradient from a blue zenith to a pale horizon and a
/// dark ground, and a small bright sun, its columns and rows at texel
/// resolution (16 x 9: the mapping's texel centres are what is checked).
fn sky_image() -> (u32, u32, Vec<[f32; 3]>) {
    (16, 9, common::sky::texels(16, 9, (5, 2), [12.0, 10.0, 7.0]))
}

/// An environment image lights Lambert spheres and a mirror ball on a
/// floor as Mitsuba's `envmap` does with the same EXR file: the same
/// mapping (camera rays that miss and the mirror see it directly), the
/// same bilinear radiance, and importance sampling that converges to the
/// same integral (the sun is one texel: found by the light sampler).
#[test]
fn an_environment_image_lights_the_scene_as_mitsubas_envmap() {
    let mut c = base("envmap");
    c.env_image = Some(sky_image());
    c.eye = [0.0, 1.5, -6.0];
    c.look_at = [0.0, 1.0, 0.0];
    c.fov_y = 60.0;
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.6, 0.6, 0.6])),
        (
            Shape::Sphere {
                c: [-1.2, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Lambert([0.8, 0.8, 0.8]),
        ),
        (
            Shape::Sphere {
                c: [1.2, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Metal(0.0),
        ),
    ];
    c.check();
}

#[test]
fn area_light_and_point_light_match_mitsuba() {
    let mut c = base("area");
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.6, 0.6, 0.6])),
        (
            Shape::Sphere {
                c: [0.0, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Lambert([0.5, 0.5, 0.9]),
        ),
    ];
    c.lights = vec![
        ceiling_light(4.0),
        Light::Point {
            p: [-3.0, 2.0, -2.0],
            intensity: [3.0, 2.0, 1.0],
        },
    ];
    c.check();
}

#[test]
fn perfect_mirror_matches_mitsubas_conductor() {
    let mut c = base("mirror");
    c.environment = [0.2, 0.2, 0.3];
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.6, 0.6, 0.6])),
        (
            Shape::Sphere {
                c: [0.0, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Metal(0.0),
        ),
        (
            Shape::Sphere {
                c: [1.5, 0.5, -1.5],
                r: 0.5,
            },
            Mat::Lambert([0.9, 0.3, 0.1]),
        ),
    ];
    c.lights = vec![ceiling_light(3.0)];
    c.check();
}

#[test]
fn rough_ggx_conductor_matches_mitsuba() {
    // Mitsuba's roughconductor masks with the separable Smith G (G1 G1),
    // glTF with the height-correlated one, which is larger (it does not
    // count a microfacet hidden from both directions twice). At alpha
    // 0.16 the difference in albedo is below 1% at all but grazing
    // angles: 2% of the mean is allowed.
    let mut c = base("rough-conductor");
    c.environment = [0.2, 0.2, 0.3];
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.6, 0.6, 0.6])),
        (
            Shape::Sphere {
                c: [0.0, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Metal(0.4),
        ),
    ];
    c.lights = vec![ceiling_light(3.0)];
    c.bias = 0.02;
    c.check();
}

#[test]
fn smooth_dielectric_matches_mitsuba() {
    // glTF's Fresnel is Schlick's (with the refracted cosine from the
    // dense side), Mitsuba's the exact dielectric one: for ior 1.5 they
    // differ by up to 0.01 in reflectance below 60 degrees and up to ~0.05
    // near grazing and at the critical angle, a share of the light that
    // reaches the camera through a few percent of the pixels: 3% of
    // the mean is allowed.
    glass_ball("glass", Mat::Glass(1.5)).check();
}

/// A ball of radius 1 of `glass` on a grey floor under the ceiling
/// light and a blue-grey sky, with the Fresnel allowance above.
fn glass_ball(name: &'static str, glass: Mat) -> Case {
    let mut c = base(name);
    c.environment = [0.3, 0.3, 0.4];
    c.max_depth = 10;
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.6, 0.6, 0.6])),
        (
            Shape::Sphere {
                c: [0.0, 1.0, 0.0],
                r: 1.0,
            },
            glass,
        ),
    ];
    c.lights = vec![ceiling_light(3.0)];
    c.bias = 0.03;
    c
}

/// Glass around an absorbing volume (`KHR_materials_volume`): each
/// segment inside a ball of radius 1 keeps exp(-sigma t) of the light,
/// with the smooth dielectric's Fresnel allowance (3% of the mean, see
/// above). Mitsuba samples the medium's distances (albedo 0 ends a path
/// at a medium event) where Tessera multiplies by the transmittance: the
/// same expectation, Mitsuba's the noisier. (The volume darkens the
/// image's mean from 0.274, the clear glass case above, to 0.238: far
/// past the allowance of 0.007 + 4 standard errors.)
#[test]
fn glass_around_an_absorbing_volume_matches_mitsubas_homogeneous_medium() {
    glass_ball(
        "absorbing glass",
        Mat::AbsorbingGlass {
            ior: 1.5,
            colour: [0.9, 0.5, 0.2],
            distance: 1.0,
        },
    )
    .check();
}

/// A model file's textured Lambert floor (glTF base colour texture,
/// metallic 0, specularFactor 0: the file's `Pbr` becomes the BSDF at each
/// hit) against Mitsuba's `diffuse` with a `bitmap` reflectance: the same
/// sRGB decoding, bilinear filter and repeat wrap, v = 0 at the image's
/// first row in both. Texels of four colours, so that a flip of u or v,
/// or a texture dropped for the factor, shows.
#[test]
fn textured_lambert_from_a_model_file_matches_mitsubas_bitmap() {
    let mut c = base("textured");
    c.environment = [0.2, 0.25, 0.3];
    let palette = [
        [230u8, 40, 40, 255],
        [40, 200, 60, 255],
        [50, 60, 220, 255],
        [240, 230, 90, 255],
    ];
    let texels = (0..16u32)
        .map(|i| palette[((i % 4) / 2 + 2 * (i / 8)) as usize])
        .collect();
    c.texture = Some((4, 4, texels));
    c.objects = vec![
        (
            // The floor y = 0, x and z in [-3, 3]: u along +x, v along -z
            // (so that it faces +y).
            Shape::Quad {
                corner: [-3.0, 0.0, 3.0],
                eu: [6.0, 0.0, 0.0],
                ev: [0.0, 0.0, -6.0],
            },
            Mat::Textured,
        ),
        (
            Shape::Sphere {
                c: [0.0, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Lambert([0.7, 0.7, 0.7]),
        ),
    ];
    c.lights = vec![ceiling_light(3.0)];
    c.check();
}

/// A white Lambert sphere inside a uniform environment returns the
/// environment: every ray from a convex object leaves it, so each sample
/// is exactly environment x albedo (1), with no noise at all.
#[test]
fn white_furnace_returns_the_environment() {
    let mut c = base("furnace");
    c.environment = [0.5, 0.5, 0.5];
    c.objects = vec![(
        Shape::Sphere {
            c: [0.0, 1.0, 0.0],
            r: 1.5,
        },
        Mat::Lambert([1.0; 3]),
    )];
    let img = c.tessera();
    for (i, p) in img.iter().enumerate() {
        for &v in p {
            assert!(
                (v - 0.5).abs() < 1e-5,
                "pixel {i}: {p:?}, not the environment 0.5"
            );
        }
    }
}

/// A Cornell box (five Lambert planes, red and green side walls) lit only
/// by a small emissive mesh under its ceiling, two triangles of an OBJ file
/// facing down, and a Lambert sphere: the emissive triangles are sampled
/// by next-event estimation with MIS, as Mitsuba samples its area emitter.
fn cornell_emissive_mesh() -> Case {
    let mut c = base("cornell-emissive-mesh");
    c.eye = [0.0, 1.0, -3.4];
    c.look_at = [0.0, 1.0, 0.0];
    c.fov_y = 42.0;
    let plane = |n: V, d: f64| Shape::Plane { n, d };
    c.objects = vec![
        (plane([0.0, 1.0, 0.0], 0.0), Mat::Lambert([0.7, 0.7, 0.7])),
        (plane([0.0, -1.0, 0.0], -2.0), Mat::Lambert([0.7, 0.7, 0.7])),
        (plane([0.0, 0.0, -1.0], -1.0), Mat::Lambert([0.7, 0.7, 0.7])),
        (plane([1.0, 0.0, 0.0], -1.0), Mat::Lambert([0.7, 0.15, 0.1])),
        (
            plane([-1.0, 0.0, 0.0], -1.0),
            Mat::Lambert([0.15, 0.6, 0.15]),
        ),
        (
            Shape::Sphere {
                c: [0.3, 0.45, 0.2],
                r: 0.45,
            },
            Mat::Lambert([0.8, 0.8, 0.8]),
        ),
    ];
    // 0.4 x 0.4 at y = 1.98, its eu x ev side (-y) emitting.
    c.lights = vec![Light::Mesh {
        corner: [-0.2, 1.98, -0.2],
        eu: [0.4, 0.0, 0.0],
        ev: [0.0, 0.0, 0.4],
        l: [12.0, 10.0, 8.0],
    }];
    c
}

#[test]
fn cornell_box_under_an_emissive_mesh_matches_mitsuba() {
    cornell_emissive_mesh().check();
}

/// Light sampling of emissive triangles against finding them by BSDF
/// sampling alone (the estimator before it, rebuilt by giving the scene's
/// `PathScene` no emitters): at equal samples per pixel its RMSE against
/// a converged render (Tessera's, 32 times the samples) is at least 3
/// times lower, and both converge to the same image (means within noise).
#[test]
fn light_sampling_emissive_triangles_cuts_the_noise_threefold() {
    use tracer_core::distributed::PathScene;
    let c = cornell_emissive_mesh();
    let reference = c.tessera_with(32 * c.spp, |_| {});
    let nee = c.tessera();
    let bsdf_only = c.tessera_with(c.spp, |frame| {
        let PreparedFrame::F32(w) = frame else {
            unreachable!()
        };
        let d = w.dist.as_mut().expect("a path-traced world");
        let p = d.path.as_mut().expect("the path integrator's scene");
        assert_eq!(p.emitters.len(), 2, "the mesh's two triangles are lights");
        *p = PathScene::new(&d.lights, p.environment, None, Vec::new(), &[]);
    });
    let (e_nee, e_bsdf) = (rmse(&nee, &reference), rmse(&bsdf_only, &reference));
    let (m_ref, m_bsdf) = (mean(&reference), mean(&bsdf_only));
    eprintln!(
        "emissive mesh at {} spp: RMSE with light sampling {e_nee:.5}, BSDF sampling only {e_bsdf:.5} ({:.1}x); means {m_ref:.5} (reference) {m_bsdf:.5} (BSDF only)",
        c.spp,
        e_bsdf / e_nee
    );
    assert!(
        e_bsdf >= 3.0 * e_nee,
        "light sampling's RMSE {e_nee} is not 3x below BSDF sampling's {e_bsdf}"
    );
    // The BSDF-only image is unbiased too: its mean is within 4 of its
    // standard errors (its RMSE over the square root of the values).
    let se = e_bsdf / ((bsdf_only.len() * 3) as f64).sqrt();
    assert!(
        (m_bsdf - m_ref).abs() <= 4.0 * se,
        "BSDF-only mean {m_bsdf} against the reference {m_ref}: over 4 standard errors {se}"
    );
}

/// A model file's spot light under path: its cone (glTF's
/// `innerConeAngle`/`outerConeAngle`) lights a disc of the floor and the
/// sphere inside it, nothing outside but what bounces; against Mitsuba's
/// `spot` with the same cones (their falloffs differ within a ring of
/// 0.12 degrees only: see [`Light::Spot`]).
#[test]
fn spot_light_cone_matches_mitsubas_spot() {
    let mut c = base("spot");
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.7, 0.7, 0.7])),
        (
            Shape::Sphere {
                c: [0.3, 0.6, 0.0],
                r: 0.6,
            },
            Mat::Lambert([0.8, 0.4, 0.2]),
        ),
    ];
    c.lights = vec![Light::Spot {
        p: [-0.3, 3.5, -0.5],
        dir: norm([0.1, -1.0, 0.1]),
        intensity: [30.0, 28.0, 24.0],
        outer: 25.0,
    }];
    c.check();
}

/// A model file's directional light under path: irradiance in lux from
/// no distance, against Mitsuba's `directional`.
#[test]
fn directional_light_matches_mitsubas_directional() {
    let mut c = base("directional");
    c.environment = [0.05, 0.05, 0.08];
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.6, 0.6, 0.6])),
        (
            Shape::Sphere {
                c: [0.0, 1.0, 0.0],
                r: 1.0,
            },
            Mat::Lambert([0.3, 0.5, 0.8]),
        ),
    ];
    c.lights = vec![Light::Directional {
        dir: norm([0.4, -0.8, 0.45]),
        irradiance: [2.0, 1.9, 1.7],
    }];
    c.check();
}

/// A glTF quad emitting its texture (four colours, one black: where a
/// sampled point reads the texel, a flipped or averaged texture shows)
/// lights a Lambert floor and sphere: its triangles are chosen by their
/// mean texel and their radiance is the texel at the sampled point,
/// against Mitsuba's area emitter of `bitmap` radiance.
#[test]
fn textured_emissive_quad_matches_mitsubas_bitmap_emitter() {
    let mut c = base("textured-emitter");
    let palette = [
        [255u8, 255, 255, 255],
        [255, 60, 20, 255],
        [0, 0, 0, 255],
        [40, 120, 255, 255],
    ];
    let texels = (0..16u32)
        .map(|i| palette[((i % 4) / 2 + 2 * (i / 8)) as usize])
        .collect();
    c.texture = Some((4, 4, texels));
    c.objects = vec![
        (FLOOR_Y, Mat::Lambert([0.7, 0.7, 0.7])),
        (
            Shape::Sphere {
                c: [0.0, 0.8, 0.0],
                r: 0.8,
            },
            Mat::Lambert([0.8, 0.8, 0.8]),
        ),
    ];
    // 3 x 3 at y = 2.5 facing down (eu x ev = -y).
    c.lights = vec![Light::TexturedQuad {
        corner: [-1.5, 2.5, -1.5],
        eu: [3.0, 0.0, 0.0],
        ev: [0.0, 0.0, 3.0],
    }];
    c.check();
}
