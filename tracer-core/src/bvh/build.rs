//! Building a tree: a binary tree by the binned surface area heuristic
//! (subtrees of many primitives on other rayon tasks), held within
//! [`MAX_DEPTH`] binary levels by median splits where the SAH would go
//! deeper, then collapsed into the 4-wide tree (a node's slots are its
//! binary grandchildren) and flattened into [`BvhNode4`]s depth first.
//!
//! The build sees only boxes and ids ([`Bvh::build`]): what the boxes bound
//! is the caller's business (`accel.rs` boxes a world's spheres and
//! triangles).

use std::time::Instant;

use glam::Vec3A;

use super::{Aabb, Bvh, BvhNode4, BvhStats, MAX_DEPTH, stack_for_depth};
use crate::geometry::PrimId;
use crate::triangle::{Triangle, Triangle4};

/// Leaves hold at most this many primitives.
const MAX_LEAF: usize = 8;
/// Binned SAH: bins per axis (at most; nodes of fewer primitives use as many bins, at least 4).
const BINS: usize = 16;
/// Relative costs of a node visit and a primitive test in the binary SAH.
/// Measured with `examples/mesh_bench` (bunny, dragon) on the 4-wide tree:
/// 3 gives the same ray rates as 2 (and 1) with a 15-20% faster build; 4
/// slows primary rays on the bunny by ~4%.
const COST_TRAVERSE: f32 = 3.0;
const COST_INTERSECT: f32 = 1.0;
/// Subtrees larger than this are built on another rayon task.
const PARALLEL_MIN: usize = 4096;

/// Source of [`Bvh::id`].
static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// Build-time tree before flattening. Kept small (40 bytes a node, a
/// box of 24): a big mesh's build holds about one node a triangle, beside
/// the triangles themselves, and that is its peak memory.
enum BuildNode {
    Leaf {
        bounds: BuildBox,
        start: u32,
        count: u32,
    },
    Inner {
        bounds: BuildBox,
        children: Box<[BuildNode; 2]>,
        median: bool,
    },
}

impl BuildNode {
    fn bounds(&self) -> Aabb {
        match self {
            BuildNode::Leaf { bounds, .. } | BuildNode::Inner { bounds, .. } => bounds.aabb(),
        }
    }
}

/// An [`Aabb`] as the build stores it, 24 bytes without its SIMD
/// alignment's padding (32): the build holds one a primitive and one a
/// node, the peak memory of a big mesh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildBox {
    min: [f32; 3],
    max: [f32; 3],
}

impl BuildBox {
    pub fn of(b: &Aabb) -> BuildBox {
        BuildBox {
            min: b.min.to_array(),
            max: b.max.to_array(),
        }
    }
    #[inline(always)]
    pub fn aabb(&self) -> Aabb {
        Aabb {
            min: Vec3A::from_array(self.min),
            max: Vec3A::from_array(self.max),
        }
    }
}

/// The primitives of a subtree under construction: their boxes and their
/// indices into the caller's arrays, permuted together. Boxes are moved
/// rather than indexed so that binning and partitioning stream through
/// memory (an index array into 28 MB of boxes misses the cache on every
/// access for a large mesh).
struct Prims<'a> {
    boxes: &'a mut [BuildBox],
    order: &'a mut [u32],
}

impl<'a> Prims<'a> {
    fn len(&self) -> usize {
        self.boxes.len()
    }
    fn split_at(self, mid: usize) -> (Prims<'a>, Prims<'a>) {
        let (bl, br) = self.boxes.split_at_mut(mid);
        let (ol, or) = self.order.split_at_mut(mid);
        (
            Prims {
                boxes: bl,
                order: ol,
            },
            Prims {
                boxes: br,
                order: or,
            },
        )
    }
}

fn ceil_log2(n: usize) -> usize {
    (usize::BITS - n.saturating_sub(1).leading_zeros()) as usize
}

impl Bvh {
    /// Builds a tree over `ids[i]` bounded by `boxes[i]`. Empty input gives
    /// an empty tree (no nodes), which traversal treats as a miss.
    pub fn build(boxes: &[Aabb], ids: &[PrimId]) -> Bvh {
        Self::build_with_depth(boxes, ids, MAX_DEPTH)
    }

