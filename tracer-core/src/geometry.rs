//! Primitives and their ray intersection tests.
//!
//! Each kind lives in its own array (no union of every kind per object), so a
//! scene pays only for the kinds it has. A primitive is named by a [`PrimId`]:
//! kind in the top bits, index below.

use crate::math::{Lanes4, Ray, Real, Vector3};

/// Kind and index of a primitive, packed in 32 bits (the GPU uses the same packing).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PrimId(pub u32);

impl PrimId {
    pub const NONE: PrimId = PrimId(u32::MAX);
    const KIND_SHIFT: u32 = 28;
    pub const SPHERE: u32 = 0;
    pub const PLANE: u32 = 1;
    /// Index into `World::triangles` (see `triangle.rs`).
    pub const TRIANGLE: u32 = 2;
    /// In a world's tree only: index into `World::instances.list` (the top
    /// level of the two-level tree, `world/instances.rs`); never a hit's id.
    pub const INSTANCE: u32 = 3;
    /// A hit on an instanced triangle: the instance's first id plus the
    /// triangle's index in its mesh (`world/instances.rs`).
    pub const INSTANCE_TRIANGLE: u32 = 4;

    #[inline(always)]
    pub fn new(kind: u32, index: u32) -> Self {
        debug_assert!(index < (1 << Self::KIND_SHIFT));
        PrimId((kind << Self::KIND_SHIFT) | index)
    }
    #[inline(always)]
    pub fn kind(self) -> u32 {
        self.0 >> Self::KIND_SHIFT
    }
    #[inline(always)]
    pub fn index(self) -> usize {
        (self.0 & ((1 << Self::KIND_SHIFT) - 1)) as usize
    }

    /// The order of closest-hit queries: a hit at `t` on `self` replaces the
    /// nearest so far (`best` on `found`) if it is nearer, or as near on a
    /// lower id. A total order, so the answer does not depend on the order
    /// in which primitives are tested (tree, packets, brute force).
    #[inline(always)]
    pub fn nearer<R: PartialOrd>(self, t: R, best: R, found: PrimId) -> bool {
        t < best || (t == best && self.0 < found.0)
    }
}

#[derive(Clone, Copy, Debug)]
pub struct Sphere<R: Real> {
    pub center: R::V3,
    pub radius: R,
    pub material: u32,
}

/// The plane { p : dot(p, normal) = distance }, `normal` of unit length; its
/// outward side is the one `normal` points to.
#[derive(Clone, Copy, Debug)]
pub struct Plane<R: Real> {
    pub normal: R::V3,
    pub distance: R,
    pub material: u32,
}

impl<R: Real> Sphere<R> {
    /// Nearest hit in (0, t_max), or `None`.
    ///
    /// `from_surface` says the ray starts on this very sphere (a secondary ray
    /// from one of its points): then one root is 0 by construction and the
    /// other is -2 (o - c).d, exact and free of the cancellation that makes
    /// the general test unreliable near the surface of large spheres. A ray
    /// leaving the surface outwards can never hit the sphere again.
    #[inline(always)]
    pub fn intersect(&self, ray: &Ray<R>, t_max: R, from_surface: bool) -> Option<R> {
        let f = ray.origin - self.center;
        let b = f.dot(ray.dir);
        if from_surface {
            let t = -R::TWO * b;
            return (t > R::ZERO && t < t_max).then_some(t);
        }
        // Discriminant from the perpendicular distance (Ray Tracing Gems ch. 7):
        // r^2 - |f - (f.d)d|^2 does not cancel catastrophically when the ray
        // origin is far from a small sphere.
        let l = f - ray.dir * b;
        let r = self.radius;
        let disc = r * r - l.length_squared();
        if !(disc >= R::ZERO) {
            return None;
        }
        let c = f.length_squared() - r * r;
        // q has no cancellation (both terms share a sign); the other root is c/q.
        let q = -b - disc.sqrt().copysign(b);
        let (t0, t1) = {
            let a = c / q;
            if a < q { (a, q) } else { (q, a) }
        };
        if t0 > R::ZERO && t0 < t_max {
            Some(t0)
        } else if t1 > R::ZERO && t1 < t_max {
            Some(t1)
        } else {
            None
        }
    }

    /// Outward unit normal and a hit point snapped back onto the surface.
    #[inline(always)]
    pub fn surface(&self, p: R::V3) -> (R::V3, R::V3) {
        let d = p - self.center;
        let n = d * (R::ONE / d.length());
        (self.center + n * self.radius, n)
    }
}

/// Four spheres in structure-of-arrays form, tested against one ray at once
/// (SSE lanes in f32). Same arithmetic as [`Sphere::intersect`], lane-wise.
/// Unused lanes have a NaN centre, which fails every comparison.
#[derive(Clone, Copy, Debug)]
pub struct SpherePack<R: Real> {
    pub cx: R::V4,
    pub cy: R::V4,
    pub cz: R::V4,
    /// Squared radii.
    pub r2: R::V4,
}

