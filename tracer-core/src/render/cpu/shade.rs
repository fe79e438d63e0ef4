//! Lane-wise Whitted shading for the stream renderer: the one SIMD twin of
//! the shading step (`render::step`): [`shade_lanes`] is `step::shade`'s
//! local part (`Surface::at`, `Surface::light_term`, the directions of
//! `Surface::add_secondary`) with the arithmetic (same IEEE operations in the same
//! order, so the same bits), over `W` hits at a time in structure-of-arrays
//! form. Spawning rays, which appends to queues, is left to a scalar pass
//! ([`super::stream`]) that reads the flags computed here.

use glam::Vec3A;

use crate::geometry::PrimId;
use crate::material::pow_f32;
use crate::math::Real;
use crate::world::World;

/// Per-material and per-(light, material) constants, built once per tile.
pub struct Tables {
    /// world.ambient * m.ambient per material.
    pub ambient: Vec<Vec3A>,
    /// shininess, specular_cos_min, reflectivity, transparency, ior per material.
    mat: Vec<[f32; 5]>,
    /// light.diffuse * m.diffuse and light.specular * m.specular, indexed
    /// `light * materials + material`.
    light_mat: Vec<[Vec3A; 2]>,
    lights: Vec<[f32; 3]>,
    /// Per primitive (spheres, then planes, then a last entry for a miss):
    /// sphere centre and radius or plane normal and distance, and material.
    prim_geom: Vec<[f32; 4]>,
    prim_mat: Vec<u32>,
    spheres: usize,
    materials: usize,
    /// Per entry of `prim_mat`: its geometry, its material's constants and
    /// the colour a ray starts from (ambient term; the background for the
    /// miss entry), together: one lookup per hit ...
    ent: Vec<[f32; 12]>,
    /// The `PrimId` of each entry (`PrimId::NONE` for the miss entry) ...
    ent_key: Vec<u32>,
    /// ... and per (light, entry), indexed `light * entries + entry`, the
    /// light's diffuse and specular times the material's.
    ent_light: Vec<[f32; 6]>,
    /// Rows `select` looks through (8 or 16, the tables padded to that), or
    /// 0 for a scalar gather (more entries).
    select_rows: usize,
}

impl Tables {
    /// `select`: whether small tables are gathered by selection (see
    /// `select`), which pays with AVX2 and AVX-512 but not with the
    /// baseline's SSE2.
    pub fn new(world: &World<f32>, select: bool) -> Self {
        // A scene without materials has no objects: every ray misses, but
        // misses read entry 0 (harmlessly), so there must be one.
        let none = world.materials.is_empty();
        let materials = world.materials.len().max(1);
        let zero = Vec3A::ZERO;
        let mut t = Tables {
            ambient: world
                .materials
                .iter()
                .map(|m| world.ambient * m.ambient)
                .chain(none.then_some(zero))
                .collect(),
            mat: (world.materials.iter().map(|m| {
                [
                    m.shininess,
                    m.specular_cos_min,
                    m.reflectivity,
                    m.transparency,
                    m.ior,
                ]
            }))
            .chain(none.then_some([0.0; 5]))
            .collect(),
            light_mat: world
                .lights
                .iter()
                .flat_map(|l| {
                    (world
                        .materials
                        .iter()
                        .map(move |m| [l.diffuse * m.diffuse, l.specular * m.specular]))
                    .chain(none.then_some([zero; 2]))
                })
                .collect(),
            lights: world.lights.iter().map(|l| l.position.into()).collect(),
            prim_geom: (world
                .spheres
                .iter()
                .map(|s| [s.center.x, s.center.y, s.center.z, s.radius]))
            .chain(
                world
                    .planes
                    .iter()
                    .map(|p| [p.normal.x, p.normal.y, p.normal.z, p.distance]),
            )
            .chain([[0.0, 1.0, 0.0, 0.0]])
            .collect(),
            prim_mat: (world.spheres.iter().map(|s| s.material))
                .chain(world.planes.iter().map(|p| p.material))
                .chain([0])
                .collect(),
            spheres: world.spheres.len(),
            materials,
            ent: Vec::new(),
            ent_key: (0..world.spheres.len() as u32)
                .map(|k| PrimId::new(PrimId::SPHERE, k).0)
                .chain((0..world.planes.len() as u32).map(|k| PrimId::new(PrimId::PLANE, k).0))
                .chain([PrimId::NONE.0])
                .collect(),
            ent_light: Vec::new(),
            select_rows: 0,
        };
        let last = t.prim_mat.len() - 1;
        t.ent = (t.prim_geom.iter().zip(&t.prim_mat).enumerate())
            .map(|(e, (g, &m))| {
                let c = t.mat[m as usize];
                let a = if e == last {
                    world.background
                } else {
                    t.ambient[m as usize]
                };
                [
                    g[0], g[1], g[2], g[3], c[0], c[1], c[2], c[3], c[4], a.x, a.y, a.z,
                ]
            })
            .collect();
        // Small tables are selected from with a fixed number of rows (see
        // `select`): padded with rows no hit selects (the stream renderer
        // never sees a triangle).
        let rows = t.ent.len();
        t.select_rows = if select {
            [8, 16].into_iter().find(|&r| rows <= r).unwrap_or(0)
        } else {
            0
        };
        let stride = rows.max(t.select_rows);
        t.ent.resize(stride, [0.0; 12]);
        t.ent_key.resize(stride, PrimId::new(PrimId::TRIANGLE, 0).0);
        t.ent_light = (0..world.lights.len())
            .flat_map(|li| (0..stride).map(move |e| (li, e)))
            .map(|(li, e)| match t.prim_mat.get(e) {
                Some(&m) => {
                    let [d, s] = t.light_mat[li * t.materials + m as usize];
                    [d.x, d.y, d.z, s.x, s.y, s.z]
                }
                None => [0.0; 6],
            })
            .collect();
        t
    }

