//! Intersection kernels of the stream renderer: many rays (structure of
//! arrays, `W` per lane group) against each sphere and plane in turn.
//!
//! Plain loops over `[f32; W]` that LLVM vectorises; each lane does exactly
//! the IEEE operations, in the same order, of `SpherePack::intersect` and
//! `Plane::intersect`, so a ray's result does not depend on `W`, on the
//! instruction set the loop was compiled for, or on the other rays of its
//! group (no FMA contraction: Rust never fuses a multiply and an add).

use crate::geometry::PrimId;
use crate::world::World;

/// Rays in structure-of-arrays form; the kernels read the first `n`, a
/// multiple of the lane count.
#[derive(Default)]
pub struct RaySoa {
    pub ox: Vec<f32>,
    pub oy: Vec<f32>,
    pub oz: Vec<f32>,
    pub dx: Vec<f32>,
    pub dy: Vec<f32>,
    pub dz: Vec<f32>,
    /// The primitive each ray starts on (`PrimId::NONE` for primary rays).
    pub skip: Vec<u32>,
}

impl RaySoa {
    /// Makes every array at least `n` long (never shrinks: contents are
    /// overwritten before they are read).
    pub fn grow(&mut self, n: usize) {
        if self.ox.len() < n {
            for v in [
                &mut self.ox,
                &mut self.oy,
                &mut self.oz,
                &mut self.dx,
                &mut self.dy,
                &mut self.dz,
            ] {
                v.resize(n, 0.0);
            }
            self.skip.resize(n, PrimId::NONE.0);
        }
    }
}

/// The spheres and planes of a world, flattened for broadcasting.
pub struct Prims {
    /// Per sphere: centre x, y, z and squared radius.
    spheres: Vec<[f32; 4]>,
    /// Per plane: normal x, y, z and distance.
    planes: Vec<[f32; 4]>,
}

impl Prims {
    pub fn new(world: &World<f32>) -> Self {
        Prims {
            spheres: world
                .spheres
                .iter()
                .map(|s| [s.center.x, s.center.y, s.center.z, s.radius * s.radius])
                .collect(),
            planes: world
                .planes
                .iter()
                .map(|p| [p.normal.x, p.normal.y, p.normal.z, p.distance])
                .collect(),
        }
    }
}

#[inline(always)]
fn lanes<const W: usize>(v: &[f32], at: usize) -> [f32; W] {
    let mut a = [0.0; W];
    a.copy_from_slice(&v[at..at + W]);
    a
}

/// `SpherePack::intersect` for one sphere and lane `l`: hit distance, or
/// +inf where there is none in (0, t_max).
#[inline(always)]
fn sphere_t<const W: usize>(
    s: [f32; 4],
    id: u32,
    o: &[[f32; W]; 3],
    d: &[[f32; W]; 3],
    skip: &[u32; W],
    t_max: f32,
    l: usize,
) -> f32 {
    let r2 = s[3];
    let fx = o[0][l] - s[0];
    let fy = o[1][l] - s[1];
    let fz = o[2][l] - s[2];
    let b = fx * d[0][l] + fy * d[1][l] + fz * d[2][l];
    let lx = fx - d[0][l] * b;
    let ly = fy - d[1][l] * b;
    let lz = fz - d[2][l] * b;
    let disc = r2 - (lx * lx + ly * ly + lz * lz);
    let on_self = skip[l] == id;
    let c = fx * fx + fy * fy + fz * fz - r2;
    // maxps/minps semantics (second operand when unordered), as glam's.
    let root = (if disc > 0.0 { disc } else { 0.0 }).sqrt();
    let q = -b - root.copysign(b);
    let a = c / q;
    let t0 = if a < q { a } else { q };
    let t1 = if a > q { a } else { q };
    let t = if t0 > 0.0 { t0 } else { t1 };
    let t = if on_self { -(b + b) } else { t };
    let valid = (disc >= 0.0 || on_self) & (t > 0.0) & (t < t_max);
    if valid { t } else { f32::INFINITY }
}

/// `Plane::intersect` for lane `l`: +inf where there is no hit in (0, t_max).
#[inline(always)]
fn plane_t<const W: usize>(
    p: [f32; 4],
    id: u32,
    o: &[[f32; W]; 3],
    d: &[[f32; W]; 3],
    skip: &[u32; W],
    t_max: f32,
    l: usize,
) -> f32 {
    let denom = p[0] * d[0][l] + p[1] * d[1][l] + p[2] * d[2][l];
    let t = (p[3] - (p[0] * o[0][l] + p[1] * o[1][l] + p[2] * o[2][l])) / denom;
    let valid = (skip[l] != id) & (t > 0.0) & (t < t_max);
    if valid { t } else { f32::INFINITY }
}

