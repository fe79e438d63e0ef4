//! What a scene takes from a model file beyond its triangles: a glTF
//! camera (or the automatic camera that frames the model), the file's
//! `KHR_lights_punctual` lights as Tessera lights, the default lighting of
//! a scene without any light, and model files given as the scene itself
//! (`tessera render model.gltf`), which are this TOML:
//!
//! ```toml
//! [[objects]]
//! type = "mesh"
//! path = "model.gltf"
//! camera = "default"   # or --camera's index or name
//! lights = true
//! ```
//!
//! The rules are the contract in docs/scene-format.md ("Model files as
//! scenes"); the numbers below are named there.

use std::path::Path;

use glam::{DMat3, DVec3};
use serde::Deserialize;
use serde::de::{self, Deserializer, SeqAccess, Visitor};

use super::desc::{CameraDesc, LightDesc, LightShape, Num, PathLightKind, Vec3, check_colour};
use super::error::SceneError;
use super::mesh_desc::Affine;
use crate::mesh::{Mesh, ModelCamera, ModelLightKind, Projection};

/// `camera = ...` of a mesh object: which camera of the file becomes the
/// scene's camera.
#[derive(Clone, Debug, PartialEq)]
pub enum CameraPick {
    /// `"default"`: the default scene's first camera (a perspective one),
    /// else the automatic camera.
    Default,
    /// `"auto"`: the automatic camera framing the placed model.
    Auto,
    /// An index in the file's `cameras` array.
    Index(u32),
    /// A camera's name (else its node's).
    Name(String),
}

impl<'de> Deserialize<'de> for CameraPick {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl Visitor<'_> for V {
            type Value = CameraPick;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a camera's index or name, \"default\" or \"auto\"")
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<CameraPick, E> {
                u32::try_from(v)
                    .map(CameraPick::Index)
                    .map_err(|_| E::custom(format!("camera index {v} is not in 0..=4294967295")))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<CameraPick, E> {
                self.visit_i64(v.min(i64::MAX as u64) as i64)
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<CameraPick, E> {
                Ok(match v {
                    "default" => CameraPick::Default,
                    "auto" => CameraPick::Auto,
                    name => CameraPick::Name(name.to_string()),
                })
            }
        }
        d.deserialize_any(V)
    }
}

/// `lights = ...` of a mesh object: which of the file's lights the scene
/// gets (none by default, so TOML scenes render as before).
#[derive(Clone, Debug, Default, PartialEq)]
pub enum LightsPick {
    #[default]
    None,
    All,
    Named(Vec<String>),
}

impl LightsPick {
    pub fn any(&self) -> bool {
        *self != LightsPick::None
    }
}

impl<'de> Deserialize<'de> for LightsPick {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = LightsPick;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("true, false or an array of the file's light names")
            }
            fn visit_bool<E: de::Error>(self, v: bool) -> Result<LightsPick, E> {
                Ok(if v { LightsPick::All } else { LightsPick::None })
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<LightsPick, A::Error> {
                let mut names = Vec::new();
                while let Some(n) = seq.next_element::<String>()? {
                    names.push(n);
                }
                Ok(LightsPick::Named(names))
            }
        }
        d.deserialize_any(V)
    }
}

/// Vertical field of view of the automatic camera, degrees.
pub const AUTO_FOV_Y: f64 = 45.0;
/// A directional light becomes a point light this many scene radii away.
pub const DIRECTIONAL_DISTANCE: f64 = 1000.0;
/// Default lighting: `world.ambient` and the headlight's colour.
pub const DEFAULT_AMBIENT: f64 = 0.2;
pub const HEADLIGHT: f64 = 0.8;
/// The path integrator's default lighting (instead of the headlight and
/// the ambient term): a uniform white sky of this radiance, the
/// environment light of the glTF sample viewer's screenshots at its
/// simplest (a white Lambert surface under it shows its base colour).
pub const DEFAULT_SKY: f64 = 1.0;

/// The box of the model's vertices as the object places them (`None` for
/// a model without vertices).
pub(crate) fn placed_bounds(mesh: &Mesh, xf: &Affine) -> Option<(DVec3, DVec3)> {
    // Instanced copies too, vertex by vertex, so a model frames the same
    // whether its copies are instanced or copied.
    let copies = mesh.instanced.iter().flat_map(|part| {
        part.transforms.iter().flat_map(move |t| {
            let t = glam::DMat4::from_cols_array(t);
            part.mesh.positions.iter().map(move |p| {
                let q = t.transform_point3(DVec3::from_array(p.map(f64::from)));
                xf.linear * q + xf.translation
            })
        })
    });
    let mut it = mesh.positions.iter().map(|p| xf.point(*p)).chain(copies);
    let first = it.next()?;
    Some(it.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p))))
}

