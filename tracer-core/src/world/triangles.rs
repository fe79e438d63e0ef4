//! Mesh objects placed into a world under construction: their triangles
//! moved by the object's transform, made camera-relative in `f64` and only
//! then rounded, with what shading needs beside them.

use std::sync::Arc;

use crate::material::{NO_PBR, Pbr};
use crate::math::{Real, Vector3};
use crate::scene::MeshDesc;
use crate::triangle::{NO_ATTRS, Triangle, TriangleShading};

use super::{Features, Material};

/// What textured triangles need beyond their shading: per vertex, the
/// texture coordinates (TEXCOORD_0 and _1, zero where a file has none)
/// and colour (COLOR_0, white where none); per textured triangle (its
/// `TriangleShading::attrs`), its three vertices' indices in them.
#[derive(Clone, Debug, Default)]
pub struct VertexAttrs {
    pub tri: Vec<[u32; 3]>,
    pub uv: [Vec<[f32; 2]>; 2],
    pub color: Vec<[f32; 4]>,
    /// Whether any material is alphaMode MASK: then every query passes
    /// through cut-outs.
    pub cutouts: bool,
}

/// Triangles of a world under construction.
#[derive(Default)]
pub(crate) struct TriangleSet<R: Real> {
    pub triangles: Vec<Triangle<R>>,
    pub shading: Vec<TriangleShading<R>>,
    /// Triangles dropped because they have no area in the render precision.
    pub degenerate: usize,
    /// The textures and glTF parameters of the file materials added
    /// (`Material::pbr` indexes this) ...
    pub pbr: Vec<Arc<Pbr>>,
    /// ... and the vertex attributes of the triangles that use them.
    pub attrs: VertexAttrs,
}

impl<R: Real> TriangleSet<R> {
    /// Adds the triangles of a mesh object, placed by its transform and made
    /// relative to `origin` (the camera). `material` is the object's material
    /// index, or `FILE_MATERIALS`: then the file's materials are appended to
    /// `materials` (and `features` updated) and used per triangle.
    pub fn add_mesh(
        &mut self,
        desc: &MeshDesc,
        material: u32,
        materials: &mut Vec<Material<R>>,
        features: &mut Features,
        max_depth: u32,
        origin: [f64; 3],
    ) {
        let Some(mesh) = desc.model.0.as_deref() else {
            return;
        };
        let xf = desc.transform();
        let origin = glam::DVec3::from_array(origin);
        let mats: Vec<u32> = if material == crate::scene::FILE_MATERIALS {
            let base = materials.len() as u32;
            for (i, (_, m)) in mesh.materials.iter().enumerate() {
                let mut m = Material::<R>::from_desc(m);
                if let Some(Some(p)) = mesh.pbr.get(i) {
                    m.emission = R::V3::from_array(p.emissive);
                    m.pbr = self.pbr.len() as u32;
                    self.attrs.cutouts |= p.alpha_mode == crate::material::AlphaMode::Mask;
                    self.pbr.push(p.clone());
                }
                features.note(&m, max_depth);
                materials.push(m);
            }
            (0..mesh.materials.len() as u32).map(|i| base + i).collect()
        } else {
            vec![material; mesh.materials.len()]
        };
        // Positions in f64, made camera-relative, and only then rounded.
        let verts: Vec<R::V3> = mesh
            .positions
            .iter()
            .map(|&p| R::V3::from_array((xf.point(p) - origin).to_array()))
            .collect();
        let nm = xf.normal_matrix();
        let normals: Vec<R::V3> = mesh
            .normals
            .iter()
            .map(|&n| {
                let n = nm * glam::DVec3::from_array(n.map(f64::from));
                let l = n.length();
                R::V3::from_array(if l > 0.0 && l.is_finite() {
                    (n / l).to_array()
                } else {
                    [0.0; 3]
                })
            })
            .collect();
        // Triangles of materials whose look varies over them keep their
        // vertices' texture coordinates and colours.
        let varies: Vec<bool> = mats
            .iter()
            .map(|&m| {
                let p = materials[m as usize].pbr;
                p != NO_PBR && self.pbr[p as usize].varies()
            })
            .collect();
        let first_vertex = self.attrs.uv[0].len() as u32;
        if varies.iter().any(|&v| v) {
            let nv = mesh.positions.len();
            for k in 0..2 {
                let uv = &mesh.uvs[k];
                if uv.len() == nv {
                    self.attrs.uv[k].extend_from_slice(uv);
                } else {
                    self.attrs.uv[k].extend(std::iter::repeat_n([0.0; 2], nv));
                }
            }
            if mesh.colors.len() == nv {
                self.attrs.color.extend_from_slice(&mesh.colors);
            } else {
                self.attrs.color.extend(std::iter::repeat_n([1.0; 4], nv));
            }
        }
        let flip = xf.mirrors();
        self.triangles.reserve(mesh.triangles.len());
        self.shading.reserve(mesh.triangles.len());
        for (t, &m) in mesh.triangles.iter().zip(&mesh.triangle_materials) {
            // A mirroring transform reverses the winding: restore it, so the
            // geometric normal stays outward.
            let t = if flip { [t[0], t[2], t[1]] } else { *t };
            let tri: Triangle<R> = Triangle::new(t.map(|i| verts[i as usize]));
            let cross = tri.cross();
            let len = cross.length();
            if !(len > R::ZERO && len.is_finite()) {
                self.degenerate += 1;
                continue;
            }
            let vertex_normals = if normals.is_empty() {
                None
            } else {
                let ns = t.map(|i| normals[i as usize]);
                // Any unknown (zero) vertex normal: shade this triangle flat.
                ns.iter()
                    .all(|n| n.length_squared() > R::ZERO)
                    .then_some(ns)
            };
            let attrs = if varies[m as usize] {
                self.attrs.tri.push(t.map(|i| first_vertex + i));
                self.attrs.tri.len() as u32 - 1
            } else {
                NO_ATTRS
            };
            self.triangles.push(tri);
            self.shading.push(TriangleShading {
                normal: cross * (R::ONE / len),
                vertex_normals,
                material: mats[m as usize],
                attrs,
            });
        }
    }
}
