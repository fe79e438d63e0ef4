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

/// A triangle as the intersection test wants it: `axes[k]` holds its
/// vertices' coordinates on axis k, vertex i in lane i (48 bytes in `f32`),
/// so the test works on all three vertices at once and picks the axes in
/// the ray's order by index. Kept apart from shading data so traversal
/// touches only these.
#[derive(Clone, Copy, Debug)]
pub struct Triangle<R: Real> {
    axes: [R::V3; 3],
}

/// What shading needs of a triangle once it has been hit, beyond its
/// corners (8 bytes: a big mesh keeps one a triangle; its vertex normals
/// are its mesh's, named by the corners' vertex indices,
/// [`VertexNormals`], and its geometric normal is computed from its
/// vertices, [`Triangle::normal`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TriangleShading {
    pub material: u32,
    /// Index of its vertices' texture coordinates and colours in the
    /// world's `VertexAttrs`, or [`NO_ATTRS`] (a material without textures).
    pub attrs: u32,
}

/// `TriangleShading::attrs` of a triangle whose material has no textures.
pub const NO_ATTRS: u32 = u32::MAX;

/// A mesh's unit vertex normals, at the same indices as its vertex
/// positions (a triangle's corners name both), or none at all when no
/// part of it has normals. A zero normal is unknown: a triangle with one
/// at a corner is shaded flat.
#[derive(Clone, Copy, Debug)]
pub struct VertexNormals<'a, R: Real>(pub &'a [R::V3]);

impl<R: Real> VertexNormals<'_, R> {
    /// Whether the triangle with these corners is shaded smoothly: all
    /// three of its vertex normals are known.
    #[inline(always)]
    pub fn smooth(&self, corners: [u32; 3]) -> bool {
        !self.0.is_empty()
            && corners
                .iter()
                .all(|&i| self.0[i as usize].length_squared() > R::ZERO)
    }

    /// Shading normal at `p` (a point on `tri`, whose corners these are):
    /// its vertex normals interpolated by barycentric weights, or the
    /// geometric normal.
    #[inline(always)]
    pub fn normal_at(&self, tri: &Triangle<R>, corners: [u32; 3], p: R::V3) -> R::V3 {
        if !self.smooth(corners) {
            return tri.normal();
        }
        let ns = corners.map(|i| self.0[i as usize]);
        let [b0, b1, b2] = tri.barycentric(p);
        let s = ns[0] * b0 + ns[1] * b1 + ns[2] * b2;
        let len = s.length();
        if len > R::ZERO && len.is_finite() {
            s * (R::ONE / len)
        } else {
            tri.normal()
        }
    }
}

/// A triangle of indexed vertices: its corners' positions gathered
/// (the world keeps a big mesh this way, 12 bytes a triangle and its
/// shared vertices, rather than as 48-byte [`Triangle`]s).
#[inline(always)]
pub fn gather<R: Real>(positions: &[R::V3], corners: [u32; 3]) -> Triangle<R> {
    Triangle::new(corners.map(|i| positions[i as usize]))
}

/// Every triangle of `corners`, gathered ([`gather`]).
pub fn gather_all<R: Real>(positions: &[R::V3], corners: &[[u32; 3]]) -> Vec<Triangle<R>> {
    corners.iter().map(|&c| gather(positions, c)).collect()
}

/// Per-ray precomputation of the watertight test: the axes in the ray's
/// order (kx, ky, kz), and the origin and shear along them, each splatted
/// over three lanes, so that a triangle's sheared vertices are
/// `A[kx] - Sx * A[kz]`, `A[ky] - Sy * A[kz]`, `Sz * A[kz]` (A = vertex -
/// origin), rounded as in the paper.
#[derive(Clone, Copy, Debug)]
pub struct TriangleRay<R: Real> {
    /// kx, ky, kz: each < 3.
    k: [usize; 3],
    /// Origin on kx, ky, kz.
    o: [R::V3; 3],
    /// Sx, Sy, Sz.
    s: [R::V3; 3],
}

