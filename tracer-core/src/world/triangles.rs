//! Mesh objects placed into a world under construction: their triangles
//! moved by the object's transform, made camera-relative in `f64` and only
//! then rounded, with what shading needs beside them.

use std::sync::Arc;

use crate::material::{NO_PBR, Pbr};
use crate::math::{Real, Vector3};
use crate::scene::MeshDesc;
use crate::triangle::{NO_ATTRS, Triangle, TriangleShading, gather, gather_all};

use super::instances::Instances;

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
    /// Unit tangent and bitangent sign in world space (`Mesh::tangents`),
    /// w 0 where unknown.
    pub tangent: Vec<[f32; 4]>,
    /// Whether any material cuts surface away (alphaMode MASK, or
    /// single-sided: `Pbr::culls_back_faces`): then every query passes
    /// through cut-outs.
    pub cutouts: bool,
}

/// Triangles of a world under construction.
#[derive(Default)]
pub(crate) struct TriangleSet<R: Real> {
    /// Vertex positions ...
    pub positions: Vec<R::V3>,
    /// ... their unit normals, at the same indices (a zero one unknown),
    /// or none while no mesh added has normals ...
    pub vertex_normals: Vec<R::V3>,
    /// ... and each triangle's corners in them, and its shading.
    pub corners: Vec<[u32; 3]>,
    pub shading: Vec<TriangleShading>,
    /// Triangles dropped because they have no area in the render precision.
    pub degenerate: usize,
    /// The textures and glTF parameters of the file materials added
    /// (`Material::pbr` indexes this) ...
    pub pbr: Vec<Arc<Pbr>>,
    /// ... and the vertex attributes of the triangles that use them.
    pub attrs: VertexAttrs,
    /// Whether a model's instanced parts are stored once and placed
    /// (`instances`), or copied into `triangles` (a moving mesh's world).
    pub instancing: bool,
    pub instances: Instances<R>,
}

impl<R: Real> TriangleSet<R> {
    /// Every triangle, gathered from its corners.
    pub fn triangles(&self) -> Vec<Triangle<R>> {
        gather_all(&self.positions, &self.corners)
    }