    /// As [`Bvh::build`], with no leaf of the binary tree `depth` or more
    /// levels deep (`depth` at least 2 + ceil(log2(n)) for n primitives), so
    /// that traversal needs at most [`stack_for_depth`]`(depth)` entries.
    pub fn build_with_depth(boxes: &[Aabb], ids: &[PrimId], depth: usize) -> Bvh {
        assert_eq!(boxes.len(), ids.len());
        let work = boxes.iter().map(BuildBox::of).collect();
        Self::build_inner(work, &|i| ids[i as usize], depth)
    }

    /// As [`Bvh::build`], partitioning `boxes` itself rather than a copy,
    /// with primitive i's id `id(i)` rather than an array of them (a big
    /// scene's peak memory holds one array of boxes and none of ids).
    pub fn build_owned(boxes: Vec<BuildBox>, id: &dyn Fn(u32) -> PrimId) -> Bvh {
        Self::build_inner(boxes, id, MAX_DEPTH)
    }

    fn build_inner(mut work: Vec<BuildBox>, ids: &dyn Fn(u32) -> PrimId, depth: usize) -> Bvh {
        let stack = depth;
        let n = work.len();
        assert!(n <= u32::MAX as usize, "{n} primitives: ids are 32-bit");
        assert!(
            stack >= 2 + ceil_log2(n),
            "a depth of {stack} cannot hold a tree over {} primitives",
            n
        );
        let start = Instant::now();
        if n == 0 {
            return Bvh::default();
        }
        let mut order: Vec<u32> = (0..n as u32).collect();
        let (bounds, cbounds) = bounds_of(&work);
        let prims = Prims {
            boxes: &mut work,
            order: &mut order,
        };
        let root = build_node(stack, prims, 0, 0, bounds, cbounds);
        drop(work);

        let mut flat = Flat {
            nodes: Vec::with_capacity(n / 2 + 1),
            prims: Vec::with_capacity(n * 3 / 2),
            stats: BvhStats {
                primitives: n,
                ..Default::default()
            },
            order: &order,
            ids,
        };
        flatten4(&root, 0, 0, &mut flat);
        let Flat {
            nodes,
            prims,
            mut stats,
            ..
        } = flat;
        stats.nodes = nodes.len();
        stats.bytes = nodes.len() * std::mem::size_of::<BvhNode4>()
            + prims.len() * std::mem::size_of::<PrimId>();
        stats.build_time = start.elapsed();
        debug_assert!(stats.stack <= stack_for_depth(stack));
        Bvh {
            nodes,
            prims,
            packets: Vec::new(),
            slots: Vec::new(),
            stats,
            id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
        }
    }

    /// Fills [`Bvh::packets`] from `triangles` (the world's, in `f32`, which
    /// `prims` refer to): lane j of packet i is the triangle at `prims[4 i + j]`,
    /// with that `PrimId` in `ids[j]`.
    /// Only for trees over triangles alone; others keep none.
    pub fn pack_triangles(&mut self, triangles: &[Triangle<f32>]) {
        self.packets.clear();
        if !self.packable(triangles.len()) {
            return;
        }
        self.packets = self
            .prims
            .chunks(4)
            .map(|c| {
                let mut p = Triangle4::default();
                for (j, id) in c.iter().enumerate().filter(|(_, id)| **id != PrimId::NONE) {
                    p.set(j, &triangles[id.index()]);
                    p.ids[j] = id.0;
                }
                p
            })
            .collect();
        self.stats.bytes += self.packets.len() * std::mem::size_of::<Triangle4>();
    }

