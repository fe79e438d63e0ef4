//! The scene file: parsed from TOML, validated, kept in `f64` as plain
//! description records. Render-ready state is built from it per precision
//! by [`crate::world::World::build`]. The format is documented in
//! `docs/scene-format.md`; it is a contract other tools write against.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::assets::{AssetSource, LocalFolder, join};

use serde::Deserialize;
use serde::de::{self, Deserializer, SeqAccess, Visitor};
use toml::Spanned;

use super::error::{Location, SceneError};
use crate::mesh::Mesh;
use crate::sampling::Sampler;

pub use super::mesh_desc::{Affine, MeshDesc, MeshModel, Rotation, Scale};
use super::model_scene::{self, ModelSceneOptions, SceneInput};

/// A number that TOML may write as an integer or a float (`1` or `1.0`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Num(pub f64);

impl<'de> Deserialize<'de> for Num {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl Visitor<'_> for V {
            type Value = Num;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a number")
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Num, E> {
                Ok(Num(v))
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Num, E> {
                Ok(Num(v as f64))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Num, E> {
                Ok(Num(v as f64))
            }
        }
        d.deserialize_any(V)
    }
}

/// Three numbers: a point, a direction or a linear RGB colour.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Vec3(pub [f64; 3]);

impl<'de> Deserialize<'de> for Vec3 {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Vec3;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an array of three numbers, like [0.0, 1.0, 0.0]")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec3, A::Error> {
                let mut out = [0.0; 3];
                for (i, slot) in out.iter_mut().enumerate() {
                    *slot = seq
                        .next_element::<Num>()?
                        .ok_or_else(|| de::Error::invalid_length(i, &self))?
                        .0;
                }
                if seq.next_element::<de::IgnoredAny>()?.is_some() {
                    return Err(de::Error::invalid_length(4, &self));
                }
                Ok(Vec3(out))
            }
        }
        d.deserialize_seq(V)
    }
}

/// `[world] environment`: a uniform colour or an image file's name.
#[derive(Clone, Debug, PartialEq)]
pub enum EnvironmentDesc {
    Colour(Vec3),
    /// A name relative to the scene's folder (`crate::assets::join`).
    File(String),
}

impl Default for EnvironmentDesc {
    fn default() -> Self {
        EnvironmentDesc::Colour(Vec3::default())
    }
}

impl EnvironmentDesc {
    /// The uniform colour (black under an image: the image is the light).
    pub fn colour(&self) -> Vec3 {
        match self {
            EnvironmentDesc::Colour(c) => *c,
            EnvironmentDesc::File(_) => Vec3::default(),
        }
    }
}

impl<'de> Deserialize<'de> for EnvironmentDesc {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = EnvironmentDesc;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str(
                    "a colour [r, g, b] or an equirectangular image file's name (\"sky.exr\": EXR, HDR, PNG or JPEG)",
                )
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<EnvironmentDesc, E> {
                Ok(EnvironmentDesc::File(v.to_string()))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<EnvironmentDesc, A::Error> {
                Vec3::deserialize(de::value::SeqAccessDeserializer::new(seq))
                    .map(EnvironmentDesc::Colour)
            }
        }
        d.deserialize_any(V)
    }
}

impl Vec3 {
    fn is_finite(&self) -> bool {
        self.0.iter().all(|v| v.is_finite())
    }
    fn dot(&self, o: &Vec3) -> f64 {
        self.0[0] * o.0[0] + self.0[1] * o.0[1] + self.0[2] * o.0[2]
    }
    fn sub(&self, o: &Vec3) -> Vec3 {
        Vec3([self.0[0] - o.0[0], self.0[1] - o.0[1], self.0[2] - o.0[2]])
    }
    fn cross(&self, o: &Vec3) -> Vec3 {
        let (a, b) = (self.0, o.0);
        Vec3([
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ])
    }
    fn length(&self) -> f64 {
        self.dot(self).sqrt()
    }
}

/// Image and sampling settings. The file's `[render]` table gives defaults;
/// the command line or a job overrides them ([`super::RenderOverrides`]).
/// Serializable under these field names, the sampler by its name; the
/// coordinator's job records are the store's own type (`SettingsRec`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, Deserialize)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    /// Samples per pixel.
    pub samples: u32,
    /// Generations of secondary rays; 0 = none.
    pub max_depth: u32,
    pub sampler: Sampler,
    /// Whitted (the thesis's model, the default) or path tracing. Absent
    /// in job records older than the path tracer: those are Whitted.
    #[serde(default)]
    pub integrator: Integrator,
}

/// How light is integrated: the thesis's Whitted model with distributed
/// ray tracing's effects, or unidirectional path tracing (docs/path-tracing.md).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Integrator {
    #[default]
    Whitted,
    Path,
}

impl Integrator {
    pub fn name(self) -> &'static str {
        match self {
            Integrator::Whitted => "whitted",
            Integrator::Path => "path",
        }
    }
}

impl std::str::FromStr for Integrator {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "whitted" => Ok(Integrator::Whitted),
            "path" => Ok(Integrator::Path),
            _ => Err(format!(
                "unknown integrator {s:?}: expected \"whitted\" or \"path\""
            )),
        }
    }
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            width: 800,
            height: 600,
            samples: 4,
            max_depth: 10,
            sampler: Sampler::Grid,
            integrator: Integrator::Whitted,
        }
    }
}

/// Largest values accepted: beyond them the fixed-point film could overflow
/// (samples) or the work is surely a typo.
pub const MAX_IMAGE_SIDE: u32 = 32_768;
pub const MAX_SAMPLES: u32 = 65_536;
pub const MAX_DEPTH: u32 = 64;

impl RenderSettings {
    /// Checks the limits; `source` names where the values came from in errors.
    pub fn validate(&self) -> Result<(), String> {
        let check = |name: &str, v: u32, lo: u32, hi: u32| {
            if v < lo || v > hi {
                Err(format!("{name} must be in {lo}..={hi}, got {v}"))
            } else {
                Ok(())
            }
        };
        check("width", self.width, 1, MAX_IMAGE_SIDE)?;
        check("height", self.height, 1, MAX_IMAGE_SIDE)?;
        check("samples", self.samples, 1, MAX_SAMPLES)?;
        check("max_depth", self.max_depth, 0, MAX_DEPTH)?;
        Ok(())
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RenderTable {
    width: Option<u32>,
    height: Option<u32>,
    samples: Option<u32>,
    max_depth: Option<u32>,
    sampler: Option<Sampler>,
    integrator: Option<Integrator>,
    target_error: Option<Num>,
    relative_error: Option<Num>,
    min_samples: Option<u32>,
    max_samples: Option<u32>,
    adaptive_mode: Option<super::adaptive::AdaptiveMode>,
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraDesc {
    pub position: Vec3,
    pub look_at: Vec3,
    #[serde(default = "default_up")]
    pub up: Vec3,
    /// Vertical field of view in degrees.
    #[serde(default = "default_fov")]
    pub fov_y: Num,
    /// Animation: camera poses at given frames, linearly interpolated between
    /// them (and held before the first and after the last). Empty: a still camera.
    #[serde(default)]
    pub keyframes: Vec<CameraKeyframe>,
    /// Depth of field: lens radius in world units; 0 is the pinhole camera.
    #[serde(default)]
    pub aperture: Num,
    /// Distance to the plane in focus along the view direction; `None`:
    /// |look_at - position| of the pose.
    #[serde(default)]
    pub focus_distance: Option<Num>,
    /// Motion blur: the open and close times of the shutter, fractions of a
    /// frame (`None`: [0, 0], no blur).
    #[serde(default)]
    pub shutter: Option<(Num, Num)>,
}

/// One `[[camera.keyframes]]` entry; fields left out take the `[camera]` table's values.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraKeyframe {
    pub frame: u32,
    pub position: Option<Vec3>,
    pub look_at: Option<Vec3>,
    pub fov_y: Option<Num>,
}

/// The camera's pose at one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraPose {
    pub position: Vec3,
    pub look_at: Vec3,
    pub fov_y: Num,
}

/// Where time `t` falls among keyframes at `frames` (increasing): held at
/// keyframe `i`, or between `i` and `i + 1` with weight `w` on the second.
pub(crate) enum Segment {
    Hold(usize),
    Between(usize, f64),
}

pub(crate) fn segment(frames: &[u32], t: f64) -> Option<Segment> {
    let (first, last) = (*frames.first()?, *frames.last()?);
    if t <= first as f64 {
        return Some(Segment::Hold(0));
    }
    if t >= last as f64 {
        return Some(Segment::Hold(frames.len() - 1));
    }
    let i = frames.partition_point(|&k| k as f64 <= t);
    // For an integer t this is exactly (frame - k0) as f64 / (k1 - k0) as f64.
    let w = (t - frames[i - 1] as f64) / (frames[i] - frames[i - 1]) as f64;
    Some(Segment::Between(i - 1, w))
}

fn lerp3(x: Vec3, y: Vec3, w: f64) -> Vec3 {
    let lerp = |a: f64, b: f64| a + (b - a) * w;
    Vec3([
        lerp(x.0[0], y.0[0]),
        lerp(x.0[1], y.0[1]),
        lerp(x.0[2], y.0[2]),
    ])
}

/// Keyframed point at time `t` (today's camera rule): `None` without keyframes.
pub(crate) fn keyframed(frames: &[u32], values: &[Vec3], t: f64) -> Option<Vec3> {
    Some(match segment(frames, t)? {
        Segment::Hold(i) => values[i],
        Segment::Between(i, w) => lerp3(values[i], values[i + 1], w),
    })
}

impl CameraDesc {
    fn pose_of(&self, k: &CameraKeyframe) -> CameraPose {
        CameraPose {
            position: k.position.unwrap_or(self.position),
            look_at: k.look_at.unwrap_or(self.look_at),
            fov_y: k.fov_y.unwrap_or(self.fov_y),
        }
    }