impl<R: Real> TriangleRay<R> {
    #[inline(always)]
    pub fn new(ray: &Ray<R>) -> Self {
        let d = [ray.dir.x(), ray.dir.y(), ray.dir.z()];
        let a = d.map(|c| c.abs());
        // kz: the dominant axis; kx, ky the next two cyclically, swapped when
        // d[kz] < 0 to keep the winding (and so the sign of det) consistent.
        let kz = if a[0] >= a[1] && a[0] >= a[2] {
            0
        } else if a[1] >= a[2] {
            1
        } else {
            2
        };
        let (mut kx, mut ky) = ((kz + 1) % 3, (kz + 2) % 3);
        if d[kz] < R::ZERO {
            std::mem::swap(&mut kx, &mut ky);
        }
        let sz = R::ONE / d[kz];
        let (sx, sy) = (d[kx] * sz, d[ky] * sz);
        let o = [ray.origin.x(), ray.origin.y(), ray.origin.z()];
        TriangleRay {
            k: [kx, ky, kz],
            o: [kx, ky, kz].map(|k| R::V3::splat(o[k])),
            s: [sx, sy, sz].map(R::V3::splat),
        }
    }
}

impl<R: Real> Triangle<R> {
    pub fn new(v: [R::V3; 3]) -> Self {
        Triangle {
            axes: [
                R::V3::new(v[0].x(), v[1].x(), v[2].x()),
                R::V3::new(v[0].y(), v[1].y(), v[2].y()),
                R::V3::new(v[0].z(), v[1].z(), v[2].z()),
            ],
        }
    }

    pub fn vertices(&self) -> [R::V3; 3] {
        let [xs, ys, zs] = self.axes;
        [
            R::V3::new(xs.x(), ys.x(), zs.x()),
            R::V3::new(xs.y(), ys.y(), zs.y()),
            R::V3::new(xs.z(), ys.z(), zs.z()),
        ]
    }

    /// Distance to the hit in (0, t_max), or `None`. Degenerate triangles
    /// (zero area, or seen exactly edge-on) are never hit and never give NaN.
    #[inline(always)]
    pub fn intersect(&self, r: &TriangleRay<R>, t_max: R) -> Option<R> {
        self.distance(r, t_max).filter(|&t| t < t_max)
    }

    /// Distance to the hit, positive and finite, if it may be at most
    /// `t_max` (see [`finish`]: the distance itself does not depend on
    /// `t_max`, and every hit at most `t_max` away is returned), or `None`.
    #[inline(always)]
    pub fn distance(&self, r: &TriangleRay<R>, t_max: R) -> Option<R> {
        // Vertices relative to the origin (lane i: vertex i), then sheared.
        // SAFETY: `TriangleRay::new` makes every entry of `k` 0, 1 or 2.
        let axis = |i: usize| unsafe { *self.axes.get_unchecked(r.k[i]) };
        let dz = axis(2) - r.o[2];
        let x = (axis(0) - r.o[0]) - dz * r.s[0]; // (ax, bx, cx)
        let y = (axis(1) - r.o[1]) - dz * r.s[1]; // (ay, by, cy)
        // Edge functions (u, v, w) = (cx by - cy bx, ax cy - ay cx, bx ay - by ax).
        let x1 = R::V3::new(x.z(), x.x(), x.y());
        let y1 = R::V3::new(y.y(), y.z(), y.x());
        let y2 = R::V3::new(y.z(), y.x(), y.y());
        let x2 = R::V3::new(x.y(), x.z(), x.x());
        let mut uvw = x1 * y1 - y2 * x2;
        if uvw.abs().min_element() == R::ZERO {
            // On (or within rounding of) an edge: the sign decides which of
            // the two neighbours owns the ray, so get it exactly. Products of
            // f32 are exact in f64; in f64 this is the same computation.
            let e = |p: R, q: R, s: R, t: R| p.to_f64() * q.to_f64() - s.to_f64() * t.to_f64();
            let (ax, bx, cx) = (x.x(), x.y(), x.z());
            let (ay, by, cy) = (y.x(), y.y(), y.z());
            let (u, v, w) = (e(cx, by, cy, bx), e(ax, cy, ay, cx), e(bx, ay, by, ax));
            if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
                return None;
            }
            uvw = R::V3::new(R::from_f64(u), R::from_f64(v), R::from_f64(w));
        } else if uvw.min_element() < R::ZERO && uvw.max_element() > R::ZERO {
            return None;
        }
        let det = uvw.x() + uvw.y() + uvw.z();
        if det == R::ZERO {
            return None;
        }
        let z = dz * r.s[2]; // (az, bz, cz)
        let t_scaled = uvw.dot(z);
        finish(t_scaled, det, t_max)
    }

    /// Unnormalised geometric normal (e1 x e2): outward for counter-clockwise winding.
    #[inline(always)]
    pub fn cross(&self) -> R::V3 {
        let v = self.vertices();
        (v[1] - v[0]).cross(v[2] - v[0])
    }

    /// Unit geometric normal, outward by the winding (a triangle with
    /// area, as every stored one has).
    #[inline(always)]
    pub fn normal(&self) -> R::V3 {
        let c = self.cross();
        c * (R::ONE / c.length())
    }
}