    /// [`Bvh::pack_triangles`] taking the triangles, which the packets then
    /// hold alone: [`Bvh::triangle`] reads one back through
    /// [`Bvh::slots`]. The triangles must be in leaf order (each id at a
    /// later slot than the one before, as `accel::build` leaves them). The
    /// packets are made from the last back and the triangles cut behind
    /// them as they go, so the two are never both held whole (a big mesh's
    /// peak memory). Gives the triangles back, unpacked, for a tree that
    /// holds other primitives or is not in leaf order.
    pub fn pack_triangles_owned(
        &mut self,
        mut triangles: Vec<Triangle<f32>>,
    ) -> Result<(), Vec<Triangle<f32>>> {
        self.packets.clear();
        self.slots.clear();
        let n = triangles.len();
        // Each triangle once, in id order: the cut behind the packets then
        // drops only packed ones.
        let mut named = 0;
        let in_order = self
            .prims
            .iter()
            .filter(|id| **id != PrimId::NONE)
            .all(|id| {
                named += 1;
                id.index() == named - 1
            })
            && named == n;
        if !self.packable(n) || !in_order || self.prims.len() >= u32::MAX as usize {
            return Err(triangles);
        }
        // Zeroed memory is not resident until written: the packets' pages
        // come as they are filled.
        let mut packets: Vec<Triangle4> = bytemuck::zeroed_vec(self.prims.len().div_ceil(4));
        let mut slots: Vec<u32> = bytemuck::zeroed_vec(n);
        const CHUNK: usize = 1 << 14;
        let mut end = packets.len();
        while end > 0 {
            let start = end.saturating_sub(CHUNK);
            for i in (start..end).rev() {
                let mut p = Triangle4::default();
                for (j, id) in self.prims[4 * i..(4 * i + 4).min(self.prims.len())]
                    .iter()
                    .enumerate()
                    .filter(|(_, id)| **id != PrimId::NONE)
                {
                    p.set(j, &triangles[id.index()]);
                    p.ids[j] = id.0;
                    slots[id.index()] = (4 * i + j) as u32;
                }
                packets[i] = p;
            }
            // Every triangle from the first of packet `start` on is packed.
            let first = self.prims[4 * start..]
                .iter()
                .find(|id| **id != PrimId::NONE)
                .map_or(n, |id| id.index());
            triangles.truncate(first);
            triangles.shrink_to_fit();
            end = start;
        }
        self.packets = packets;
        self.slots = slots;
        self.stats.bytes += self.packets.len() * std::mem::size_of::<Triangle4>()
            + self.slots.len() * std::mem::size_of::<u32>();
        Ok(())
    }

    /// Whether `prims` names triangles below `n` alone (or nothing).
    fn packable(&self, n: usize) -> bool {
        self.prims
            .iter()
            .all(|p| *p == PrimId::NONE || (p.kind() == PrimId::TRIANGLE && p.index() < n))
    }

    /// Triangle `index` of a tree packed by [`Bvh::pack_triangles_owned`].
    #[inline]
    pub fn triangle(&self, index: usize) -> Triangle<f32> {
        let slot = self.slots[index] as usize;
        self.packets[slot / 4].triangle(slot % 4)
    }
}

fn bounds_of(boxes: &[BuildBox]) -> (Aabb, Aabb) {
    let mut b = Aabb::EMPTY;
    let mut c = Aabb::EMPTY;
    for p in boxes {
        let p = &p.aabb();
        b.grow(p);
        c.grow_point(p.centroid());
    }
    (b, c)
}

/// Builds the subtree over `prims` (which start at `offset` in the final
/// order), at depth `depth`, partitioning them in place. `bounds` and
/// `cbounds` bound the primitives' boxes and centroids; `stack` is the
/// traversal stack size (leaves at most `stack - 1` deep).
fn build_node(
    stack: usize,
    prims: Prims,
    offset: usize,
    depth: usize,
    bounds: Aabb,
    cbounds: Aabb,
) -> BuildNode {
    let n = prims.len();
    if n == 1 {
        return BuildNode::Leaf {
            bounds: BuildBox::of(&bounds),
            start: offset as u32,
            count: 1,
        };
    }
    // Depth budget: median splits finish any subtree within ceil(log2 n)
    // more levels, so use them once the SAH could overrun the stack.
    let median = depth + ceil_log2(n) >= stack - 1;
    let split = if median {
        None
    } else {
        sah_split(prims.boxes, &bounds, &cbounds)
    };
    let mut prims = prims;
    let (mid, lb, rb) = match split {
        Some(Split::Leaf) => {
            return BuildNode::Leaf {
                bounds: BuildBox::of(&bounds),
                start: offset as u32,
                count: n as u32,
            };
        }
        Some(Split::Bin {
            axis,
            bin,
            lo,
            scale,
            top,
            left,
            right,
        }) => {
            let (mid, lc, rc) = partition_bins(&mut prims, axis, bin, lo, scale, top);
            (mid, (left, lc), (right, rc))
        }
        None => {
            if !median && n <= MAX_LEAF {
                return BuildNode::Leaf {
                    bounds: BuildBox::of(&bounds),
                    start: offset as u32,
                    count: n as u32,
                };
            }
            let mid = median_split(&mut prims, &cbounds);
            (
                mid,
                bounds_of(&prims.boxes[..mid]),
                bounds_of(&prims.boxes[mid..]),
            )
        }
    };
    let (left, right) = prims.split_at(mid);
    let build_l = move || build_node(stack, left, offset, depth + 1, lb.0, lb.1);
    let build_r = move || build_node(stack, right, offset + mid, depth + 1, rb.0, rb.1);
    let (l, r) = if n >= PARALLEL_MIN {
        rayon::join(build_l, build_r)
    } else {
        (build_l(), build_r())
    };
    BuildNode::Inner {
        bounds: BuildBox::of(&bounds),
        children: Box::new([l, r]),
        median,
    }
}