    /// Index of primitive `id` in `prim_geom` and `prim_mat`.
    #[inline(always)]
    fn entry(&self, id: PrimId) -> usize {
        if id == PrimId::NONE {
            self.prim_mat.len() - 1
        } else if id.kind() == PrimId::SPHERE {
            id.index()
        } else {
            self.spheres + id.index()
        }
    }
}

/// What shading decided for each hit of a generation (index `i`), and for
/// each (light, hit) (index `light * n + i`).
#[derive(Default)]
pub struct Shaded {
    /// The colour each ray starts from: the ambient term, or the background.
    pub local: [Vec<f32>; 3],
    /// Transparency of the material hit: the refracted ray's weight.
    pub transparency: Vec<f32>,
    /// Origins offset to the viewer's side and to the other side.
    pub above: [Vec<f32>; 3],
    pub below: [Vec<f32>; 3],
    /// Per (light, hit): shadow ray wanted, its origin (on the light's side),
    /// direction and length, and what the light adds if unblocked.
    pub light_on: Vec<bool>,
    pub light_origin: [Vec<f32>; 3],
    pub light_dir: [Vec<f32>; 3],
    pub light_t_max: Vec<f32>,
    pub light_contrib: [Vec<f32>; 3],
    /// Refracted ray (from `below`) wanted, and its direction.
    pub refract_on: Vec<bool>,
    pub refract_dir: [Vec<f32>; 3],
    /// Reflected ray (from `above`) weight (0: none), and its direction.
    pub reflect_w: Vec<f32>,
    pub reflect_dir: [Vec<f32>; 3],
}

/// Sizes a scratch array; every element is overwritten before it is read.
fn sized<T: Copy + Default>(v: &mut Vec<T>, n: usize) {
    // Never shrunk, so never refilled when the next generation is larger.
    if v.len() < n {
        v.resize(n, T::default());
    }
}

#[inline(always)]
fn arr<const W: usize, T>(v: &[T], at: usize) -> &[T; W] {
    v[at..at + W]
        .try_into()
        .expect("lane group inside the padded queue")
}

/// Each lane's entry in the tables, for [`gather`]'s scalar path only.
#[inline(always)]
fn entries<const W: usize>(tab: &Tables, ids: &[u32; W]) -> [usize; W] {
    let mut e = [0; W];
    if tab.select_rows == 0 {
        for l in 0..W {
            e[l] = tab.entry(PrimId(ids[l]));
        }
    }
    e
}

/// Row `ents[l]` of `table` (whose rows belong to the primitives `keys`)
/// for each lane `l` whose primitive is `ids[l]`, as lane arrays: by
/// [`select`] for small tables (every thesis scene), else lane by lane.
#[inline(always)]
fn gather<const W: usize, const K: usize>(
    tab: &Tables,
    table: &[[f32; K]],
    ids: &[u32; W],
    ents: &[usize; W],
) -> [[f32; W]; K] {
    match tab.select_rows {
        8 => select::<W, K, 8>(table, &tab.ent_key, ids),
        16 => select::<W, K, 16>(table, &tab.ent_key, ids),
        _ => {
            let mut out = [[0.0f32; W]; K];
            for l in 0..W {
                let row = table[ents[l]];
                for k in 0..K {
                    out[k][l] = row[k];
                }
            }
            out
        }
    }
}