#[inline(always)]
fn load<const W: usize>(rays: &RaySoa, at: usize) -> ([[f32; W]; 3], [[f32; W]; 3], [u32; W]) {
    let o = [
        lanes(&rays.ox, at),
        lanes(&rays.oy, at),
        lanes(&rays.oz, at),
    ];
    let d = [
        lanes(&rays.dx, at),
        lanes(&rays.dy, at),
        lanes(&rays.dz, at),
    ];
    let mut skip = [0; W];
    skip.copy_from_slice(&rays.skip[at..at + W]);
    (o, d, skip)
}

/// Nearest hit of every ray (`t` +inf and `id` `PrimId::NONE` for a miss),
/// with `World::closest_hit`'s tie-breaking: spheres in order, then planes,
/// an earlier primitive kept on equal distance.
#[inline(always)]
pub fn closest_hits<const W: usize>(
    prims: &Prims,
    rays: &RaySoa,
    n: usize,
    t_out: &mut Vec<f32>,
    id_out: &mut Vec<u32>,
) {
    debug_assert_eq!(n % W, 0);
    if t_out.len() < n {
        t_out.resize(n, 0.0);
        id_out.resize(n, 0);
    }
    for at in (0..n).step_by(W) {
        let (o, d, skip) = load::<W>(rays, at);
        let mut best = [f32::INFINITY; W];
        let mut best_id = [PrimId::NONE.0; W];
        for (k, &s) in prims.spheres.iter().enumerate() {
            let id = PrimId::new(PrimId::SPHERE, k as u32).0;
            for l in 0..W {
                // Finite only below `best`.
                let t = sphere_t(s, id, &o, &d, &skip, best[l], l);
                let closer = t < f32::INFINITY;
                best[l] = if closer { t } else { best[l] };
                best_id[l] = if closer { id } else { best_id[l] };
            }
        }
        for (k, &p) in prims.planes.iter().enumerate() {
            let id = PrimId::new(PrimId::PLANE, k as u32).0;
            for l in 0..W {
                let t = plane_t(p, id, &o, &d, &skip, best[l], l);
                let closer = t < f32::INFINITY;
                best[l] = if closer { t } else { best[l] };
                best_id[l] = if closer { id } else { best_id[l] };
            }
        }
        t_out[at..at + W].copy_from_slice(&best);
        id_out[at..at + W].copy_from_slice(&best_id);
    }
}

/// Whether anything lies on each ray before its `t_max` (`World::occluded`),
/// for the rays marked `active` (the others are reported blocked). A lane
/// group stops as soon as all its rays are blocked.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn occluded<const W: usize>(
    prims: &Prims,
    o: [&[f32]; 3],
    d: [&[f32]; 3],
    skip: &[u32],
    t_max: &[f32],
    active: &[bool],
    out: &mut [bool],
) {
    let n = t_max.len();
    debug_assert_eq!(n % W, 0);
    for at in (0..n).step_by(W) {
        let o = [lanes(o[0], at), lanes(o[1], at), lanes(o[2], at)];
        let d = [lanes(d[0], at), lanes(d[1], at), lanes(d[2], at)];
        let mut sk = [0; W];
        sk.copy_from_slice(&skip[at..at + W]);
        let tm: [f32; W] = lanes(t_max, at);
        // Lane masks as u32 (0 or 1): their AND-reduction is a few vector
        // instructions, where one over bools is a chain of scalar tests.
        let act: &[bool; W] = active[at..at + W]
            .try_into()
            .expect("lane group inside the padded queue");
        let mut blocked = [0u32; W];
        for l in 0..W {
            blocked[l] = !act[l] as u32;
        }
        let all = |b: &[u32; W]| b.iter().fold(1, |a, &x| a & x) != 0;
        'group: {
            if all(&blocked) {
                break 'group;
            }
            for (k, &s) in prims.spheres.iter().enumerate() {
                let id = PrimId::new(PrimId::SPHERE, k as u32).0;
                for l in 0..W {
                    blocked[l] |= (sphere_t(s, id, &o, &d, &sk, tm[l], l) < f32::INFINITY) as u32;
                }
                // Checking after every sphere costs more than it saves.
                if k % 4 == 3 && all(&blocked) {
                    break 'group;
                }
            }
            for (k, &p) in prims.planes.iter().enumerate() {
                let id = PrimId::new(PrimId::PLANE, k as u32).0;
                for l in 0..W {
                    blocked[l] |= (plane_t(p, id, &o, &d, &sk, tm[l], l) < f32::INFINITY) as u32;
                }
                if all(&blocked) {
                    break 'group;
                }
            }
        }
        let out: &mut [bool; W] = (&mut out[at..at + W])
            .try_into()
            .expect("lane group inside the padded queue");
        for l in 0..W {
            out[l] = blocked[l] != 0;
        }
    }
}
