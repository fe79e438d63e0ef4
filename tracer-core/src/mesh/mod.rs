//! Triangle meshes loaded from model files: OBJ (+MTL) through `tobj`,
//! glTF 2.0 (.gltf/.glb) through `gltf`, PLY (ASCII or binary, optionally
//! gzipped) through a small reader here. A loaded [`Mesh`] is in the file's
//! own model space; the scene's transform is applied by `World::build`.

mod gltf_file;
mod obj;
mod ply;
mod tangents;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::material::Pbr;

use crate::assets::{AssetError, AssetSource, LocalFolder};

use crate::scene::{MaterialDesc, Num, Vec3, check_colour, check_weight};

/// A triangle mesh as read from a file.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    /// Unit vertex normals, one per position, or empty when the file has
    /// none. A zero entry means "unknown": triangles using it shade flat.
    pub normals: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    /// Per triangle, an index into `materials`.
    pub triangle_materials: Vec<u32>,
    /// The file's materials mapped to the Blinn-Phong model (at least one).
    pub materials: Vec<(String, MaterialDesc)>,
    /// Per material (same index; shorter or empty: none), its textures
    /// and glTF parameters as authored, looked up at each hit.
    pub pbr: Vec<Option<Arc<Pbr>>>,
    /// Per vertex texture coordinates (TEXCOORD_0 and _1), in glTF's
    /// texture space (v down), or empty when no vertex has them.
    pub uvs: [Vec<[f32; 2]>; 2],
    /// Per vertex linear RGBA colour (COLOR_0), or empty.
    pub colors: Vec<[f32; 4]>,
    /// Per vertex tangent for normal maps (glTF TANGENT: xyz, w the
    /// bitangent's sign, +-1), from the file or MikkTSpace (`tangents.rs`);
    /// w 0 where unknown; empty when no material has a normal map.
    pub tangents: Vec<[f32; 4]>,
    /// What was read with a default instead of refused (a missing MTL
    /// library, `Ni 0`): shown to the user, the file still renders.
    pub warnings: Vec<String>,
    /// glTF cameras as placed by the default scene's nodes, in the order
    /// of a depth-first walk of its node tree (the first is the file's
    /// default camera). Empty for other formats.
    pub cameras: Vec<ModelCamera>,
    /// glTF `KHR_lights_punctual` lights as placed by the default scene's
    /// nodes, in the same order. Empty for other formats.
    pub lights: Vec<ModelLight>,
    /// Geometry placed more than once (a glTF mesh used by several nodes,
    /// or by `EXT_mesh_gpu_instancing`), stored once: the world traces it
    /// through a two-level tree instead of copying it. Empty for other formats.
    pub instanced: Vec<InstancedPart>,
}

/// Geometry of a model stored once and placed many times.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct InstancedPart {
    /// The geometry in its own space: positions, normals, triangles and
    /// `triangle_materials` (indices into the owning [`Mesh`]'s
    /// `materials`; this mesh's own `materials` stay empty).
    pub mesh: Mesh,
    /// Where each copy goes in the model's space: column-major 4x4
    /// affine matrices (glam's `DMat4`), each invertible.
    pub transforms: Vec<[f64; 16]>,
}

impl Mesh {
    /// Triangles as placed: the plain ones and every instanced copy.
    pub fn placed_triangles(&self) -> usize {
        self.triangles.len()
            + self
                .instanced
                .iter()
                .map(|p| p.mesh.triangles.len() * p.transforms.len())
                .sum::<usize>()
    }
}

/// A camera of a model file, in the file's model space (node transforms
/// applied, the scene's placement not yet).
#[derive(Clone, Debug, PartialEq)]
pub struct ModelCamera {
    /// Index in the file's `cameras` array.
    pub index: usize,
    /// The camera's name, else its node's name.
    pub name: Option<String>,
    pub projection: Projection,
    pub position: [f64; 3],
    /// Unit view direction (the node's -Z axis).
    pub forward: [f64; 3],
    /// The node's +Y axis (not necessarily unit or orthogonal to `forward`).
    pub up: [f64; 3],
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// `yfov` in radians; `aspect_ratio` width / height when the file gives one.
    Perspective {
        yfov: f64,
        aspect_ratio: Option<f64>,
    },
    Orthographic {
        xmag: f64,
        ymag: f64,
    },
}

