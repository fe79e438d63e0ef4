//! Instanced geometry, the world's two-level tree: a mesh placed many times
//! is stored once, in its own (object) space, with a tree of its own (the
//! bottom level); each placement is an [`Instance`] (a transform and the
//! mesh's index) that the world's tree holds as one primitive
//! (`PrimId::INSTANCE`, the top level). A ray that reaches an instance is
//! moved into object space (its direction not renormalised, so distances
//! along it are the world's) and walks the mesh's tree there.
//!
//! A hit on triangle k of instance i is `PrimId::INSTANCE_TRIANGLE` with
//! index `first(i) + k`: one id per placed triangle, so that a ray leaving
//! one copy skips that triangle of that copy only.

use crate::bvh::{self, Aabb, Bvh};
use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3};
use crate::triangle::{Triangle, TriangleRay, TriangleShading};

/// A mesh stored once: triangles in object space, in its tree's leaf order.
#[derive(Clone, Debug, Default)]
pub struct InstancedMesh<R: Real> {
    pub triangles: Vec<Triangle<R>>,
    /// Their corners' indices in its vertices (which name their normals) ...
    pub corners: Vec<[u32; 3]>,
    /// ... and their shading.
    pub shading: Vec<TriangleShading>,
    /// Unit vertex normals in object space, or none
    /// ([`crate::triangle::VertexNormals`]).
    pub vertex_normals: Vec<R::V3>,
    pub tree: Bvh,
    /// The bounds of its triangles, in object space, in `f64`.
    pub lo: [f64; 3],
    pub hi: [f64; 3],
}

/// An affine map as its three linear columns and translation, flat
/// (12 numbers: an instance costs about 100 bytes with its two maps).
#[derive(Clone, Copy, Debug)]
pub struct Affine3<R: Real>(pub [R; 12]);

impl<R: Real> Affine3<R> {
    fn col(&self, c: usize) -> R::V3 {
        R::V3::new(self.0[3 * c], self.0[3 * c + 1], self.0[3 * c + 2])
    }
    #[inline(always)]
    pub fn vector(&self, v: R::V3) -> R::V3 {
        self.col(0) * v.x() + self.col(1) * v.y() + self.col(2) * v.z()
    }
    #[inline(always)]
    pub fn point(&self, p: R::V3) -> R::V3 {
        self.vector(p) + self.col(3)
    }
    /// The normal matrix of this map's inverse applied to `n` (not unit):
    /// the inverse transpose of the inverse's linear part is this map's
    /// linear part transposed.
    #[inline(always)]
    pub fn transposed(&self, n: R::V3) -> R::V3 {
        R::V3::new(self.col(0).dot(n), self.col(1).dot(n), self.col(2).dot(n))
    }
    fn from_mat(m: glam::DMat4) -> Self {
        let c = m.to_cols_array();
        Affine3([0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14].map(|i| R::from_f64(c[i])))
    }
}

impl<R: Real> Instance<R> {
    /// Whether it mirrors (its linear part's determinant is negative).
    pub fn mirrors(&self) -> bool {
        let c = |k: usize| self.to_world.col(k);
        c(0).cross(c(1)).dot(c(2)) < R::ZERO
    }
}

/// One placement of a mesh.
#[derive(Clone, Copy, Debug)]
pub struct Instance<R: Real> {
    /// Object space to the world's camera-relative space.
    pub to_world: Affine3<R>,
    /// Its inverse: rays into object space. Normals go to the world by
    /// its transpose.
    pub to_object: Affine3<R>,
    pub mesh: u32,
    /// The id index of its first triangle (see the module docs).
    pub first: u32,
}

/// A world's instanced meshes and their placements.
#[derive(Clone, Debug, Default)]
pub struct Instances<R: Real> {
    pub meshes: Vec<InstancedMesh<R>>,
    pub list: Vec<Instance<R>>,
    /// Placements dropped because their transform is singular or not finite.
    pub dropped: usize,
}

/// Ids of instanced triangles share 28 bits with the kind's other ids.
pub(crate) const MAX_PLACED: u64 = 1 << 28;

impl<R: Real> Instances<R> {
    /// Adds a mesh (triangles, their corners and shading, and vertex
    /// normals in object space) with its tree; returns its index.
    pub(crate) fn add_mesh(
        &mut self,
        mut triangles: Vec<Triangle<R>>,
        mut corners: Vec<[u32; 3]>,
        mut shading: Vec<TriangleShading>,
        vertex_normals: Vec<R::V3>,
    ) -> u32 {
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for t in &triangles {
            for v in t.vertices() {
                let v = v.to_array();
                for k in 0..3 {
                    lo[k] = lo[k].min(v[k]);
                    hi[k] = hi[k].max(v[k]);
                }
            }
        }
        // Its tree over its triangles (kept: instances are tested through
        // their packets); the positions are needed for none of it.
        let tree = crate::accel::build(
            &[],
            &[],
            crate::accel::TriangleArrays {
                positions: &Vec::new(),
                corners: &mut corners,
                shading: &mut shading,
                triangles: &mut triangles,
            },
            Some(true),
        )
        .unwrap_or_default();
        self.meshes.push(InstancedMesh {
            triangles,
            corners,
            shading,
            vertex_normals,
            tree,
            lo,
            hi,
        });
        self.meshes.len() as u32 - 1
    }