/// The last step of the test, given `t_scaled` and a non-zero `det`: the
/// distance `t_scaled / det` if it is positive and finite and may be at
/// most `t_max`. Shared by the scalar and the 4-wide forms, so that both
/// round alike. The test before the division is conservative (its bound is
/// widened by 2^-20, well above the rounding of `t_max * det` and of the
/// quotient), so every distance at most `t_max` is returned, and a returned
/// distance may exceed `t_max`: callers compare. A triangle's distance thus
/// depends on it and the ray alone, and the nearest hit (ties to the lower
/// [`PrimId`](crate::geometry::PrimId)) is the same whatever order the
/// triangles are met in: by single rays, by packets or by brute force.
#[inline(always)]
pub fn finish<R: Real>(t_scaled: R, det: R, t_max: R) -> Option<R> {
    let bound = t_max * det * R::from_f64(1.0 + 1.0 / (1u64 << 20) as f64);
    let may = if det > R::ZERO {
        t_scaled > R::ZERO && t_scaled <= bound
    } else {
        t_scaled < R::ZERO && t_scaled >= bound
    };
    if !may {
        return None;
    }
    let t = t_scaled / det;
    (t > R::ZERO && t < R::INFINITY).then_some(t)
}

/// Four triangles in the form the 4-wide (SSE) pass of the test wants:
/// `rows[3 * i + a]` holds vertex i's coordinate on axis a, triangle j in
/// lane j (`f32` only; the BVH keeps these in leaf order, see `bvh/build.rs`),
/// and what each lane is to the caller (the BVH: its packed `PrimId`, so a
/// hit needs no second lookup; `u32::MAX` for an unused lane).
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Triangle4 {
    pub rows: [[f32; 4]; 9],
    pub ids: [u32; 4],
}

impl Default for Triangle4 {
    fn default() -> Self {
        Triangle4 {
            rows: [[0.0; 4]; 9],
            ids: [u32::MAX; 4],
        }
    }
}

impl Triangle4 {
    /// Puts `t` into lane `j` (its id is left to the caller).
    pub fn set(&mut self, j: usize, t: &Triangle<f32>) {
        for (i, v) in t.vertices().iter().enumerate() {
            for a in 0..3 {
                self.rows[3 * i + a][j] = v[a];
            }
        }
    }

    /// The triangle in lane `j`, as [`Triangle4::set`] was given it.
    #[inline]
    pub fn triangle(&self, j: usize) -> Triangle<f32> {
        let r =
            |i: usize| glam::Vec3A::new(self.rows[i][j], self.rows[i + 1][j], self.rows[i + 2][j]);
        Triangle::new([r(0), r(3), r(6)])
    }
}

/// What the 4-wide pass leaves to finish lane by lane: `candidates`, lanes
/// whose edge functions agree in sign and whose `det` is non-zero (they hit
/// if [`finish`]`(t_scaled, det, t_max)` gives a distance within the limit); `exact`, lanes for the
/// scalar [`Triangle::intersect`] (an edge function is zero, so it needs the
/// exact re-evaluation, or some value is NaN). All other lanes miss.
#[derive(Clone, Copy, Debug)]
pub struct Edges4 {
    pub candidates: u32,
    pub exact: u32,
    pub t_scaled: [f32; 4],
    pub det: [f32; 4],
}