/// A `KHR_lights_punctual` light, in model space, in the file's units:
/// `intensity` in candela (point, spot) or lux (directional).
#[derive(Clone, Debug, PartialEq)]
pub struct ModelLight {
    /// Index in the file's `KHR_lights_punctual.lights` array.
    pub index: usize,
    pub name: Option<String>,
    pub kind: ModelLightKind,
    pub color: [f64; 3],
    pub intensity: f64,
    pub position: [f64; 3],
    /// Unit direction the light shines in (the node's -Z axis).
    pub direction: [f64; 3],
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ModelLightKind {
    Point,
    /// Cone half-angles in radians.
    Spot {
        inner: f64,
        outer: f64,
    },
    Directional,
}

impl ModelLightKind {
    pub fn name(&self) -> &'static str {
        match self {
            ModelLightKind::Point => "point",
            ModelLightKind::Spot { .. } => "spot",
            ModelLightKind::Directional => "directional",
        }
    }
}

/// Why a model file could not be loaded. Display names the file.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}", path = .path.display())]
pub struct MeshError {
    pub path: PathBuf,
    pub message: String,
}

impl MeshError {
    pub(crate) fn new(path: &Path, message: impl Into<String>) -> Self {
        MeshError {
            path: path.to_owned(),
            message: message.into(),
        }
    }
}

thread_local! {
    static IN_LOADER: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// `catch_unwind` whose panics print nothing: a third-party parser's panic
/// on a malformed file becomes this module's error message, and its panic
/// text ("thread panicked at ...") never reaches the user. Other threads'
/// panics are reported as before.
fn quiet_catch_unwind<T>(f: impl FnOnce() -> T) -> std::thread::Result<T> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !IN_LOADER.with(|c| c.get()) {
                previous(info);
            }
        }));
    });
    let was = IN_LOADER.with(|c| c.replace(true));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    IN_LOADER.with(|c| c.set(was));
    result
}

/// An asset error as a loader's message (the file is named by `MeshError`).
pub(crate) fn cannot_read(e: &AssetError) -> String {
    match e {
        AssetError::Io { message, .. } => format!("cannot read model file: {message}"),
        AssetError::NotAFile { .. } => "is not a regular file".into(),
        AssetError::Missing { .. } => {
            "is not among the job's files (the client did not send it)".into()
        }
        AssetError::TooLarge { size, limit, .. } => {
            format!("{size} bytes is over the limit of {limit} bytes a file")
        }
    }
}

/// Largest unpacked `.obj.gz`: OBJ text is read whole (about 70 bytes a
/// triangle, so some 15 M triangles), and a small gzip bomb must not
/// exhaust memory.
const MAX_GUNZIPPED: u64 = 1 << 30;

/// The whole of a gzip stream (several members, as `gzip` concatenates
/// them, read as one).
fn gunzip(bytes: &[u8]) -> Result<Vec<u8>, String> {
    use std::io::Read as _;
    let mut out = Vec::new();
    flate2::read::MultiGzDecoder::new(bytes)
        .take(MAX_GUNZIPPED + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("invalid gzip data: {e}"))?;
    if out.len() as u64 > MAX_GUNZIPPED {
        return Err(format!(
            "unpacks to more than {MAX_GUNZIPPED} bytes, the limit for a gzipped OBJ"
        ));
    }
    Ok(out)
}

/// Material of files (or parts) that define none: plain light grey.
pub fn default_material() -> MaterialDesc {
    MaterialDesc {
        ambient: Vec3([0.8; 3]),
        diffuse: Vec3([0.8; 3]),
        specular: Vec3([0.0; 3]),
        shininess: Num(1.0),
        reflectivity: Num(0.0),
        transparency: Num(0.0),
        ior: Num(1.0),
        gloss: Num(0.0),
        translucency: Num(0.0),
    }
}

