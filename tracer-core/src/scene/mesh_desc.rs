//! `type = "mesh"` objects: a model file and its placement.

use std::sync::Arc;

use glam::{DMat3, DVec3};
use serde::Deserialize;
use serde::de::{self, Deserializer, SeqAccess, Visitor};

use super::desc::{MeshKeyframe, Num, Vec3, keyframed};
use super::model_scene::{CameraPick, LightsPick};
use crate::mesh::Mesh;

/// A triangle mesh from a model file, placed by scale, then `rotate_euler`
/// (about x, then y, then z), then `rotate` (about an axis), then `translate`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MeshDesc {
    /// OBJ (+MTL), glTF 2.0 (.gltf/.glb) or PLY (.ply/.ply.gz), relative to the scene file.
    pub path: String,
    /// Where the model comes from, for a file not kept beside the scene
    /// (a licence forbids it, or it is large): said when the file cannot
    /// be loaded, so that a reader knows where to get it.
    #[serde(default)]
    pub source: Option<String>,
    #[serde(default)]
    pub translate: Vec3,
    #[serde(default)]
    pub rotate: Option<Rotation>,
    /// Degrees about x, y and z, applied in that order.
    #[serde(default)]
    pub rotate_euler: Option<Vec3>,
    #[serde(default)]
    pub scale: Scale,
    /// Overrides every material of the file.
    #[serde(default)]
    pub material: Option<String>,
    /// Motion: `translate` at given frames, interpolated like the camera's
    /// keyframes. Empty: the mesh stays at `translate`.
    #[serde(default)]
    pub keyframes: Vec<MeshKeyframe>,
    /// The scene's camera from this model: one of its glTF cameras, or
    /// the automatic camera framing it (then the scene has no `[camera]`).
    #[serde(default)]
    pub camera: Option<CameraPick>,
    /// The model's glTF lights the scene gets (default none).
    #[serde(default)]
    pub lights: LightsPick,
    /// Copies of the model, each placed by its own keys after the
    /// object's placement; the model is stored once (instancing). Empty:
    /// one copy, at the object's placement.
    #[serde(default)]
    pub instances: Vec<MeshInstance>,
    /// The loaded model (filled by `SceneDesc::parse`, not part of the format).
    #[serde(skip)]
    pub model: MeshModel,
}

/// One copy of a mesh object's model: scale, then `rotate_euler`, then
/// `rotate`, then `translate`, as the object's own keys.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MeshInstance {
    #[serde(default)]
    pub translate: Vec3,
    #[serde(default)]
    pub rotate: Option<Rotation>,
    #[serde(default)]
    pub rotate_euler: Option<Vec3>,
    #[serde(default)]
    pub scale: Scale,
}

impl MeshInstance {
    /// Model space (as the object places it) -> world space.
    pub fn transform(&self) -> Affine {
        placement(
            &self.scale,
            &self.rotate_euler,
            &self.rotate,
            &self.translate,
        )
    }
}

#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Rotation {
    pub axis: Vec3,
    pub degrees: Num,
}

/// A uniform (`scale = 2`) or per-axis (`scale = [1, 2, 1]`) scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scale(pub [f64; 3]);

impl Default for Scale {
    fn default() -> Self {
        Scale([1.0; 3])
    }
}

impl<'de> Deserialize<'de> for Scale {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Scale;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a number or an array of three numbers")
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Scale, E> {
                Ok(Scale([v; 3]))
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Scale, E> {
                Ok(Scale([v as f64; 3]))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Scale, E> {
                Ok(Scale([v as f64; 3]))
            }
            fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<Scale, A::Error> {
                Vec3::deserialize(de::value::SeqAccessDeserializer::new(seq)).map(|v| Scale(v.0))
            }
        }
        d.deserialize_any(V)
    }
}

/// The loaded mesh. Shared, not compared: two descriptions of the same
/// file and placement are equal whatever was read (the file is the input).
#[derive(Clone, Default)]
pub struct MeshModel(pub Option<Arc<Mesh>>);

impl MeshModel {
    pub fn new(mesh: Mesh) -> Self {
        MeshModel(Some(Arc::new(mesh)))
    }
}

impl PartialEq for MeshModel {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for MeshModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.0 {
            Some(m) => write!(f, "MeshModel({} triangles)", m.triangles.len()),
            None => f.write_str("MeshModel(not loaded)"),
        }
    }
}

/// An affine map x -> linear x + translation, in `f64`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Affine {
    pub linear: DMat3,
    pub translation: DVec3,
}