/// Centre and radius (half the diagonal) of a box; a box of no size has
/// radius 1, so there is still a distance to frame it from.
fn centre_radius((lo, hi): (DVec3, DVec3)) -> (DVec3, f64) {
    let r = (hi - lo).length() / 2.0;
    (
        (lo + hi) / 2.0,
        if r > 0.0 && r.is_finite() { r } else { 1.0 },
    )
}

/// The scene's camera from a model, and the aspect ratio its file gives
/// (width / height) if any.
pub(crate) struct PickedCamera {
    pub camera: CameraDesc,
    pub aspect_ratio: Option<f64>,
}

fn camera_desc(position: DVec3, look_at: DVec3, up: DVec3, fov_y: f64) -> CameraDesc {
    CameraDesc {
        position: Vec3(position.to_array()),
        look_at: Vec3(look_at.to_array()),
        up: Vec3(up.to_array()),
        fov_y: Num(fov_y),
        keyframes: Vec::new(),
        aperture: Num(0.0),
        focus_distance: None,
        shutter: None,
    }
}

/// The automatic camera: looks along -Z (glTF's front view) at the centre
/// c of the placed model's box, +Y up, with a vertical field of view of
/// [`AUTO_FOV_Y`], from the distance r / sin(a) at which the box's
/// bounding sphere (radius r, half the box's diagonal) touches the
/// narrower pair of the image's edges: a = min(fov_y / 2, atan(tan(fov_y /
/// 2) * width / height)).
pub(crate) fn auto_camera(bounds: (DVec3, DVec3), width: u32, height: u32) -> CameraDesc {
    let (c, r) = centre_radius(bounds);
    let half = (AUTO_FOV_Y / 2.0).to_radians();
    let a = half.min((half.tan() * width as f64 / height as f64).atan());
    let distance = r / a.sin();
    camera_desc(c + DVec3::Z * distance, c, DVec3::Y, AUTO_FOV_Y)
}

/// A camera as the messages name it: its index, its name if any, its kind.
fn describe(c: &ModelCamera) -> String {
    let kind = match c.projection {
        Projection::Perspective { .. } => "perspective",
        Projection::Orthographic { .. } => "orthographic",
    };
    format!("{} ({kind})", name_of(c))
}

/// Its index and its name if any, without its kind.
fn name_of(c: &ModelCamera) -> String {
    match &c.name {
        Some(n) => format!("{} {n:?}", c.index),
        None => c.index.to_string(),
    }
}

fn list_cameras(mesh: &Mesh) -> String {
    if mesh.cameras.is_empty() {
        return "the file's default scene places no camera".into();
    }
    let list: Vec<String> = mesh.cameras.iter().map(describe).collect();
    format!("its cameras: {}", list.join(", "))
}