impl Mesh {
    /// Loads a model file from this machine's disk (its MTL or buffers from
    /// beside it): [`Mesh::load_from`] on the file's folder.
    pub fn load(path: &Path, need_materials: bool) -> Result<Mesh, MeshError> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        Mesh::load_from(&LocalFolder::of_scene(path), &name, need_materials)
    }

    /// Loads the model `name` of `source` by its extension: .obj, .obj.gz,
    /// .gltf, .glb, .ply, .ply.gz. Files it refers to (an OBJ's MTL, a glTF's
    /// buffers) are read through `source` too, named relative to it.
    /// `need_materials`: whether the file's materials will be used (when
    /// false, a missing MTL library is not an error).
    pub fn load_from(
        source: &dyn AssetSource,
        name: &str,
        need_materials: bool,
    ) -> Result<Mesh, MeshError> {
        let path = Path::new(name);
        let lower = name.to_lowercase();
        // "not found" and "not a file" come before any format-specific message.
        let bytes = source
            .read(name)
            .map_err(|e| MeshError::new(path, cannot_read(&e)))?;
        // Third-party parsers on untrusted input: a panic in one must be an
        // error for this file, not the end of the process.
        let result = quiet_catch_unwind(|| {
            if lower.ends_with(".obj") {
                obj::load(source, name, &bytes, need_materials)
            } else if lower.ends_with(".obj.gz") {
                // As `.ply.gz`: the whole file gunzipped; its MTL library
                // is looked for beside it, as for a plain OBJ.
                let plain = gunzip(&bytes).map_err(|m| MeshError::new(path, m))?;
                obj::load(source, name, &plain, need_materials)
            } else if lower.ends_with(".gltf") || lower.ends_with(".glb") {
                gltf_file::load(source, name, &bytes)
            } else if lower.ends_with(".ply") || lower.ends_with(".ply.gz") {
                ply::load(name, &bytes)
            } else {
                Err(MeshError::new(
                    path,
                    "unknown model format: expected .obj, .obj.gz, .gltf, .glb, .ply or .ply.gz",
                ))
            }
        })
        .unwrap_or_else(|_| {
            Err(MeshError::new(
                path,
                "the model loader failed on this file (malformed data)",
            ))
        });
        let mut mesh = result?;
        mesh.validate().map_err(|m| MeshError::new(path, m))?;
        Ok(mesh)
    }

    /// Checks indices and values; zero or non-finite normals become "unknown".
    fn validate(&mut self) -> Result<(), String> {
        if self.triangles.is_empty() && self.instanced.is_empty() {
            return Err("contains no triangles".into());
        }
        if self.materials.is_empty() {
            self.materials.push(("default".into(), default_material()));
        }
        let nm = self.materials.len();
        self.validate_geometry(nm)?;
        for (i, part) in self.instanced.iter_mut().enumerate() {
            part.mesh
                .validate_geometry(nm)
                .map_err(|e| format!("instanced part {i}: {e}"))?;
        }
        for (name, m) in &self.materials {
            check_material(m).map_err(|e| format!("material {name:?}: {e}"))?;
        }
        Ok(())
    }

    /// Checks indices and values of the geometry against `nm` materials.
    fn validate_geometry(&mut self, nm: usize) -> Result<(), String> {
        if self.triangle_materials.len() != self.triangles.len() {
            return Err("internal: one material per triangle expected".into());
        }
        let nv = self.positions.len();
        if let Some((i, p)) = self
            .positions
            .iter()
            .enumerate()
            .find(|(_, p)| !p.iter().all(|c| c.is_finite()))
        {
            return Err(format!("vertex {i} is not finite: {p:?}"));
        }
        if let Some((i, t)) = self
            .triangles
            .iter()
            .enumerate()
            .find(|(_, t)| t.iter().any(|&v| v as usize >= nv))
        {
            return Err(format!(
                "triangle {i} refers to vertex {} but there are only {nv} vertices",
                t.iter().max().unwrap_or(&0)
            ));
        }
        for (k, uv) in self.uvs.iter().enumerate() {
            if !uv.is_empty() && uv.len() != nv {
                return Err(format!(
                    "{} TEXCOORD_{k} values for {nv} vertices",
                    uv.len()
                ));
            }
        }
        if !self.tangents.is_empty() && self.tangents.len() != nv {
            return Err(format!(
                "{} TANGENT values for {nv} vertices",
                self.tangents.len()
            ));
        }
        if !self.colors.is_empty() && self.colors.len() != nv {
            return Err(format!(
                "{} COLOR_0 values for {nv} vertices",
                self.colors.len()
            ));
        }
        if let Some(&m) = self.triangle_materials.iter().find(|&&m| m as usize >= nm) {
            return Err(format!("material index {m} out of range (there are {nm})"));
        }
        if !self.normals.is_empty() {
            if self.normals.len() != nv {
                return Err(format!("{} normals for {nv} vertices", self.normals.len()));
            }
            for n in &mut self.normals {
                let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                *n = if len > 0.0 && len.is_finite() {
                    n.map(|c| c / len)
                } else {
                    [0.0; 3]
                };
            }
        }
        Ok(())
    }
}

