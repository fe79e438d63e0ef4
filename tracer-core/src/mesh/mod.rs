//! Triangle meshes loaded from model files: OBJ (+MTL) through `tobj`,
//! glTF 2.0 (.gltf/.glb) through `gltf`, PLY (ASCII or binary, optionally
//! gzipped) through a small reader here. A loaded [`Mesh`] is in the file's
//! own model space; the scene's transform is applied by `World::build`.

mod gltf_file;
mod obj;
mod ply;

use std::path::{Path, PathBuf};

use crate::scene::{MaterialDesc, Num, Vec3};

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
    }
}

impl Mesh {
    /// Loads a model by its extension: .obj, .gltf, .glb, .ply, .ply.gz.
    /// `need_materials`: whether the file's materials will be used (when
    /// false, a missing MTL library is not an error).
    pub fn load(path: &Path, need_materials: bool) -> Result<Mesh, MeshError> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_lowercase())
            .unwrap_or_default();
        // Give "not found" and "is a directory" before any format-specific message.
        match std::fs::metadata(path) {
            Err(e) => return Err(MeshError::new(path, format!("cannot read model file: {e}"))),
            Ok(m) if !m.is_file() => return Err(MeshError::new(path, "is not a file")),
            Ok(_) => {}
        }
        // Third-party parsers on untrusted input: a panic in one must be an
        // error for this file, not the end of the process.
        let result = std::panic::catch_unwind(|| {
            if name.ends_with(".obj") {
                obj::load(path, need_materials)
            } else if name.ends_with(".gltf") || name.ends_with(".glb") {
                gltf_file::load(path)
            } else if name.ends_with(".ply") || name.ends_with(".ply.gz") {
                ply::load(path)
            } else {
                Err(MeshError::new(
                    path,
                    "unknown model format: expected .obj, .gltf, .glb, .ply or .ply.gz",
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
        if self.triangles.is_empty() {
            return Err("contains no triangles".into());
        }
        if self.materials.is_empty() {
            self.materials.push(("default".into(), default_material()));
        }
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
        let nm = self.materials.len();
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
        for (name, m) in &self.materials {
            check_material(m).map_err(|e| format!("material {name:?}: {e}"))?;
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
        if !c.0.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(format!(
                "{f} must be three finite numbers >= 0, got {:?}",
                c.0
            ));
        }
    }
    for (f, v) in [
        ("shininess", m.shininess),
        ("reflectivity", m.reflectivity),
        ("transparency", m.transparency),
    ] {
        if !(v.0.is_finite() && v.0 >= 0.0) {
            return Err(format!("{f} must be a finite number >= 0, got {}", v.0));
        }
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
            e.contains("bad.obj: invalid OBJ: position parse error"),
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
        let e = Mesh::load(&p, true).unwrap_err().to_string();
        assert!(
            e.contains("nomtl.obj: cannot load its material library") && e.contains("gone.mtl"),
            "{e}"
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
        assert!(e.contains("is not a file"), "{e}");
    }
}