/// The scene's camera from `pick` of `mesh` placed by `xf`. `width` and
/// `height`: the image's size as far as the scene gives it (for the
/// automatic camera). Errors name the cameras the file has.
pub(crate) fn pick_camera(
    mesh: &Mesh,
    xf: &Affine,
    pick: &CameraPick,
    width: u32,
    height: u32,
    warnings: &mut Vec<String>,
) -> Result<PickedCamera, String> {
    let auto = || -> Result<PickedCamera, String> {
        let bounds = placed_bounds(mesh, xf).ok_or("the model has no vertices to frame")?;
        Ok(PickedCamera {
            camera: auto_camera(bounds, width, height),
            aspect_ratio: None,
        })
    };
    let camera = match pick {
        CameraPick::Auto => return auto(),
        CameraPick::Default => {
            match mesh
                .cameras
                .iter()
                .find(|c| matches!(c.projection, Projection::Perspective { .. }))
            {
                Some(c) => {
                    if let Some(first) = mesh.cameras.first().filter(|f| *f != c) {
                        warnings.push(format!(
                            "its first camera, {}, cannot be rendered (Tessera's camera is a pinhole); camera {} is used",
                            describe(first),
                            describe(c)
                        ));
                    }
                    c
                }
                None => {
                    if let Some(first) = mesh.cameras.first() {
                        warnings.push(format!(
                            "its cameras are orthographic ({}), which Tessera's pinhole camera cannot render; the automatic camera is used",
                            describe(first)
                        ));
                    }
                    return auto();
                }
            }
        }
        CameraPick::Index(i) => mesh
            .cameras
            .iter()
            .find(|c| c.index == *i as usize)
            .ok_or_else(|| {
                format!(
                    "no camera {i} is placed by the file's default scene ({})",
                    list_cameras(mesh)
                )
            })?,
        CameraPick::Name(n) => mesh
            .cameras
            .iter()
            .find(|c| c.name.as_deref() == Some(n))
            .ok_or_else(|| {
                format!(
                    "no camera named {n:?} in the file's default scene ({})",
                    list_cameras(mesh)
                )
            })?,
    };
    let (yfov, aspect_ratio) = match camera.projection {
        Projection::Perspective { yfov, aspect_ratio } => (yfov, aspect_ratio),
        Projection::Orthographic { .. } => {
            return Err(format!(
                "camera {} is orthographic, which Tessera's camera model (a pinhole, docs/scene-format.md) cannot render: pick a perspective camera ({}) or \"auto\"",
                name_of(camera),
                list_cameras(mesh)
            ));
        }
    };
    if let Some(a) = aspect_ratio.filter(|a| !(a.is_finite() && *a > 0.0)) {
        return Err(format!(
            "camera {}: aspectRatio must be a finite number > 0, got {a}",
            describe(camera)
        ));
    }
    let position = xf.linear * DVec3::from_array(camera.position) + xf.translation;
    let forward = (xf.linear * DVec3::from_array(camera.forward)).normalize_or_zero();
    let up = xf.linear * DVec3::from_array(camera.up);
    Ok(PickedCamera {
        camera: camera_desc(position, position + forward, up, yfov.to_degrees()),
        aspect_ratio,
    })
}

/// The image size for a camera of aspect ratio `a` when the scene gives
/// `width`, `height` or neither: the one given decides the other
/// (rounded, at least 1); neither: width 800 and the height from it.
pub(crate) fn size_for_aspect(a: f64, width: Option<u32>, height: Option<u32>) -> (u32, u32) {
    let side = |v: f64| v.round().clamp(1.0, u32::MAX as f64) as u32;
    match (width, height) {
        (Some(w), Some(h)) => (w, h),
        (Some(w), None) => (w, side(w as f64 / a)),
        (None, Some(h)) => (side(h as f64 * a), h),
        (None, None) => (800, side(800.0 / a)),
    }
}

