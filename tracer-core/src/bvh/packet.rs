//! Packet traversal: up to [`PACKET`] rays through the tree together, for
//! coherent rays (a block of camera rays: [`closest_hits`]; their shadow
//! rays to one light: [`occluded_hits`]). Each node is fetched once per
//! packet and its four boxes are tested against all of the packet's rays
//! that reached it, 4, 8 or 16 rays per SSE, AVX2 or AVX-512 instruction
//! (structure of arrays over rays); a subtree is visited with the mask of
//! the rays that met its box, and a leaf is tested ray by ray with the
//! single-ray leaf test. The single-ray traversal is bound by the latency
//! of one chain of dependent loads and tests; here the rays of a packet are
//! independent work for the same node.
//!
//! The answer is the single-ray [`closest_hit`]'s, bit for bit: every ray
//! meets a superset of the boxes that hold a hit nearer than its nearest, a
//! triangle's distance does not depend on what was found before
//! (`triangle::finish`), and ties go by [`PrimId::nearer`], so only the
//! order of the work differs. Rays whose direction signs differ from the
//! first ray's go through [`closest_hit`] (or [`occluded`]) one by one (the
//! packet picks each node's near and far planes once for all its rays).

use std::mem::MaybeUninit;

use super::traverse::{CULL_WIDEN, EXIT_WIDEN, far_to_near};
use super::{Bvh, Primitives, STACK, closest_hit, occluded};
use crate::geometry::PrimId;
use crate::math::Ray;
use crate::simd::SimdLevel;

/// Rays in a packet at most: 4 SSE groups of 4, 2 AVX2 groups of 8, one AVX-512 vector.
pub const PACKET: usize = 16;

/// A subtree still to visit, with the rays that met its box (bit j: ray j)
/// and the nearest of their entry distances.
#[derive(Clone, Copy)]
struct Entry {
    child: u32,
    count: u32,
    mask: u32,
    t: f32,
}

/// One value per ray of a packet, 64-byte aligned for SSE, AVX2 and AVX-512 loads.
#[repr(C, align(64))]
#[derive(Clone, Copy)]
struct Lanes([f32; PACKET]);

/// The node test for rendering at this process's SIMD level
/// ([`crate::simd::level`]): AVX2 where the CPU has it, also on AVX-512
/// CPUs. The AVX-512 walk is faster for ray queries alone (`mesh_bench`),
/// but whole mesh renders on the 2-core Xeon VM were 5% slower with it
/// than with SSE, and 4-9% faster with AVX2: while a core runs 512-bit
/// code its clock drops, and the shading between the packets pays too.
pub fn render_level() -> SimdLevel {
    match crate::simd::level() {
        SimdLevel::Avx512 => SimdLevel::Avx2,
        l => l,
    }
}

/// For each ray j of `rays` (at most [`PACKET`]), `(best[j], found[j])`
/// becomes the nearest of itself and the tree's hits along the ray, as
/// [`closest_hit`] gives it. `skip` is the primitive all the rays start on
/// (`PrimId::NONE` for camera rays). Nodes are tested at [`render_level`]:
/// 4 rays per SSE instruction, or 8 per AVX2 one (elsewhere than x86-64,
/// the rays go one by one).
pub fn closest_hits<P: Primitives<f32>>(
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    best: &mut [f32],
    found: &mut [PrimId],
    skip: PrimId,
) {
    let done = closest_hits_at(render_level(), view, bvh, rays, best, found, skip);
    debug_assert!(done);
}

/// [`closest_hits`] with the node test of `level` (baseline: SSE, 4 rays
/// per instruction; AVX2: 8; AVX-512: 16): the same answers at every level.
/// False (and nothing done) if this CPU lacks the level.
pub fn closest_hits_at<P: Primitives<f32>>(
    level: SimdLevel,
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    best: &mut [f32],
    found: &mut [PrimId],
    skip: PrimId,
) -> bool {
    assert!(
        rays.len() <= PACKET && best.len() == rays.len() && found.len() == rays.len(),
        "a packet holds at most {PACKET} rays"
    );
    if !level.is_available() {
        return false;
    }
    if bvh.nodes.is_empty() || rays.is_empty() {
        return true;
    }
    #[cfg(target_arch = "x86_64")]
    if rays.len() > 1 {
        walk_at::<P, false>(level, view, bvh, rays, best, found, &[skip; PACKET]);
        return true;
    }
    for (j, ray) in rays.iter().enumerate() {
        if let Some((t, id)) = closest_hit(view, bvh, ray, best[j], found[j], skip) {
            (best[j], found[j]) = (t, id);
        }
    }
    true
}

