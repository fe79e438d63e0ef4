//! Single-ray traversal of the 4-wide tree: the slab test of a node's four
//! boxes, near-first descent with a fixed stack of [`STACK`] entries, and
//! the leaf tests. The primitives are reached through a [`Primitives`]
//! view, so the tree can be walked over any store of spheres and triangles
//! (a world, a moving mesh's own world, a test's) without knowing it.

use std::mem::MaybeUninit;

use super::{Bvh, BvhNode4, STACK};
use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3};
use crate::triangle::{TriangleRay, finish};

/// What traversal needs from the primitives that a tree's [`PrimId`]s name.
/// Implemented by the store that owns them (`World`); traversal is generic
/// over it, so each store gets its own monomorphised walk and the calls
/// inline into the leaf loop.
pub trait Primitives<R: Real> {
    /// Distance along `ray` to the primitive `id` (one the tree holds), if
    /// it may be at most `t_max` (a farther one may be returned: callers
    /// compare); `skip` is the primitive the ray starts on. `tri` is the
    /// ray's set-up for the triangle test. Occlusion asks the same question
    /// with its `t_max`.
    fn intersect(
        &self,
        id: PrimId,
        ray: &Ray<R>,
        tri: &TriangleRay<R>,
        t_max: R,
        skip: PrimId,
    ) -> Option<R>;
}

/// Exit distances are widened by this factor (Ize 2013, "Robust BVH ray
/// traversal") so that rounding never culls a box the ray grazes.
pub(super) const EXIT_WIDEN: f64 = 1.000_000_4;

/// A box is culled only when the ray enters it beyond the nearest hit so far
/// times this factor. The entry distance and a triangle's distance round
/// differently, so a triangle inside a box can be hit a few ulps before the
/// box's computed entry; without the slack a box could be culled or not
/// depending on which hit was found first, and the answer (the distance, or
/// the lower id of a tie) would depend on the visiting order, which differs
/// between single rays, packets and brute force. 2^-14 is far above those
/// ulps and costs only the rare visits of boxes entered just behind a hit.
pub(super) const CULL_WIDEN: f64 = 1.0 + 1.0 / 16384.0;

/// Per-ray state of the 4-wide slab test: origin, reciprocal direction
/// (zeros made huge-but-finite, so `0 * inv` is 0, never NaN), and for each
/// axis the rows of [`BvhNode4::b`] holding the near and the far planes
/// (min where the direction is positive). Choosing planes by the sign
/// rather than taking min/max of both gives the same distances for a box
/// and rejects the inverted boxes of empty slots.
#[derive(Clone, Copy)]
struct BoxRay<R: Real> {
    origin: [R; 3],
    inv: [R; 3],
    near: [usize; 3],
    far: [usize; 3],
    #[cfg(target_arch = "x86_64")]
    sse: [std::arch::x86_64::__m128; 6],
}

impl<R: Real> BoxRay<R> {
    #[inline(always)]
    fn new(ray: &Ray<R>) -> Self {
        let big = R::from_f64(f32::MAX as f64);
        let inv1 = |d: R| {
            let i = R::ONE / d;
            if i.is_finite() { i } else { big.copysign(d) }
        };
        let d = ray.dir;
        let inv = [inv1(d.x()), inv1(d.y()), inv1(d.z())];
        let origin = [ray.origin.x(), ray.origin.y(), ray.origin.z()];
        let neg = inv.map(|i| (i < R::ZERO) as usize);
        #[cfg(target_arch = "x86_64")]
        let sse = {
            use std::arch::x86_64::_mm_set1_ps;
            // Only used when R is f32, where this conversion is exact.
            let f = |x: R| x.to_f64() as f32;
            // SAFETY: SSE is part of x86_64.
            unsafe {
                [
                    _mm_set1_ps(f(origin[0])),
                    _mm_set1_ps(f(origin[1])),
                    _mm_set1_ps(f(origin[2])),
                    _mm_set1_ps(f(inv[0])),
                    _mm_set1_ps(f(inv[1])),
                    _mm_set1_ps(f(inv[2])),
                ]
            }
        };
        BoxRay {
            origin,
            inv,
            near: [0, 1, 2].map(|a| 2 * a + neg[a]),
            far: [0, 1, 2].map(|a| 2 * a + 1 - neg[a]),
            #[cfg(target_arch = "x86_64")]
            sse,
        }
    }
}

