//! Triangles: the watertight ray-triangle test of Woop, Benthin and Wald,
//! "Watertight Ray/Triangle Intersection" (JCGT 2013), and shading data.
//!
//! Watertight means a ray through a shared edge or vertex of a closed mesh
//! hits at least one of the triangles sharing it: the edge functions are
//! computed from per-vertex values that do not depend on the triangle, in a
//! ray-aligned frame, so two triangles sharing an edge compute the very same
//! edge function for it (with opposite sign), and a zero edge function is
//! re-evaluated in `f64` to get its sign right.

use crate::math::{Ray, Real, Vector3};

/// A triangle as the intersection test wants it: its three vertices.
/// Kept apart from shading data so traversal touches only these 3 vectors.
#[derive(Clone, Copy, Debug)]
pub struct Triangle<R: Real> {
    pub v: [R::V3; 3],
}

/// What shading needs of a triangle once it has been hit.
#[derive(Clone, Copy, Debug)]
pub struct TriangleShading<R: Real> {
    /// Unit geometric normal, outward by the winding (counter-clockwise seen from outside).
    pub normal: R::V3,
    /// Unit vertex normals for smooth shading, or `None` for flat shading.
    pub vertex_normals: Option<[R::V3; 3]>,
    pub material: u32,
}

/// Per-ray precomputation of the watertight test: the ray-aligned shear
/// written as three rows, so that a vertex's transformed coordinates are
/// dot products. Each row has one entry 1 and at most one other non-zero
/// entry, so `dot` rounds exactly like the paper's `A[kx] - Sx * A[kz]`.
#[derive(Clone, Copy, Debug)]
pub struct TriangleRay<R: Real> {
    origin: R::V3,
    row_x: R::V3,
    row_y: R::V3,
    /// Unit vector along the ray direction's dominant axis, times Sz.
    row_z: R::V3,
}

impl<R: Real> TriangleRay<R> {
    #[inline(always)]
    pub fn new(ray: &Ray<R>) -> Self {
        let d = ray.dir;
        let a = d.abs();
        // kz: the dominant axis; kx, ky the next two cyclically, swapped when
        // d[kz] < 0 to keep the winding (and so the sign of det) consistent.
        let kz = if a.x() >= a.y() && a.x() >= a.z() {
            0
        } else if a.y() >= a.z() {
            1
        } else {
            2
        };
        let comp = |k: usize| match k {
            0 => d.x(),
            1 => d.y(),
            _ => d.z(),
        };
        let unit = |k: usize, s: R| match k {
            0 => R::V3::new(s, R::ZERO, R::ZERO),
            1 => R::V3::new(R::ZERO, s, R::ZERO),
            _ => R::V3::new(R::ZERO, R::ZERO, s),
        };
        let dz = comp(kz);
        let (mut kx, mut ky) = ((kz + 1) % 3, (kz + 2) % 3);
        if dz < R::ZERO {
            std::mem::swap(&mut kx, &mut ky);
        }
        let sx = comp(kx) / dz;
        let sy = comp(ky) / dz;
        let sz = R::ONE / dz;
        TriangleRay {
            origin: ray.origin,
            row_x: unit(kx, R::ONE) + unit(kz, -sx),
            row_y: unit(ky, R::ONE) + unit(kz, -sy),
            row_z: unit(kz, sz),
        }
    }
}