enum Split {
    Leaf,
    /// Primitives whose centroid bins below `bin` on `axis` go left; the
    /// binning (`lo`, `scale`) and both sides' box bounds.
    Bin {
        axis: usize,
        bin: usize,
        lo: Vec3A,
        scale: Vec3A,
        top: f32,
        left: Aabb,
        right: Aabb,
    },
}

/// Bins of a centroid on the three axes: `(c - lo) * scale` truncated and
/// clamped to [0, top] (NaN lands in the last bin, `top`). The one function
/// both binning and partitioning use, so their counts agree.
#[inline(always)]
fn bins_of(c: Vec3A, lo: Vec3A, scale: Vec3A, top: f32) -> [usize; 3] {
    // `min` first: SSE's min returns its second operand for a NaN.
    let f = ((c - lo) * scale).min(Vec3A::splat(top)).max(Vec3A::ZERO);
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{__m128, __m128i, _mm_cvttps_epi32};
        // SAFETY: SSE2 is part of x86_64; both types are 16 plain bytes.
        let i: [i32; 4] =
            unsafe { std::mem::transmute::<__m128i, [i32; 4]>(_mm_cvttps_epi32(__m128::from(f))) };
        [i[0] as usize, i[1] as usize, i[2] as usize]
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        [f.x as usize, f.y as usize, f.z as usize]
    }
}

#[derive(Clone, Copy)]
struct Bin {
    bounds: Aabb,
    count: u32,
}

/// Best binned SAH split over the three axes, `Leaf` when a leaf is cheaper
/// (and allowed), `None` when the centroids cannot be separated by bins.
/// One pass over the primitives bins all three axes at once.
fn sah_split(boxes: &[BuildBox], bounds: &Aabb, cbounds: &Aabb) -> Option<Split> {
    let n = boxes.len();
    let lo = cbounds.min;
    // Bins in use: as many as primitives, from 4 up to BINS (small nodes,
    // which are most nodes, then sweep fewer empty bins).
    let nb = n.clamp(4, BINS);
    let top = (nb - 1) as f32;
    let extent = cbounds.max - lo;
    // Axes with no spread (or one too small to bin) get scale 0: every
    // primitive lands in bin 0 there, so they offer no split.
    let scale = Vec3A::from_array([0, 1, 2].map(|a| {
        let s = nb as f32 * (1.0 - 1e-6) / extent[a];
        if extent[a] > 0.0 && s.is_finite() {
            s
        } else {
            0.0
        }
    }));
    let empty = Bin {
        bounds: Aabb::EMPTY,
        count: 0,
    };
    let mut bins = [[empty; BINS]; 3];
    for b in boxes {
        let b = &b.aabb();
        let k = bins_of(b.centroid(), lo, scale, top);
        for axis in 0..3 {
            let bin = &mut bins[axis][k[axis]];
            bin.bounds.grow(b);
            bin.count += 1;
        }
    }
    // Best (cost, axis, bin); bin 0 means none yet (a split has bin >= 1).
    let (mut best_cost, mut best_axis, mut best_bin) = (f32::INFINITY, 0usize, 0usize);
    for (axis, bins) in bins.iter().enumerate() {
        // Sweep from the right to get the cost of each right side.
        let mut right_area = [0.0f32; BINS];
        let mut right_count = [0u32; BINS];
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for b in (1..nb).rev() {
            acc.grow(&bins[b].bounds);
            cnt += bins[b].count;
            right_area[b] = acc.half_area();
            right_count[b] = cnt;
        }
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for b in 0..nb - 1 {
            acc.grow(&bins[b].bounds);
            cnt += bins[b].count;
            let rc = right_count[b + 1];
            let cost = acc.half_area() * cnt as f32 + right_area[b + 1] * rc as f32;
            // Branch-free: which bin wins is data-dependent and mispredicts.
            let better = cnt != 0 && rc != 0 && (cost < best_cost || best_bin == 0);
            best_cost = if better { cost } else { best_cost };
            best_axis = if better { axis } else { best_axis };
            best_bin = if better { b + 1 } else { best_bin };
        }
    }
    if best_bin == 0 {
        return None;
    }
    let (cost, axis, bin) = (best_cost, best_axis, best_bin);
    let parent = bounds.half_area();
    let split_cost = COST_TRAVERSE + COST_INTERSECT * cost / parent;
    let leaf_cost = COST_INTERSECT * n as f32;
    // A flat parent (area 0) gives NaN or inf: then just split.
    if n <= MAX_LEAF && parent > 0.0 && leaf_cost <= split_cost {
        return Some(Split::Leaf);
    }
    let side = |range: std::ops::Range<usize>| {
        let mut b = Aabb::EMPTY;
        for k in range {
            b.grow(&bins[axis][k].bounds);
        }
        b
    };
    Some(Split::Bin {
        axis,
        bin,
        lo,
        scale,
        top,
        left: side(0..bin),
        right: side(bin..nb),
    })
}