/// The slab test of a ray against the four boxes of `node`: a bit mask of
/// the slots it meets within [0, limit] (callers pass their nearest hit
/// times [`CULL_WIDEN`]), and their entry distances. In
/// `f32` on x86_64 one SSE pass over the node's rows; elsewhere (the `f64`
/// reference) the same arithmetic slot by slot.
#[inline(always)]
fn test4<R: Real>(node: &BvhNode4, r: &BoxRay<R>, limit: R) -> (u32, [R; 4]) {
    #[cfg(target_arch = "x86_64")]
    if std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>() {
        use std::arch::x86_64::*;
        // SAFETY: R is f32 (so the copies are f32 to f32 and [f32; 4] to
        // [f32; 4]); `near`/`far` entries are < 6 by construction; a node
        // is 64-byte aligned, so each row is 16-byte aligned; SSE is part of x86_64.
        unsafe {
            let tm: f32 = std::mem::transmute_copy::<R, f32>(&limit);
            let row = |i: usize| _mm_load_ps(node.b.get_unchecked(i).as_ptr());
            let [ox, oy, oz, ix, iy, iz] = r.sse;
            let t0x = _mm_mul_ps(_mm_sub_ps(row(r.near[0]), ox), ix);
            let t0y = _mm_mul_ps(_mm_sub_ps(row(r.near[1]), oy), iy);
            let t0z = _mm_mul_ps(_mm_sub_ps(row(r.near[2]), oz), iz);
            let t1x = _mm_mul_ps(_mm_sub_ps(row(r.far[0]), ox), ix);
            let t1y = _mm_mul_ps(_mm_sub_ps(row(r.far[1]), oy), iy);
            let t1z = _mm_mul_ps(_mm_sub_ps(row(r.far[2]), oz), iz);
            let t0 = _mm_max_ps(_mm_max_ps(t0x, t0y), _mm_max_ps(t0z, _mm_setzero_ps()));
            let t1 = _mm_mul_ps(
                _mm_min_ps(_mm_min_ps(t1x, t1y), t1z),
                _mm_set1_ps(EXIT_WIDEN as f32),
            );
            let hit = _mm_and_ps(_mm_cmple_ps(t0, t1), _mm_cmple_ps(t0, _mm_set1_ps(tm)));
            let mut t = [0f32; 4];
            _mm_storeu_ps(t.as_mut_ptr(), t0);
            return (
                _mm_movemask_ps(hit) as u32,
                std::mem::transmute_copy::<[f32; 4], [R; 4]>(&t),
            );
        }
    }
    let widen = R::from_f64(EXIT_WIDEN as f32 as f64);
    let mut mask = 0;
    let mut t = [R::ZERO; 4];
    for (k, tk) in t.iter_mut().enumerate() {
        let d = |rows: &[usize; 3], a: usize| {
            (R::from_f64(node.b[rows[a]][k] as f64) - r.origin[a]) * r.inv[a]
        };
        let t0 = d(&r.near, 0)
            .max(d(&r.near, 1))
            .max(d(&r.near, 2).max(R::ZERO));
        let t1 = d(&r.far, 0).min(d(&r.far, 1)).min(d(&r.far, 2)) * widen;
        if t0 <= t1 && t0 <= limit {
            mask |= 1 << k;
            *tk = t0;
        }
    }
    (mask, t)
}