/// Bit j: whether ray j of `rays` (at most [`PACKET`]) meets a primitive
/// of the tree before `t_max[j]`, leaving primitive `skip[j]`, as
/// [`occluded`] answers it (the same boxes and leaves are tested for each
/// ray). For coherent shadow rays (from neighbouring points to one light).
/// Nodes are tested at [`render_level`].
pub fn occluded_hits<P: Primitives<f32>>(
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    t_max: &[f32],
    skip: &[PrimId],
) -> u32 {
    occluded_hits_at(render_level(), view, bvh, rays, t_max, skip)
        .expect("the render level is available")
}

/// [`occluded_hits`] with the node test of `level`; `None` if this CPU lacks it.
pub fn occluded_hits_at<P: Primitives<f32>>(
    level: SimdLevel,
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    t_max: &[f32],
    skip: &[PrimId],
) -> Option<u32> {
    let n = rays.len();
    assert!(
        n <= PACKET && t_max.len() == n && skip.len() == n,
        "a packet holds at most {PACKET} rays"
    );
    if !level.is_available() {
        return None;
    }
    if bvh.nodes.is_empty() || n == 0 {
        return Some(0);
    }
    #[cfg(target_arch = "x86_64")]
    if n > 1 {
        let mut best = [0.0; PACKET];
        best[..n].copy_from_slice(t_max);
        let mut skips = [PrimId::NONE; PACKET];
        skips[..n].copy_from_slice(skip);
        return Some(walk_at::<P, true>(
            level,
            view,
            bvh,
            rays,
            &mut best[..n],
            &mut [PrimId::NONE; PACKET][..n],
            &skips,
        ));
    }
    Some((0..n).fold(0, |m, j| {
        m | (occluded(view, bvh, &rays[j], t_max[j], skip[j]) as u32) << j
    }))
}

/// The walk at `level`, which this CPU has (checked by the callers).
#[cfg(target_arch = "x86_64")]
fn walk_at<P: Primitives<f32>, const ANY: bool>(
    level: SimdLevel,
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    best: &mut [f32],
    found: &mut [PrimId],
    skip: &[PrimId; PACKET],
) -> u32 {
    match level {
        // SAFETY: the callers checked that the CPU has the level.
        SimdLevel::Avx512 => unsafe { walk_avx512::<P, ANY>(view, bvh, rays, best, found, skip) },
        SimdLevel::Avx2 => unsafe { walk_avx2::<P, ANY>(view, bvh, rays, best, found, skip) },
        SimdLevel::Baseline => walk_sse::<P, ANY>(view, bvh, rays, best, found, skip),
    }
}

#[cfg(target_arch = "x86_64")]
#[inline(never)]
fn walk_sse<P: Primitives<f32>, const ANY: bool>(
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    best: &mut [f32],
    found: &mut [PrimId],
    skip: &[PrimId; PACKET],
) -> u32 {
    walk::<P, 4, ANY>(view, bvh, rays, best, found, skip)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline(never)]
fn walk_avx512<P: Primitives<f32>, const ANY: bool>(
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    best: &mut [f32],
    found: &mut [PrimId],
    skip: &[PrimId; PACKET],
) -> u32 {
    walk::<P, 16, ANY>(view, bvh, rays, best, found, skip)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline(never)]
fn walk_avx2<P: Primitives<f32>, const ANY: bool>(
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    best: &mut [f32],
    found: &mut [PrimId],
    skip: &[PrimId; PACKET],
) -> u32 {
    walk::<P, 8, ANY>(view, bvh, rays, best, found, skip)
}