/// Moves primitives of bins < `bin` to the front; returns how many and the
/// centroid bounds of both sides (gathered here rather than per bin: one
/// box grow per primitive instead of three). Bins are computed exactly as
/// in [`sah_split`], so the counts match.
fn partition_bins(
    prims: &mut Prims,
    axis: usize,
    bin: usize,
    lo: Vec3A,
    scale: Vec3A,
    top: f32,
) -> (usize, Aabb, Aabb) {
    let (mut lc, mut rc) = (Aabb::EMPTY, Aabb::EMPTY);
    // Classifies a box, growing its side's centroid bounds.
    let mut left = |b: &BuildBox| {
        let c = b.aabb().centroid();
        let l = bins_of(c, lo, scale, top)[axis] < bin;
        if l {
            lc.grow_point(c)
        } else {
            rc.grow_point(c)
        }
        l
    };
    // Hoare's scheme: each primitive is classified once, each misplaced pair swapped once.
    let (mut i, mut j) = (0, prims.len());
    loop {
        while i < j && left(&prims.boxes[i]) {
            i += 1;
        }
        if i == j {
            break;
        }
        // boxes[i] goes right (and is counted so); find a left one from the end.
        j -= 1;
        while i < j && !left(&prims.boxes[j]) {
            j -= 1;
        }
        if i == j {
            break;
        }
        prims.boxes.swap(i, j);
        prims.order.swap(i, j);
        i += 1;
    }
    debug_assert!(i > 0 && i < prims.len());
    (i, lc, rc)
}

/// Halves the primitives by count along the widest centroid axis (in their
/// current order when all centroids coincide): always makes progress,
/// whatever the geometry. Rare (degenerate or depth-limited subtrees), so it
/// sorts pairs in a scratch vector.
fn median_split(prims: &mut Prims, cbounds: &Aabb) -> usize {
    let mid = prims.len() / 2;
    let ext = cbounds.max - cbounds.min;
    let axis = if ext.x >= ext.y && ext.x >= ext.z {
        0
    } else if ext.y >= ext.z {
        1
    } else {
        2
    };
    if ext[axis] > 0.0 {
        let mut pairs: Vec<(BuildBox, u32)> = prims
            .boxes
            .iter()
            .copied()
            .zip(prims.order.iter().copied())
            .collect();
        pairs.select_nth_unstable_by(mid, |a, b| {
            a.0.aabb().centroid()[axis].total_cmp(&b.0.aabb().centroid()[axis])
        });
        for (k, (b, o)) in pairs.into_iter().enumerate() {
            prims.boxes[k] = b;
            prims.order[k] = o;
        }
    }
    mid
}

