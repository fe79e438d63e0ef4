//! Mesh objects placed into a world under construction: their triangles
//! moved by the object's transform, made camera-relative in `f64` and only
//! then rounded, with what shading needs beside them.

use crate::math::{Real, Vector3};
use crate::scene::MeshDesc;
use crate::triangle::{Triangle, TriangleShading};

use super::{Features, Material};

/// Triangles of a world under construction.
#[derive(Default)]
pub(crate) struct TriangleSet<R: Real> {
    pub triangles: Vec<Triangle<R>>,
    pub shading: Vec<TriangleShading<R>>,
    /// Triangles dropped because they have no area in the render precision.
    pub degenerate: usize,
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
            for (_, m) in &mesh.materials {
                let m = Material::<R>::from_desc(m);
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
            self.triangles.push(tri);
            self.shading.push(TriangleShading {
                normal: cross * (R::ONE / len),
                vertex_normals,
                material: mats[m as usize],
            });
        }
    }
}