/// The row of `table` whose key is `ids[l]`, for each lane `l` (exactly
/// one row matches): the rows' bits AND-ed with lane masks and OR-ed
/// together, field by field over a fixed number of rows, which LLVM
/// unrolls and vectorises over the lanes with the sums in registers. A
/// scalar gather stores lane by lane into arrays that are read back as
/// vectors, and an accumulation over a run-time number of rows goes
/// through masked stores: both stall on store forwarding.
#[inline(always)]
fn select<const W: usize, const K: usize, const N: usize>(
    table: &[[f32; K]],
    keys: &[u32],
    ids: &[u32; W],
) -> [[f32; W]; K] {
    let table: &[[f32; K]; N] = table[..N]
        .try_into()
        .expect("tables padded to the selected rows");
    let keys: &[u32; N] = keys[..N]
        .try_into()
        .expect("tables padded to the selected rows");
    let mut masks = [[0u32; W]; N];
    for e in 0..N {
        for l in 0..W {
            masks[e][l] = 0u32.wrapping_sub((ids[l] == keys[e]) as u32);
        }
    }
    let mut out = [[0.0f32; W]; K];
    for k in 0..K {
        for l in 0..W {
            let mut acc = 0u32;
            for e in 0..N {
                acc |= table[e][k].to_bits() & masks[e][l];
            }
            out[k][l] = f32::from_bits(acc);
        }
    }
    out
}

#[inline(always)]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    // glam's Vec3A::dot order: (x + y) + z.
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline(always)]
fn max0(x: f32) -> f32 {
    // f32::max(x, 0) for the values shading sees (NaN only in masked-out lanes).
    if x > 0.0 { x } else { 0.0 }
}