impl<R: Real> SpherePack<R> {
    /// Packs spheres four by four; pack `i` lane `j` is sphere `4i + j`.
    pub fn pack(spheres: &[Sphere<R>]) -> Vec<Self> {
        spheres
            .chunks(4)
            .map(|c| {
                let nan = R::from_f64(f64::NAN);
                let lane = |f: &dyn Fn(&Sphere<R>) -> R, pad: R| {
                    let mut a = [pad; 4];
                    for (j, s) in c.iter().enumerate() {
                        a[j] = f(s);
                    }
                    R::V4::from_array(a)
                };
                SpherePack {
                    cx: lane(&|s| s.center.x(), nan),
                    cy: lane(&|s| s.center.y(), nan),
                    cz: lane(&|s| s.center.z(), nan),
                    r2: lane(&|s| s.radius * s.radius, R::ZERO),
                }
            })
            .collect()
    }

    /// Per-lane hit distance, +inf where there is no hit in (0, t_max).
    /// `self_lane` is the lane of the sphere the ray starts on, if it is in this pack.
    #[inline(always)]
    pub fn intersect(&self, o: [R::V4; 3], d: [R::V4; 3], t_max: R, self_lane: usize) -> R::V4 {
        let zero = R::V4::splat(R::ZERO);
        let inf = R::V4::splat(R::INFINITY);
        let fx = o[0] - self.cx;
        let fy = o[1] - self.cy;
        let fz = o[2] - self.cz;
        let b = fx * d[0] + fy * d[1] + fz * d[2];
        let lx = fx - d[0] * b;
        let ly = fy - d[1] * b;
        let lz = fz - d[2] * b;
        // r^2 - |l|^2: no cancellation against a large b^2 (see Sphere::intersect).
        let disc = self.r2 - (lx * lx + ly * ly + lz * lz);
        let on_self = R::V4::lane(self_lane);
        // Most rays miss most spheres: leave before the square root and division.
        let candidate = disc.cmpge(zero) | on_self;
        if R::V4::bitmask(candidate) == 0 {
            return inf;
        }
        let c = fx * fx + fy * fy + fz * fz - self.r2;
        let q = -b - disc.max(zero).sqrt().copysign(b);
        let a = c / q;
        let (t0, t1) = (a.min(q), a.max(q));
        let t = R::V4::select(t0.cmpgt(zero), t0, t1);
        // The sphere the ray starts on: only the far root -2 (o-c).d.
        let t = R::V4::select(on_self, -(b + b), t);
        let valid = candidate & t.cmpgt(zero) & t.cmplt(R::V4::splat(t_max));
        R::V4::select(valid, t, R::V4::splat(R::INFINITY))
    }
}

/// Four planes in structure-of-arrays form, for the loops that test a ray
/// against every plane (planes are unbounded, so they stay outside the
/// tree): one division for four planes. Each lane does `Plane::intersect`'s
/// operations in its order, so a lane's distance is the scalar test's, bit
/// for bit.
#[derive(Clone, Copy, Debug)]
pub struct PlanePack<R: Real> {
    pub nx: R::V4,
    pub ny: R::V4,
    pub nz: R::V4,
    pub distance: R::V4,
}

impl<R: Real> PlanePack<R> {
    /// Packs planes four by four; pack `i` lane `j` is plane `4i + j`. A
    /// missing plane's lanes are zero: 0/0, which no test accepts.
    pub fn pack(planes: &[Plane<R>]) -> Vec<Self> {
        planes
            .chunks(4)
            .map(|c| {
                let lane = |f: &dyn Fn(&Plane<R>) -> R| {
                    let mut a = [R::ZERO; 4];
                    for (j, p) in c.iter().enumerate() {
                        a[j] = f(p);
                    }
                    R::V4::from_array(a)
                };
                PlanePack {
                    nx: lane(&|p| p.normal.x()),
                    ny: lane(&|p| p.normal.y()),
                    nz: lane(&|p| p.normal.z()),
                    distance: lane(&|p| p.distance),
                }
            })
            .collect()
    }

    /// Per-lane hit distance, +inf where there is none in (0, t_max) or
    /// where the lane is `self_lane` (the plane the ray starts on; 4: none).
    #[inline(always)]
    pub fn intersect(&self, o: [R::V4; 3], d: [R::V4; 3], t_max: R, self_lane: usize) -> R::V4 {
        let denom = self.nx * d[0] + self.ny * d[1] + self.nz * d[2];
        let t = (self.distance - (self.nx * o[0] + self.ny * o[1] + self.nz * o[2])) / denom;
        // A ray parallel to a plane gives +-inf or NaN: both fail the test.
        let inf = R::V4::splat(R::INFINITY);
        let valid = t.cmpgt(R::V4::splat(R::ZERO)) & t.cmplt(R::V4::splat(t_max));
        R::V4::select(R::V4::lane(self_lane), inf, R::V4::select(valid, t, inf))
    }
}