/// Writes the wide node of the binary subtree `node` (an interior node, or
/// the root leaf of a one-leaf tree) and, after it, its subtrees; returns
/// its index. Its slots are the binary node's grandchildren, or a child
/// itself where that is a leaf: each wide level is two binary levels, so
/// the depth bound of the binary build carries over (see [`super::STACK`]).
/// `need` is the traversal stack occupancy on arrival at this node. Leaves
/// get their primitives copied to `out.prims` in this depth-first order,
/// each leaf starting at a multiple of 4 (padded with `PrimId::NONE`), so
/// that a leaf's triangles fill whole [`Triangle4`] packets.
fn flatten4(node: &BuildNode, depth: usize, need: usize, out: &mut Flat) -> u32 {
    let at = out.nodes.len();
    out.nodes.push(BvhNode4::EMPTY);
    let stats = &mut out.stats;
    let mut slots: [Option<&BuildNode>; 4] = [None; 4];
    let mut n = 0;
    match node {
        BuildNode::Leaf { .. } => {
            slots[0] = Some(node);
            n = 1;
        }
        BuildNode::Inner {
            children, median, ..
        } => {
            stats.depth_limited |= *median;
            for c in children.iter() {
                match c {
                    BuildNode::Inner {
                        children: grand,
                        median,
                        ..
                    } => {
                        stats.depth_limited |= *median;
                        slots[n] = Some(&grand[0]);
                        slots[n + 1] = Some(&grand[1]);
                        n += 2;
                    }
                    leaf => {
                        slots[n] = Some(leaf);
                        n += 1;
                    }
                }
            }
        }
    }
    // This node pushes at most n - 1 entries before descending into one.
    let need = need + n - 1;
    stats.stack = stats.stack.max(need);
    let mut node = BvhNode4::EMPTY;
    for (k, c) in slots[..n].iter().flatten().enumerate() {
        node.set_box(k, &c.bounds());
        match c {
            BuildNode::Leaf { start, count, .. } => {
                let stats = &mut out.stats;
                stats.leaves += 1;
                stats.depth = stats.depth.max(depth + 1);
                let (start, count) = (*start as usize, *count as usize);
                stats.max_leaf_size = stats.max_leaf_size.max(count);
                let first = out.prims.len().next_multiple_of(4);
                out.prims.resize(first, PrimId::NONE);
                out.prims.extend(
                    out.order[start..start + count]
                        .iter()
                        .map(|&i| (out.ids)(i)),
                );
                node.child[k] = first as u32;
                node.count[k] = count as u32;
            }
            BuildNode::Inner { .. } => node.child[k] = flatten4(c, depth + 1, need, out),
        }
    }
    out.nodes[at] = node;
    at as u32
}