#[cfg(target_arch = "x86_64")]
impl TriangleRay<f32> {
    /// The watertight test of four triangles at once, up to the division,
    /// for the lanes in `lanes` (bit j: lane j). Each lane does exactly the
    /// IEEE operations of [`Triangle::intersect`] in the same order (the
    /// products commute), so it rounds alike; where that test would branch
    /// on NaN or take its exact path, the lane is left to it.
    #[inline(always)]
    pub fn edges4(&self, p: &Triangle4, lanes: u32) -> Edges4 {
        use std::arch::x86_64::*;
        // SAFETY: SSE is part of x86_64; `k` entries are < 3, so the rows
        // indexed are < 9; `Triangle4` is 16-byte aligned, so each row is.
        unsafe {
            let row = |v: usize, a: usize| {
                _mm_load_ps(
                    p.rows
                        .get_unchecked(3 * v + *self.k.get_unchecked(a))
                        .as_ptr(),
                )
            };
            let (ox, oy, oz) = (
                _mm_set1_ps(self.o[0].x),
                _mm_set1_ps(self.o[1].x),
                _mm_set1_ps(self.o[2].x),
            );
            let (sx, sy, sz) = (
                _mm_set1_ps(self.s[0].x),
                _mm_set1_ps(self.s[1].x),
                _mm_set1_ps(self.s[2].x),
            );
            let dz = [0, 1, 2].map(|v| _mm_sub_ps(row(v, 2), oz));
            let x = [0, 1, 2].map(|v| _mm_sub_ps(_mm_sub_ps(row(v, 0), ox), _mm_mul_ps(dz[v], sx)));
            let y = [0, 1, 2].map(|v| _mm_sub_ps(_mm_sub_ps(row(v, 1), oy), _mm_mul_ps(dz[v], sy)));
            // (u, v, w) = (cx by - cy bx, ax cy - ay cx, bx ay - by ax).
            let u = _mm_sub_ps(_mm_mul_ps(x[2], y[1]), _mm_mul_ps(y[2], x[1]));
            let v = _mm_sub_ps(_mm_mul_ps(x[0], y[2]), _mm_mul_ps(y[0], x[2]));
            let w = _mm_sub_ps(_mm_mul_ps(x[1], y[0]), _mm_mul_ps(y[1], x[0]));
            let det = _mm_add_ps(_mm_add_ps(u, v), w);
            // uvw . z, z = dz * sz, summed as glam's dot: (u az + v bz) + w cz.
            let zu = _mm_mul_ps(u, _mm_mul_ps(dz[0], sz));
            let zv = _mm_mul_ps(v, _mm_mul_ps(dz[1], sz));
            let zw = _mm_mul_ps(w, _mm_mul_ps(dz[2], sz));
            let t_scaled = _mm_add_ps(_mm_add_ps(zu, zv), zw);
            let zero = _mm_setzero_ps();
            macro_rules! any {
                ($cmp:ident) => {
                    _mm_or_ps(_mm_or_ps($cmp(u, zero), $cmp(v, zero)), $cmp(w, zero))
                };
            }
            let on_edge = any!(_mm_cmpeq_ps);
            let nan = _mm_or_ps(
                _mm_or_ps(_mm_cmpunord_ps(u, v), _mm_cmpunord_ps(w, det)),
                _mm_cmpunord_ps(t_scaled, t_scaled),
            );
            let exact = _mm_or_ps(on_edge, nan);
            let mixed = _mm_and_ps(any!(_mm_cmplt_ps), any!(_mm_cmpgt_ps));
            let out = _mm_or_ps(_mm_or_ps(mixed, _mm_cmpeq_ps(det, zero)), exact);
            let mut e = Edges4 {
                candidates: !(_mm_movemask_ps(out) as u32) & lanes,
                exact: _mm_movemask_ps(exact) as u32 & lanes,
                t_scaled: [0.0; 4],
                det: [0.0; 4],
            };
            _mm_storeu_ps(e.t_scaled.as_mut_ptr(), t_scaled);
            _mm_storeu_ps(e.det.as_mut_ptr(), det);
            e
        }
    }
}