impl Affine {
    pub fn point(&self, p: [f32; 3]) -> DVec3 {
        self.linear * DVec3::from_array(p.map(f64::from)) + self.translation
    }
    /// Matrix for normals (inverse transpose), up to a positive factor.
    pub fn normal_matrix(&self) -> DMat3 {
        self.linear.inverse().transpose()
    }
    /// Whether the map mirrors (then triangle windings must be flipped).
    pub fn mirrors(&self) -> bool {
        self.linear.determinant() < 0.0
    }
}

impl MeshDesc {
    /// Checks the placement values; `Err((field, message))`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if self.path.trim().is_empty() {
            return Err(("path", "must name a model file".into()));
        }
        if !self.translate.0.iter().all(|v| v.is_finite()) {
            return Err((
                "translate",
                format!("must be finite, got {:?}", self.translate.0),
            ));
        }
        for (i, k) in self.keyframes.iter().enumerate() {
            if !k.translate.0.iter().all(|v| v.is_finite()) {
                return Err((
                    "keyframes",
                    format!(
                        "keyframes[{i}].translate must be finite, got {:?}",
                        k.translate.0
                    ),
                ));
            }
            if i > 0 && k.frame <= self.keyframes[i - 1].frame {
                return Err((
                    "keyframes",
                    format!(
                        "keyframes must be in increasing frame order, got frame {} after frame {}",
                        k.frame,
                        self.keyframes[i - 1].frame
                    ),
                ));
            }
        }
        check_placement(&self.scale, &self.rotate, &self.rotate_euler)?;
        for (i, inst) in self.instances.iter().enumerate() {
            let at = |(f, m): (&str, String)| ("instances", format!("instances[{i}].{f} {m}"));
            if !inst.translate.0.iter().all(|v| v.is_finite()) {
                return Err(at((
                    "translate",
                    format!("must be finite, got {:?}", inst.translate.0),
                )));
            }
            check_placement(&inst.scale, &inst.rotate, &inst.rotate_euler).map_err(at)?;
        }
        if !self.instances.is_empty() && !self.keyframes.is_empty() {
            return Err((
                "instances",
                "cannot be combined with keyframes (a moving mesh is one copy)".into(),
            ));
        }
        Ok(())
    }

    /// The translation at time `t` (in frames).
    pub fn translate_at(&self, t: f64) -> Vec3 {
        let frames: Vec<u32> = self.keyframes.iter().map(|k| k.frame).collect();
        let values: Vec<Vec3> = self.keyframes.iter().map(|k| k.translate).collect();
        keyframed(&frames, &values, t).unwrap_or(self.translate)
    }

    /// Model space -> world space.
    pub fn transform(&self) -> Affine {
        placement(
            &self.scale,
            &self.rotate_euler,
            &self.rotate,
            &self.translate,
        )
    }
}

/// Checks scale and rotations of a placement; `Err((field, message))`.
fn check_placement(
    scale: &Scale,
    rotate: &Option<Rotation>,
    rotate_euler: &Option<Vec3>,
) -> Result<(), (&'static str, String)> {
    if !scale.0.iter().all(|v| v.is_finite() && *v != 0.0) {
        return Err((
            "scale",
            format!("must be finite and non-zero, got {:?}", scale.0),
        ));
    }
    if let Some(r) = rotate {
        let a = r.axis.0;
        let len = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        if !(len.is_finite() && len > 0.0) {
            return Err((
                "rotate",
                format!("axis must be a finite, non-zero vector, got {a:?}"),
            ));
        }
        if !r.degrees.0.is_finite() {
            return Err((
                "rotate",
                format!("degrees must be finite, got {}", r.degrees.0),
            ));
        }
    }
    if let Some(e) = rotate_euler.filter(|e| !e.0.iter().all(|v| v.is_finite())) {
        return Err(("rotate_euler", format!("must be finite, got {:?}", e.0)));
    }
    Ok(())
}

/// Scale, then `rotate_euler` (about x, then y, then z), then `rotate`,
/// then `translate`.
fn placement(
    scale: &Scale,
    rotate_euler: &Option<Vec3>,
    rotate: &Option<Rotation>,
    translate: &Vec3,
) -> Affine {
    let mut linear = DMat3::from_diagonal(DVec3::from_array(scale.0));
    if let Some(e) = rotate_euler {
        let [x, y, z] = e.0.map(f64::to_radians);
        linear = DMat3::from_rotation_z(z)
            * DMat3::from_rotation_y(y)
            * DMat3::from_rotation_x(x)
            * linear;
    }
    if let Some(r) = rotate {
        let axis = DVec3::from_array(r.axis.0).normalize();
        linear = DMat3::from_axis_angle(axis, r.degrees.0.to_radians()) * linear;
    }
    Affine {
        linear,
        translation: DVec3::from_array(translate.0),
    }
}
