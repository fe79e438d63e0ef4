//! Meshes and the acceleration structure in the render-ready [`World`]:
//! turning loaded meshes into world triangles, deciding per scene whether a
//! BVH pays off, and the hit queries with and without it. Kept apart from
//! `world.rs` so that the sphere/plane fast path there stays as it is.

use crate::bvh::{self, Aabb, Bvh};
use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3};
use crate::scene::MeshDesc;
use crate::triangle::{Triangle, TriangleRay, TriangleShading};
use crate::world::{Features, Material, World};

/// Scenes with fewer spheres than this and no triangles keep the plain loop
/// over spheres: a tree only adds box tests there. Measured with
/// `cargo run --release -p tracer-core --example accel_crossover` (2-core
/// machine, one thread, rays per CPU-second, the 4-wide `SpherePack` loop):
/// the loop wins up to 4 spheres (25 vs 23 M rays/s), ties at 6-8, loses
/// from 10 on (20 vs 23; 9 vs 21 at 64). Re-measure when either gets faster.
pub const SPHERE_BVH_MIN: usize = 10;

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

/// Builds the tree over `world`'s spheres and triangles when the scene needs
/// one, and reorders the triangles to the tree's leaf order (so a leaf's
/// triangles are neighbours in memory).
pub(crate) fn build_accel<R: Real>(world: &mut World<R>, force: Option<bool>) {
    let wanted =
        force.unwrap_or(!world.triangles.is_empty() || world.spheres.len() >= SPHERE_BVH_MIN);
    if !wanted || (world.triangles.is_empty() && world.spheres.is_empty()) {
        world.accel = None;
        return;
    }
    let mut boxes = Vec::with_capacity(world.spheres.len() + world.triangles.len());
    let mut ids = Vec::with_capacity(boxes.capacity());
    for (i, s) in world.spheres.iter().enumerate() {
        let c = s.center.to_array();
        let r = s.radius.to_f64();
        boxes.push(Aabb::outward(c.map(|x| x - r), c.map(|x| x + r)));
        ids.push(PrimId::new(PrimId::SPHERE, i as u32));
    }
    for (i, t) in world.triangles.iter().enumerate() {
        let v = t.vertices();
        let lo = v[0].min(v[1]).min(v[2]).to_array();
        let hi = v[0].max(v[1]).max(v[2]).to_array();
        boxes.push(Aabb::outward(lo, hi));
        ids.push(PrimId::new(PrimId::TRIANGLE, i as u32));
    }
    let mut tree = Bvh::build(&boxes, &ids);
    let n = world.triangles.len();
    if n > 0 {
        let mut triangles = Vec::with_capacity(n);
        let mut shading = Vec::with_capacity(n);
        for id in tree
            .prims
            .iter_mut()
            .filter(|id| id.kind() == PrimId::TRIANGLE)
        {
            triangles.push(world.triangles[id.index()]);
            shading.push(world.triangle_shading[id.index()]);
            *id = PrimId::new(PrimId::TRIANGLE, triangles.len() as u32 - 1);
        }
        world.triangles = triangles;
        world.triangle_shading = shading;
    }
    // The 4-wide triangle test (f32 only) wants the leaves' triangles packed.
    // Not with spheres: packing them too (NaN lanes sent to the sphere test)
    // made the bunny scene (a glass sphere in the tree) 9% slower.
    if std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>() && world.spheres.is_empty() {
        // SAFETY: R is f32, so this is the same type.
        let tris = unsafe {
            &*(world.triangles.as_slice() as *const [Triangle<R>] as *const [Triangle<f32>])
        };
        tree.pack_triangles(tris);
    }
    world.accel = Some(tree);
}

impl<R: Real> World<R> {
    /// Rebuilds (`Some(true)`), drops (`Some(false)`) or re-decides (`None`)
    /// the acceleration structure. Without one, every query tests every
    /// primitive: the brute-force reference the tree is checked against.
    pub fn set_accel(&mut self, force: Option<bool>) {
        build_accel(self, force);
    }