    /// The pose at `frame`: linear interpolation between the keyframes around
    /// it (keyframes are sorted by frame, checked at parse time).
    pub fn at(&self, frame: u32) -> CameraPose {
        self.at_time(frame as f64)
    }

    /// The pose at a real-valued time (in frames): the same rule as [`Self::at`].
    pub fn at_time(&self, t: f64) -> CameraPose {
        let frames: Vec<u32> = self.keyframes.iter().map(|k| k.frame).collect();
        match segment(&frames, t) {
            None => CameraPose {
                position: self.position,
                look_at: self.look_at,
                fov_y: self.fov_y,
            },
            Some(Segment::Hold(i)) => self.pose_of(&self.keyframes[i]),
            Some(Segment::Between(i, w)) => {
                let (a, b) = (
                    self.pose_of(&self.keyframes[i]),
                    self.pose_of(&self.keyframes[i + 1]),
                );
                CameraPose {
                    position: lerp3(a.position, b.position, w),
                    look_at: lerp3(a.look_at, b.look_at, w),
                    fov_y: Num(a.fov_y.0 + (b.fov_y.0 - a.fov_y.0) * w),
                }
            }
        }
    }

    /// The shutter interval `[open, close]` in fractions of a frame.
    pub fn shutter(&self) -> (f64, f64) {
        self.shutter.map_or((0.0, 0.0), |(a, b)| (a.0, b.0))
    }
}

fn default_up() -> Vec3 {
    Vec3([0.0, 1.0, 0.0])
}
fn default_fov() -> Num {
    Num(60.0)
}

#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct WorldDesc {
    #[serde(default)]
    pub ambient: Vec3,
    #[serde(default)]
    pub background: Vec3,
    /// Radiance from every direction no surface or light is met in, for
    /// the path integrator (black when left out; Whitted uses
    /// `background`): a colour, or an equirectangular image file's name
    /// (`crate::environment`), read when the scene is parsed.
    #[serde(default)]
    pub environment: EnvironmentDesc,
    /// Multiplies an environment image's radiance (default 1).
    #[serde(default)]
    pub environment_scale: Option<Num>,
    /// Turns an environment image about +Y, in degrees (default 0).
    #[serde(default)]
    pub environment_rotation: Option<Num>,
    /// The image `environment` names, decoded (set by the parser).
    #[serde(skip)]
    pub environment_map: Option<std::sync::Arc<crate::environment::EnvironmentMap>>,
    /// Set (never read from a file) where the scene got the default
    /// lighting of model files (`model_scene::headlight`): the path
    /// integrator then lights it by [`crate::scene::DEFAULT_SKY`]
    /// instead (docs/scene-format.md, "Lights of a model").
    #[serde(skip)]
    pub default_lighting: bool,
}

/// `[bsdf.NAME]`: the path integrator's BSDF of material NAME given
/// directly (glTF metallic-roughness parameters, `crate::bsdf::Bsdf`),
/// instead of the mapping of its Blinn-Phong keys. Defaults are glTF's.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BsdfDesc {
    #[serde(default = "white")]
    pub base_colour: Vec3,
    #[serde(default = "one")]
    pub metallic: Num,
    #[serde(default = "one")]
    pub roughness: Num,
    #[serde(default = "default_ior")]
    pub ior: Num,
    #[serde(default)]
    pub transmission: Num,
    #[serde(default = "one")]
    pub specular: Num,
    #[serde(default = "white")]
    pub specular_colour: Vec3,
    #[serde(default)]
    pub emission: Vec3,
    /// The volume inside (`KHR_materials_volume`'s attenuation): light that
    /// travels `attenuation_distance` inside keeps `attenuation_colour` of
    /// itself. Without a distance nothing is absorbed.
    #[serde(default = "white")]
    pub attenuation_colour: Vec3,
    #[serde(default)]
    pub attenuation_distance: Option<Num>,
}

fn default_ior() -> Num {
    Num(1.5)
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MaterialDesc {
    #[serde(default)]
    pub ambient: Vec3,
    #[serde(default)]
    pub diffuse: Vec3,
    #[serde(default)]
    pub specular: Vec3,
    #[serde(default = "one")]
    pub shininess: Num,
    #[serde(default)]
    pub reflectivity: Num,
    #[serde(default)]
    pub transparency: Num,
    #[serde(default = "one")]
    pub ior: Num,
    /// Glossy reflection: half-angle in degrees of the cone the reflected
    /// ray is drawn from, in [0, 90); 0 is the perfect mirror.
    #[serde(default)]
    pub gloss: Num,
    /// Translucency: the same for the refracted ray.
    #[serde(default)]
    pub translucency: Num,
}

fn one() -> Num {
    Num(1.0)
}
fn white() -> Vec3 {
    Vec3([1.0; 3])
}

/// A validated light.
#[derive(Clone, Debug, PartialEq)]
pub struct LightDesc {
    pub shape: LightShape,
    /// A point light's position; an area light's centre.
    pub position: Vec3,
    pub diffuse: Vec3,
    pub specular: Vec3,
    /// Shadow rays per hit (stratified over the light); 1 for point lights.
    pub samples: u32,
    /// A model file's light in physical units, for the path integrator,
    /// whose point lights fall off as 1/d² (its `diffuse` and `specular`
    /// are scaled for Whitted's lights, which do not): the colour times
    /// the candela of a point or spot light, or times lux * d² at the
    /// distance the directional light is placed. `None`: `diffuse`.
    pub path_radiance: Option<Vec3>,
    /// A model file's spot or directional light as its own kind for the
    /// path integrator (Whitted renders it as the point light above).
    pub path_kind: Option<PathLightKind>,
}

/// What a model file's spot and directional lights are under the path
/// integrator (docs/scene-format.md, "Lights of a model").
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PathLightKind {
    /// A point light at `position` of intensity `path_radiance` (candela)
    /// on its axis, shining along unit `direction` within its cone:
    /// glTF's smooth falloff from the cosines of the inner and outer
    /// cone angles (`KHR_lights_punctual`).
    Spot {
        direction: Vec3,
        cos_inner: f64,
        cos_outer: f64,
    },
    /// Light travelling along unit `direction` with `irradiance` (colour
    /// x lux) on a surface facing it, from no distance; `radius` bounds
    /// the scene it lights (its power, for choosing among lights).
    Directional {
        direction: Vec3,
        irradiance: Vec3,
        radius: f64,
    },
}

/// Where a light's points lie.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LightShape {
    /// At `position`.
    Point,
    /// The parallelogram corner + a edge_u + b edge_v, a and b in [0, 1].
    Quad {
        corner: Vec3,
        edge_u: Vec3,
        edge_v: Vec3,
    },
    /// The sphere's surface.
    Sphere { center: Vec3, radius: f64 },
}

impl LightShape {
    pub fn is_area(&self) -> bool {
        !matches!(self, LightShape::Point)
    }
}

#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(rename_all = "lowercase")]
enum LightType {
    #[default]
    Point,
    Quad,
    Sphere,
    Spot,
    Directional,
}

/// Where a TOML directional light stands for Whitted: this far along its
/// reversed direction (its light then arrives parallel to within a
/// millionth of a radian over a scene of unit size).
pub const DIRECTIONAL_STAND_IN: f64 = 1e6;

/// A `[[lights]]` entry as written.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LightFile {
    #[serde(rename = "type", default)]
    kind: LightType,
    position: Option<Vec3>,
    corner: Option<Vec3>,
    edge_u: Option<Vec3>,
    edge_v: Option<Vec3>,
    center: Option<Vec3>,
    radius: Option<Num>,
    samples: Option<u32>,
    /// A spot light's axis and cone half-angles in degrees (glTF's outer
    /// and inner cone: full light inside the inner, none past the outer).
    direction: Option<Vec3>,
    cone_angle: Option<Num>,
    inner_cone_angle: Option<Num>,
    #[serde(default = "white")]
    diffuse: Vec3,
    #[serde(default = "white")]
    specular: Vec3,
}

/// Largest `samples` of one light.
pub const MAX_LIGHT_SAMPLES: u32 = 4096;