/// A node's slot `k` against the 16 rays, 8 per AVX instruction; as [`slot16`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn slot8(
    b: &[[f32; 4]; 6],
    k: usize,
    near: [usize; 3],
    far: [usize; 3],
    o: &[Lanes; 3],
    inv: &[Lanes; 3],
    limit: &Lanes,
    mask: u32,
) -> (u32, f32) {
    use std::arch::x86_64::*;
    // SAFETY: `Lanes` is 64-byte aligned and 16 wide (h < 2); the row indices are < 6 and k < 4.
    unsafe {
        let s = |i: usize| _mm256_set1_ps(*b.get_unchecked(i).get_unchecked(k));
        let (n0, n1, n2, f0, f1, f2) = (
            s(near[0]),
            s(near[1]),
            s(near[2]),
            s(far[0]),
            s(far[1]),
            s(far[2]),
        );
        let inf = _mm256_set1_ps(f32::INFINITY);
        let mut tmin = inf;
        let mut m = 0u32;
        for h in 0..2 {
            let hm = (mask >> (8 * h)) & 0xff;
            if hm == 0 {
                continue;
            }
            let l = |x: &Lanes| _mm256_load_ps(x.0.as_ptr().add(8 * h));
            let t0x = _mm256_mul_ps(_mm256_sub_ps(n0, l(&o[0])), l(&inv[0]));
            let t0y = _mm256_mul_ps(_mm256_sub_ps(n1, l(&o[1])), l(&inv[1]));
            let t0z = _mm256_mul_ps(_mm256_sub_ps(n2, l(&o[2])), l(&inv[2]));
            let t1x = _mm256_mul_ps(_mm256_sub_ps(f0, l(&o[0])), l(&inv[0]));
            let t1y = _mm256_mul_ps(_mm256_sub_ps(f1, l(&o[1])), l(&inv[1]));
            let t1z = _mm256_mul_ps(_mm256_sub_ps(f2, l(&o[2])), l(&inv[2]));
            let t0 = _mm256_max_ps(
                _mm256_max_ps(t0x, t0y),
                _mm256_max_ps(t0z, _mm256_setzero_ps()),
            );
            let t1 = _mm256_mul_ps(
                _mm256_min_ps(_mm256_min_ps(t1x, t1y), t1z),
                _mm256_set1_ps(EXIT_WIDEN as f32),
            );
            let hit = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_LE_OS>(t0, t1),
                _mm256_cmp_ps::<_CMP_LE_OS>(t0, l(limit)),
            );
            let bits = _mm256_movemask_ps(hit) as u32 & hm;
            if bits != 0 {
                m |= bits << (8 * h);
                tmin = _mm256_min_ps(tmin, _mm256_blendv_ps(inf, t0, hit));
            }
        }
        if m == 0 {
            return (0, f32::INFINITY);
        }
        let q = _mm_min_ps(
            _mm256_castps256_ps128(tmin),
            _mm256_extractf128_ps::<1>(tmin),
        );
        let q = _mm_min_ps(q, _mm_movehl_ps(q, q));
        let q = _mm_min_ss(q, _mm_shuffle_ps::<0x55>(q, q));
        (m, _mm_cvtss_f32(q))
    }
}