impl<R: Real> Triangle<R> {
    /// Distance to the hit in (0, t_max), or `None`. Degenerate triangles
    /// (zero area, or seen exactly edge-on) are never hit and never give NaN.
    #[inline(always)]
    pub fn intersect(&self, r: &TriangleRay<R>, t_max: R) -> Option<R> {
        let a = self.v[0] - r.origin;
        let b = self.v[1] - r.origin;
        let c = self.v[2] - r.origin;
        let (ax, ay) = (a.dot(r.row_x), a.dot(r.row_y));
        let (bx, by) = (b.dot(r.row_x), b.dot(r.row_y));
        let (cx, cy) = (c.dot(r.row_x), c.dot(r.row_y));
        let mut u = cx * by - cy * bx;
        let mut v = ax * cy - ay * cx;
        let mut w = bx * ay - by * ax;
        if u == R::ZERO || v == R::ZERO || w == R::ZERO {
            // On (or within rounding of) an edge: the sign decides which of
            // the two neighbours owns the ray, so get it exactly. Products of
            // f32 are exact in f64; in f64 this is the same computation.
            let f = |p: R, q: R, s: R, t: R| R::from_f64(p.to_f64() * q.to_f64() - s.to_f64() * t.to_f64());
            let (u64_, v64, w64) = (
                cx.to_f64() * by.to_f64() - cy.to_f64() * bx.to_f64(),
                ax.to_f64() * cy.to_f64() - ay.to_f64() * cx.to_f64(),
                bx.to_f64() * ay.to_f64() - by.to_f64() * ax.to_f64(),
            );
            if (u64_ < 0.0 || v64 < 0.0 || w64 < 0.0) && (u64_ > 0.0 || v64 > 0.0 || w64 > 0.0) {
                return None;
            }
            u = f(cx, by, cy, bx);
            v = f(ax, cy, ay, cx);
            w = f(bx, ay, by, ax);
        } else if (u < R::ZERO || v < R::ZERO || w < R::ZERO) && (u > R::ZERO || v > R::ZERO || w > R::ZERO) {
            return None;
        }
        let det = u + v + w;
        if det == R::ZERO {
            return None;
        }
        let az = a.dot(r.row_z);
        let bz = b.dot(r.row_z);
        let cz = c.dot(r.row_z);
        let t_scaled = u * az + v * bz + w * cz;
        // t = t_scaled / det must lie in (0, t_max); test before dividing.
        let inside = if det > R::ZERO {
            t_scaled > R::ZERO && t_scaled < t_max * det
        } else {
            t_scaled < R::ZERO && t_scaled > t_max * det
        };
        if !inside {
            return None;
        }
        let t = t_scaled / det;
        (t > R::ZERO && t < t_max).then_some(t)
    }

    /// Unnormalised geometric normal (e1 x e2): outward for counter-clockwise winding.
    #[inline(always)]
    pub fn cross(&self) -> R::V3 {
        (self.v[1] - self.v[0]).cross(self.v[2] - self.v[0])
    }
}

impl<R: Real> TriangleShading<R> {
    /// Shading normal at `p` (a point on `tri`): the vertex normals
    /// interpolated by barycentric weights, or the geometric normal.
    #[inline(always)]
    pub fn normal_at(&self, tri: &Triangle<R>, p: R::V3) -> R::V3 {
        let Some(ns) = self.vertex_normals else {
            return self.normal;
        };
        let e1 = tri.v[1] - tri.v[0];
        let e2 = tri.v[2] - tri.v[0];
        let d = p - tri.v[0];
        let n = e1.cross(e2);
        let nn = n.length_squared();
        // p = v0 + b1 e1 + b2 e2; clamped so points rounded just outside stay sane.
        let b1 = (d.cross(e2).dot(n) / nn).max(R::ZERO).min(R::ONE);
        let b2 = (e1.cross(d).dot(n) / nn).max(R::ZERO).min(R::ONE - b1);
        let b0 = R::ONE - b1 - b2;
        let s = ns[0] * b0 + ns[1] * b1 + ns[2] * b2;
        let len = s.length();
        if len > R::ZERO && len.is_finite() { s * (R::ONE / len) } else { self.normal }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DVec3, Vec3A};