impl<R: Real> Plane<R> {
    /// Nearest hit in (0, t_max). A ray starting on the plane never hits it again.
    #[inline(always)]
    pub fn intersect(&self, ray: &Ray<R>, t_max: R, from_surface: bool) -> Option<R> {
        if from_surface {
            return None;
        }
        let denom = self.normal.dot(ray.dir);
        let t = (self.distance - self.normal.dot(ray.origin)) / denom;
        // A ray parallel to the plane gives +-inf or NaN: both fail the test.
        (t > R::ZERO && t < t_max).then_some(t)
    }

    /// Outward unit normal and the hit point projected onto the plane.
    #[inline(always)]
    pub fn surface(&self, p: R::V3) -> (R::V3, R::V3) {
        let off = self.normal.dot(p) - self.distance;
        (p - self.normal * off, self.normal)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packs_agree_with_the_scalar_test() {
        let spheres: Vec<Sphere<f32>> = (0..7)
            .map(|i| Sphere {
                center: glam::Vec3A::new(i as f32 - 3.0, 0.3 * i as f32, 5.0 + i as f32),
                radius: 0.4 + 0.1 * i as f32,
                material: 0,
            })
            .collect();
        let packs = SpherePack::pack(&spheres);
        assert_eq!(packs.len(), 2);
        let mut hits = 0;
        for k in 0..2000u32 {
            let a = k as f32 * 0.01;
            let dir = glam::Vec3A::new(a.sin() * 0.4, (a * 1.7).cos() * 0.3, 1.0).normalize();
            let ray = Ray::<f32>::new(glam::Vec3A::ZERO, dir);
            let o = [glam::Vec4::splat(0.0); 3];
            let d = [
                glam::Vec4::splat(dir.x),
                glam::Vec4::splat(dir.y),
                glam::Vec4::splat(dir.z),
            ];
            for (i, s) in spheres.iter().enumerate() {
                let want = s.intersect(&ray, 100.0, false);
                let got = packs[i / 4].intersect(o, d, 100.0, usize::MAX).to_array()[i % 4];
                match want {
                    Some(t) => {
                        hits += 1;
                        assert!((t - got).abs() <= 1e-5 * t, "sphere {i}: {t} vs {got}")
                    }
                    None => assert_eq!(got, f32::INFINITY, "sphere {i}"),
                }
            }
        }
        assert!(hits > 300, "the rays should hit something: {hits}");
    }

    #[test]
    fn plane_packs_give_the_scalar_tests_bits() {
        // Six planes (two packs, the second half empty), rays from inside
        // and outside the box they make, every plane the skipped one in turn.
        let planes: Vec<Plane<f32>> = [
            ([0.0, 1.0, 0.0], 0.0),
            ([0.0, -1.0, 0.0], -2.0),
            ([0.0, 0.0, -1.0], -1.0),
            ([1.0, 0.0, 0.0], -1.0),
            ([-0.6, 0.0, 0.8], -1.3),
            ([0.267, 0.535, 0.802], 0.7),
        ]
        .iter()
        .map(|&(n, d)| Plane {
            normal: glam::Vec3A::from_array(n),
            distance: d,
            material: 0,
        })
        .collect();
        let packs = PlanePack::pack(&planes);
        assert_eq!(packs.len(), 2);
        let (mut hits, mut misses) = (0, 0);
        for k in 0..3000u32 {
            let a = k as f32 * 0.013;
            let dir = glam::Vec3A::new(a.sin(), (a * 1.7).cos(), (a * 0.3).cos() - 0.5).normalize();
            let origin = glam::Vec3A::new((a * 2.3).sin() * 3.0, 1.0, (a * 0.7).cos());
            let ray = Ray::<f32>::new(origin, dir);
            let s = |v: glam::Vec3A| [v.x, v.y, v.z].map(|x: f32| glam::Vec4::new(x, x, x, x));
            let t_max = if k % 3 == 0 { 2.5 } else { f32::INFINITY };
            for skip in 0..=planes.len() {
                for (i, p) in planes.iter().enumerate() {
                    let want = p.intersect(&ray, t_max, i == skip);
                    let lane = if skip / 4 == i / 4 { skip % 4 } else { 4 };
                    let got = packs[i / 4]
                        .intersect(s(origin), s(dir), t_max, lane)
                        .to_array()[i % 4];
                    match want {
                        Some(t) => {
                            hits += 1;
                            assert_eq!(t.to_bits(), got.to_bits(), "plane {i}")
                        }
                        None => {
                            misses += 1;
                            assert_eq!(got, f32::INFINITY, "plane {i}")
                        }
                    }
                }
            }
        }
        assert!(
            hits > 10_000 && misses > 10_000,
            "{hits} hits, {misses} misses"
        );
    }

    // The scalar sphere and plane tests against a table of cases, with the
    // packs, the SIMD lanes and the world: tests/geometry.rs.
}