impl<R: Real> Triangle<R> {
    /// Barycentric weights of `p` (a point on the triangle) for its three
    /// vertices, clamped so points rounded just outside stay sane.
    #[inline(always)]
    pub fn barycentric(&self, p: R::V3) -> [R; 3] {
        let v = self.vertices();
        let e1 = v[1] - v[0];
        let e2 = v[2] - v[0];
        let d = p - v[0];
        let n = e1.cross(e2);
        let nn = n.length_squared();
        // p = v0 + b1 e1 + b2 e2.
        let b1 = (d.cross(e2).dot(n) / nn).max(R::ZERO).min(R::ONE);
        let b2 = (e1.cross(d).dot(n) / nn).max(R::ZERO).min(R::ONE - b1);
        [R::ONE - b1 - b2, b1, b2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DVec3, Vec3A};

    /// A big mesh keeps its corners (12 bytes) and one of these a
    /// triangle (docs/meshes.md, "Big scenes"); small ones their
    /// `Triangle`s too (48 in `f32`).
    #[test]
    fn a_triangle_takes_20_bytes_beside_its_vertices() {
        assert_eq!(std::mem::size_of::<Triangle<f32>>(), 48);
        assert_eq!(std::mem::size_of::<TriangleShading>(), 8);
    }

    /// The shading normal interpolates the normals its corners name, and
    /// a triangle with an unknown (zero) one, or of a mesh without
    /// normals, is flat: its geometric normal.
    #[test]
    fn vertex_normals_are_read_by_corner() {
        let tri = Triangle::<f32>::new([Vec3A::ZERO, Vec3A::X, Vec3A::Y]);
        let normals = [
            Vec3A::Z,
            Vec3A::X,
            Vec3A::new(0.0, 0.6, 0.8),
            Vec3A::Y,
            Vec3A::ZERO,
        ];
        let ns = VertexNormals::<f32>(&normals);
        assert_eq!(
            ns.normal_at(&tri, [3, 3, 3], Vec3A::new(0.2, 0.2, 0.0)),
            Vec3A::Y
        );
        let n = ns.normal_at(&tri, [0, 0, 2], Vec3A::new(0.0, 0.5, 0.0));
        let want = (Vec3A::Z * 0.5 + Vec3A::new(0.0, 0.6, 0.8) * 0.5).normalize();
        assert!((n - want).length() < 1e-6, "{n}");
        assert!(ns.smooth([0, 1, 2]) && !ns.smooth([0, 4, 2]));
        assert_eq!(
            ns.normal_at(&tri, [0, 4, 2], Vec3A::new(0.2, 0.2, 0.0)),
            Vec3A::Z
        );
        let none = VertexNormals::<f32>(&[]);
        assert!(!none.smooth([0, 1, 2]));
        assert_eq!(
            none.normal_at(&tri, [0, 1, 2], Vec3A::new(0.2, 0.2, 0.0)),
            Vec3A::Z
        );
        assert_eq!(tri.normal(), Vec3A::Z);
        let positions = [Vec3A::ZERO, Vec3A::Y, Vec3A::X];
        let t = gather::<f32>(&positions, [0, 2, 1]);
        assert_eq!(t.vertices(), tri.vertices());
    }

    fn tri64(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> Triangle<f64> {
        Triangle::new([
            DVec3::from_array(a),
            DVec3::from_array(b),
            DVec3::from_array(c),
        ])
    }

    // Hits and misses of either winding, scalar and 4-wide: tests/geometry.rs.

    #[test]
    fn degenerate_triangles_never_hit_and_never_nan() {
        let dir = DVec3::new(0.3, 0.2, 1.0).normalize();
        let r = TriangleRay::new(&Ray::<f64>::new(DVec3::ZERO, dir));
        let p = dir * 5.0;
        // A point, a segment containing the hit point, and a triangle seen edge-on.
        assert_eq!(
            tri64(p.to_array(), p.to_array(), p.to_array()).intersect(&r, f64::INFINITY),
            None
        );
        // A segment along the ray: rounding may leave it a sliver of area;
        // touching it anywhere along [4, 6] is right, NaN or elsewhere is not.
        let seg = tri64((p - dir).to_array(), p.to_array(), (p + dir).to_array());
        assert!(
            seg.intersect(&r, f64::INFINITY)
                .is_none_or(|t| (4.0 - 1e-9..=6.0 + 1e-9).contains(&t))
        );
        let side = DVec3::new(1.0, 0.0, 0.0).cross(dir).normalize();
        let edge_on = tri64(
            (p - side).to_array(),
            (p + side).to_array(),
            (p + dir).to_array(),
        );
        let plane_n = edge_on.cross();
        assert!(plane_n.dot(dir).abs() < 1e-12);
        // The ray lies in this triangle's plane: a hit or a miss are both
        // fair (the paper's test may report one), but never a NaN.
        assert!(
            edge_on
                .intersect(&r, f64::INFINITY)
                .is_none_or(|t| t.is_finite() && t > 0.0)
        );
        // Vertices a rounding error apart (a sliver with no area in f32).
        let q = Vec3A::new(0.5, 0.25, 4.0);
        let sliver = Triangle::<f32>::new([q, q + Vec3A::new(1e-30, 0.0, 0.0), q]);
        let r32 = TriangleRay::new(&Ray::<f32>::new(Vec3A::ZERO, q.normalize()));
        assert_eq!(sliver.intersect(&r32, f32::INFINITY), None);
    }

    /// The 4-wide pass, finished lane by lane, gives the scalar test's
    /// result bit for bit: random triangles, slivers, points, vertices on a
    /// small grid (rays through shared edges and vertices), huge coordinates.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn four_wide_test_matches_the_scalar_one_bit_for_bit() {
        let h = |i: u32| crate::sampling::hash_u32(i) as f32 / u32::MAX as f32 - 0.5;
        let mut n = 0u32;
        let mut hits = 0;
        for i in 0..40_000u32 {
            let mut p = Triangle4::default();
            let tris: Vec<Triangle<f32>> = (0..4u32)
                .map(|j| {
                    let k = (i * 4 + j) * 16;
                    let v = |a: u32| match i % 4 {
                        0 => Vec3A::new(h(k + a), h(k + a + 1), h(k + a + 2) + 2.0),
                        1 => Vec3A::new(
                            (h(k + a) * 8.0).round() / 4.0,
                            (h(k + a + 1) * 8.0).round() / 4.0,
                            2.0,
                        ),
                        2 => Vec3A::new(h(k), h(k + 1), 2.0) + Vec3A::splat(h(k + a) * 1e-6),
                        _ => Vec3A::new(h(k + a), h(k + a + 1), h(k + a + 2)) * 3e19,
                    };
                    Triangle::new([v(3), v(6), v(9)])
                })
                .collect();
            for (j, t) in tris.iter().enumerate() {
                p.set(j, t);
            }
            let o = Vec3A::new(h(i * 7 + 1) * 0.1, h(i * 7 + 2) * 0.1, h(i * 7 + 3) * 0.1);
            let target = if i % 4 == 1 {
                Vec3A::new(
                    (h(i * 7 + 4) * 8.0).round() / 8.0,
                    (h(i * 7 + 5) * 8.0).round() / 8.0,
                    2.0,
                )
            } else {
                Vec3A::new(h(i * 7 + 4), h(i * 7 + 5), 2.0)
            };
            let r = TriangleRay::new(&Ray::<f32>::new(o, (target - o).normalize()));
            let t_max = if i % 3 == 0 {
                f32::INFINITY
            } else {
                2.0 + h(i * 7 + 6)
            };
            let lanes = if i % 5 == 0 { 0b0111 } else { 0b1111 };
            let e = r.edges4(&p, lanes);
            assert_eq!(e.candidates & e.exact, 0);
            for (j, t) in tris.iter().enumerate() {
                let want = if (lanes >> j) & 1 != 0 {
                    t.intersect(&r, t_max)
                } else {
                    None
                };
                let got = if (e.exact >> j) & 1 != 0 {
                    n += 1;
                    t.intersect(&r, t_max)
                } else if (e.candidates >> j) & 1 != 0 {
                    finish(e.t_scaled[j], e.det[j], t_max).filter(|&t| t < t_max)
                } else {
                    None
                };
                assert_eq!(
                    got.map(f32::to_bits),
                    want.map(f32::to_bits),
                    "case {i} lane {j}"
                );
                hits += want.is_some() as u32;
            }
        }
        assert!(n > 100 && hits > 3_000, "{n} exact lanes, {hits} hits");
    }

    #[test]
    fn ray_through_shared_edge_never_leaks_in_f32() {
        // Two triangles sharing the diagonal of the unit square at z = 3,
        // rays through points on the diagonal (ends excluded: the square's
        // corners are on the mesh boundary): at least one must report a hit.
        let q = [
            Vec3A::new(0.0, 0.0, 3.0),
            Vec3A::new(1.0, 0.0, 3.0),
            Vec3A::new(1.0, 1.0, 3.0),
            Vec3A::new(0.0, 1.0, 3.0),
        ];
        let t1 = Triangle::<f32>::new([q[0], q[1], q[2]]);
        let t2 = Triangle::<f32>::new([q[0], q[2], q[3]]);
        let origin = Vec3A::new(0.123, 0.456, -0.7);
        for i in 1..1000 {
            let s = i as f32 / 1000.0;
            let target = Vec3A::new(s, s, 3.0);
            let ray = Ray::<f32>::new(origin, (target - origin).normalize());
            let tr = TriangleRay::new(&ray);
            let hits = t1.intersect(&tr, f32::INFINITY).is_some() as u32
                + t2.intersect(&tr, f32::INFINITY).is_some() as u32;
            assert!(hits >= 1, "leak at s = {s}");
        }
    }
}