/// A sphere's `[[objects.keyframes]]` entry.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SphereKeyframe {
    pub frame: u32,
    pub center: Vec3,
}

/// A mesh's `[[objects.keyframes]]` entry: its `translate` at a frame.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MeshKeyframe {
    pub frame: u32,
    pub translate: Vec3,
}

// A scene has few objects, described once: a mesh's larger description
// is not worth a box in every match.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(tag = "type", rename_all = "lowercase", deny_unknown_fields)]
pub enum ObjectDesc {
    Sphere {
        center: Vec3,
        radius: Num,
        material: String,
        /// Motion: centres at given frames, interpolated like the camera's
        /// keyframes. Empty: the sphere stays at `center`.
        #[serde(default)]
        keyframes: Vec<SphereKeyframe>,
    },
    Plane {
        normal: Vec3,
        distance: Num,
        material: String,
    },
    /// A triangle mesh from a model file (see [`MeshDesc`]).
    Mesh(MeshDesc),
}

impl ObjectDesc {
    /// The scene material named by the object; `None` for a mesh that uses its file's materials.
    pub fn material(&self) -> Option<&str> {
        match self {
            ObjectDesc::Sphere { material, .. } | ObjectDesc::Plane { material, .. } => {
                Some(material)
            }
            ObjectDesc::Mesh(m) => m.material.as_deref(),
        }
    }
    /// A sphere's centre at time `t` (in frames).
    pub fn sphere_center_at(center: &Vec3, keyframes: &[SphereKeyframe], t: f64) -> Vec3 {
        let frames: Vec<u32> = keyframes.iter().map(|k| k.frame).collect();
        let values: Vec<Vec3> = keyframes.iter().map(|k| k.center).collect();
        keyframed(&frames, &values, t).unwrap_or(*center)
    }

    pub fn kind(&self) -> &'static str {
        match self {
            ObjectDesc::Sphere { .. } => "sphere",
            ObjectDesc::Plane { .. } => "plane",
            ObjectDesc::Mesh(_) => "mesh",
        }
    }
}

/// `object_materials` entry of a mesh without a `material`: each triangle
/// uses its file's material (appended to the world's materials at build).
pub const FILE_MATERIALS: u32 = u32::MAX;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    render: Option<RenderTable>,
    /// May be left out when a mesh object gives the camera (`camera = ...`).
    camera: Option<CameraDesc>,
    #[serde(default)]
    world: WorldDesc,
    #[serde(default)]
    materials: BTreeMap<String, Spanned<MaterialDesc>>,
    #[serde(default)]
    bsdf: BTreeMap<String, Spanned<BsdfDesc>>,
    #[serde(default)]
    lights: Vec<Spanned<LightFile>>,
    #[serde(default)]
    objects: Vec<Spanned<ObjectDesc>>,
}

/// A validated scene, in the file's own (`f64`, world-space) terms.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneDesc {
    /// Where it was loaded from (for messages, and to resolve relative paths).
    pub path: PathBuf,
    pub render: RenderSettings,
    pub camera: CameraDesc,
    pub world: WorldDesc,
    /// Materials by name, in name order; objects refer to them by index.
    pub materials: Vec<(String, MaterialDesc)>,
    pub lights: Vec<LightDesc>,
    pub objects: Vec<ObjectDesc>,
    /// Index into `materials` for each object.
    pub object_materials: Vec<u32>,
    /// `[bsdf.NAME]` of each of `materials` (by index) that has one.
    pub bsdfs: Vec<Option<BsdfDesc>>,
    /// What the scene's model files gave defaults for (each names the
    /// object and the file); the scene renders, the user is told.
    pub warnings: Vec<String>,
    /// `[render]`'s adaptive-sampling keys (`target_error`,
    /// `relative_error`, `min_samples`, `max_samples`, `adaptive_mode`), each checked on its own; the command line may add
    /// to them (see [`super::adaptive::AdaptiveSpec::resolve`]).
    pub adaptive: super::adaptive::AdaptiveSpec,
}

impl SceneDesc {
    /// The objects' loaded models (object i's at i, `None` for objects
    /// without one), shared.
    pub fn models(&self) -> Vec<Option<std::sync::Arc<crate::mesh::Mesh>>> {
        self.objects
            .iter()
            .map(|o| match o {
                ObjectDesc::Mesh(m) => m.model.0.clone(),
                _ => None,
            })
            .collect()
    }

    /// Takes the objects' loaded models out (object i's at i, `None` for
    /// objects without one), leaving the description without them: for
    /// `World::build_from`, which then holds a model's only reference and
    /// frees it before the tree's build.
    pub fn take_models(&mut self) -> Vec<Option<std::sync::Arc<crate::mesh::Mesh>>> {
        let models = self.models();
        for o in &mut self.objects {
            if let ObjectDesc::Mesh(m) = o {
                m.model.0 = None;
            }
        }
        models
    }

    /// Reads and validates a scene file and the files it references from
    /// this machine's disk (paths relative to the scene's folder).
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SceneError> {
        let path = path.as_ref();
        let src = std::fs::read_to_string(path).map_err(|error| SceneError::Io {
            path: path.to_owned(),
            error,
        })?;
        Self::parse(&src, path)
    }

    /// Parses and validates scene text; `path` is used in messages and its
    /// folder holds the files the scene references.
    pub fn parse(src: &str, path: impl AsRef<Path>) -> Result<Self, SceneError> {
        let path = path.as_ref();
        Self::parse_from(src, path, &LocalFolder::of_scene(path))
    }

    /// The scene text of a path given as the scene (`tessera render PATH`,
    /// `tessera submit PATH`): a TOML file's text, or for a model file
    /// (.gltf, .glb, .obj, .obj.gz) the TOML of "Model files as scenes"
    /// (docs/scene-format.md). A PLY is refused with the TOML to write,
    /// and `--camera` (`options.camera`) applies to model files only.
    pub fn input_text(path: &Path, options: &ModelSceneOptions) -> Result<String, SceneError> {
        match SceneInput::of(path)? {
            SceneInput::Model => Ok(model_scene::model_scene_text(path, options)),
            SceneInput::Toml if options.camera.is_some() => Err(SceneError::Input {
                path: path.to_owned(),
                message: "--camera picks a camera of a model file given as the scene (.gltf, .glb); \
                          a TOML scene has its [camera], or takes a model's with `camera = ...` on its mesh object"
                    .into(),
            }),
            SceneInput::Toml => std::fs::read_to_string(path).map_err(|error| SceneError::Io {
                path: path.to_owned(),
                error,
            }),
        }
    }

    /// Parses what [`Self::input_text`] gave for `path`, from `files`; a
    /// model file's errors and warnings are said in its own and the
    /// flags' terms, not the generated TOML's.
    pub fn parse_input(
        text: &str,
        path: &Path,
        files: &dyn AssetSource,
        options: &ModelSceneOptions,
    ) -> Result<Self, SceneError> {
        if SceneInput::of(path)? == SceneInput::Toml {
            let mut scene = Self::parse_from(text, path, files)?;
            if let Some(name) = &options.environment {
                scene.set_environment(files, name)?;
            }
            return Ok(scene);
        }
        let mut scene = Self::parse_from(text, path, files)
            .map_err(|e| model_scene::model_scene_error(e, path, options))?;
        let prefix = format!("{}: objects[0] (mesh).path: ", path.display());
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
        for w in &mut scene.warnings {
            if let (Some(rest), Some(name)) = (w.strip_prefix(&prefix), &name)
                && let Some(rest) = rest.strip_prefix(&format!("{name}: "))
            {
                *w = format!("{}: {rest}", path.display());
            }
        }
        Ok(scene)
    }

    /// `--environment`: the image `name` (relative to the scene's folder)
    /// as the environment, read from `files`, with the scene's own
    /// `environment_scale` and `environment_rotation`.
    pub fn set_environment(
        &mut self,
        files: &dyn AssetSource,
        name: &str,
    ) -> Result<(), SceneError> {
        let scale = self.world.environment_scale.map_or(1.0, |n| n.0);
        let rotation = self.world.environment_rotation.map_or(0.0, |n| n.0);
        let map =
            load_environment(files, name, scale, rotation).map_err(|m| SceneError::Input {
                path: self.path.clone(),
                message: format!("--environment: {m}"),
            })?;
        self.world.environment = EnvironmentDesc::File(name.to_string());
        self.world.environment_map = Some(std::sync::Arc::new(map));
        Ok(())
    }

    /// [`Self::input_text`] and [`Self::parse_input`] from this machine's
    /// disk: what `tessera render PATH` renders.
    pub fn load_input(path: &Path, options: &ModelSceneOptions) -> Result<Self, SceneError> {
        let text = Self::input_text(path, options)?;
        Self::parse_input(&text, path, &LocalFolder::of_scene(path), options)
    }