/// The flattened tree as it is written, and what the leaves refer to.
struct Flat<'a> {
    nodes: Vec<BvhNode4>,
    prims: Vec<PrimId>,
    stats: BvhStats,
    /// The build's order: leaf `start..start + count` covers `ids[order[start..start + count]]`.
    order: &'a [u32],
    ids: &'a dyn Fn(u32) -> PrimId,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::STACK;

    fn unit_box(c: [f32; 3], r: f32) -> Aabb {
        let c = Vec3A::from_array(c);
        Aabb {
            min: c - Vec3A::splat(r),
            max: c + Vec3A::splat(r),
        }
    }

    /// Checks the layout invariants: every primitive in exactly one leaf,
    /// children inside their parents, empty slots inverted, the stack need
    /// as recorded and within `stack`.
    fn check(bvh: &Bvh, boxes: &[Aabb], stack: usize) {
        let mut seen = vec![0u32; boxes.len()];
        let mut todo = vec![(
            0usize,
            0usize,
            Aabb {
                min: Vec3A::splat(f32::NEG_INFINITY),
                max: Vec3A::splat(f32::INFINITY),
            },
        )];
        let mut most = 0;
        while let Some((i, need, parent)) = todo.pop() {
            let n = bvh.nodes[i];
            let used = (0..4).filter(|&k| !n.is_empty(k)).count();
            assert!(used >= 1);
            let need = need + used - 1;
            most = most.max(need);
            assert!(need <= stack, "node {i} needs {need} stack entries");
            for k in 0..4 {
                let nb = n.slot_box(k);
                if n.is_empty(k) {
                    assert!(
                        nb.min.cmpgt(nb.max).all(),
                        "empty slot {k} of node {i} has a box"
                    );
                    continue;
                }
                assert!(nb.min.cmpge(parent.min).all() && nb.max.cmple(parent.max).all());
                if n.count[k] == 0 {
                    assert!(n.child[k] as usize > i);
                    todo.push((n.child[k] as usize, need, nb));
                } else {
                    for p in &bvh.prims[n.child[k] as usize..(n.child[k] + n.count[k]) as usize] {
                        let b = boxes[p.index()];
                        assert!(b.min.cmpge(nb.min).all() && b.max.cmple(nb.max).all());
                        seen[p.index()] += 1;
                    }
                }
            }
        }
        assert_eq!(most, bvh.stats.stack);
        assert!(seen.iter().all(|&s| s == 1));
    }

    /// The build tree's node stays at 40 bytes (a big mesh's build holds
    /// about one a triangle: docs/meshes.md, "Big scenes").
    #[test]
    fn a_build_node_takes_40_bytes() {
        assert_eq!(std::mem::size_of::<BuildNode>(), 40);
    }

    #[test]
    fn builds_a_valid_tree_over_scattered_boxes() {
        let boxes: Vec<Aabb> = (0..5000u32)
            .map(|i| {
                let h = crate::sampling::hash_u32(i);
                unit_box(
                    [
                        (h & 1023) as f32,
                        ((h >> 10) & 1023) as f32,
                        ((h >> 20) & 1023) as f32,
                    ],
                    0.5,
                )
            })
            .collect();
        let ids: Vec<PrimId> = (0..boxes.len() as u32)
            .map(|i| PrimId::new(PrimId::SPHERE, i))
            .collect();
        let bvh = Bvh::build(&boxes, &ids);
        check(&bvh, &boxes, STACK);
        assert!(
            bvh.stats.depth < 20 && !bvh.stats.depth_limited,
            "{:?}",
            bvh.stats
        );
    }

    #[test]
    fn identical_boxes_and_a_degenerate_chain_stay_within_the_stack() {
        // All in one spot: no split separates them; median splits by index.
        let same = vec![unit_box([1.0, 2.0, 3.0], 0.0); 10_000];
        let ids: Vec<PrimId> = (0..same.len() as u32)
            .map(|i| PrimId::new(PrimId::TRIANGLE, i))
            .collect();
        let bvh = Bvh::build(&same, &ids);
        check(&bvh, &same, STACK);
        assert!(bvh.stats.depth <= ceil_log2(10_000).div_ceil(2));
        // Boxes at x = 2^i: the SAH peels off a few of the farthest at each
        // level (the others share the first bin), a chain 34 deep. Built for
        // a stack of 12 entries, the depth budget must take over.
        let chain: Vec<Aabb> = (0..120)
            .map(|i| unit_box([2f32.powi(i), 0.0, 0.0], 1e-3))
            .collect();
        let ids: Vec<PrimId> = (0..chain.len() as u32)
            .map(|i| PrimId::new(PrimId::TRIANGLE, i))
            .collect();
        let free = Bvh::build(&chain, &ids);
        check(&free, &chain, STACK);
        assert!(
            free.stats.depth > 15 && !free.stats.depth_limited,
            "{:?}",
            free.stats
        );
        let bounded = Bvh::build_with_depth(&chain, &ids, 12);
        check(&bounded, &chain, stack_for_depth(12));
        assert!(
            bounded.stats.depth_limited && bounded.stats.depth == 6,
            "{:?}",
            bounded.stats
        );
    }

    /// A tree that names some triangles only keeps them all: packing them
    /// away would drop the unnamed ones.
    #[test]
    fn triangles_the_tree_does_not_name_are_not_given_up() {
        let tri = |x: f32| {
            Triangle::<f32>::new([
                Vec3A::new(x, 0.0, 0.0),
                Vec3A::new(x + 1.0, 0.0, 0.0),
                Vec3A::Y,
            ])
        };
        let tris = vec![tri(0.0), tri(2.0), tri(4.0)];
        let boxes = [
            unit_box([0.5, 0.5, 0.0], 1.0),
            unit_box([2.5, 0.5, 0.0], 1.0),
        ];
        let ids = [0, 1].map(|i| PrimId::new(PrimId::TRIANGLE, i));
        let mut tree = Bvh::build(&boxes, &ids);
        let back = tree.pack_triangles_owned(tris).unwrap_err();
        assert_eq!(back.len(), 3);
        assert!(tree.packets.is_empty() && tree.slots.is_empty());
    }
}