fn check_material(m: &MaterialDesc) -> Result<(), String> {
    for (f, c) in [
        ("ambient", &m.ambient),
        ("diffuse", &m.diffuse),
        ("specular", &m.specular),
    ] {
        check_colour(c).map_err(|e| format!("{f} {e}"))?;
    }
    for (f, v) in [
        ("shininess", m.shininess),
        ("reflectivity", m.reflectivity),
        ("transparency", m.transparency),
    ] {
        check_weight(v.0).map_err(|e| format!("{f} {e}"))?;
    }
    if !(m.ior.0.is_finite() && m.ior.0 > 0.0) {
        return Err(format!("ior must be a finite number > 0, got {}", m.ior.0));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, data: &[u8]) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, data).unwrap();
        p
    }

    fn tmpdir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("tessera-mesh-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn obj_with_mtl_maps_materials_and_normals() {
        let d = tmpdir("obj");
        write(&d, "m.mtl", b"newmtl shiny\nKa 0.1 0.2 0.3\nKd 0.5 0.6 0.7\nKs 0.9 0.9 0.9\nNs 64\nd 0.25\nNi 1.5\nillum 3\n");
        let p = write(
            &d,
            "q.obj",
            b"mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 2\nusemtl shiny\nf 1//1 2//1 3//1 4//1\n",
        );
        let m = Mesh::load(&p, true).unwrap();
        assert_eq!(m.triangles.len(), 2);
        assert_eq!(m.positions.len(), 4);
        assert_eq!(m.normals, vec![[0.0, 0.0, 1.0]; 4]);
        let (name, mat) = &m.materials[m.triangle_materials[0] as usize];
        assert_eq!(name, "shiny");
        assert_eq!(
            mat.ambient,
            Vec3([0.1f32 as f64, 0.2f32 as f64, 0.3f32 as f64])
        );
        assert_eq!(mat.diffuse.0[2], 0.7f32 as f64);
        assert_eq!(mat.shininess, Num(64.0));
        assert_eq!(mat.transparency, Num(0.75));
        assert_eq!(mat.ior, Num(1.5));
        assert_eq!(
            mat.reflectivity,
            Num(0.9f32 as f64),
            "illum 3: mirror weight from Ks"
        );
    }

    #[test]
    fn broken_files_give_errors_naming_file_and_problem() {
        let d = tmpdir("bad");
        let e = Mesh::load(&d.join("absent.obj"), true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("absent.obj: cannot read model file") && e.contains("No such file"),
            "{e}"
        );
        let p = write(&d, "bad.obj", b"v 0 0 0\nv 1 0 zero\nf 1 2 3\n");
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains(
                "bad.obj: invalid OBJ: line 2: position parse error: \"zero\" is not a number"
            ),
            "{e}"
        );
        let p = write(&d, "oob.obj", b"v 0 0 0\nv 1 0 0\nf 1 2 7\n");
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains("oob.obj: invalid OBJ: face vertex index out of bounds"),
            "{e}"
        );
        let p = write(
            &d,
            "nomtl.obj",
            b"mtllib gone.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        );
        let m = Mesh::load(&p, true).unwrap();
        assert_eq!(m.materials, vec![("default".into(), default_material())]);
        assert_eq!(m.warnings.len(), 1);
        assert!(
            m.warnings[0].starts_with("cannot load its material library (mtllib gone.mtl)")
                && m.warnings[0].contains("its faces use the default grey material"),
            "{:?}",
            m.warnings
        );
        assert!(
            Mesh::load(&p, false).is_ok(),
            "with a material override the MTL is not needed"
        );
        let p = write(&d, "empty.obj", b"# nothing\nv 0 0 0\n");
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(e.contains("empty.obj: contains no triangles"), "{e}");
        let p = write(
            &d,
            "bad.gltf",
            b"{ \"asset\": { \"version\": \"2.0\" }, \"meshes\": [ { \"primitives\": 3 } ] }",
        );
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(e.contains("bad.gltf: invalid glTF:"), "{e}");
        let p = write(&d, "trunc.glb", b"glTF\x02\x00\x00\x00\xff\x00\x00\x00");
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(e.contains("trunc.glb: invalid glTF:"), "{e}");
        let p = write(&d, "x.stl", b"solid x\n");
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(e.contains("x.stl: unknown model format"), "{e}");
        let e = Mesh::load(&d, true).unwrap_err().to_string();
        assert!(e.contains("is not a regular file"), "{e}");
    }

    /// A glTF of one triangle whose position accessor is `accessor` (JSON),
    /// over a 36-byte buffer of three vertices.
    fn gltf_with(accessor: &str, view: &str) -> String {
        use base64::Engine as _;
        let mut b = Vec::new();
        for v in [[0f32, 0., 0.], [1., 0., 0.], [0., 1., 0.]] {
            for c in v {
                b.extend_from_slice(&c.to_le_bytes());
            }
        }
        let uri = base64::engine::general_purpose::STANDARD.encode(&b);
        format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":36,"uri":"data:application/octet-stream;base64,{uri}"}}],
            "bufferViews":[{view}],"accessors":[{accessor}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}]}}"#
        )
    }

    #[test]
    fn hostile_model_files_are_errors_at_once_not_aborts_or_hangs() {
        let d = tmpdir("hostile");
        let start = std::time::Instant::now();
        let ok_view = r#"{"buffer":0,"byteLength":36}"#;
        let good = gltf_with(
            r#"{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}"#,
            ok_view,
        );
        let p = write(&d, "good.gltf", good.as_bytes());
        assert_eq!(Mesh::load(&p, true).unwrap().triangles.len(), 1);
        // A sparse accessor of 2^32-1 elements and no data: 51 GB if believed.
        let sparse = gltf_with(
            r#"{"componentType":5126,"count":4294967295,"type":"VEC3","min":[0,0,0],"max":[1,1,0],"sparse":{"count":4294967295,
               "indices":{"bufferView":0,"componentType":5125},"values":{"bufferView":0}}}"#,
            ok_view,
        );
        let p = write(&d, "sparse.gltf", sparse.as_bytes());
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains(
                "sparse.gltf: mesh 0 primitive 0: accessor 0: 4294967295 elements without data"
            ),
            "{e}"
        );
        // A stride smaller than the element: the crate would panic.
        let stride = gltf_with(
            r#"{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}"#,
            r#"{"buffer":0,"byteLength":36,"byteStride":4}"#,
        );
        let p = write(&d, "stride.gltf", stride.as_bytes());
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains("accessor 0: byteStride 4 is smaller than its 12-byte elements"),
            "{e}"
        );
        // More elements than the view holds.
        let long = gltf_with(
            r#"{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}"#,
            ok_view,
        );
        let p = write(&d, "long.gltf", long.as_bytes());
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains("accessor 0: 4 elements need 48 bytes, its buffer view has 36"),
            "{e}"
        );
        // A PLY element with no properties and a count near 2^63 is nothing to read.
        let p = write(
            &d,
            "empty-element.ply",
            b"ply\nformat ascii 1.0\nelement junk 9223372036854775807\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
        );
        assert_eq!(Mesh::load(&p, true).unwrap().triangles.len(), 1);
        // ASCII rows with more values than the header declares (colours a
        // writer added): the extra values end with their line.
        let p = write(
            &d,
            "extra.ply",
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 255 0 0\n1 0 0 0 255 0\n0 1 0 0 0 255\n3 0 1 2 7\n",
        );
        let m = Mesh::load(&p, true).unwrap();
        assert_eq!(
            m.positions,
            vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
        );
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
        // Faces before vertices: read, then checked against the vertices.
        let p = write(
            &d,
            "faces-first.ply",
            b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n3 0 1 2\n0 0 0\n1 0 0\n0 1 0\n",
        );
        assert_eq!(Mesh::load(&p, true).unwrap().triangles, vec![[0, 1, 2]]);
        let p = write(
            &d,
            "faces-first-bad.ply",
            b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n3 0 1 9\n0 0 0\n1 0 0\n0 1 0\n",
        );
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains(
                "faces-first-bad.ply: triangle 0 refers to vertex 9 but there are only 3 vertices"
            ),
            "{e}"
        );
        // `Kd 1` (one value, grey) is legal MTL; tobj alone panics on it.
        write(&d, "grey.mtl", b"newmtl g\nKd 0.5\nKs 1\n");
        let p = write(
            &d,
            "grey.obj",
            b"mtllib grey.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl g\nf 1 2 3\n",
        );
        let m = Mesh::load(&p, true).unwrap();
        assert_eq!(m.materials[0].1.diffuse, Vec3([0.5; 3]));
        assert_eq!(m.materials[0].1.specular, Vec3([1.0; 3]));
        // `Ni 0` is no index of refraction: 1, with a warning.
        write(&d, "ni.mtl", b"newmtl n\nKd 1 1 1\nNi 0\n");
        let p = write(
            &d,
            "ni.obj",
            b"mtllib ni.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl n\nf 1 2 3\n",
        );
        let m = Mesh::load(&p, true).unwrap();
        assert_eq!(m.materials[0].1.ior, Num(1.0));
        assert_eq!(
            m.warnings,
            vec!["material \"n\": Ni 0 is no index of refraction; 1 is used".to_string()]
        );
        // Colours past what f32 holds.
        write(&d, "hot.mtl", b"newmtl h\nKd 1e39 1 1\n");
        let p = write(
            &d,
            "hot.obj",
            b"mtllib hot.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl h\nf 1 2 3\n",
        );
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains("material \"h\": ambient must be three finite numbers >= 0 and at most 1e6"),
            "{e}"
        );
        assert!(
            start.elapsed() < std::time::Duration::from_secs(5),
            "{:?}",
            start.elapsed()
        );
    }
}