    /// Parses and validates scene text, reading every file it references
    /// from `files` (by name relative to the scene's folder, see
    /// [`crate::assets`]); `path` is used in messages only.
    pub fn parse_from(
        src: &str,
        path: impl AsRef<Path>,
        files: &dyn AssetSource,
    ) -> Result<Self, SceneError> {
        let path = path.as_ref().to_path_buf();
        let file = parse_toml(src, &path)?;
        let sp = Spans { src, path: &path };
        let invalid = |span, field, message| sp.invalid(span, field, message);
        let table_span = |name: &str| sp.table(name);

        let (mut render, adaptive) = render_of(file.render.as_ref(), &sp)?;
        // What `[render]` gives of the size: a model camera's aspect ratio decides the rest.
        let given_size = file
            .render
            .as_ref()
            .map_or((None, None), |t| (t.width, t.height));

        let cam_err =
            |field: &str, m: String| invalid(table_span("camera"), format!("camera.{field}"), m);
        if let Some(cam) = &file.camera {
            check_camera(cam).map_err(|(f, m)| cam_err(&f, m))?;
        }

        let mut world = world_of(&file.world, files, &sp)?;

        let materials = materials_of(&file.materials, &sp)?;
        let bsdfs = bsdfs_of(&file.bsdf, &materials, &sp)?;

        // What the scene renders with a default for, said to the user.
        let mut warnings = Vec::new();
        let mut lights = Vec::with_capacity(file.lights.len());
        for (i, l) in file.lights.iter().enumerate() {
            lights.push(light_of(i, l, &sp, &mut warnings)?);
        }

        // The camera and lights mesh objects give (`camera`, `lights`).
        let mut picked: Option<(usize, model_scene::PickedCamera, std::ops::Range<usize>)> = None;
        let mut model_lights = Vec::new();
        let mut uses_model_lights = false;
        let mut objects = Vec::with_capacity(file.objects.len());
        let mut object_materials = Vec::with_capacity(file.objects.len());
        for (i, o) in file.objects.iter().enumerate() {
            let ov = o.get_ref();
            let err = |f: &str, m: String| {
                invalid(o.span(), format!("objects[{i}] ({}).{f}", ov.kind()), m)
            };
            let mut ov = ov.clone();
            match &mut ov {
                ObjectDesc::Sphere { .. } | ObjectDesc::Plane { .. } => {
                    check_analytic(&mut ov).map_err(|(f, m)| err(&f, m))?;
                }
                ObjectDesc::Mesh(m) => {
                    m.validate().map_err(|(f, msg)| err(f, msg))?;
                    let name = join("", &m.path);
                    let mesh =
                        Mesh::load_from(files, &name, m.material.is_none()).map_err(|e| {
                            let from = m.source.as_deref().map_or(String::new(), |s| {
                                format!(" (the scene says the model comes from: {s})")
                            });
                            err("path", format!("cannot load model: {e}{from}"))
                        })?;
                    let mut notes = mesh.warnings.clone();
                    let xf = m.transform();
                    if let Some(pick) = &m.camera {
                        if file.camera.is_some() {
                            return Err(err(
                                "camera",
                                "the scene's [camera] table gives the camera already: remove one of the two".into(),
                            ));
                        }
                        if let Some((j, _, _)) = &picked {
                            return Err(err(
                                "camera",
                                format!(
                                    "objects[{j}] gives the scene's camera already: only one object may"
                                ),
                            ));
                        }
                        let camera = model_scene::pick_camera(
                            &mesh,
                            &xf,
                            pick,
                            render.width,
                            render.height,
                            &mut notes,
                        )
                        .map_err(|m| err("camera", m))?;
                        picked = Some((i, camera, o.span()));
                    }
                    uses_model_lights |= m.lights.any();
                    model_lights.extend(
                        model_scene::file_lights(&mesh, &xf, &m.lights, &mut notes)
                            .map_err(|m| err("lights", m))?,
                    );
                    warnings.extend(notes.iter().map(|w| {
                        format!("{}: objects[{i}] (mesh).path: {name}: {w}", path.display())
                    }));
                    m.model = MeshModel::new(mesh);
                }
            }
            let Some(name) = ov.material() else {
                object_materials.push(FILE_MATERIALS);
                objects.push(ov);
                continue;
            };
            let Some(index) = materials.iter().position(|(n, _)| n == name) else {
                let known: Vec<_> = materials.iter().map(|(n, _)| n.as_str()).collect();
                return Err(err(
                    "material",
                    format!(
                        "unknown material {name:?}; defined materials: {}",
                        if known.is_empty() {
                            "none".to_string()
                        } else {
                            known.join(", ")
                        }
                    ),
                ));
            };
            object_materials.push(index as u32);
            objects.push(ov);
        }

        let camera = match (file.camera, picked) {
            (Some(camera), _) => camera,
            (None, Some((i, p, span))) => {
                let field = format!("objects[{i}] (mesh).camera");
                check_camera(&p.camera).map_err(|(f, m)| {
                    invalid(span.clone(), field.clone(), format!("the camera's {f} {m}"))
                })?;
                if let Some(a) = p.aspect_ratio {
                    (render.width, render.height) =
                        model_scene::size_for_aspect(a, given_size.0, given_size.1);
                    render.validate().map_err(|m| {
                        invalid(
                            span.clone(),
                            field.clone(),
                            format!("with the camera's aspectRatio {a}: {m}"),
                        )
                    })?;
                }
                p.camera
            }
            (None, None) => {
                return Err(SceneError::Parse {
                    path,
                    location: Location { line: 1, column: 1 },
                    message: "missing table [camera] (or `camera = ...` on a mesh object: one of its glTF cameras, or \"auto\")".into(),
                });
            }
        };
        // Lights from models come after the file's own, in object order.
        lights.extend(model_lights);
        if uses_model_lights && lights.is_empty() && world.ambient.0 == [0.0; 3] {
            lights.push(model_scene::headlight(&camera));
            world.ambient = Vec3([model_scene::DEFAULT_AMBIENT; 3]);
            world.default_lighting = true;
        }

        Ok(SceneDesc {
            warnings,
            path,
            render,
            camera,
            world,
            materials,
            lights,
            objects,
            object_materials,
            bsdfs,
            adaptive,
        })
    }
}

/// The checks of a camera (`[camera]`, or one a mesh object gives):
/// `Err((field, message))`.
fn check_camera(cam: &CameraDesc) -> Result<(), (String, String)> {
    let ce = |field: &str, m: String| (field.to_string(), m);
    if !cam.up.is_finite() {
        return Err(ce("up", format!("must be finite, got {:?}", cam.up.0)));
    }
    let still = CameraPose {
        position: cam.position,
        look_at: cam.look_at,
        fov_y: cam.fov_y,
    };
    let poses = std::iter::once((String::new(), still)).chain(
        cam.keyframes
            .iter()
            .enumerate()
            .map(|(i, k)| (format!("keyframes[{i}]."), cam.pose_of(k))),
    );
    for (prefix, pose) in poses {
        for (name, v) in [("position", &pose.position), ("look_at", &pose.look_at)] {
            if !v.is_finite() {
                return Err(ce(
                    &format!("{prefix}{name}"),
                    format!("must be finite, got {:?}", v.0),
                ));
            }
        }
        let forward = pose.look_at.sub(&pose.position);
        if forward.length() == 0.0 {
            return Err(ce(
                &format!("{prefix}look_at"),
                "must differ from the camera position".into(),
            ));
        }
        if cam.up.cross(&forward).length() <= 1e-12 * cam.up.length() * forward.length() {
            return Err(ce(
                &format!("{prefix}up"),
                "must not be zero or parallel to the view direction (look_at - position)".into(),
            ));
        }
        if !(pose.fov_y.0 > 0.0 && pose.fov_y.0 < 180.0) {
            return Err(ce(
                &format!("{prefix}fov_y"),
                format!("must be in (0, 180) degrees, got {}", pose.fov_y.0),
            ));
        }
    }
    for (i, w) in cam.keyframes.windows(2).enumerate() {
        if w[1].frame <= w[0].frame {
            return Err(ce(
                &format!("keyframes[{}].frame", i + 1),
                format!(
                    "keyframes must be in increasing frame order, got frame {} after frame {}",
                    w[1].frame, w[0].frame
                ),
            ));
        }
    }

    if !(cam.aperture.0.is_finite() && (0.0..=MAX_VALUE).contains(&cam.aperture.0)) {
        return Err(ce(
            "aperture",
            format!(
                "must be a finite number >= 0 and at most 1e6, got {}",
                cam.aperture.0
            ),
        ));
    }
    if let Some(f) = cam.focus_distance
        && !(f.0.is_finite() && f.0 > 0.0 && f.0 <= MAX_VALUE * MAX_VALUE)
    {
        return Err(ce(
            "focus_distance",
            format!("must be a finite number > 0, got {}", f.0),
        ));
    }
    if let Some((open, close)) = cam.shutter
        && !(open.0 >= 0.0 && open.0 <= close.0 && close.0 <= 1.0)
    {
        return Err(ce(
            "shutter",
            format!(
                "must be [open, close] with 0 <= open <= close <= 1, got [{}, {}]",
                open.0, close.0
            ),
        ));
    }
    Ok(())
}

