//! Tangents for normal maps. glTF asks for MikkTSpace tangents where a
//! primitive with a normal texture has no TANGENT attribute: the
//! `mikktspace` crate (gltf-rs's port of Mikkelsen's reference code)
//! makes them per triangle corner, and a vertex whose corners got
//! different tangents is split, so that tangents stay per vertex.

use std::collections::HashMap;
use std::sync::Arc;

use super::Mesh;
use crate::material::Pbr;

/// Fills in the tangents of `mesh`'s triangles whose material (`pbr`, by
/// `triangle_materials`) has a normal texture and whose vertices have no
/// tangent from the file (w 0), from their positions, normals and the
/// normal texture's texture coordinates. Triangles without normals or
/// those coordinates keep w 0 (their normal map is not applied).
pub(crate) fn complete(mesh: &mut Mesh, pbr: &[Option<Arc<Pbr>>]) {
    let uv_set = |m: u32| -> Option<usize> {
        let p = pbr.get(m as usize)?.as_ref()?;
        p.normal_texture.as_ref().map(|t| t.uv_set as usize)
    };
    let nv = mesh.positions.len();
    if !mesh.triangle_materials.iter().any(|&m| uv_set(m).is_some()) {
        return;
    }
    if mesh.tangents.len() != nv {
        mesh.tangents = vec![[0.0; 4]; nv];
    }
    let faces: Vec<(usize, usize)> = mesh
        .triangles
        .iter()
        .zip(&mesh.triangle_materials)
        .enumerate()
        .filter_map(|(f, (t, &m))| {
            let set = uv_set(m)?;
            let known = t.iter().all(|&i| mesh.tangents[i as usize][3] != 0.0);
            let usable = mesh.normals.len() == nv && mesh.uvs[set].len() == nv;
            (usable && !known).then_some((f, set))
        })
        .collect();
    if faces.is_empty() {
        return;
    }
    let mut g = Faces {
        mesh,
        faces: &faces,
        out: vec![[0.0; 4]; 3 * faces.len()],
    };
    if !mikktspace::generate_tangents(&mut g) {
        return;
    }
    let out = std::mem::take(&mut g.out);
    // Each corner's tangent on its vertex; a vertex already given another
    // (by the file, or by another corner) is copied for this corner.
    let mut placed: HashMap<(u32, [u32; 4]), u32> = HashMap::new();
    let mut set = vec![false; nv];
    for (k, &(f, _)) in faces.iter().enumerate() {
        for c in 0..3 {
            let t = out[3 * k + c];
            let v = mesh.triangles[f][c];
            let key = (v, t.map(f32::to_bits));
            let to = match placed.get(&key) {
                Some(&to) => to,
                None if !set[v as usize] && mesh.tangents[v as usize][3] == 0.0 => {
                    set[v as usize] = true;
                    mesh.tangents[v as usize] = t;
                    v
                }
                None => copy_vertex(mesh, v, t),
            };
            placed.insert(key, to);
            mesh.triangles[f][c] = to;
        }
    }
}

/// Appends a copy of vertex `v` with tangent `t`; its index.
fn copy_vertex(mesh: &mut Mesh, v: u32, t: [f32; 4]) -> u32 {
    let i = v as usize;
    mesh.positions.push(mesh.positions[i]);
    if !mesh.normals.is_empty() {
        mesh.normals.push(mesh.normals[i]);
    }
    for uv in &mut mesh.uvs {
        if !uv.is_empty() {
            uv.push(uv[i]);
        }
    }
    if !mesh.colors.is_empty() {
        mesh.colors.push(mesh.colors[i]);
    }
    mesh.tangents.push(t);
    mesh.positions.len() as u32 - 1
}

/// The triangles to make tangents for, as mikktspace sees them.
struct Faces<'a> {
    mesh: &'a Mesh,
    /// (triangle, texture coordinate set).
    faces: &'a [(usize, usize)],
    out: Vec<[f32; 4]>,
}

impl Faces<'_> {
    fn vertex(&self, face: usize, vert: usize) -> usize {
        self.mesh.triangles[self.faces[face].0][vert] as usize
    }
}

impl mikktspace::Geometry for Faces<'_> {
    fn num_faces(&self) -> usize {
        self.faces.len()
    }
    fn num_vertices_of_face(&self, _face: usize) -> usize {
        3
    }
    fn position(&self, face: usize, vert: usize) -> [f32; 3] {
        self.mesh.positions[self.vertex(face, vert)]
    }
    fn normal(&self, face: usize, vert: usize) -> [f32; 3] {
        self.mesh.normals[self.vertex(face, vert)]
    }
    // glTF's v runs down the image; MikkTSpace's bitangent follows
    // increasing v, and glTF's (a normal texture's green) points up it:
    // v is flipped, as Blender does before exporting TANGENT.
    fn tex_coord(&self, face: usize, vert: usize) -> [f32; 2] {
        let [u, v] = self.mesh.uvs[self.faces[face].1][self.vertex(face, vert)];
        [u, 1.0 - v]
    }
    fn set_tangent_encoded(&mut self, tangent: [f32; 4], face: usize, vert: usize) {
        self.out[3 * face + vert] = tangent;
    }
}
