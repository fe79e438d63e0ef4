//! The world's hit queries: nearest hit, occlusion and surface of one ray,
//! of packets of rays, through the tree where the world has one, by brute
//! force over every primitive where it has triangles but no tree (the
//! reference the tree is checked against), else by the 4-wide sphere loop.
//! Also the world as the tree's [`bvh::Primitives`] view, which is how the
//! tree reaches the spheres and triangles its ids name.

use crate::bvh::{self, Bvh};
use crate::geometry::PrimId;
use crate::math::{Lanes4, Ray, Real, Vector3};
use crate::texture::SurfaceAttrs;
use crate::triangle::{Triangle, TriangleRay, VertexNormals};

use super::World;

/// Most cut-out surfaces a ray passes through before one counts as hit.
const MAX_CUTOUT_LAYERS: usize = 64;

impl<R: Real> World<R> {
    /// Lane of `skip` (the primitive a ray starts on) within pack `pack`
    /// of the primitives of `kind` (spheres or planes), or 4 (none).
    #[inline(always)]
    fn self_lane(skip: PrimId, kind: u32, pack: usize) -> usize {
        if skip.kind() == kind && skip.index() / 4 == pack {
            skip.index() % 4
        } else {
            4
        }
    }

    /// Whether any lane of a pack's distances is a hit (finite).
    #[inline(always)]
    fn any_hit(t: R::V4) -> bool {
        R::V4::bitmask(t.cmplt(R::V4::splat(R::INFINITY))) != 0
    }

    /// Takes each finite lane of `t` (pack `pack` of the primitives of
    /// `kind`) that is strictly nearer than `best`, in lane order: the
    /// scalar loop's answer, ties to the lower index.
    #[inline(always)]
    fn take_nearer(t: R::V4, kind: u32, pack: usize, best: &mut R, id: &mut PrimId) {
        if Self::any_hit(t) {
            for (j, tj) in t.to_array().into_iter().enumerate() {
                if tj < *best {
                    *best = tj;
                    *id = PrimId::new(kind, (pack * 4 + j) as u32);
                }
            }
        }
    }

    /// The nearest of `(best, id)` and the planes' hits, planes taken in
    /// order and a hit taken only if strictly nearer: the scalar loop's
    /// answer, four planes at a time.
    #[inline(always)]
    fn nearest_plane(
        &self,
        (o, d): ([R::V4; 3], [R::V4; 3]),
        mut best: R,
        mut id: PrimId,
        skip: PrimId,
    ) -> (R, PrimId) {
        for (pi, pack) in self.plane_packs.iter().enumerate() {
            let t = pack.intersect(o, d, best, Self::self_lane(skip, PrimId::PLANE, pi));
            Self::take_nearer(t, PrimId::PLANE, pi, &mut best, &mut id);
        }
        (best, id)
    }

    /// Whether a plane lies on the ray in (0, t_max).
    #[inline(always)]
    fn plane_blocks(&self, (o, d): ([R::V4; 3], [R::V4; 3]), t_max: R, skip: PrimId) -> bool {
        self.plane_packs.iter().enumerate().any(|(pi, pack)| {
            let t = pack.intersect(o, d, t_max, Self::self_lane(skip, PrimId::PLANE, pi));
            Self::any_hit(t)
        })
    }

    #[inline(always)]
    fn splat_ray(ray: &Ray<R>) -> ([R::V4; 3], [R::V4; 3]) {
        let o = [
            R::V4::splat(ray.origin.x()),
            R::V4::splat(ray.origin.y()),
            R::V4::splat(ray.origin.z()),
        ];
        let d = [
            R::V4::splat(ray.dir.x()),
            R::V4::splat(ray.dir.y()),
            R::V4::splat(ray.dir.z()),
        ];
        (o, d)
    }

    /// Nearest hit in (0, inf); `skip` is the primitive the ray starts on.
    /// Cut-outs (alphaMode MASK where alpha is below the cutoff) are passed
    /// through.
    #[inline(always)]
    pub fn closest_hit(&self, ray: &Ray<R>, skip: PrimId) -> Option<(R, PrimId)> {
        self.past_cutouts(ray, self.closest_solid_or_cut(ray, skip))
    }