/// A scene file's text and name, for errors that point at a place in it.
struct Spans<'a> {
    src: &'a str,
    path: &'a Path,
}

impl Spans<'_> {
    /// An invalid value: points at the offending key's line when it is
    /// written inside `span` (`radius = -1`), else at the start of the span
    /// (its table).
    fn invalid(&self, span: std::ops::Range<usize>, field: String, message: String) -> SceneError {
        let key = field.rsplit('.').next().unwrap_or("");
        let offset = key_offset(self.src, span.clone(), key).unwrap_or(span.start);
        SceneError::Invalid {
            path: self.path.to_path_buf(),
            location: Location::of_offset(self.src, offset),
            field,
            message,
        }
    }

    /// The span of top-level table `name`'s header, for errors about
    /// values in it (0..0 where the file has none).
    fn table(&self, name: &str) -> std::ops::Range<usize> {
        let header = format!("[{name}]");
        self.src
            .find(&header)
            .map(|i| i..i + header.len())
            .unwrap_or(0..0)
    }
}

/// The scene file's TOML, or an error at its line and column (an element
/// of an array of tables named with its index).
fn parse_toml(src: &str, path: &Path) -> Result<SceneFile, SceneError> {
    toml::from_str(src).map_err(|e| {
        if let Err((offset, message)) = locate_parse_error(src) {
            return SceneError::Parse {
                path: path.to_path_buf(),
                location: Location::of_offset(src, offset),
                message,
            };
        }
        let start = e.span().map_or(0, |s| s.start);
        let mut message = e.message().trim_end().to_string();
        // Errors inside an array-of-tables element point at its header:
        // say which element, since the header line is the same for all.
        if let Some(name) = src
            .get(start..)
            .and_then(|r| r.strip_prefix("[["))
            .and_then(|r| r.split("]]").next())
        {
            let index = src[..start].matches(&format!("[[{name}]]")).count();
            message = format!("{name}[{index}]: {message}");
        }
        SceneError::Parse {
            path: path.to_path_buf(),
            location: Location::of_offset(src, start),
            message,
        }
    })
}

/// `[render]`'s settings over the defaults, and its adaptive keys, checked.
fn render_of(
    table: Option<&RenderTable>,
    sp: &Spans<'_>,
) -> Result<(RenderSettings, super::adaptive::AdaptiveSpec), SceneError> {
    let invalid = |field: String, message| sp.invalid(sp.table("render"), field, message);
    let mut render = RenderSettings::default();
    let mut adaptive = super::adaptive::AdaptiveSpec::default();
    if let Some(t) = table {
        adaptive = super::adaptive::AdaptiveSpec {
            target_error: t.target_error.map(|n| n.0),
            relative_error: t.relative_error.map(|n| n.0),
            min_samples: t.min_samples,
            max_samples: t.max_samples,
            mode: t.adaptive_mode,
        };
        adaptive
            .check()
            .map_err(|(key, m)| invalid(format!("render.{key}"), m))?;
        // The file's table overrides the defaults as flags override the file.
        render = super::RenderOverrides {
            width: t.width,
            height: t.height,
            samples: t.samples,
            max_depth: t.max_depth,
            sampler: t.sampler,
            integrator: t.integrator,
        }
        .over(&render);
    }
    render.validate().map_err(|m| {
        // "samples must be ...": the field, then what is wrong with it.
        let (key, what) = m.split_once(' ').unwrap_or(("", &m));
        invalid(format!("render.{key}"), what.into())
    })?;
    Ok((render, adaptive))
}

/// A sphere's or a plane's values checked (the field at fault and why),
/// a plane's normal made unit length.
fn check_analytic(o: &mut ObjectDesc) -> Result<(), (String, String)> {
    match o {
        ObjectDesc::Sphere {
            center,
            radius,
            keyframes,
            ..
        } => {
            if !center.is_finite() {
                return Err((
                    "center".into(),
                    format!("must be finite, got {:?}", center.0),
                ));
            }
            for (k, key) in keyframes.iter().enumerate() {
                if !key.center.is_finite() {
                    return Err((
                        format!("keyframes[{k}].center"),
                        format!("must be finite, got {:?}", key.center.0),
                    ));
                }
                if k > 0 && key.frame <= keyframes[k - 1].frame {
                    return Err((
                        format!("keyframes[{k}].frame"),
                        format!(
                            "keyframes must be in increasing frame order, got frame {} after frame {}",
                            key.frame,
                            keyframes[k - 1].frame
                        ),
                    ));
                }
            }
            if !(radius.0.is_finite() && radius.0 > 0.0) {
                return Err((
                    "radius".into(),
                    format!("must be a finite number > 0, got {}", radius.0),
                ));
            }
        }
        ObjectDesc::Plane {
            normal, distance, ..
        } => {
            let len = normal.length();
            if !normal.is_finite() || !(len > 0.0) {
                return Err((
                    "normal".into(),
                    format!("must be a finite, non-zero vector, got {:?}", normal.0),
                ));
            }
            if !distance.0.is_finite() {
                return Err((
                    "distance".into(),
                    format!("must be finite, got {}", distance.0),
                ));
            }
            // Normalise: { p : p.n = d } is the same plane as { p : p.(n/|n|) = d/|n| }.
            normal.0 = normal.0.map(|v| v / len);
            distance.0 /= len;
        }
        _ => {}
    }
    Ok(())
}

/// `[world]` checked, its environment image loaded from `files`.
fn world_of(
    desc: &WorldDesc,
    files: &dyn AssetSource,
    sp: &Spans,
) -> Result<WorldDesc, SceneError> {
    let invalid = |span, field, message| sp.invalid(span, field, message);
    let world_span = sp.table("world");
    check_colour(&desc.ambient)
        .map_err(|m| invalid(world_span.clone(), "world.ambient".into(), m))?;
    check_colour(&desc.background)
        .map_err(|m| invalid(world_span.clone(), "world.background".into(), m))?;
    let mut world = desc.clone();
    match &world.environment {
        EnvironmentDesc::Colour(c) => {
            check_colour(c)
                .map_err(|m| invalid(world_span.clone(), "world.environment".into(), m))?;
            for (key, given) in [
                ("environment_scale", world.environment_scale.is_some()),
                ("environment_rotation", world.environment_rotation.is_some()),
            ] {
                if given {
                    return Err(invalid(
                        world_span.clone(),
                        format!("world.{key}"),
                        "applies to an environment image only (environment = \"sky.exr\")".into(),
                    ));
                }
            }
        }
        EnvironmentDesc::File(f) => {
            let scale = world.environment_scale.map_or(1.0, |n| n.0);
            if !(scale.is_finite() && (0.0..=MAX_VALUE).contains(&scale)) {
                return Err(invalid(
                    world_span.clone(),
                    "world.environment_scale".into(),
                    format!("must be a finite number >= 0 and at most 1e6, got {scale}"),
                ));
            }
            let rotation = world.environment_rotation.map_or(0.0, |n| n.0);
            if !(rotation.is_finite() && rotation.abs() <= 360.0) {
                return Err(invalid(
                    world_span.clone(),
                    "world.environment_rotation".into(),
                    format!("must be degrees in [-360, 360], got {rotation}"),
                ));
            }
            world.environment_map = Some(std::sync::Arc::new(
                load_environment(files, f, scale, rotation)
                    .map_err(|m| invalid(world_span.clone(), "world.environment".into(), m))?,
            ));
        }
    }

    Ok(world)
}

/// `[materials.NAME]` checked, in name order.
fn materials_of(
    file: &BTreeMap<String, Spanned<MaterialDesc>>,
    sp: &Spans,
) -> Result<Vec<(String, MaterialDesc)>, SceneError> {
    let invalid = |span, field, message| sp.invalid(span, field, message);
    let mut materials = Vec::with_capacity(file.len());
    for (name, m) in file {
        let field = |f: &str| format!("materials.{name}.{f}");
        let err = |f: &str, msg: String| invalid(m.span(), field(f), msg);
        let mv = m.get_ref();
        for (f, c) in [
            ("ambient", &mv.ambient),
            ("diffuse", &mv.diffuse),
            ("specular", &mv.specular),
        ] {
            check_colour(c).map_err(|msg| err(f, msg))?;
        }
        for (f, v) in [
            ("shininess", mv.shininess),
            ("reflectivity", mv.reflectivity),
            ("transparency", mv.transparency),
        ] {
            check_weight(v.0).map_err(|m| err(f, m))?;
        }
        for (f, v) in [("gloss", mv.gloss), ("translucency", mv.translucency)] {
            if !(v.0 >= 0.0 && v.0 < 90.0) {
                return Err(err(
                    f,
                    format!("must be a half-angle in degrees in [0, 90), got {}", v.0),
                ));
            }
        }
        if !(mv.ior.0.is_finite() && mv.ior.0 > 0.0) {
            return Err(err(
                "ior",
                format!("must be a finite number > 0, got {}", mv.ior.0),
            ));
        }
        materials.push((name.clone(), mv.clone()));
    }
    Ok(materials)
}