/// A node's slot `k` against the 16 rays at once (AVX-512F): the mask of
/// the rays in `mask` that meet its box within their `limit`, and the
/// nearest of their entry distances. The same arithmetic as the SSE form.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn slot16(
    b: &[[f32; 4]; 6],
    k: usize,
    near: [usize; 3],
    far: [usize; 3],
    o: &[Lanes; 3],
    inv: &[Lanes; 3],
    limit: &Lanes,
    mask: u32,
) -> (u32, f32) {
    use std::arch::x86_64::*;
    // SAFETY: `Lanes` is 64-byte aligned and 16 wide; the row indices are < 6 and k < 4.
    unsafe {
        let l = |x: &Lanes| _mm512_load_ps(x.0.as_ptr());
        let s = |i: usize| _mm512_set1_ps(*b.get_unchecked(i).get_unchecked(k));
        let (ox, oy, oz) = (l(&o[0]), l(&o[1]), l(&o[2]));
        let (ix, iy, iz) = (l(&inv[0]), l(&inv[1]), l(&inv[2]));
        let t0x = _mm512_mul_ps(_mm512_sub_ps(s(near[0]), ox), ix);
        let t0y = _mm512_mul_ps(_mm512_sub_ps(s(near[1]), oy), iy);
        let t0z = _mm512_mul_ps(_mm512_sub_ps(s(near[2]), oz), iz);
        let t1x = _mm512_mul_ps(_mm512_sub_ps(s(far[0]), ox), ix);
        let t1y = _mm512_mul_ps(_mm512_sub_ps(s(far[1]), oy), iy);
        let t1z = _mm512_mul_ps(_mm512_sub_ps(s(far[2]), oz), iz);
        let t0 = _mm512_max_ps(
            _mm512_max_ps(t0x, t0y),
            _mm512_max_ps(t0z, _mm512_setzero_ps()),
        );
        let t1 = _mm512_mul_ps(
            _mm512_min_ps(_mm512_min_ps(t1x, t1y), t1z),
            _mm512_set1_ps(EXIT_WIDEN as f32),
        );
        let m = _mm512_mask_cmp_ps_mask::<_CMP_LE_OS>(mask as __mmask16, t0, t1);
        let m = _mm512_mask_cmp_ps_mask::<_CMP_LE_OS>(m, t0, l(limit));
        if m == 0 {
            return (0, f32::INFINITY);
        }
        (m as u32, _mm512_mask_reduce_min_ps(m, t0))
    }
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(clippy::needless_range_loop)] // rays by group index, over several arrays
/// The packet walk. Closest hits (`ANY` false): `best`/`found` in and out,
/// returns 0. Occlusion (`ANY`): `best` holds each ray's `t_max`, returns
/// the mask of blocked rays; a ray leaves the walk once blocked.
fn walk<P: Primitives<f32>, const W: usize, const ANY: bool>(
    view: &P,
    bvh: &Bvh,
    rays: &[Ray<f32>],
    best: &mut [f32],
    found: &mut [PrimId],
    skip: &[PrimId; PACKET],
) -> u32 {
    // SAFETY: SSE is part of x86_64; `Lanes` and the node rows are 16-byte
    // aligned and `g < 4`, so the loads stay inside them; the row indices
    // `near`/`far` are < 6 by construction; stack entries below `sp` were
    // written before `sp` passed them; a `tr[j]` is read only once set.
    unsafe {
        use std::arch::x86_64::*;

        use super::traverse::leaf;
        use crate::triangle::TriangleRay;

        // Origins and directions by lanes, four rays transposed at a time
        // (lane stores and vector loads would stall store forwarding);
        // unused lanes repeat the first ray (masked off, but finite).
        let ray_at = |j: usize| &rays[if j < rays.len() { j } else { 0 }];
        let transpose = |v: [__m128; 4]| {
            let (t0, t1) = (_mm_unpacklo_ps(v[0], v[1]), _mm_unpacklo_ps(v[2], v[3]));
            let (t2, t3) = (_mm_unpackhi_ps(v[0], v[1]), _mm_unpackhi_ps(v[2], v[3]));
            [
                _mm_movelh_ps(t0, t1),
                _mm_movehl_ps(t1, t0),
                _mm_movelh_ps(t2, t3),
            ]
        };
        let og = [0, 1, 2, 3]
            .map(|g| transpose([0, 1, 2, 3].map(|k| __m128::from(ray_at(4 * g + k).origin))));
        let dg = [0, 1, 2, 3]
            .map(|g| transpose([0, 1, 2, 3].map(|k| __m128::from(ray_at(4 * g + k).dir))));
        // The same by lanes in memory, for the AVX2 and AVX-512 node tests.
        let mut o = [Lanes([0.0; PACKET]); 3];
        if W > 4 {
            for g in 0..4 {
                for a in 0..3 {
                    _mm_store_ps(o[a].0.as_mut_ptr().add(4 * g), og[g][a]);
                }
            }
        }
        let group = |l: &Lanes, g: usize| _mm_load_ps(l.0.as_ptr().add(4 * g));
        // Reciprocal directions as `BoxRay::new` makes them (a non-finite one
        // becomes f32::MAX with the direction's sign), and their signs: bit
        // 3a + k of `neg[g]` says ray 4g + k goes down axis a.
        let big = _mm_set1_ps(f32::MAX);
        let sign = _mm_set1_ps(-0.0);
        let inf = _mm_set1_ps(f32::INFINITY);
        let zero = _mm_setzero_ps();
        let mut neg = [0u32; 4];
        let mut invl = [Lanes([0.0; PACKET]); 3];
        let ig = [0, 1, 2, 3].map(|g| {
            [0, 1, 2].map(|a| {
                let dv = dg[g][a];
                let i = _mm_div_ps(_mm_set1_ps(1.0), dv);
                let finite = _mm_cmplt_ps(_mm_andnot_ps(sign, i), inf);
                let i = _mm_or_ps(
                    _mm_and_ps(finite, i),
                    _mm_andnot_ps(finite, _mm_or_ps(big, _mm_and_ps(sign, dv))),
                );
                neg[g] |= (_mm_movemask_ps(_mm_cmplt_ps(i, zero)) as u32) << (4 * a);
                if W > 4 {
                    _mm_store_ps(invl[a].0.as_mut_ptr().add(4 * g), i);
                }
                i
            })
        });
        // Rays in the packet: those with the first ray's direction signs (so
        // the same near and far planes); the others go one by one.
        let octant = |j: usize| {
            let n = neg[j / 4] >> (j % 4);
            (n & 1, (n >> 4) & 1, (n >> 8) & 1)
        };
        let (nx, ny, nz) = octant(0);
        let near = [nx as usize, 2 + ny as usize, 4 + nz as usize];
        let far = near.map(|r| r ^ 1);
        let mut bt = Lanes([f32::INFINITY; PACKET]);
        let mut fo = [PrimId::NONE; PACKET];
        let mut active = 0u32;
        let mut blocked = 0u32;
        for (j, ray) in rays.iter().enumerate() {
            if octant(j) != (nx, ny, nz) {
                if ANY {
                    blocked |= (occluded(view, bvh, ray, best[j], skip[j]) as u32) << j;
                } else if let Some((t, id)) =
                    closest_hit(view, bvh, ray, best[j], found[j], skip[j])
                {
                    (best[j], found[j]) = (t, id);
                }
                continue;
            }
            active |= 1 << j;
            bt.0[j] = best[j];
            fo[j] = found[j];
        }
        // Boxes are culled beyond the nearest hit times CULL_WIDEN (see there).
        let cull = |t: f32| t * CULL_WIDEN as f32;
        let mut lim = Lanes(bt.0.map(cull));
        // In registers for the SSE node test; a leaf updates one lane of them.
        let mut limv = [0, 1, 2, 3].map(|g| group(&lim, g));
        let lane_mask = [0, 1, 2, 3].map(|k| {
            _mm_castsi128_ps(_mm_set_epi32(
                -((k == 3) as i32),
                -((k == 2) as i32),
                -((k == 1) as i32),
                -((k == 0) as i32),
            ))
        });
        let widen = _mm_set1_ps(EXIT_WIDEN as f32);
        // Rays still looking (occlusion: not blocked yet).
        let mut open = active;

        // Set up at a ray's first leaf.
        let mut tr = [const { MaybeUninit::<TriangleRay<f32>>::uninit() }; PACKET];
        let mut tr_ready = 0u32;
        let mut stack = [const { MaybeUninit::<Entry>::uninit() }; STACK];
        let mut sp = 0usize;
        let mut cur = Entry {
            child: 0,
            count: 0,
            mask: active,
            t: 0.0,
        };
        'walk: loop {
            if cur.count == 0 {
                let n = &bvh.nodes[cur.child as usize];
                let rows = [0, 1, 2, 3, 4, 5].map(|i| _mm_load_ps(n.b.get_unchecked(i).as_ptr()));
                let mut cm = [0u32; 4];
                let mut ct = [f32::INFINITY; 4];
                macro_rules! slot {
                    ($k:literal) => {
                        // An empty slot (child and count 0; node 0 is the root, never a child).
                        if W == 16 && (n.child[$k] != 0 || n.count[$k] != 0) {
                            (cm[$k], ct[$k]) =
                                slot16(&n.b, $k, near, far, &o, &invl, &lim, cur.mask);
                        } else if W == 8 && (n.child[$k] != 0 || n.count[$k] != 0) {
                            (cm[$k], ct[$k]) =
                                slot8(&n.b, $k, near, far, &o, &invl, &lim, cur.mask);
                        } else if n.child[$k] != 0 || n.count[$k] != 0 {
                            let s = |i: usize| _mm_shuffle_ps::<{ $k * 0x55 }>(rows[i], rows[i]);
                            let (n0, n1, n2) = (s(near[0]), s(near[1]), s(near[2]));
                            let (f0, f1, f2) = (s(far[0]), s(far[1]), s(far[2]));
                            let mut tmin = inf;
                            let mut m = 0u32;
                            for g in 0..4 {
                                let gm = (cur.mask >> (4 * g)) & 15;
                                if gm == 0 {
                                    continue;
                                }
                                let [ox, oy, oz] = og[g];
                                let [ix, iy, iz] = ig[g];
                                // The arithmetic of `test4`, for four rays against one box.
                                let t0x = _mm_mul_ps(_mm_sub_ps(n0, ox), ix);
                                let t0y = _mm_mul_ps(_mm_sub_ps(n1, oy), iy);
                                let t0z = _mm_mul_ps(_mm_sub_ps(n2, oz), iz);
                                let t1x = _mm_mul_ps(_mm_sub_ps(f0, ox), ix);
                                let t1y = _mm_mul_ps(_mm_sub_ps(f1, oy), iy);
                                let t1z = _mm_mul_ps(_mm_sub_ps(f2, oz), iz);
                                let t0 = _mm_max_ps(_mm_max_ps(t0x, t0y), _mm_max_ps(t0z, zero));
                                let t1 = _mm_mul_ps(_mm_min_ps(_mm_min_ps(t1x, t1y), t1z), widen);
                                let hit =
                                    _mm_and_ps(_mm_cmple_ps(t0, t1), _mm_cmple_ps(t0, limv[g]));
                                let hm = _mm_movemask_ps(hit) as u32 & gm;
                                if hm != 0 {
                                    m |= hm << (4 * g);
                                    tmin = _mm_min_ps(
                                        tmin,
                                        _mm_or_ps(_mm_and_ps(hit, t0), _mm_andnot_ps(hit, inf)),
                                    );
                                }
                            }
                            if m != 0 {
                                let h = _mm_min_ps(tmin, _mm_movehl_ps(tmin, tmin));
                                let h = _mm_min_ss(h, _mm_shuffle_ps::<0x55>(h, h));
                                cm[$k] = m;
                                ct[$k] = _mm_cvtss_f32(h);
                            }
                        }
                    };
                }
                slot!(0);
                slot!(1);
                slot!(2);
                slot!(3);
                let entry = |k: usize| Entry {
                    child: n.child[k],
                    count: n.count[k],
                    mask: cm[k],
                    t: ct[k],
                };
                let hits = (cm[0] != 0) as u32
                    | ((cm[1] != 0) as u32) << 1
                    | ((cm[2] != 0) as u32) << 2
                    | ((cm[3] != 0) as u32) << 3;
                if hits != 0 {
                    // Nearest first (by the nearest entry of any ray), the rest pushed far to near.
                    let mut e = [entry(0); 4];
                    let mut len = 0;
                    let mut m = hits;
                    while m != 0 {
                        e[len] = entry(m.trailing_zeros() as usize);
                        len += 1;
                        m &= m - 1;
                    }
                    far_to_near(&mut e[..len], |x| x.t);
                    for x in &e[..len - 1] {
                        stack[sp].write(*x);
                        sp += 1;
                    }
                    cur = e[len - 1];
                    continue 'walk;
                }
            } else {
                let mut m = cur.mask & open;
                while m != 0 {
                    let j = m.trailing_zeros() as usize;
                    m &= m - 1;
                    if tr_ready & (1 << j) == 0 {
                        tr[j].write(TriangleRay::new(&rays[j]));
                        tr_ready |= 1 << j;
                    }
                    let leaf_ref = (cur.child as usize, cur.count as usize);
                    if ANY {
                        let (mut t, mut id) = (bt.0[j], PrimId::NONE);
                        if leaf::<f32, P, true>(
                            view,
                            bvh,
                            &rays[j],
                            tr[j].assume_init_ref(),
                            leaf_ref,
                            &mut t,
                            &mut id,
                            skip[j],
                        ) {
                            open &= !(1 << j);
                            if open == 0 {
                                break 'walk;
                            }
                        }
                        continue;
                    }
                    leaf::<f32, P, false>(
                        view,
                        bvh,
                        &rays[j],
                        tr[j].assume_init_ref(),
                        leaf_ref,
                        &mut bt.0[j],
                        &mut fo[j],
                        skip[j],
                    );
                    let l = cull(bt.0[j]);
                    lim.0[j] = l;
                    let (g, k) = (j / 4, j % 4);
                    limv[g] = _mm_or_ps(
                        _mm_and_ps(lane_mask[k], _mm_set1_ps(l)),
                        _mm_andnot_ps(lane_mask[k], limv[g]),
                    );
                }
            }
            // Pop the next subtree, keeping the rays that may still find something nearer in it.
            loop {
                if sp == 0 {
                    break 'walk;
                }
                sp -= 1;
                // SAFETY: entries below `sp` were written before `sp` was raised past them.
                let mut e = stack[sp].assume_init();
                let t = _mm_set1_ps(e.t);
                let mut keep = 0u32;
                for g in 0..4 {
                    if (e.mask >> (4 * g)) & 15 != 0 {
                        keep |= (_mm_movemask_ps(_mm_cmple_ps(t, limv[g])) as u32) << (4 * g);
                    }
                }
                e.mask &= keep & open;
                if e.mask != 0 {
                    cur = e;
                    break;
                }
            }
        }
        if ANY {
            return blocked | (active & !open);
        }
        let mut m = active;
        while m != 0 {
            let j = m.trailing_zeros() as usize;
            m &= m - 1;
            (best[j], found[j]) = (bt.0[j], fo[j]);
        }
        0
    }
}