    /// `hit` (the nearest, cut-outs included) where the world has no
    /// cut-outs, else the first hit beyond them ([`Self::through_cutouts`]).
    #[inline(always)]
    fn past_cutouts(&self, ray: &Ray<R>, hit: Option<(R, PrimId)>) -> Option<(R, PrimId)> {
        if !self.attrs.cutouts {
            return hit;
        }
        self.through_cutouts(ray, hit)
    }

    /// The first hit beyond the cut-outs, starting from `hit`: each cut-out
    /// hit is left by a ray from it along the same direction (at most
    /// [`MAX_CUTOUT_LAYERS`] of them; past that the surface counts as hit).
    #[cold]
    fn through_cutouts(&self, ray: &Ray<R>, mut hit: Option<(R, PrimId)>) -> Option<(R, PrimId)> {
        let mut t0 = R::ZERO;
        for _ in 0..MAX_CUTOUT_LAYERS {
            let (t, id) = hit?;
            let p = ray.at(t0 + t);
            if !self.cut_away(id, p, ray.dir) {
                return Some((t0 + t, id));
            }
            t0 += t;
            hit = self.closest_solid_or_cut(&Ray::new(p, ray.dir), id);
        }
        hit.map(|(t, id)| (t0 + t, id))
    }

    /// Whether the point `p` of primitive `id`, met along `dir`, is cut
    /// away: a MASK material's alpha there is below its cutoff, or `dir`
    /// meets the back face of a single-sided surface
    /// (`Pbr::culls_back_faces`).
    pub fn cut_away(&self, id: PrimId, p: R::V3, dir: R::V3) -> bool {
        let (material, normal) = match id.kind() {
            PrimId::TRIANGLE => (
                self.triangle_shading[id.index()].material,
                self.triangle_normal(id.index()),
            ),
            PrimId::INSTANCE_TRIANGLE => {
                let (_, n, material) = self.instances.surface(id.index(), p);
                (material, n)
            }
            _ => return false,
        };
        let m = &self.materials[material as usize];
        if m.pbr == crate::material::NO_PBR {
            return false;
        }
        let pbr = &self.pbr[m.pbr as usize];
        if pbr.culls_back_faces() && normal.dot(dir) > R::ZERO {
            return true;
        }
        if pbr.alpha_mode != crate::material::AlphaMode::Mask {
            return false;
        }
        pbr.cut_away(&self.attrs_at(id, p))
    }