/// Tests the primitives `prims[first .. first + count]` of a leaf: `best`
/// and `found` are updated on each hit that is [`PrimId::nearer`]. With
/// `ANY`, stops at the first hit before `best` (and returns true). In `f32` over packed triangles the 4-wide test
/// does the bulk of the work; lanes it leaves open are finished in order
/// with the same arithmetic as the scalar test, so the result is the same.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn leaf<R: Real, P: Primitives<R>, const ANY: bool>(
    view: &P,
    bvh: &Bvh,
    ray: &Ray<R>,
    tr: &TriangleRay<R>,
    (first, count): (usize, usize),
    best: &mut R,
    found: &mut PrimId,
    skip: PrimId,
) -> bool {
    #[cfg(target_arch = "x86_64")]
    if std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>()
        && first % 4 == 0
        && (first + count).div_ceil(4) <= bvh.packets.len()
    {
        // SAFETY: R is f32, so these are the same types.
        let (tr, best) = unsafe {
            (
                &*(tr as *const TriangleRay<R> as *const TriangleRay<f32>),
                &mut *(best as *mut R as *mut f32),
            )
        };
        let end = first + count;
        let mut p = first;
        while p < end {
            let packet = &bvh.packets[p / 4];
            let e = tr.edges4(packet, (1u32 << (end - p).min(4)) - 1);
            let mut m = e.candidates | e.exact;
            while m != 0 {
                let j = m.trailing_zeros() as usize;
                m &= m - 1;
                // The same as prims[p + j] (`pack_triangles`), without touching prims.
                let id = PrimId(packet.ids[j]);
                if id == skip {
                    continue;
                }
                let t = if (e.exact >> j) & 1 != 0 {
                    // The packet holds the triangle itself.
                    packet.triangle(j).distance(tr, *best)
                } else {
                    finish(e.t_scaled[j], e.det[j], *best)
                };
                if let Some(t) = t {
                    if ANY {
                        if t < *best {
                            return true;
                        }
                    } else if id.nearer(t, *best, *found) {
                        *best = t;
                        *found = id;
                    }
                }
            }
            p += 4;
        }
        return false;
    }
    for &id in &bvh.prims[first..first + count] {
        if let Some(t) = view.intersect(id, ray, tr, *best, skip) {
            if ANY {
                if t < *best {
                    return true;
                }
            } else if id.nearer(t, *best, *found) {
                *best = t;
                *found = id;
            }
        }
    }
    false
}

/// Sorts subtrees to visit by entry distance, farthest first (insertion
/// sort: there are at most four).
#[inline(always)]
pub(super) fn far_to_near<E, T: PartialOrd>(e: &mut [E], t: impl Fn(&E) -> T) {
    for i in 1..e.len() {
        let mut j = i;
        while j > 0 && t(&e[j - 1]) < t(&e[j]) {
            e.swap(j - 1, j);
            j -= 1;
        }
    }
}

/// A subtree still to visit: a slot's `child` and `count` (a node when
/// `count` is 0, else a leaf) and the distance at which the ray enters it.
#[derive(Clone, Copy)]
struct Entry<R> {
    child: u32,
    count: u32,
    t: R,
}