/// `[bsdf.NAME]` checked, each at its material's index (`None`: mapped
/// from the Blinn-Phong material).
fn bsdfs_of(
    file: &BTreeMap<String, Spanned<BsdfDesc>>,
    materials: &[(String, MaterialDesc)],
    sp: &Spans,
) -> Result<Vec<Option<BsdfDesc>>, SceneError> {
    let invalid = |span, field, message| sp.invalid(span, field, message);
    let mut bsdfs = vec![None; materials.len()];
    for (name, b) in file {
        let err = |f: &str, msg: String| invalid(b.span(), format!("bsdf.{name}.{f}"), msg);
        let Some(i) = materials.iter().position(|(n, _)| n == name) else {
            return Err(invalid(
                b.span(),
                format!("bsdf.{name}"),
                format!("names no material: [materials.{name}] is missing"),
            ));
        };
        let bv = b.get_ref();
        for (f, c) in [
            ("base_colour", &bv.base_colour),
            ("specular_colour", &bv.specular_colour),
            ("emission", &bv.emission),
        ] {
            check_colour(c).map_err(|m| err(f, m))?;
        }
        for (f, v) in [
            ("metallic", bv.metallic),
            ("roughness", bv.roughness),
            ("transmission", bv.transmission),
            ("specular", bv.specular),
        ] {
            if !(0.0..=1.0).contains(&v.0) {
                return Err(err(f, format!("must be in [0, 1], got {}", v.0)));
            }
        }
        if bv.base_colour.0.iter().any(|&c| c > 1.0) {
            return Err(err(
                "base_colour",
                format!(
                    "must be in [0, 1] (a reflectance), got {:?}",
                    bv.base_colour.0
                ),
            ));
        }
        if bv
            .attenuation_colour
            .0
            .iter()
            .any(|&c| !(c > 0.0 && c <= 1.0))
        {
            return Err(err(
                "attenuation_colour",
                format!(
                    "must be in (0, 1] (the share of light kept over attenuation_distance), got {:?}",
                    bv.attenuation_colour.0
                ),
            ));
        }
        if let Some(d) = bv.attenuation_distance
            && !(d.0.is_finite() && d.0 > 0.0)
        {
            return Err(err(
                "attenuation_distance",
                format!("must be a finite distance above 0, got {}", d.0),
            ));
        }
        if !(bv.ior.0.is_finite() && bv.ior.0 >= 1.0 && bv.ior.0 <= 10.0) {
            return Err(err(
                "ior",
                format!("must be a finite number in [1, 10], got {}", bv.ior.0),
            ));
        }
        bsdfs[i] = Some(bv.clone());
    }

    Ok(bsdfs)
}

/// `[[lights]]` entry `i` checked: its shape and the path integrator's
/// kind; what renders differently under Whitted goes to `warnings`.
fn light_of(
    i: usize,
    l: &Spanned<LightFile>,
    sp: &Spans,
    warnings: &mut Vec<String>,
) -> Result<LightDesc, SceneError> {
    let invalid = |span, field, message| sp.invalid(span, field, message);
    let lv = l.get_ref();
    let err = |f: &str, m: String| invalid(l.span(), format!("lights[{i}].{f}"), m);
    let kind = match lv.kind {
        LightType::Point => "point",
        LightType::Quad => "quad",
        LightType::Sphere => "sphere",
        LightType::Spot => "spot",
        LightType::Directional => "directional",
    };
    let point = |f: &str, v: Option<Vec3>| -> Result<Vec3, SceneError> {
        let v = v.ok_or_else(|| err(f, format!("missing (a {kind} light needs it)")))?;
        if v.is_finite() && v.0.iter().all(|x| x.abs() <= 1e15) {
            Ok(v)
        } else {
            Err(err(f, format!("must be finite, got {:?}", v.0)))
        }
    };
    // A spot's axis, a directional light's way: unit, from `direction`.
    let unit_direction = || -> Result<Vec3, SceneError> {
        let d = point("direction", lv.direction)?;
        let len = d.length();
        if !(len > 0.0) {
            return Err(err("direction", "must not be zero".into()));
        }
        Ok(Vec3(d.0.map(|x| x / len)))
    };
    // Fields of the other light types are mistakes, said as such.
    let allowed: &[&str] = match lv.kind {
        LightType::Point => &["position"],
        LightType::Quad => &["corner", "edge_u", "edge_v", "samples"],
        LightType::Sphere => &["center", "radius", "samples"],
        LightType::Spot => &["position", "direction", "cone_angle", "inner_cone_angle"],
        LightType::Directional => &["direction"],
    };
    for (f, present) in [
        ("position", lv.position.is_some()),
        ("corner", lv.corner.is_some()),
        ("edge_u", lv.edge_u.is_some()),
        ("edge_v", lv.edge_v.is_some()),
        ("center", lv.center.is_some()),
        ("radius", lv.radius.is_some()),
        ("samples", lv.samples.is_some()),
        ("direction", lv.direction.is_some()),
        ("cone_angle", lv.cone_angle.is_some()),
        ("inner_cone_angle", lv.inner_cone_angle.is_some()),
    ] {
        if present && !allowed.contains(&f) {
            return Err(err(
                f,
                format!(
                    "not a field of a {kind} light (type = \"{kind}\" takes {})",
                    allowed.join(", ")
                ),
            ));
        }
    }
    let mut path_kind = None;
    let (shape, position) = match lv.kind {
        LightType::Point => (LightShape::Point, point("position", lv.position)?),
        LightType::Spot => {
            let direction = unit_direction()?;
            // glTF's defaults: outer pi/4, inner 0.
            let outer = lv.cone_angle.map_or(45.0, |a| a.0);
            let inner = lv.inner_cone_angle.map_or(0.0, |a| a.0);
            if !(outer > 0.0 && outer <= 90.0) {
                return Err(err(
                    "cone_angle",
                    format!("must be in (0, 90] degrees, got {outer}"),
                ));
            }
            if !(inner >= 0.0 && inner < outer) {
                return Err(err(
                    "inner_cone_angle",
                    format!("must be in [0, cone_angle = {outer}) degrees, got {inner}"),
                ));
            }
            path_kind = Some(PathLightKind::Spot {
                direction,
                cos_inner: inner.to_radians().cos(),
                cos_outer: outer.to_radians().cos(),
            });
            warnings.push(format!(
                "lights[{i}]: a spot light renders as a point light under Whitted, shining every way (its cone is the path integrator's only)"
            ));
            (LightShape::Point, point("position", lv.position)?)
        }
        LightType::Directional => {
            let direction = unit_direction()?;
            // The world gives it the scene's radius (its power).
            path_kind = Some(PathLightKind::Directional {
                direction,
                irradiance: lv.diffuse,
                radius: 0.0,
            });
            (
                LightShape::Point,
                Vec3(direction.0.map(|x| -x * DIRECTIONAL_STAND_IN)),
            )
        }
        LightType::Quad => {
            let corner = point("corner", lv.corner)?;
            let edge_u = point("edge_u", lv.edge_u)?;
            let edge_v = point("edge_v", lv.edge_v)?;
            let area = edge_u.cross(&edge_v).length();
            if !(area > 1e-12 * edge_u.length() * edge_v.length()) || area == 0.0 {
                return Err(err(
                    "edge_v",
                    format!(
                        "edge_u {:?} and edge_v {:?} must span a parallelogram (non-zero, not parallel)",
                        edge_u.0, edge_v.0
                    ),
                ));
            }
            let centre = Vec3(std::array::from_fn(|k| {
                corner.0[k] + 0.5 * edge_u.0[k] + 0.5 * edge_v.0[k]
            }));
            (
                LightShape::Quad {
                    corner,
                    edge_u,
                    edge_v,
                },
                centre,
            )
        }
        LightType::Sphere => {
            let center = point("center", lv.center)?;
            let radius = lv
                .radius
                .ok_or_else(|| err("radius", "missing (a sphere light needs it)".into()))?
                .0;
            if !(radius.is_finite() && radius > 0.0 && radius <= 1e15) {
                return Err(err(
                    "radius",
                    format!("must be a finite number > 0, got {radius}"),
                ));
            }
            (LightShape::Sphere { center, radius }, center)
        }
    };
    let samples = lv.samples.unwrap_or(1);
    if !(1..=MAX_LIGHT_SAMPLES).contains(&samples) {
        return Err(err(
            "samples",
            format!("must be in 1..={MAX_LIGHT_SAMPLES}, got {samples}"),
        ));
    }
    for (f, c) in [("diffuse", &lv.diffuse), ("specular", &lv.specular)] {
        check_colour(c).map_err(|m| err(f, m))?;
    }
    Ok(LightDesc {
        shape,
        position,
        diffuse: lv.diffuse,
        specular: lv.specular,
        samples,
        path_radiance: None,
        path_kind,
    })
}