    /// The hit triangle `id` (a world triangle or an instance's) as
    /// shading sees it, or `None` for other primitives.
    #[inline]
    pub fn placed_triangle(&self, id: PrimId) -> Option<PlacedTriangle<'_, R>> {
        match id.kind() {
            PrimId::TRIANGLE => Some(PlacedTriangle {
                triangle: self.triangle(id.index()),
                corners: self.corners[id.index()],
                shading: &self.triangle_shading[id.index()],
                vertex_normals: &self.vertex_normals,
                instance: None,
            }),
            PrimId::INSTANCE_TRIANGLE => {
                let (instance, mesh, k) = self.instances.locate(id.index());
                Some(PlacedTriangle {
                    triangle: mesh.triangles[k],
                    corners: mesh.corners[k],
                    shading: &mesh.shading[k],
                    vertex_normals: &mesh.vertex_normals,
                    instance: Some(instance),
                })
            }
            _ => None,
        }
    }

    /// Texture coordinates (sets 0 and 1) and vertex colour at `p` on
    /// triangle `id` (a world triangle or an instance's), interpolated by
    /// barycentric weights, and the footprint's level of detail in each
    /// set ([`World::texture_lod`]); [`SurfaceAttrs::NONE`] for a triangle
    /// without them and for other primitives.
    pub fn attrs_at(&self, id: PrimId, p: R::V3) -> SurfaceAttrs {
        let Some(t) = self.placed_triangle(id) else {
            return SurfaceAttrs::NONE;
        };
        let a = t.shading.attrs;
        if a == crate::triangle::NO_ATTRS {
            return SurfaceAttrs::NONE;
        }
        let vs = self.attrs.tri[a as usize];
        let b = t.barycentric(p).map(|w| w.to_f64() as f32);
        let mix2 = |v: &[[f32; 2]]| -> [f32; 2] {
            std::array::from_fn(|k| {
                v[vs[0] as usize][k] * b[0]
                    + v[vs[1] as usize][k] * b[1]
                    + v[vs[2] as usize][k] * b[2]
            })
        };
        let c = &self.attrs.color;
        let colour = std::array::from_fn(|k| {
            c[vs[0] as usize][k] * b[0] + c[vs[1] as usize][k] * b[1] + c[vs[2] as usize][k] * b[2]
        });
        SurfaceAttrs {
            uv: [mix2(&self.attrs.uv[0]), mix2(&self.attrs.uv[1])],
            colour,
            lod: self.texture_lod(t.corners(), p, vs),
        }
    }

    /// The level of detail of a pixel's footprint at `p` on the triangle
    /// of world-space `corners` (of attribute vertices `vs`), per UV set: log2 of the
    /// footprint's side in texture coordinates (docs/meshes.md, "Texture
    /// filtering"). The footprint is the camera's: a cone of one pixel's
    /// angle from the camera (this world's origin) to `p`, whatever path
    /// the ray took (pbrt-v4 approximates every ray after the camera's so,
    /// `Camera::Approximate_dp_dxy`), narrowed as pbrt-v4 does where a
    /// pixel takes many samples: its side times max(1/8, 1/√spp), the
    /// samples then covering the pixel between them. On the surface its area grows by
    /// 1/|cos| of the angle to the normal (the geometric mean of the
    /// ellipse's axes: an isotropic filter's compromise between blur and
    /// aliasing at grazing angles), and in texture space by the triangle's
    /// texture-coordinate area over its area. pbr.wgsl `texture_lod` is its
    /// mirror (in f32).
    pub fn texture_lod(&self, corners: [R::V3; 3], p: R::V3, vs: [u32; 3]) -> [f32; 2] {
        let [p0, p1, p2] = corners;
        let c = (p1 - p0).cross(p2 - p0);
        let area = c.length().to_f64();
        let dist = p.length().to_f64();
        let cos = (c.dot(p).to_f64() / (area * dist)).abs().max(1e-4);
        let spread = 2.0 * self.camera.up.length().to_f64() * self.camera.inv_height.to_f64();
        let per_sample = (1.0 / self.settings.samples.max(1) as f64).max(1.0 / 64.0);
        let foot = spread * spread * dist * dist / cos * per_sample;
        std::array::from_fn(|set| {
            let uv = vs.map(|v| self.attrs.uv[set][v as usize]);
            let (d1, d2) = (
                [uv[1][0] - uv[0][0], uv[1][1] - uv[0][1]],
                [uv[2][0] - uv[0][0], uv[2][1] - uv[0][1]],
            );
            let uv_area = (d1[0] as f64 * d2[1] as f64 - d2[0] as f64 * d1[1] as f64).abs();
            let lod = 0.5 * (foot * uv_area / area).log2();
            if lod.is_nan() {
                f32::NEG_INFINITY
            } else {
                lod as f32
            }
        })
    }

    /// The attributes (`attrs_at`) and tangent (`VertexAttrs::tangent`,
    /// interpolated, in the world's space, w the first vertex's sign, turned
    /// by a mirroring instance) at `p` on triangle `id`; `None` without
    /// attributes or where a vertex's tangent is unknown.
    pub fn tangent_at(&self, id: PrimId, p: R::V3) -> Option<(SurfaceAttrs, [f32; 4])> {
        let t = self.placed_triangle(id)?;
        let a = t.shading.attrs;
        if a == crate::triangle::NO_ATTRS {
            return None;
        }
        let vs = self.attrs.tri[a as usize];
        let tangents = vs.map(|v| {
            self.attrs
                .tangent
                .get(v as usize)
                .copied()
                .unwrap_or_default()
        });
        if tangents.iter().any(|t| t[3] == 0.0) {
            return None;
        }
        let b = t.barycentric(p).map(|w| w.to_f64() as f32);
        let at = self.attrs_at(id, p);
        let mix: [f32; 3] = std::array::from_fn(|k| {
            tangents[0][k] * b[0] + tangents[1][k] * b[1] + tangents[2][k] * b[2]
        });
        let Some(inst) = t.instance else {
            return Some((at, [mix[0], mix[1], mix[2], tangents[0][3]]));
        };
        // Tangents move with the surface (the placement's linear part); a
        // mirror flips the bitangent, as for a copied mesh.
        let v = inst
            .to_world
            .vector(R::V3::from_array(mix.map(f64::from)))
            .to_array()
            .map(|x| x as f32);
        let sign = if inst.mirrors() { -1.0 } else { 1.0 };
        Some((at, [v[0], v[1], v[2], tangents[0][3] * sign]))
    }

    /// Nearest hit, cut-outs included.
    #[inline(always)]
    fn closest_solid_or_cut(&self, ray: &Ray<R>, skip: PrimId) -> Option<(R, PrimId)> {
        if let Some(tree) = &self.accel {
            return self.closest_hit_accel(tree, ray, skip);
        }
        if self.triangle_count() > 0 || !self.instances.list.is_empty() {
            return self.closest_hit_brute(ray, skip);
        }
        let mut best = R::INFINITY;
        let mut id = PrimId::NONE;
        let (o, d) = Self::splat_ray(ray);
        for (pi, pack) in self.sphere_packs.iter().enumerate() {
            let t = pack.intersect(o, d, best, Self::self_lane(skip, PrimId::SPHERE, pi));
            // Every finite lane is closer than `best`; take the nearest.
            Self::take_nearer(t, PrimId::SPHERE, pi, &mut best, &mut id);
        }
        let (best, id) = self.nearest_plane((o, d), best, id, skip);
        (id != PrimId::NONE).then_some((best, id))
    }

    /// Whether anything but cut-outs lies on the ray before `t_max`.
    #[inline(always)]
    pub fn occluded(&self, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
        if self.attrs.cutouts {
            return self.closest_hit(ray, skip).is_some_and(|(t, _)| t < t_max);
        }
        self.occluded_solid_or_cut(ray, t_max, skip)
    }

    /// Whether anything lies on the ray before `t_max`, cut-outs included.
    #[inline(always)]
    fn occluded_solid_or_cut(&self, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
        if let Some(tree) = &self.accel {
            return self.occluded_accel(tree, ray, t_max, skip);
        }
        if self.triangle_count() > 0 || !self.instances.list.is_empty() {
            return self.occluded_brute(ray, t_max, skip);
        }
        let (o, d) = Self::splat_ray(ray);
        for (pi, pack) in self.sphere_packs.iter().enumerate() {
            let t = pack.intersect(o, d, t_max, Self::self_lane(skip, PrimId::SPHERE, pi));
            if Self::any_hit(t) {
                return true;
            }
        }
        self.plane_blocks((o, d), t_max, skip)
    }

    /// Surface point (snapped onto the primitive), outward normal and material of a hit.
    #[inline(always)]
    pub fn surface(&self, id: PrimId, p: R::V3) -> (R::V3, R::V3, u32) {
        match id.kind() {
            PrimId::SPHERE => {
                let s = &self.spheres[id.index()];
                let (p, n) = s.surface(p);
                (p, n, s.material)
            }
            PrimId::TRIANGLE => self.triangle_surface(id.index(), p),
            PrimId::INSTANCE_TRIANGLE => self.instances.surface(id.index(), p),
            _ => {
                let pl = &self.planes[id.index()];
                let (p, n) = pl.surface(p);
                (p, n, pl.material)
            }
        }
    }

    /// `closest_hit` of worlds with a tree: planes by loop, the rest by tree.
    #[inline]
    fn closest_hit_accel(&self, tree: &Bvh, ray: &Ray<R>, skip: PrimId) -> Option<(R, PrimId)> {
        let (best, id) = self.closest_plane(ray, skip);
        let hit = bvh::closest_hit(self, tree, ray, best, id, skip);
        self.resolve(ray, hit, skip)
    }

    /// A hit as the tree gives it, with an instance's id (the top level
    /// knows only which instance) made the id of the triangle hit: the
    /// instance's nearest hit, found again the same way.
    #[inline(always)]
    fn resolve(&self, ray: &Ray<R>, hit: Option<(R, PrimId)>, skip: PrimId) -> Option<(R, PrimId)> {
        match hit {
            Some((_, id)) if id.kind() == PrimId::INSTANCE => {
                self.instances.closest(id.index(), ray, R::INFINITY, skip)
            }
            hit => hit,
        }
    }

    /// `out[j] = self.closest_hit(&rays[j], skip)` for every ray, the same
    /// answers; in `f32` with a tree, packets of [`bvh::PACKET`] rays go
    /// through the tree together ([`bvh::closest_hits`]), which pays for
    /// coherent rays (neighbouring camera rays). A packet's hit on a
    /// cut-out goes on alone, as `closest_hit` does.
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
                let hit = (found[j] != PrimId::NONE).then_some((best[j], found[j]));
                out[j] = w.past_cutouts(&rays[j], w.resolve(&rays[j], hit, skip));
            }
        }
    }

    /// `out[j] = self.occluded(&rays[j], t_max[j], skip[j])` for every ray,
    /// the same answers; in `f32` with a tree, packets of [`bvh::PACKET`]
    /// rays go through the tree together ([`bvh::occluded_hits`]). Where
    /// cut-outs may have blocked a ray, it is asked again alone (a cut-out
    /// only ever takes a hit away).
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
                let mut hit = (blocked >> j) & 1 != 0;
                if hit && w.attrs.cutouts {
                    hit = w.occluded(&rays[j], t_max[j], skip[j]);
                }
                *o = hit || w.plane_blocks(World::<f32>::splat_ray(&rays[j]), t_max[j], skip[j]);
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
    fn closest_plane(&self, ray: &Ray<R>, skip: PrimId) -> (R, PrimId) {
        self.nearest_plane(Self::splat_ray(ray), R::INFINITY, PrimId::NONE, skip)
    }

    #[inline]
    fn occluded_accel(&self, tree: &Bvh, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
        self.plane_blocks(Self::splat_ray(ray), t_max, skip)
            || bvh::occluded(self, tree, ray, t_max, skip)
    }

    /// `closest_hit` without a tree when there are triangles: every
    /// primitive, with the tree's order on ties ([`PrimId::nearer`]).
    fn closest_hit_brute(&self, ray: &Ray<R>, skip: PrimId) -> Option<(R, PrimId)> {
        let (mut best, mut id) = self.closest_plane(ray, skip);
        for i in 0..self.instances.list.len() {
            if let Some((t, pid)) = self.instances.closest(i, ray, best, skip)
                && pid.nearer(t, best, id)
            {
                best = t;
                id = pid;
            }
        }
        let tr = TriangleRay::new(ray);
        for (i, t) in self.triangles().enumerate() {
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

    fn occluded_brute(&self, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
        let tr = TriangleRay::new(ray);
        self.triangles().enumerate().any(|(i, t)| {
            PrimId::new(PrimId::TRIANGLE, i as u32) != skip && t.intersect(&tr, t_max).is_some()
        }) || (0..self.instances.list.len())
            .any(|i| self.instances.closest(i, ray, t_max, skip).is_some())
            || self.spheres.iter().enumerate().any(|(i, s)| {
                s.intersect(ray, t_max, PrimId::new(PrimId::SPHERE, i as u32) == skip)
                    .is_some()
            })
            || self.plane_blocks(Self::splat_ray(ray), t_max, skip)
    }

    /// Point snapped onto the triangle's plane, its outward geometric normal, and material.
    #[inline]
    fn triangle_surface(&self, index: usize, p: R::V3) -> (R::V3, R::V3, u32) {
        // The triangle read once (a big world's, from its packet).
        let t = self.triangle(index);
        let normal = self.kept_normal(index).unwrap_or_else(|| t.normal());
        let v0 = t.vertices()[0];
        let p = p - normal * normal.dot(p - v0);
        (p, normal, self.triangle_shading[index].material)
    }

    /// Normal to shade with at `p` on primitive `id`: for smooth triangles the
    /// interpolated vertex normal, turned to the side of `n` (the geometric
    /// normal facing the viewer); `n` itself elsewhere, and wherever the
    /// interpolated normal would face away from the viewer `v` (silhouettes),
    /// so that no reflected ray is sent into the surface.
    #[inline(always)]
    pub fn shading_normal(&self, id: PrimId, p: R::V3, n: R::V3, v: R::V3) -> R::V3 {
        // A flat world triangle (a mesh without normals) is answered from
        // its corners' normals, before the triangle is read (gathered,
        // maybe); an instance's is read from its mesh.
        if id.kind() == PrimId::TRIANGLE
            && !VertexNormals::<R>(&self.vertex_normals).smooth(self.corners[id.index()])
        {
            return n;
        }
        let Some(t) = self.placed_triangle(id).filter(|t| t.smooth()) else {
            return n;
        };
        let ns = t.normal_at(p);
        let ns = if ns.dot(n) < R::ZERO { -ns } else { ns };
        if ns.dot(v) > R::ZERO { ns } else { n }
    }
}

/// The tree holds this world's spheres, instances and triangles (`accel::build`).
impl<R: Real> bvh::Primitives<R> for World<R> {
    #[inline(always)]
    fn intersect(
        &self,
        id: PrimId,
        ray: &Ray<R>,
        tri: &TriangleRay<R>,
        t_max: R,
        skip: PrimId,
    ) -> Option<R> {
        if id.kind() == PrimId::TRIANGLE {
            // A ray leaving a triangle cannot hit that (flat) triangle again.
            if id == skip {
                return None;
            }
            self.triangle(id.index()).distance(tri, t_max)
        } else if id.kind() == PrimId::INSTANCE {
            self.instances
                .closest(id.index(), ray, t_max, skip)
                .map(|(t, _)| t)
        } else {
            self.spheres[id.index()].intersect(ray, R::INFINITY, id == skip)
        }
    }
}

/// A hit triangle as shading sees it ([`World::placed_triangle`]): a world
/// triangle, or an instance's in its mesh's space with the instance that
/// places it.
#[derive(Clone, Copy)]
pub struct PlacedTriangle<'a, R: Real> {
    pub triangle: Triangle<R>,
    /// Its vertices' indices in its mesh's vertex normals (and positions).
    pub corners: [u32; 3],
    pub shading: &'a crate::triangle::TriangleShading,
    /// Its mesh's vertex normals.
    pub vertex_normals: &'a [R::V3],
    pub instance: Option<&'a super::Instance<R>>,
}