    /// `closest_hit` of worlds with a tree: planes by loop, the rest by tree.
    #[inline]
    pub(crate) fn closest_hit_accel(
        &self,
        tree: &Bvh,
        ray: &Ray<R>,
        skip: PrimId,
    ) -> Option<(R, PrimId)> {
        let (best, id) = self.closest_plane(ray, skip);
        bvh::closest_hit(self, tree, ray, best, id, skip)
    }

    /// `out[j] = self.closest_hit(&rays[j], skip)` for every ray, the same
    /// answers; in `f32` with a tree, packets of [`bvh::PACKET`] rays go
    /// through the tree together ([`bvh::closest_hits`]), which pays for
    /// coherent rays (neighbouring camera rays).
    pub fn closest_hits(&self, rays: &[Ray<R>], skip: PrimId, out: &mut [Option<(R, PrimId)>]) {
        assert_eq!(rays.len(), out.len());
        let Some((w, tree)) = self.f32_tree() else {
            for (o, r) in out.iter_mut().zip(rays) {
                *o = self.closest_hit(r, skip);
            }
            return;
        };
        // SAFETY: R is f32 here (the downcast succeeded), so these are the same types.
        let (rays, out) = unsafe {
            (
                &*(rays as *const [Ray<R>] as *const [Ray<f32>]),
                &mut *(out as *mut [Option<(R, PrimId)>] as *mut [Option<(f32, PrimId)>]),
            )
        };
        for (rays, out) in rays.chunks(bvh::PACKET).zip(out.chunks_mut(bvh::PACKET)) {
            let mut best = [f32::INFINITY; bvh::PACKET];
            let mut found = [PrimId::NONE; bvh::PACKET];
            for (j, r) in rays.iter().enumerate() {
                (best[j], found[j]) = w.closest_plane(r, skip);
            }
            let n = rays.len();
            bvh::closest_hits(w, tree, rays, &mut best[..n], &mut found[..n], skip);
            for j in 0..n {
                out[j] = (found[j] != PrimId::NONE).then_some((best[j], found[j]));
            }
        }
    }

    /// `out[j] = self.occluded(&rays[j], t_max[j], skip[j])` for every ray,
    /// the same answers; in `f32` with a tree, packets of [`bvh::PACKET`]
    /// rays go through the tree together ([`bvh::occluded_hits`]).
    pub fn occluded_many(&self, rays: &[Ray<R>], t_max: &[R], skip: &[PrimId], out: &mut [bool]) {
        assert!(rays.len() == t_max.len() && rays.len() == skip.len() && rays.len() == out.len());
        let Some((w, tree)) = self.f32_tree() else {
            for j in 0..rays.len() {
                out[j] = self.occluded(&rays[j], t_max[j], skip[j]);
            }
            return;
        };
        // SAFETY: R is f32 here (the downcast succeeded), so these are the same types.
        let (rays, t_max) = unsafe {
            (
                &*(rays as *const [Ray<R>] as *const [Ray<f32>]),
                &*(t_max as *const [R] as *const [f32]),
            )
        };
        let n = bvh::PACKET;
        for ((rays, t_max), (skip, out)) in rays
            .chunks(n)
            .zip(t_max.chunks(n))
            .zip(skip.chunks(n).zip(out.chunks_mut(n)))
        {
            let blocked = bvh::occluded_hits(w, tree, rays, t_max, skip);
            for (j, o) in out.iter_mut().enumerate() {
                *o = (blocked >> j) & 1 != 0
                    || w.planes.iter().enumerate().any(|(i, p)| {
                        p.intersect(
                            &rays[j],
                            t_max[j],
                            PrimId::new(PrimId::PLANE, i as u32) == skip[j],
                        )
                        .is_some()
                    });
            }
        }
    }

    /// This world as `f32` with its tree, if it is one: what the packet walks take.
    fn f32_tree(&self) -> Option<(&World<f32>, &Bvh)> {
        let w = (self as &dyn std::any::Any).downcast_ref::<World<f32>>()?;
        Some((w, w.accel.as_ref()?))
    }