/// Byte offset of a line `key = ...` in the table that starts at `span`
/// (toml spans of array-of-tables elements cover only their header, so
/// the search runs on to the next table header).
fn key_offset(src: &str, span: std::ops::Range<usize>, key: &str) -> Option<usize> {
    if key.is_empty() {
        return None;
    }
    let text = src.get(span.start..)?;
    let mut offset = 0;
    for (i, line) in text.split_inclusive('\n').enumerate() {
        let trimmed = line.trim_start();
        if i > 0 && trimmed.starts_with('[') {
            break;
        }
        if let Some(rest) = trimmed.strip_prefix(key)
            && rest.trim_start().starts_with('=')
        {
            return Some(span.start + offset + (line.len() - trimmed.len()));
        }
        offset += line.len();
    }
    None
}

/// Largest colour component or material weight. Scenes render in f32
/// (f32::MAX is 3.4e38): a product of a few values this size stays finite,
/// where 1e39 would already be infinite when converted.
pub const MAX_VALUE: f64 = 1e6;

/// The environment image `file` (as written in the scene: relative to its
/// folder) read from `files`, decoded; the error says which file and why.
fn load_environment(
    files: &dyn AssetSource,
    file: &str,
    scale: f64,
    rotation: f64,
) -> Result<crate::environment::EnvironmentMap, String> {
    let name = join("", file);
    let bytes = files.read(&name).map_err(|e| e.to_string())?;
    crate::environment::EnvironmentMap::decode(&name, &bytes, scale, rotation)
        .map_err(|m| format!("{name}: {m}"))
}

pub(crate) fn check_colour(c: &Vec3) -> Result<(), String> {
    if c.is_finite() && c.0.iter().all(|&v| (0.0..=MAX_VALUE).contains(&v)) {
        Ok(())
    } else {
        Err(format!(
            "must be three finite numbers >= 0 and at most 1e6 (larger overflow f32), got {:?}",
            c.0
        ))
    }
}

pub(crate) fn check_weight(v: f64) -> Result<(), String> {
    if v.is_finite() && (0.0..=MAX_VALUE).contains(&v) {
        Ok(())
    } else {
        Err(format!(
            "must be a finite number >= 0 and at most 1e6 (larger overflow f32), got {v}"
        ))
    }
}

/// Where a deserialisation error really is. `toml::from_str` reports an
/// error inside an array-of-tables element at the array's first header
/// and names no element; here each table and element is deserialised on
/// its own from the spanned document, so the error names its element's
/// full path and points at the offending key or value (with a suggestion
/// for a misspelt key). `Ok`: not an error of one table (syntax errors,
/// unknown top-level keys), which toml's own message locates well.
fn locate_parse_error(src: &str) -> Result<(), (usize, String)> {
    use toml::de::{DeTable, DeValue};
    type Value<'i> = toml::Spanned<DeValue<'i>>;
    fn named<'i>(t: &DeTable<'i>, name: &str) -> Option<Value<'i>> {
        t.iter()
            .find(|(k, _)| k.get_ref().as_ref() == name)
            .map(|(_, v)| v.clone())
    }
    fn check<'i, T: Deserialize<'i>>(v: &Value<'i>, path: &str) -> Result<(), (usize, String)> {
        match T::deserialize(toml::de::ValueDeserializer::from(v.clone())) {
            Ok(_) => Ok(()),
            Err(e) => Err(explain::<T>(v, path, &e)),
        }
    }
    let Ok(doc) = DeTable::parse(src) else {
        return Ok(());
    };
    let root = doc.get_ref();
    if let Some(v) = named(root, "render") {
        check::<RenderTable>(&v, "render")?;
    }
    if let Some(cam) = named(root, "camera") {
        if let DeValue::Table(t) = cam.get_ref()
            && let Some(keys) = named(t, "keyframes")
            && let DeValue::Array(a) = keys.get_ref()
        {
            for (i, k) in a.iter().enumerate() {
                check::<CameraKeyframe>(k, &format!("camera.keyframes[{i}]"))?;
            }
        }
        check::<CameraDesc>(&cam, "camera")?;
    }
    if let Some(v) = named(root, "world") {
        check::<WorldDesc>(&v, "world")?;
    }
    if let Some(v) = named(root, "materials")
        && let DeValue::Table(t) = v.get_ref()
    {
        for (k, m) in t.iter() {
            check::<MaterialDesc>(m, &format!("materials.{}", k.get_ref()))?;
        }
    }
    if let Some(v) = named(root, "lights")
        && let DeValue::Array(a) = v.get_ref()
    {
        for (i, e) in a.iter().enumerate() {
            check::<LightFile>(e, &format!("lights[{i}]"))?;
        }
    }
    if let Some(v) = named(root, "objects")
        && let DeValue::Array(a) = v.get_ref()
    {
        for (i, e) in a.iter().enumerate() {
            let mut path = format!("objects[{i}]");
            if let DeValue::Table(t) = e.get_ref()
                && let Some(ty) = named(t, "type")
                && let DeValue::String(ty) = ty.get_ref()
            {
                path = format!("{path} ({ty})");
            }
            check::<ObjectDesc>(e, &path)?;
        }
    }
    Ok(())
}