    /// Places mesh `mesh` by `to_world` (object space to the world's
    /// camera-relative space, in `f64`). Singular or non-finite maps are
    /// dropped (their copy has no area). Returns false, adding nothing,
    /// when the placed triangles would exceed the ids' 28 bits.
    pub(crate) fn place(&mut self, mesh: u32, to_world: glam::DMat4) -> bool {
        let inv = to_world.inverse();
        let det = to_world.determinant();
        if !(det != 0.0 && det.is_finite() && inv.is_finite() && to_world.is_finite()) {
            self.dropped += 1;
            return true;
        }
        let first = self.list.last().map_or(0, |l| {
            l.first as u64 + self.meshes[l.mesh as usize].triangles.len() as u64
        });
        let n = self.meshes[mesh as usize].triangles.len() as u64;
        if first + n > MAX_PLACED {
            return false;
        }
        self.list.push(Instance {
            to_world: Affine3::from_mat(to_world),
            to_object: Affine3::from_mat(inv),
            mesh,
            first: first as u32,
        });
        true
    }

    /// The world-space (camera-relative) boxes of the instances, for the top level.
    pub(crate) fn boxes(&self) -> Vec<Aabb> {
        self.list
            .iter()
            .map(|inst| {
                let m = &self.meshes[inst.mesh as usize];
                let c = inst.to_world.0.map(|x| x.to_f64());
                let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
                for corner in 0..8 {
                    let p = [0, 1, 2].map(|k| {
                        if corner >> k & 1 == 0 {
                            m.lo[k]
                        } else {
                            m.hi[k]
                        }
                    });
                    for k in 0..3 {
                        let w = c[k] * p[0] + c[3 + k] * p[1] + c[6 + k] * p[2] + c[9 + k];
                        lo[k] = lo[k].min(w);
                        hi[k] = hi[k].max(w);
                    }
                }
                // Widened by a relative margin: the transformed triangles are
                // rounded in `R`, in object space, not where this box is.
                let pad = [0, 1, 2]
                    .map(|k| (hi[k] - lo[k]).abs().max(lo[k].abs().max(hi[k].abs())) * 1e-5);
                Aabb::outward(
                    [0, 1, 2].map(|k| lo[k] - pad[k]),
                    [0, 1, 2].map(|k| hi[k] + pad[k]),
                )
            })
            .collect()
    }

    /// Instance and local triangle of an `INSTANCE_TRIANGLE` id's index.
    #[inline]
    pub(crate) fn locate(&self, index: usize) -> (&Instance<R>, &InstancedMesh<R>, usize) {
        let i = self.list.partition_point(|l| l.first as usize <= index) - 1;
        let inst = &self.list[i];
        (
            inst,
            &self.meshes[inst.mesh as usize],
            index - inst.first as usize,
        )
    }

    /// Nearest hit on instance `i` no farther than `t_max` (a tie at
    /// `t_max` included): distance and the hit's `INSTANCE_TRIANGLE` id.
    /// `skip`: the (any-kind) id the ray starts on.
    #[inline]
    pub fn closest(&self, i: usize, ray: &Ray<R>, t_max: R, skip: PrimId) -> Option<(R, PrimId)> {
        let inst = &self.list[i];
        let m = &self.meshes[inst.mesh as usize];
        let local = Ray::new(
            inst.to_object.point(ray.origin),
            inst.to_object.vector(ray.dir),
        );
        let first = inst.first as usize;
        let local_skip = if skip.kind() == PrimId::INSTANCE_TRIANGLE
            && (first..first + m.triangles.len()).contains(&skip.index())
        {
            PrimId::new(PrimId::TRIANGLE, (skip.index() - first) as u32)
        } else {
            PrimId::NONE
        };
        bvh::closest_hit(m, &m.tree, &local, t_max, PrimId::NONE, local_skip).map(|(t, id)| {
            (
                t,
                PrimId::new(PrimId::INSTANCE_TRIANGLE, (first + id.index()) as u32),
            )
        })
    }

    /// Point snapped onto the hit triangle, its outward unit normal and
    /// material (all in the world's space).
    #[inline]
    pub fn surface(&self, index: usize, p: R::V3) -> (R::V3, R::V3, u32) {
        let (inst, m, k) = self.locate(index);
        let t = &m.triangles[k];
        let (v0, normal) = (t.vertices()[0], t.normal());
        let q = inst.to_object.point(p);
        let q = q - normal * normal.dot(q - v0);
        let n = inst.to_object.transposed(normal).normalize();
        (inst.to_world.point(q), n, m.shading[k].material)
    }
}

/// A mesh's tree holds its triangles only.
impl<R: Real> bvh::Primitives<R> for InstancedMesh<R> {
    #[inline(always)]
    fn intersect(
        &self,
        id: PrimId,
        _ray: &Ray<R>,
        tri: &TriangleRay<R>,
        t_max: R,
        skip: PrimId,
    ) -> Option<R> {
        if id == skip {
            return None;
        }
        self.triangles[id.index()].distance(tri, t_max)
    }
}
