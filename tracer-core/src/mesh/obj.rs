//! Wavefront OBJ with MTL materials, through `tobj`.

use std::path::Path;

use super::{Mesh, MeshError, default_material};
use crate::scene::{MaterialDesc, Num, Vec3};

pub(super) fn load(path: &Path, need_materials: bool) -> Result<Mesh, MeshError> {
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, materials) = tobj::load_obj(path, &options)
        .map_err(|e| MeshError::new(path, format!("invalid OBJ: {e}")))?;
    let materials = match materials {
        Ok(m) => m,
        Err(_) if !need_materials => Vec::new(),
        Err(e) => {
            // tobj does not say which library failed: name the file's mtllib lines.
            let libs = std::fs::read_to_string(path)
                .unwrap_or_default()
                .lines()
                .filter_map(|l| {
                    l.trim()
                        .strip_prefix("mtllib")
                        .map(|r| r.trim().to_string())
                })
                .collect::<Vec<_>>()
                .join(", ");
            return Err(MeshError::new(
                path,
                format!(
                    "cannot load its material library (mtllib {libs}): {e}; give the object a `material` to ignore it"
                ),
            ));
        }
    };
    let mut mesh = Mesh {
        materials: materials
            .iter()
            .map(|m| (m.name.clone(), map_material(m)))
            .collect(),
        ..Default::default()
    };
    let default_index = mesh.materials.len() as u32;
    let mut need_default = false;
    let any_normals = models.iter().any(|m| !m.mesh.normals.is_empty());
    for model in &models {
        let m = &model.mesh;
        let base = mesh.positions.len() as u32;
        let count = m.positions.len() / 3;
        mesh.positions
            .extend(m.positions.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
        if any_normals {
            if m.normals.len() == m.positions.len() {
                mesh.normals
                    .extend(m.normals.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
            } else {
                mesh.normals.extend(std::iter::repeat_n([0.0; 3], count));
            }
        }
        let material = match m.material_id {
            Some(id) if id < materials.len() => id as u32,
            _ => {
                need_default = true;
                default_index
            }
        };
        for t in m.indices.chunks_exact(3) {
            mesh.triangles.push([base + t[0], base + t[1], base + t[2]]);
            mesh.triangle_materials.push(material);
        }
    }
    if need_default {
        mesh.materials.push(("default".into(), default_material()));
    }
    Ok(mesh)
}

/// MTL -> Blinn-Phong: Ka ambient (Kd when absent), Kd diffuse, Ks specular,
/// Ns shininess, d (or 1 - Tr) opacity, Ni ior; illum 3, 5 and 7 (the
/// "reflection on" models) make Ks's largest component the mirror weight.
fn map_material(m: &tobj::Material) -> MaterialDesc {
    let v = |c: Option<[f32; 3]>, d: [f64; 3]| Vec3(c.map(|c| c.map(f64::from)).unwrap_or(d));
    let diffuse = v(m.diffuse, [0.8; 3]);
    let specular = v(m.specular, [0.0; 3]);
    let opacity = match (
        m.dissolve,
        m.unknown_param
            .get("Tr")
            .and_then(|t| t.trim().parse::<f32>().ok()),
    ) {
        (Some(d), _) => d as f64,
        (None, Some(tr)) => 1.0 - tr as f64,
        (None, None) => 1.0,
    };
    let reflective = matches!(m.illumination_model, Some(3 | 5 | 7));
    MaterialDesc {
        ambient: v(m.ambient, diffuse.0),
        diffuse,
        specular,
        shininess: Num(m.shininess.map_or(1.0, f64::from)),
        reflectivity: Num(if reflective {
            specular.0.iter().cloned().fold(0.0, f64::max)
        } else {
            0.0
        }),
        transparency: Num((1.0 - opacity).clamp(0.0, 1.0)),
        ior: Num(m.optical_density.map_or(1.0, f64::from)),
    }
}