/// The file's lights picked by `pick`, as Tessera lights, placed by `xf`.
///
/// glTF's point and spot lights give radiance intensity / d^2 at distance
/// d (candela, as the Khronos sample viewer renders them) and a
/// Lambertian surface reflects base colour / pi of it; Tessera's point
/// lights have no falloff (`l.diffuse * m.diffuse * N.L`, "Shading"). So a
/// point light's `diffuse` and `specular` are colour * intensity / (pi *
/// d_ref^2) with d_ref^2 = |p - c|^2 + r^2, the mean squared distance from
/// the light at p to the corners of the placed model's box (centre c,
/// half-diagonal r): right at that distance, too dark nearer, too bright
/// farther. Spot lights are point lights (no cone), with a warning.
/// Directional lights (lux) are point lights [`DIRECTIONAL_DISTANCE`]
/// radii from c against their direction, colour * intensity / pi: exact
/// but for that parallax.
pub(crate) fn file_lights(
    mesh: &Mesh,
    xf: &Affine,
    pick: &LightsPick,
    warnings: &mut Vec<String>,
) -> Result<Vec<LightDesc>, String> {
    let picked: Vec<_> = match pick {
        LightsPick::None => return Ok(Vec::new()),
        LightsPick::All => mesh.lights.iter().collect(),
        LightsPick::Named(names) => {
            let mut out = Vec::new();
            for n in names {
                let found: Vec<_> = mesh
                    .lights
                    .iter()
                    .filter(|l| l.name.as_deref() == Some(n))
                    .collect();
                if found.is_empty() {
                    let known: Vec<String> = mesh
                        .lights
                        .iter()
                        .map(|l| format!("{:?}", l.name.as_deref().unwrap_or("unnamed")))
                        .collect();
                    return Err(format!(
                        "no light named {n:?} in the file's default scene (its lights: {})",
                        if known.is_empty() {
                            "none".into()
                        } else {
                            known.join(", ")
                        }
                    ));
                }
                out.extend(found);
            }
            out
        }
    };
    if picked.is_empty() {
        return Ok(Vec::new());
    }
    let (c, r) = centre_radius(placed_bounds(mesh, xf).unwrap_or((DVec3::ZERO, DVec3::ZERO)));
    let normal_xf: DMat3 = xf.linear;
    let mut out = Vec::with_capacity(picked.len());
    let mut falloff = 0;
    for l in picked {
        let name = format!(
            "light {} {:?} ({})",
            l.index,
            l.name.as_deref().unwrap_or("unnamed"),
            l.kind.name()
        );
        let p = xf.linear * DVec3::from_array(l.position) + xf.translation;
        let dir = (normal_xf * DVec3::from_array(l.direction)).normalize_or_zero();
        // (position, Whitted's scale, the path integrator's scale and kind)
        let (position, scale, path_scale, path_kind) = match l.kind {
            ModelLightKind::Directional => {
                let d = DIRECTIONAL_DISTANCE * r;
                let irradiance = Vec3(l.color.map(|v| v * l.intensity));
                (
                    c - dir * d,
                    l.intensity / std::f64::consts::PI,
                    l.intensity * d * d,
                    Some(PathLightKind::Directional {
                        direction: Vec3(dir.to_array()),
                        irradiance,
                        radius: r.max(1e-3),
                    }),
                )
            }
            ModelLightKind::Point | ModelLightKind::Spot { .. } => {
                falloff += 1;
                let mut kind = None;
                if let ModelLightKind::Spot { inner, outer } = l.kind {
                    warnings.push(format!(
                        "{name} (cone {:.1}..{:.1} degrees) renders as a point light under Whitted, shining every way (its cone is the path integrator's only)",
                        inner.to_degrees(),
                        outer.to_degrees()
                    ));
                    kind = Some(PathLightKind::Spot {
                        direction: Vec3(dir.to_array()),
                        cos_inner: inner.cos(),
                        cos_outer: outer.cos(),
                    });
                }
                let d2 = (p - c).length_squared() + r * r;
                (
                    p,
                    l.intensity / (std::f64::consts::PI * d2),
                    l.intensity,
                    kind,
                )
            }
        };
        let colour = Vec3(l.color.map(|v| v * scale));
        check_colour(&colour).map_err(|m| format!("{name}: its radiance {m}"))?;
        let path_radiance = Vec3(l.color.map(|v| v * path_scale));
        if !path_radiance.0.iter().all(|v| v.is_finite()) {
            return Err(format!(
                "{name}: its radiance in physical units is not finite (intensity {})",
                l.intensity
            ));
        }
        if !position.is_finite() || position.abs().max_element() > 1e15 {
            return Err(format!("{name}: position {position:?} is not finite"));
        }
        out.push(LightDesc {
            shape: LightShape::Point,
            position: Vec3(position.to_array()),
            diffuse: colour,
            specular: colour,
            samples: 1,
            path_radiance: Some(path_radiance),
            path_kind,
        });
    }
    if falloff > 0 {
        warnings.push(format!(
            "{falloff} point or spot light(s) render without inverse-square falloff: each at its brightness at one reference distance, unless --integrator path (docs/scene-format.md, \"Lights of a model\")"
        ));
    }
    Ok(out)
}

/// The default lighting of a scene that takes its lights from models and
/// has no light at all: a white point light of [`HEADLIGHT`] at the
/// camera (a headlight) and `world.ambient` [`DEFAULT_AMBIENT`].
pub(crate) fn headlight(camera: &CameraDesc) -> LightDesc {
    LightDesc {
        shape: LightShape::Point,
        position: camera.position,
        diffuse: Vec3([HEADLIGHT; 3]),
        specular: Vec3([HEADLIGHT; 3]),
        samples: 1,
        path_radiance: None,
        path_kind: None,
    }
}

/// Options of a model file given as the scene (`tessera render FILE`).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ModelSceneOptions {
    /// `--camera`: an index or a name ("auto": the automatic camera).
    pub camera: Option<String>,
    /// `--width` and `--height`: written into the scene so the camera's
    /// aspect ratio decides only what is not given.
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// `--environment`: an environment image in place of the scene's
    /// environment, by name as the scene would write it (relative to its
    /// folder, or absolute).
    pub environment: Option<String>,
}