    fn tri64(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> Triangle<f64> {
        Triangle { v: [DVec3::from_array(a), DVec3::from_array(b), DVec3::from_array(c)] }
    }

    #[test]
    fn hits_inside_misses_outside_either_winding() {
        let t = tri64([-1.0, -1.0, 5.0], [1.0, -1.0, 5.0], [0.0, 1.0, 5.0]);
        let flipped = tri64([-1.0, -1.0, 5.0], [0.0, 1.0, 5.0], [1.0, -1.0, 5.0]);
        for tri in [t, flipped] {
            let r = Ray::<f64>::new(DVec3::ZERO, DVec3::Z);
            assert_eq!(tri.intersect(&TriangleRay::new(&r), f64::INFINITY), Some(5.0));
            assert_eq!(tri.intersect(&TriangleRay::new(&r), 5.0), None, "t_max is exclusive");
            let back = Ray::<f64>::new(DVec3::ZERO, -DVec3::Z);
            assert_eq!(tri.intersect(&TriangleRay::new(&back), f64::INFINITY), None);
            let beside = Ray::<f64>::new(DVec3::new(2.0, 0.0, 0.0), DVec3::Z);
            assert_eq!(tri.intersect(&TriangleRay::new(&beside), f64::INFINITY), None);
        }
    }

    #[test]
    fn degenerate_triangles_never_hit_and_never_nan() {
        let dir = DVec3::new(0.3, 0.2, 1.0).normalize();
        let r = TriangleRay::new(&Ray::<f64>::new(DVec3::ZERO, dir));
        let p = dir * 5.0;
        // A point, a segment containing the hit point, and a triangle seen edge-on.
        assert_eq!(tri64(p.to_array(), p.to_array(), p.to_array()).intersect(&r, f64::INFINITY), None);
        // A segment along the ray: rounding may leave it a sliver of area;
        // touching it anywhere along [4, 6] is right, NaN or elsewhere is not.
        let seg = tri64((p - dir).to_array(), p.to_array(), (p + dir).to_array());
        assert!(seg.intersect(&r, f64::INFINITY).is_none_or(|t| (4.0 - 1e-9..=6.0 + 1e-9).contains(&t)));
        let side = DVec3::new(1.0, 0.0, 0.0).cross(dir).normalize();
        let edge_on = tri64((p - side).to_array(), (p + side).to_array(), (p + dir).to_array());
        let plane_n = edge_on.cross();
        assert!(plane_n.dot(dir).abs() < 1e-12);
        // The ray lies in this triangle's plane: a hit or a miss are both
        // fair (the paper's test may report one), but never a NaN.
        assert!(edge_on.intersect(&r, f64::INFINITY).is_none_or(|t| t.is_finite() && t > 0.0));
        // Vertices a rounding error apart (a sliver with no area in f32).
        let q = Vec3A::new(0.5, 0.25, 4.0);
        let sliver = Triangle::<f32> { v: [q, q + Vec3A::new(1e-30, 0.0, 0.0), q] };
        let r32 = TriangleRay::new(&Ray::<f32>::new(Vec3A::ZERO, q.normalize()));
        assert_eq!(sliver.intersect(&r32, f32::INFINITY), None);
    }

    #[test]
    fn ray_through_shared_edge_never_leaks_in_f32() {
        // Two triangles sharing the diagonal of the unit square at z = 3,
        // rays through points on the diagonal (ends excluded: the square's
        // corners are on the mesh boundary): at least one must report a hit.
        let q = [Vec3A::new(0.0, 0.0, 3.0), Vec3A::new(1.0, 0.0, 3.0), Vec3A::new(1.0, 1.0, 3.0), Vec3A::new(0.0, 1.0, 3.0)];
        let t1 = Triangle::<f32> { v: [q[0], q[1], q[2]] };
        let t2 = Triangle::<f32> { v: [q[0], q[2], q[3]] };
        let origin = Vec3A::new(0.123, 0.456, -0.7);
        for i in 1..1000 {
            let s = i as f32 / 1000.0;
            let target = Vec3A::new(s, s, 3.0);
            let ray = Ray::<f32>::new(origin, (target - origin).normalize());
            let tr = TriangleRay::new(&ray);
            let hits = t1.intersect(&tr, f32::INFINITY).is_some() as u32 + t2.intersect(&tr, f32::INFINITY).is_some() as u32;
            assert!(hits >= 1, "leak at s = {s}");
        }
    }
}