impl<R: Real> PlacedTriangle<'_, R> {
    /// Whether it is shaded smoothly (its corners' vertex normals known).
    #[inline]
    pub fn smooth(&self) -> bool {
        VertexNormals::<R>(self.vertex_normals).smooth(self.corners)
    }

    /// Barycentric weights of world point `p` (taken in the triangle's own
    /// space: an affine map keeps them).
    #[inline]
    pub fn barycentric(&self, p: R::V3) -> [R; 3] {
        match self.instance {
            None => self.triangle.barycentric(p),
            Some(i) => self.triangle.barycentric(i.to_object.point(p)),
        }
    }

    /// Its corners in the world's space, in its attribute vertices' order.
    #[inline]
    pub fn corners(&self) -> [R::V3; 3] {
        let v = self.triangle.vertices();
        match self.instance {
            None => v,
            Some(i) => v.map(|v| i.to_world.point(v)),
        }
    }

    /// Its interpolated vertex normal (or geometric normal, when flat) at
    /// world point `p`, unit, in the world's space.
    #[inline]
    pub fn normal_at(&self, p: R::V3) -> R::V3 {
        match self.instance {
            None => {
                VertexNormals::<R>(self.vertex_normals).normal_at(&self.triangle, self.corners, p)
            }
            Some(i) => {
                let n = VertexNormals::<R>(self.vertex_normals).normal_at(
                    &self.triangle,
                    self.corners,
                    i.to_object.point(p),
                );
                i.to_object.transposed(n).normalize()
            }
        }
    }
}