/// What a path given as the scene holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneInput {
    /// A TOML scene file.
    Toml,
    /// A model file (.gltf, .glb, .obj, .obj.gz) rendered as a scene.
    Model,
}

impl SceneInput {
    /// By extension: model files are scenes of their own; a PLY is refused
    /// (it has no camera, lights or materials: the message shows the
    /// TOML to write); anything else is read as TOML.
    pub fn of(path: &Path) -> Result<SceneInput, SceneError> {
        let lower = path.to_string_lossy().to_lowercase();
        if [".gltf", ".glb", ".obj", ".obj.gz"]
            .iter()
            .any(|e| lower.ends_with(e))
        {
            return Ok(SceneInput::Model);
        }
        if lower.ends_with(".ply") || lower.ends_with(".ply.gz") {
            let name = file_name(path);
            return Err(SceneError::Input {
                path: path.to_owned(),
                message: format!(
                    "a PLY file is a mesh without camera, lights or materials, so it is not a scene by itself: \
                     wrap it in a TOML scene (docs/scene-format.md), for example scene.toml beside it:\n\n\
                     [[objects]]\ntype = \"mesh\"\npath = {}\ncamera = \"auto\"   # frames the mesh\n\
                     lights = true      # none in a PLY: the default lighting\n\n\
                     and render that: tessera render scene.toml",
                    toml_string(&name)
                ),
            });
        }
        Ok(SceneInput::Toml)
    }
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

fn toml_string(s: &str) -> String {
    toml::Value::String(s.to_string()).to_string()
}

/// The TOML scene of a model file given as the scene: the file as a mesh
/// object with its camera (`--camera`, else "default") and its lights,
/// and `[render]` with the size flags given (see [`size_for_aspect`]).
pub fn model_scene_text(path: &Path, options: &ModelSceneOptions) -> String {
    let mut s = String::from(
        "# A model file as a scene (docs/scene-format.md, \"Model files as scenes\").\n",
    );
    if options.width.is_some() || options.height.is_some() {
        s.push_str("[render]\n");
        if let Some(w) = options.width {
            s.push_str(&format!("width = {w}\n"));
        }
        if let Some(h) = options.height {
            s.push_str(&format!("height = {h}\n"));
        }
    }
    if let Some(env) = &options.environment {
        s.push_str(&format!("[world]\nenvironment = {}\n", toml_string(env)));
    }
    let camera = match options.camera.as_deref() {
        None => toml_string("default"),
        Some(c) => match c.trim().parse::<u32>() {
            Ok(i) => i.to_string(),
            Err(_) => toml_string(c),
        },
    };
    s.push_str(&format!(
        "[[objects]]\ntype = \"mesh\"\npath = {}\ncamera = {camera}\nlights = true\n",
        toml_string(&file_name(path))
    ));
    s
}

/// TOML scene text with `[world] environment` set to the image `name`
/// (`--environment` on a TOML scene, for the farm: the job carries the
/// scene it renders). The scene's comments and layout are not kept.
pub fn with_environment(text: &str, name: &str) -> Result<String, String> {
    let mut table: toml::Table = text.parse().map_err(|e: toml::de::Error| e.to_string())?;
    let world = table
        .entry("world")
        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
    let Some(world) = world.as_table_mut() else {
        return Err("`world` is not a table".into());
    };
    world.insert("environment".into(), toml::Value::String(name.to_string()));
    Ok(table.to_string())
}

/// A model scene's error said in the model's and the flags' terms: the
/// generated TOML's lines and fields mean nothing to the user.
pub(crate) fn model_scene_error(
    e: SceneError,
    path: &Path,
    options: &ModelSceneOptions,
) -> SceneError {
    let SceneError::Invalid { field, message, .. } = e else {
        return e;
    };
    let name = file_name(path);
    let message = if let Some(rest) = message.strip_prefix("cannot load model: ") {
        rest.strip_prefix(&format!("{name}: "))
            .unwrap_or(rest)
            .to_string()
    } else if field.ends_with(".camera") {
        match &options.camera {
            Some(c) => format!("--camera {c}: {message}"),
            None => message,
        }
    } else if field.starts_with("world.environment") {
        format!("--environment: {message}")
    } else if field.starts_with("render.") {
        format!("--{}: {message}", field.trim_start_matches("render."))
    } else {
        message
    };
    SceneError::Input {
        path: path.to_owned(),
        message,
    }
}