    /// Nearest plane hit, as (distance, id), or (infinity, `PrimId::NONE`).
    #[inline(always)]
    pub(crate) fn closest_plane(&self, ray: &Ray<R>, skip: PrimId) -> (R, PrimId) {
        let mut best = R::INFINITY;
        let mut id = PrimId::NONE;
        for (i, p) in self.planes.iter().enumerate() {
            let pid = PrimId::new(PrimId::PLANE, i as u32);
            if let Some(t) = p.intersect(ray, R::INFINITY, pid == skip)
                && pid.nearer(t, best, id)
            {
                best = t;
                id = pid;
            }
        }
        (best, id)
    }

    #[inline]
    pub(crate) fn occluded_accel(&self, tree: &Bvh, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
        self.planes.iter().enumerate().any(|(i, p)| {
            p.intersect(ray, t_max, PrimId::new(PrimId::PLANE, i as u32) == skip)
                .is_some()
        }) || bvh::occluded(self, tree, ray, t_max, skip)
    }

    /// `closest_hit` without a tree when there are triangles: every
    /// primitive, with the tree's order on ties ([`PrimId::nearer`]).
    pub(crate) fn closest_hit_brute(&self, ray: &Ray<R>, skip: PrimId) -> Option<(R, PrimId)> {
        let (mut best, mut id) = self.closest_plane(ray, skip);
        let tr = TriangleRay::new(ray);
        for (i, t) in self.triangles.iter().enumerate() {
            let pid = PrimId::new(PrimId::TRIANGLE, i as u32);
            if pid == skip {
                continue;
            }
            if let Some(d) = t.distance(&tr, best)
                && pid.nearer(d, best, id)
            {
                best = d;
                id = pid;
            }
        }
        for (i, s) in self.spheres.iter().enumerate() {
            let pid = PrimId::new(PrimId::SPHERE, i as u32);
            if let Some(t) = s.intersect(ray, R::INFINITY, pid == skip)
                && pid.nearer(t, best, id)
            {
                best = t;
                id = pid;
            }
        }
        (id != PrimId::NONE).then_some((best, id))
    }

    pub(crate) fn occluded_brute(&self, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
        let tr = TriangleRay::new(ray);
        self.triangles.iter().enumerate().any(|(i, t)| {
            PrimId::new(PrimId::TRIANGLE, i as u32) != skip && t.intersect(&tr, t_max).is_some()
        }) || self.spheres.iter().enumerate().any(|(i, s)| {
            s.intersect(ray, t_max, PrimId::new(PrimId::SPHERE, i as u32) == skip)
                .is_some()
        }) || self.planes.iter().enumerate().any(|(i, p)| {
            p.intersect(ray, t_max, PrimId::new(PrimId::PLANE, i as u32) == skip)
                .is_some()
        })
    }

    /// Point snapped onto the triangle's plane, its outward geometric normal, and material.
    #[inline]
    pub(crate) fn triangle_surface(&self, index: usize, p: R::V3) -> (R::V3, R::V3, u32) {
        let s = &self.triangle_shading[index];
        let v0 = self.triangles[index].vertices()[0];
        let p = p - s.normal * s.normal.dot(p - v0);
        (p, s.normal, s.material)
    }

    /// Normal to shade with at `p` on primitive `id`: for smooth triangles the
    /// interpolated vertex normal, turned to the side of `n` (the geometric
    /// normal facing the viewer); `n` itself elsewhere, and wherever the
    /// interpolated normal would face away from the viewer `v` (silhouettes),
    /// so that no reflected ray is sent into the surface.
    #[inline(always)]
    pub fn shading_normal(&self, id: PrimId, p: R::V3, n: R::V3, v: R::V3) -> R::V3 {
        if id.kind() != PrimId::TRIANGLE {
            return n;
        }
        let s = &self.triangle_shading[id.index()];
        if s.vertex_normals.is_none() {
            return n;
        }
        let ns = s.normal_at(&self.triangles[id.index()], p);
        let ns = if ns.dot(n) < R::ZERO { -ns } else { ns };
        if ns.dot(v) > R::ZERO { ns } else { n }
    }
}

/// Bytes of a world's triangle data (intersection + shading arrays).
pub fn triangle_bytes<R: Real>(world: &World<R>) -> usize {
    world.triangles.len()
        * (std::mem::size_of::<Triangle<R>>() + std::mem::size_of::<TriangleShading<R>>())
}