/// The nearest of `(best, found)` (a hit found elsewhere, or infinity and
/// `PrimId::NONE`) and the hits on the tree's primitives, by
/// [`PrimId::nearer`]; `None` if there is none.
#[inline]
pub fn closest_hit<R: Real, P: Primitives<R>>(
    view: &P,
    bvh: &Bvh,
    ray: &Ray<R>,
    mut best: R,
    mut found: PrimId,
    skip: PrimId,
) -> Option<(R, PrimId)> {
    if bvh.nodes.is_empty() {
        return (found != PrimId::NONE).then_some((best, found));
    }
    let br = BoxRay::new(ray);
    let widen = R::from_f64(CULL_WIDEN as f32 as f64);
    let mut limit = best * widen;
    // Set up at the first leaf: many rays (most primary rays past a model) never reach one.
    let mut tr: Option<TriangleRay<R>> = None;
    // Uninitialised: zeroing the stack per ray costs more than a short traversal.
    let mut stack = [const { MaybeUninit::<Entry<R>>::uninit() }; STACK];
    let mut sp = 0usize;
    // The subtree being visited; the root is node 0.
    let mut cur = Entry {
        child: 0,
        count: 0,
        t: R::ZERO,
    };
    loop {
        if cur.count == 0 {
            let n = &bvh.nodes[cur.child as usize];
            let (mask, t) = test4(n, &br, limit);
            let slot = |k: usize| Entry {
                child: n.child[k],
                count: n.count[k],
                t: t[k],
            };
            if mask != 0 {
                let a = mask.trailing_zeros() as usize;
                let rest = mask & (mask - 1);
                if rest == 0 {
                    cur = slot(a);
                    continue;
                }
                let b = rest.trailing_zeros() as usize;
                let rest = rest & (rest - 1);
                if rest == 0 {
                    // Two: the nearer now, the farther later.
                    let (near, far) = if t[a] <= t[b] { (a, b) } else { (b, a) };
                    stack[sp].write(slot(far));
                    sp += 1;
                    cur = slot(near);
                    continue;
                }
                // Three or four: sorted far to near, all but the nearest pushed.
                let mut e = [
                    slot(a),
                    slot(b),
                    slot(rest.trailing_zeros() as usize),
                    slot(0),
                ];
                let mut len = 3;
                let rest = rest & (rest - 1);
                if rest != 0 {
                    e[3] = slot(rest.trailing_zeros() as usize);
                    len = 4;
                }
                far_to_near(&mut e[..len], |x| x.t);
                for x in &e[..len - 1] {
                    stack[sp].write(*x);
                    sp += 1;
                }
                cur = e[len - 1];
                continue;
            }
        } else {
            let tr = tr.get_or_insert_with(|| TriangleRay::new(ray));
            leaf::<R, P, false>(
                view,
                bvh,
                ray,
                tr,
                (cur.child as usize, cur.count as usize),
                &mut best,
                &mut found,
                skip,
            );
            limit = best * widen;
        }
        // Pop the next subtree that may still hold something nearer.
        loop {
            if sp == 0 {
                return (found != PrimId::NONE).then_some((best, found));
            }
            sp -= 1;
            // SAFETY: entries below `sp` were written before `sp` was raised past them.
            let e = unsafe { stack[sp].assume_init() };
            if e.t <= limit {
                cur = e;
                break;
            }
        }
    }
}

/// Whether any primitive of the tree lies on the ray before `t_max`. Leaves
/// are tested as soon as their box is met (any hit ends the search).
#[inline]
pub fn occluded<R: Real, P: Primitives<R>>(
    view: &P,
    bvh: &Bvh,
    ray: &Ray<R>,
    t_max: R,
    skip: PrimId,
) -> bool {
    if bvh.nodes.is_empty() {
        return false;
    }
    let br = BoxRay::new(ray);
    let limit = t_max * R::from_f64(CULL_WIDEN as f32 as f64);
    // Set up at the first leaf: many rays (most primary rays past a model) never reach one.
    let mut tr: Option<TriangleRay<R>> = None;
    let mut stack = [const { MaybeUninit::<u32>::uninit() }; STACK];
    let mut sp = 0usize;
    let mut node = 0usize;
    loop {
        let n = &bvh.nodes[node];
        let (mut mask, _) = test4(n, &br, limit);
        let mut next = None;
        while mask != 0 {
            let k = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            if n.count[k] > 0 {
                let (mut t, mut id) = (t_max, PrimId::NONE);
                let tr = tr.get_or_insert_with(|| TriangleRay::new(ray));
                if leaf::<R, P, true>(
                    view,
                    bvh,
                    ray,
                    tr,
                    (n.child[k] as usize, n.count[k] as usize),
                    &mut t,
                    &mut id,
                    skip,
                ) {
                    return true;
                }
            } else if next.is_none() {
                next = Some(n.child[k] as usize);
            } else {
                stack[sp].write(n.child[k]);
                sp += 1;
            }
        }
        if let Some(c) = next {
            node = c;
            continue;
        }
        if sp == 0 {
            return false;
        }
        sp -= 1;
        // SAFETY: entries below `sp` were written before `sp` was raised past them.
        node = unsafe { stack[sp].assume_init() } as usize;
    }
}