    /// Adds the triangles of a mesh object (`desc`, whose loaded model is
    /// `mesh`), placed by its transform and made relative to `origin` (the
    /// camera). `material` is the object's material index, or
    /// `FILE_MATERIALS`: then the file's materials are appended to
    /// `materials` (and `features` updated) and used per triangle.
    #[allow(clippy::too_many_arguments)]
    pub fn add_mesh(
        &mut self,
        desc: &MeshDesc,
        mesh: Option<&crate::mesh::Mesh>,
        material: u32,
        materials: &mut Vec<Material<R>>,
        features: &mut Features,
        max_depth: u32,
        origin: [f64; 3],
    ) {
        let Some(mesh) = mesh else {
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
                    self.attrs.cutouts |=
                        p.alpha_mode == crate::material::AlphaMode::Mask || p.culls_back_faces();
                    self.pbr.push(p.clone());
                    features.note_pbr(p, max_depth);
                }
                features.note(&m, max_depth);
                materials.push(m);
            }
            (0..mesh.materials.len() as u32).map(|i| base + i).collect()
        } else {
            vec![material; mesh.materials.len()]
        };
        // Triangles of materials whose look varies over them keep their
        // vertices' texture coordinates and colours.
        let varies: Vec<bool> = mats
            .iter()
            .map(|&m| {
                let p = materials[m as usize].pbr;
                p != NO_PBR && self.pbr[p as usize].varies()
            })
            .collect();
        let to_world = |a: crate::scene::Affine| {
            glam::DMat4::from_mat3_translation(a.linear, a.translation - origin)
        };
        // The object's copies: its `instances` after its own placement, or
        // itself once. A model placed once keeps its triangles in world
        // space, rounded from f64 (as before instancing existed).
        let copies: Vec<glam::DMat4> = if desc.instances.is_empty() {
            // Positions in f64, made camera-relative, and only then rounded.
            self.add_geometry(
                mesh,
                |p| xf.point(p) - origin,
                xf.normal_matrix(),
                xf.mirrors(),
                &mats,
                &varies,
            );
            vec![to_world(xf)]
        } else {
            let copies: Vec<_> = desc
                .instances
                .iter()
                .map(|i| {
                    let outer = i.transform();
                    to_world(crate::scene::Affine {
                        linear: outer.linear * xf.linear,
                        translation: outer.linear * xf.translation + outer.translation,
                    })
                })
                .collect();
            self.add_placed(mesh, &copies, &mats, &varies);
            copies
        };
        for part in &mesh.instanced {
            let list: Vec<glam::DMat4> = copies
                .iter()
                .flat_map(|c| {
                    part.transforms
                        .iter()
                        .map(move |t| *c * glam::DMat4::from_cols_array(t))
                })
                .collect();
            self.add_placed(&part.mesh, &list, &mats, &varies);
        }
    }

    /// Adds `mesh` placed by each of `list` (object space to the
    /// camera-relative world): stored once and instanced, or copied when
    /// this set does not instance (or the ids run out). A textured mesh's
    /// vertex attributes join the set's once, in the mesh's space
    /// (`World::tangent_at` moves its tangents with each instance).
    fn add_placed(
        &mut self,
        mesh: &crate::mesh::Mesh,
        list: &[glam::DMat4],
        mats: &[u32],
        varies: &[bool],
    ) {
        let mut id = None;
        if self.instancing {
            // The mesh once, in its own space, with its own tree.
            let mut own = TriangleSet::default();
            own.add_geometry(
                mesh,
                |p| glam::DVec3::from_array(p.map(f64::from)),
                glam::DMat3::IDENTITY,
                false,
                mats,
                varies,
            );
            self.degenerate += own.degenerate * list.len();
            let (tri0, vertex0) = (self.attrs.tri.len() as u32, self.attrs.uv[0].len() as u32);
            for s in &mut own.shading {
                if s.attrs != NO_ATTRS {
                    s.attrs += tri0;
                }
            }
            let triangles = own.triangles();
            let a = own.attrs;
            self.attrs
                .tri
                .extend(a.tri.iter().map(|t| t.map(|v| v + vertex0)));
            for (set, uv) in self.attrs.uv.iter_mut().zip(a.uv) {
                set.extend(uv);
            }
            self.attrs.color.extend(a.color);
            self.attrs.tangent.extend(a.tangent);
            id = Some(self.instances.add_mesh(
                triangles,
                own.corners,
                own.shading,
                own.vertex_normals,
            ));
        }
        for &m in list {
            if let Some(id) = id
                && self.instances.place(id, m)
            {
                continue;
            }
            let linear = glam::DMat3::from_mat4(m);
            self.add_geometry(
                mesh,
                |p| m.transform_point3(glam::DVec3::from_array(p.map(f64::from))),
                linear.inverse().transpose(),
                linear.determinant() < 0.0,
                mats,
                varies,
            );
        }
    }

    /// Adds `mesh`'s triangles, each vertex placed by `place` (in `f64`,
    /// then rounded), normals by `normal_matrix`; `flip`: the map mirrors.
    fn add_geometry(
        &mut self,
        mesh: &crate::mesh::Mesh,
        place: impl Fn([f32; 3]) -> glam::DVec3,
        nm: glam::DMat3,
        flip: bool,
        mats: &[u32],
        varies: &[bool],
    ) {
        let first = self.positions.len() as u32;
        let nv = mesh.positions.len();
        self.positions.extend(
            mesh.positions
                .iter()
                .map(|&p| R::V3::from_array(place(p).to_array())),
        );
        // The mesh's vertex normals join the set's, placed, at its
        // vertices' indices; a zero one is unknown. A set without any
        // keeps none.
        if !mesh.normals.is_empty() || !self.vertex_normals.is_empty() {
            // The vertices before this mesh's, unknown if they had none.
            self.vertex_normals
                .resize(first as usize, R::V3::splat(R::ZERO));
            self.vertex_normals
                .extend(mesh.normals.iter().take(nv).map(|&n| {
                    let n = nm * glam::DVec3::from_array(n.map(f64::from));
                    let l = n.length();
                    R::V3::from_array(if l > 0.0 && l.is_finite() {
                        (n / l).to_array()
                    } else {
                        [0.0; 3]
                    })
                }));
            self.vertex_normals
                .resize(first as usize + nv, R::V3::splat(R::ZERO));
        }
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
            if mesh.tangents.len() == nv {
                // Tangents move with the surface (the placement's linear
                // part, the inverse transpose of `nm`); a mirror flips the
                // bitangent.
                let linear = nm.inverse().transpose();
                let sign = if flip { -1.0 } else { 1.0 };
                self.attrs.tangent.extend(mesh.tangents.iter().map(|t| {
                    let v = (linear * glam::DVec3::new(t[0] as f64, t[1] as f64, t[2] as f64))
                        .normalize_or_zero()
                        .as_vec3();
                    [v.x, v.y, v.z, t[3] * sign]
                }));
            } else {
                self.attrs.tangent.extend(std::iter::repeat_n([0.0; 4], nv));
            }
        }
        self.corners.reserve(mesh.triangles.len());
        self.shading.reserve(mesh.triangles.len());
        for (t, &m) in mesh.triangles.iter().zip(&mesh.triangle_materials) {
            // A mirroring transform reverses the winding: restore it, so the
            // geometric normal stays outward.
            let t = if flip { [t[0], t[2], t[1]] } else { *t };
            let corners = t.map(|i| first + i);
            let cross = gather::<R>(&self.positions, corners).cross();
            let len = cross.length();
            if !(len > R::ZERO && len.is_finite()) {
                self.degenerate += 1;
                continue;
            }
            let attrs = if varies[m as usize] {
                self.attrs.tri.push(t.map(|i| first_vertex + i));
                self.attrs.tri.len() as u32 - 1
            } else {
                NO_ATTRS
            };
            self.corners.push(corners);
            self.shading.push(TriangleShading {
                material: mats[m as usize],
                attrs,
            });
        }
    }
}