/// An error of the table `v` at `path`, at its key or value.
fn explain<'i, T: Deserialize<'i>>(
    v: &toml::Spanned<toml::de::DeValue<'i>>,
    path: &str,
    e: &toml::de::Error,
) -> (usize, String) {
    use toml::de::DeValue;
    let message = e.message().trim_end();
    let keys: Vec<(String, std::ops::Range<usize>, std::ops::Range<usize>)> = match v.get_ref() {
        DeValue::Table(t) => t
            .iter()
            .map(|(k, val)| (k.get_ref().to_string(), k.span(), val.span()))
            .collect(),
        _ => Vec::new(),
    };
    if let Some(rest) = message.strip_prefix("unknown field `") {
        let mut parts = rest.split('`');
        let name = parts.next().unwrap_or_default();
        // "..., expected one of `a`, `b`" or "expected `a`": every other piece.
        let expected: Vec<&str> = parts.skip(1).step_by(2).collect();
        let offset = keys
            .iter()
            .find(|(k, _, _)| k == name)
            .map_or(v.span().start, |(_, ks, _)| ks.start);
        // Of equally close names, the plural of the one typed first:
        // `sample` is `samples` (a count), not `sampler`.
        let hint = expected
            .iter()
            .map(|c| {
                (
                    edit_distance(name, c),
                    c.strip_suffix('s') != Some(name),
                    *c,
                )
            })
            .filter(|&(d, _, c)| d <= 2.max(name.len() / 4) && d < c.len())
            .min()
            .map_or(String::new(), |(_, _, c)| format!("; did you mean `{c}`?"));
        let valid = if expected.is_empty() {
            String::new()
        } else {
            format!(
                " (valid: {})",
                expected
                    .iter()
                    .map(|c| format!("`{c}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        };
        return (
            offset,
            format!("{path}.{name}: unknown field `{name}`{hint}{valid}"),
        );
    }
    // A wrong value (`radius = "one"`): toml places it at the table. The
    // key at fault is the one whose absence changes the error.
    if let DeValue::Table(t) = v.get_ref() {
        for (k, val) in t.iter() {
            let mut without = t.clone();
            without.remove(k);
            let again = T::deserialize(toml::de::ValueDeserializer::from(toml::Spanned::new(
                v.span(),
                DeValue::Table(without),
            )));
            if again.as_ref().err().map(|e| e.message().trim_end()) != Some(message) {
                return (
                    val.span().start,
                    format!("{path}.{}: {message}", k.get_ref()),
                );
            }
        }
    }
    let at = e.span().map_or(v.span().start, |s| s.start);
    (at, format!("{path}: {message}"))
}

/// Levenshtein distance, for "did you mean".
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut prev = row[0];
        row[0] = i + 1;
        for (j, &cb) in b.iter().enumerate() {
            let cur = row[j + 1];
            row[j + 1] = (prev + usize::from(ca != cb)).min(row[j] + 1).min(cur + 1);
            prev = cur;
        }
    }
    row[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
[camera]
position = [0, 1, -6]
look_at = [0.0, 1.0, 0.0]

[materials.red]
diffuse = [1, 0, 0]

[[objects]]
type = "sphere"
center = [0.0, 1.0, 0.0]
radius = 1
material = "red"
"#;

    #[test]
    fn minimal_scene_takes_defaults() {
        let s = SceneDesc::parse(MINIMAL, "min.toml").unwrap();
        assert_eq!(s.render, RenderSettings::default());
        assert_eq!(s.camera.fov_y, Num(60.0));
        assert_eq!(s.objects.len(), 1);
        assert_eq!(s.materials[0].1.ior, Num(1.0));
    }

    fn err(src: &str) -> String {
        SceneDesc::parse(src, "bad.toml").unwrap_err().to_string()
    }

    #[test]
    fn errors_name_file_line_and_field() {
        let e = err(&MINIMAL.replace("radius = 1", "radius = -1"));
        assert!(
            e.starts_with(
                "bad.toml:12:1: objects[0] (sphere).radius: must be a finite number > 0, got -1"
            ),
            "{e}"
        );
        let e = err(&MINIMAL.replace("material = \"red\"", "material = \"blue\""));
        assert!(
            e.contains(
                "objects[0] (sphere).material: unknown material \"blue\"; defined materials: red"
            ),
            "{e}"
        );
        let e = err(&MINIMAL.replace("radius = 1", "radius = 1\ncolour = 3"));
        assert!(
            e.starts_with("bad.toml:") && e.contains("unknown field `colour`"),
            "{e}"
        );
        let e = err(&MINIMAL.replace("radius = 1", "radius = \"big\""));
        assert!(e.contains("bad.toml:") && e.contains("a number"), "{e}");
        let e = err(&MINIMAL.replace("[camera]", "[camera"));
        assert!(e.starts_with("bad.toml:2:"), "{e}");
        let e = err(&MINIMAL.replace("radius = 1", "radius = nan"));
        assert!(
            e.contains("radius: must be a finite number > 0, got NaN"),
            "{e}"
        );
    }

    #[test]
    fn values_past_what_f32_holds_are_refused() {
        let src = MINIMAL.replace("diffuse = [1, 0, 0]", "diffuse = [1e39, 0, 0]");
        let e = err(&src);
        assert!(
            e.contains("materials.red.diffuse: must be three finite numbers >= 0 and at most 1e6 (larger overflow f32), got [1e39, 0.0, 0.0]"),
            "{e}"
        );
        let src = MINIMAL.replace(
            "diffuse = [1, 0, 0]",
            "diffuse = [1, 0, 0]\nshininess = 1e300",
        );
        assert!(err(&src).contains("shininess: must be a finite number >= 0 and at most 1e6"));
    }

    #[test]
    fn camera_keyframes_interpolate_linearly_and_hold_at_the_ends() {
        let src = MINIMAL.replace(
            "look_at = [0.0, 1.0, 0.0]\n",
            "look_at = [0.0, 1.0, 0.0]\n[[camera.keyframes]]\nframe = 1\nposition = [0, 1, -6]\n\
             [[camera.keyframes]]\nframe = 5\nposition = [4, 3, -2]\nfov_y = 40\n",
        );
        let s = SceneDesc::parse(&src, "anim.toml").unwrap();
        let at = |f| s.camera.at(f);
        assert_eq!(at(0), at(1));
        assert_eq!(at(1).position, Vec3([0.0, 1.0, -6.0]));
        assert_eq!(at(1).fov_y, Num(60.0)); // left out: the [camera] table's
        assert_eq!(at(2).position, Vec3([1.0, 1.5, -5.0]));
        assert_eq!(at(3).fov_y, Num(50.0));
        assert_eq!(at(3).look_at, Vec3([0.0, 1.0, 0.0]));
        assert_eq!(at(5).position, Vec3([4.0, 3.0, -2.0]));
        assert_eq!(at(9), at(5));
        // A still camera ignores the frame.
        let still = SceneDesc::parse(MINIMAL, "still.toml").unwrap();
        assert_eq!(still.camera.at(7).position, still.camera.position);
        // Out-of-order keyframes and degenerate poses are refused by name.
        let e = err(&src.replace("frame = 5", "frame = 1"));
        assert!(
            e.contains("camera.keyframes[1].frame: keyframes must be in increasing frame order"),
            "{e}"
        );
        let e = err(&src.replace("position = [4, 3, -2]", "position = [0, 1, 0]"));
        assert!(
            e.contains("camera.keyframes[1].look_at: must differ from the camera position"),
            "{e}"
        );
    }

    #[test]
    fn plane_normal_is_normalised_with_its_distance() {
        let src = MINIMAL.replace(
            "type = \"sphere\"\ncenter = [0.0, 1.0, 0.0]\nradius = 1",
            "type = \"plane\"\nnormal = [0, 2, 0]\ndistance = 4",
        );
        let s = SceneDesc::parse(&src, "p.toml").unwrap();
        assert_eq!(
            s.objects[0],
            ObjectDesc::Plane {
                normal: Vec3([0.0, 1.0, 0.0]),
                distance: Num(2.0),
                material: "red".into()
            }
        );
        let e = err(&src.replace("[0, 2, 0]", "[0, 0, 0]"));
        assert!(
            e.contains("objects[0] (plane).normal: must be a finite, non-zero vector"),
            "{e}"
        );
    }

    #[test]
    fn distributed_fields_are_validated_by_name() {
        let quad = "[[lights]]\ntype = \"quad\"\ncorner = [0, 4, 0]\nedge_u = [1, 0, 0]\nedge_v = [0, 0, 1]\nsamples = 4\n";
        let s = SceneDesc::parse(&format!("{MINIMAL}{quad}"), "q.toml").unwrap();
        assert_eq!(s.lights[0].samples, 4);
        assert_eq!(s.lights[0].position, Vec3([0.5, 4.0, 0.5]));
        let e = err(&format!(
            "{MINIMAL}{}",
            quad.replace("[0, 0, 1]", "[2, 0, 0]")
        ));
        assert!(
            e.contains("lights[0].edge_v: edge_u [1.0, 0.0, 0.0] and edge_v [2.0, 0.0, 0.0] must span a parallelogram"),
            "{e}"
        );
        let e = err(&format!(
            "{MINIMAL}{}",
            quad.replace("samples = 4", "samples = 0")
        ));
        assert!(
            e.contains("lights[0].samples: must be in 1..=4096, got 0"),
            "{e}"
        );
        let e = err(&format!(
            "{MINIMAL}{}",
            quad.replace("corner = [0, 4, 0]\n", "")
        ));
        assert!(
            e.contains("lights[0].corner: missing (a quad light needs it)"),
            "{e}"
        );
        let e = err(&format!(
            "{MINIMAL}[[lights]]\nposition = [0, 1, 0]\nsamples = 2\n"
        ));
        assert!(
            e.contains("lights[0].samples: not a field of a point light"),
            "{e}"
        );
        let e = err(&format!(
            "{MINIMAL}[[lights]]\ntype = \"sphere\"\ncenter = [0, 1, 0]\nradius = 0\n"
        ));
        assert!(
            e.contains("lights[0].radius: must be a finite number > 0, got 0"),
            "{e}"
        );
        let e = err(&format!("{MINIMAL}[[lights]]\ntype = \"disc\"\n"));
        assert!(e.contains("lights[0]") && e.contains("disc"), "{e}");
        let e = err(&MINIMAL.replace("diffuse = [1, 0, 0]", "diffuse = [1, 0, 0]\ngloss = 90"));
        assert!(
            e.contains("materials.red.gloss: must be a half-angle in degrees in [0, 90), got 90"),
            "{e}"
        );
        let e = err(&MINIMAL.replace("diffuse = [1, 0, 0]", "translucency = -1"));
        assert!(
            e.contains("materials.red.translucency: must be a half-angle"),
            "{e}"
        );
        let cam = |line: &str| {
            err(&MINIMAL.replace(
                "look_at = [0.0, 1.0, 0.0]",
                &format!("look_at = [0.0, 1.0, 0.0]\n{line}"),
            ))
        };
        let e = cam("shutter = [0.5, 0.25]");
        assert!(
            e.contains("camera.shutter: must be [open, close] with 0 <= open <= close <= 1, got [0.5, 0.25]"),
            "{e}"
        );
        assert!(cam("shutter = [0, 1.5]").contains("camera.shutter"));
        assert!(cam("aperture = -1").contains("camera.aperture: must be a finite number >= 0"));
        assert!(
            cam("focus_distance = 0")
                .contains("camera.focus_distance: must be a finite number > 0")
        );
        let e = err(&format!(
            "{MINIMAL}[[objects.keyframes]]\nframe = 3\ncenter = [0, 0, 0]\n[[objects.keyframes]]\nframe = 2\ncenter = [0, 1, 0]\n"
        ));
        assert!(
            e.contains("objects[0] (sphere).keyframes[1].frame: keyframes must be in increasing frame order"),
            "{e}"
        );
        // Sphere keyframes interpolate like the camera's, at real times.
        let s = SceneDesc::parse(
            &format!("{MINIMAL}[[objects.keyframes]]\nframe = 2\ncenter = [0, 0, 0]\n[[objects.keyframes]]\nframe = 4\ncenter = [4, 0, 0]\n"),
            "k.toml",
        )
        .unwrap();
        let ObjectDesc::Sphere {
            center, keyframes, ..
        } = &s.objects[0]
        else {
            panic!()
        };
        assert_eq!(
            ObjectDesc::sphere_center_at(center, keyframes, 3.5),
            Vec3([3.0, 0.0, 0.0])
        );
        assert_eq!(
            ObjectDesc::sphere_center_at(center, keyframes, 1.0),
            Vec3([0.0, 0.0, 0.0])
        );
        assert_eq!(
            ObjectDesc::sphere_center_at(center, keyframes, 9.0),
            Vec3([4.0, 0.0, 0.0])
        );
        assert_eq!(ObjectDesc::sphere_center_at(center, &[], 9.0), *center);
    }
}