/// Shades the `n` (a multiple of `W`) rays `o`, `d` with closest hits `t`,
/// `id` at generation `depth`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn shade_lanes<const W: usize>(
    world: &World<f32>,
    tab: &Tables,
    o: [&[f32]; 3],
    d: [&[f32]; 3],
    t: &[f32],
    id: &[u32],
    depth: u32,
    s: &mut Shaded,
) {
    let n = t.len();
    let nl = tab.lights.len();
    sized(&mut s.transparency, n);
    for v in s
        .local
        .iter_mut()
        .chain(s.above.iter_mut())
        .chain(s.below.iter_mut())
        .chain(s.refract_dir.iter_mut())
        .chain(s.reflect_dir.iter_mut())
    {
        sized(v, n);
    }
    sized(&mut s.refract_on, n);
    sized(&mut s.reflect_w, n);
    for v in [&mut s.light_t_max]
        .into_iter()
        .chain(s.light_origin.iter_mut())
        .chain(s.light_dir.iter_mut())
        .chain(s.light_contrib.iter_mut())
    {
        sized(v, n * nl);
    }
    sized(&mut s.light_on, n * nl);
    let secondary = depth < world.settings.max_depth;
    let (rel, min) = (<f32 as Real>::OFFSET_REL, <f32 as Real>::OFFSET_MIN);
    let shorten = 1.0 - <f32 as Real>::SHADOW_SHORTEN;

    for at in (0..n).step_by(W) {
        let (ox, oy, oz) = (
            arr::<W, _>(o[0], at),
            arr::<W, _>(o[1], at),
            arr::<W, _>(o[2], at),
        );
        let (dx, dy, dz) = (
            arr::<W, _>(d[0], at),
            arr::<W, _>(d[1], at),
            arr::<W, _>(d[2], at),
        );
        let tt = arr::<W, _>(t, at);
        // Primitive and material constants of each lane's hit.
        let ids = arr::<W, _>(id, at);
        let ents = entries::<W>(tab, ids);
        let e = gather::<W, 12>(tab, &tab.ent, ids, &ents);
        let g = [e[0], e[1], e[2], e[3]];
        let mc = [e[4], e[5], e[6], e[7], e[8]];
        let local = [e[9], e[10], e[11]];
        let mut hit = [false; W];
        let mut sphere = [false; W];
        for l in 0..W {
            hit[l] = ids[l] != PrimId::NONE.0;
            // (PrimId::NONE's kind is not SPHERE.)
            sphere[l] = PrimId(ids[l]).kind() == PrimId::SPHERE;
        }
        for (to, from) in s.local.iter_mut().zip(&local) {
            to[at..at + W].copy_from_slice(from);
        }
        s.transparency[at..at + W].copy_from_slice(&mc[3]);
        let mut p = [[0.0f32; W]; 3];
        let mut nn = [[0.0f32; W]; 3];
        let mut v = [[0.0f32; W]; 3];
        let mut entering = [false; W];
        let mut cos_i = [0.0f32; W];
        for l in 0..W {
            // ray.at(t), then World::surface.
            let hp = [
                ox[l] + dx[l] * tt[l],
                oy[l] + dy[l] * tt[l],
                oz[l] + dz[l] * tt[l],
            ];
            let c = [g[0][l], g[1][l], g[2][l]];
            // Sphere: normal (p - c) / |p - c|, point snapped to c + n r.
            let dd = [hp[0] - c[0], hp[1] - c[1], hp[2] - c[2]];
            let inv = 1.0 / dot(dd, dd).sqrt();
            let ns = [dd[0] * inv, dd[1] * inv, dd[2] * inv];
            let ps = [
                c[0] + ns[0] * g[3][l],
                c[1] + ns[1] * g[3][l],
                c[2] + ns[2] * g[3][l],
            ];
            // Plane: normal as given, point projected onto it.
            let off = dot(c, hp) - g[3][l];
            let pp = [hp[0] - c[0] * off, hp[1] - c[1] * off, hp[2] - c[2] * off];
            let (pt, n_out) = if sphere[l] { (ps, ns) } else { (pp, c) };
            let vv = [-dx[l], -dy[l], -dz[l]];
            let ent = dot(n_out, vv) >= 0.0;
            let nf = if ent {
                n_out
            } else {
                [-n_out[0], -n_out[1], -n_out[2]]
            };
            for k in 0..3 {
                p[k][l] = pt[k];
                nn[k][l] = nf[k];
                v[k][l] = vv[k];
            }
            entering[l] = ent;
            cos_i[l] = dot(nf, vv);
        }
        // offset_origin: scale from the largest coordinate, to either side.
        let mut above = [[0.0f32; W]; 3];
        let mut below = [[0.0f32; W]; 3];
        for l in 0..W {
            let m = p[0][l].abs().max(p[1][l].abs()).max(p[2][l].abs());
            let scale = m * rel + min;
            for c in 0..3 {
                above[c][l] = p[c][l] + nn[c][l] * scale;
                below[c][l] = p[c][l] + -nn[c][l] * scale;
            }
        }
        for c in 0..3 {
            s.above[c][at..at + W].copy_from_slice(&above[c]);
            s.below[c][at..at + W].copy_from_slice(&below[c]);
        }
        for (li, lp) in tab.lights.iter().enumerate() {
            let base = li * n + at;
            let entries = tab.ent.len();
            let lc = gather::<W, 6>(
                tab,
                &tab.ent_light[li * entries..(li + 1) * entries],
                ids,
                &ents,
            );
            // Results in lane arrays, stored after the loop: indexing the
            // queues inside it would stop LLVM from vectorising it.
            let mut on = [false; W];
            let mut origin = [[0.0f32; W]; 3];
            let mut t_max = [0.0f32; W];
            let mut dir = [[0.0f32; W]; 3];
            let mut add = [[0.0f32; W]; 3];
            let mut ndotl = [0.0f32; W];
            let mut ndoth = [0.0f32; W];
            // Lanes (of hits) whose specular term passes the cut-off, as u32
            // (0 or 1) for a cheap OR-reduction.
            let mut want_spec = [0u32; W];
            for l in 0..W {
                let pt = [p[0][l], p[1][l], p[2][l]];
                let ns = [nn[0][l], nn[1][l], nn[2][l]];
                let vv = [v[0][l], v[1][l], v[2][l]];
                let to = [lp[0] - pt[0], lp[1] - pt[1], lp[2] - pt[2]];
                let dist = dot(to, to).sqrt();
                let inv = 1.0 / dist;
                let ld = [to[0] * inv, to[1] * inv, to[2] * inv];
                ndotl[l] = max0(dot(ns, ld));
                let h = [ld[0] + vv[0], ld[1] + vv[1], ld[2] + vv[2]];
                let h_len = dot(h, h).sqrt();
                ndoth[l] = if h_len > 0.0 {
                    max0(dot(ns, h) / h_len)
                } else {
                    0.0
                };
                want_spec[l] = (hit[l] & (ndoth[l] > mc[1][l])) as u32;
                on[l] = hit[l] & (dist > 0.0);
                // Leave on the light's side of the surface.
                let from_above = dot(ns, ld) >= 0.0;
                for c in 0..3 {
                    origin[c][l] = if from_above { above[c][l] } else { below[c][l] };
                }
                t_max[l] = dist * shorten;
                for c in 0..3 {
                    dir[c][l] = ld[c];
                }
            }
            // The power only where some lane of the group needs it (a group
            // without a highlight skips it): a lane below the cut-off gets 0
            // either way, and misses are not lit at all.
            let mut spec = [0.0f32; W];
            if want_spec.iter().fold(0, |a, &x| a | x) != 0 {
                for l in 0..W {
                    // Clamped base: the lanes that skip the specular term
                    // still evaluate the power, harmlessly.
                    let sp = pow_f32(if ndoth[l] > 0.0 { ndoth[l] } else { 1.0 }, mc[0][l]);
                    spec[l] = if ndoth[l] > mc[1][l] { sp } else { 0.0 };
                }
            }
            for l in 0..W {
                let contrib = [0, 1, 2].map(|c| lc[c][l] * ndotl[l] + lc[3 + c][l] * spec[l]);
                on[l] &= contrib[0].max(contrib[1]).max(contrib[2]) > 0.0;
                for c in 0..3 {
                    add[c][l] = contrib[c];
                }
            }
            let r = base..base + W;
            s.light_on[r.clone()].copy_from_slice(&on);
            for (to, from) in s.light_origin.iter_mut().zip(&origin) {
                to[r.clone()].copy_from_slice(from);
            }
            s.light_t_max[r.clone()].copy_from_slice(&t_max);
            for c in 0..3 {
                s.light_dir[c][r.clone()].copy_from_slice(&dir[c]);
                s.light_contrib[c][r.clone()].copy_from_slice(&add[c]);
            }
        }
        if !secondary {
            s.refract_on[at..at + W].fill(false);
            s.reflect_w[at..at + W].fill(0.0);
            continue;
        }
        let mut refract = [false; W];
        let mut refract_dir = [[0.0f32; W]; 3];
        let mut reflect_w = [0.0f32; W];
        let mut reflect_dir = [[0.0f32; W]; 3];
        for l in 0..W {
            let ns = [nn[0][l], nn[1][l], nn[2][l]];
            let vv = [v[0][l], v[1][l], v[2][l]];
            let (reflectivity, transparency, ior) = (mc[2][l], mc[3][l], mc[4][l]);
            let ci = cos_i[l];
            // Snell: eta = n1/n2; entering from outside goes 1 -> ior.
            let eta = if entering[l] { 1.0 / ior } else { ior };
            let k = 1.0 - eta * eta * (1.0 - ci * ci);
            let transparent = transparency > 0.0;
            let tir = transparent & (k < 0.0);
            refract[l] = hit[l] & transparent & (k >= 0.0);
            let a = eta * ci - max0(k).sqrt();
            let r = [
                -vv[0] * eta + ns[0] * a,
                -vv[1] * eta + ns[1] * a,
                -vv[2] * eta + ns[2] * a,
            ];
            let inv = 1.0 / dot(r, r).sqrt();
            let w = if tir {
                reflectivity + transparency
            } else {
                reflectivity
            };
            reflect_w[l] = if hit[l] { w } else { 0.0 };
            // R = 2(V.N)N - V
            let two_c = 2.0 * ci;
            let rr = [
                ns[0] * two_c - vv[0],
                ns[1] * two_c - vv[1],
                ns[2] * two_c - vv[2],
            ];
            let inv2 = 1.0 / dot(rr, rr).sqrt();
            for c in 0..3 {
                refract_dir[c][l] = r[c] * inv;
                reflect_dir[c][l] = rr[c] * inv2;
            }
        }
        let r = at..at + W;
        s.refract_on[r.clone()].copy_from_slice(&refract);
        s.reflect_w[r.clone()].copy_from_slice(&reflect_w);
        for c in 0..3 {
            s.refract_dir[c][r.clone()].copy_from_slice(&refract_dir[c]);
            s.reflect_dir[c][r.clone()].copy_from_slice(&reflect_dir[c]);
        }
    }
}
