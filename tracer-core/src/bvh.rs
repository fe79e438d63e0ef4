//! Bounding volume hierarchy over the bounded primitives of a world
//! (triangles and spheres; infinite planes stay outside), built with the
//! binned surface area heuristic and flattened into one array of 32-byte
//! nodes that the CPU traverses here and the GPU (`render/gpu/bvh.wgsl`)
//! traverses as is, uploaded unchanged.
//!
//! Layout (mirrored by `bvh.wgsl`'s `struct BvhNode`; `#[repr(C)]`, `Pod`):
//! - `nodes[0]` is the root (`nodes[1]` is unused padding). An interior node
//!   (`count == 0`) has its two children side by side at `first` and
//!   `first + 1`, `first` even: the pair is one 64-byte cache line (the
//!   array is stored as 64-byte aligned [`NodePair`]s). A leaf (`count > 0`)
//!   covers `prims[first .. first + count]`, which are packed [`PrimId`]s.
//! - Bounds are `f32`, rounded outward from the world's coordinates, so
//!   they are conservative for the `f64` reference as well.
//! - No leaf is deeper than [`MAX_DEPTH`] - 1 (the root is depth 0), so a
//!   traversal stack of [`MAX_DEPTH`] entries never overflows: the builder
//!   switches from SAH to median splits where a subtree could get deeper.

use std::mem::MaybeUninit;
use std::time::{Duration, Instant};

use bytemuck::{Pod, Zeroable};
use glam::Vec3A;

use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3};
use crate::triangle::TriangleRay;
use crate::world::World;

/// Entries of the traversal stack; the tree is built no deeper than this.
pub const MAX_DEPTH: usize = 64;
/// Leaves hold at most this many primitives (unless they all share one centroid).
const MAX_LEAF: usize = 8;
/// Binned SAH: bins per axis.
const BINS: usize = 16;
/// Relative costs of a node visit (two box tests) and a primitive test.
/// Measured with `examples/mesh_bench` (bunny, dragon): 2 gives the same
/// ray rates as 1 with 35% fewer nodes and a 20% faster build; 3 builds
/// faster still but slows incoherent rays on the dragon by ~8%.
const COST_TRAVERSE: f32 = 2.0;
const COST_INTERSECT: f32 = 1.0;
/// Subtrees larger than this are built on another rayon task.
const PARALLEL_MIN: usize = 4096;

/// One node of the flattened tree (see the module docs for the layout).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct BvhNode {
    pub min: [f32; 3],
    /// Interior: index of the left child (the right one follows it). Leaf: first index into `prims`.
    pub first: u32,
    pub max: [f32; 3],
    /// 0 for an interior node, else the number of primitives of the leaf.
    pub count: u32,
}

/// Two sibling nodes, aligned to a cache line: a traversal step loads both.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct NodePair(pub [BvhNode; 2]);

/// An axis-aligned box in `f32`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: Vec3A,
    pub max: Vec3A,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb { min: Vec3A::splat(f32::INFINITY), max: Vec3A::splat(f32::NEG_INFINITY) };

    /// The `f32` box that contains the `f64` box [lo, hi].
    pub fn outward(lo: [f64; 3], hi: [f64; 3]) -> Aabb {
        let down = |x: f64| {
            let f = x as f32;
            if f as f64 > x { f.next_down() } else { f }
        };
        let up = |x: f64| {
            let f = x as f32;
            if (f as f64) < x { f.next_up() } else { f }
        };
        Aabb { min: Vec3A::from_array(lo.map(down)), max: Vec3A::from_array(hi.map(up)) }
    }
    #[inline]
    pub fn grow(&mut self, o: &Aabb) {
        self.min = self.min.min(o.min);
        self.max = self.max.max(o.max);
    }
    #[inline]
    fn grow_point(&mut self, p: Vec3A) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }
    /// Half the surface area (the SAH only compares ratios); 0 for empty boxes.
    #[inline]
    fn half_area(&self) -> f32 {
        let d = (self.max - self.min).max(Vec3A::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    }
    #[inline]
    fn centroid(&self) -> Vec3A {
        (self.min + self.max) * 0.5
    }
}

/// Figures about a built tree, for reports and tests.
#[derive(Clone, Copy, Debug, Default)]
pub struct BvhStats {
    pub build_time: Duration,
    pub nodes: usize,
    pub leaves: usize,
    pub primitives: usize,
    /// Depth of the deepest leaf (the root is depth 0).
    pub depth: usize,
    pub max_leaf_size: usize,
    /// Bytes of `nodes` + `prims`.
    pub bytes: usize,
    /// Whether some subtree was built with median splits to respect [`MAX_DEPTH`].
    pub depth_limited: bool,
}

#[derive(Clone, Debug, Default)]
pub struct Bvh {
    /// The node array, as cache-line pairs: node `i` is `pairs[i / 2].0[i % 2]`.
    pub pairs: Vec<NodePair>,
    pub prims: Vec<PrimId>,
    pub stats: BvhStats,
    /// Unique per build (never 0 for a built tree; 0 for a tree made any
    /// other way): lets a GPU renderer keep an uploaded tree while the
    /// same world renders tile after tile, without comparing its contents.
    pub id: u64,
}

/// Source of [`Bvh::id`].
static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// Build-time tree before flattening.
enum BuildNode {
    Leaf { bounds: Aabb, start: usize, count: usize },
    Inner { bounds: Aabb, children: Box<[BuildNode; 2]>, median: bool },
}

impl BuildNode {
    fn bounds(&self) -> &Aabb {
        match self {
            BuildNode::Leaf { bounds, .. } | BuildNode::Inner { bounds, .. } => bounds,
        }
    }
}

/// The primitives of a subtree under construction: their boxes and their
/// indices into the caller's arrays, permuted together. Boxes are moved
/// rather than indexed so that binning and partitioning stream through
/// memory (an index array into 28 MB of boxes misses the cache on every
/// access for a large mesh).
struct Prims<'a> {
    boxes: &'a mut [Aabb],
    order: &'a mut [u32],
}

impl<'a> Prims<'a> {
    fn len(&self) -> usize {
        self.boxes.len()
    }
    fn split_at(self, mid: usize) -> (Prims<'a>, Prims<'a>) {
        let (bl, br) = self.boxes.split_at_mut(mid);
        let (ol, or) = self.order.split_at_mut(mid);
        (Prims { boxes: bl, order: ol }, Prims { boxes: br, order: or })
    }
}

fn ceil_log2(n: usize) -> usize {
    (usize::BITS - n.saturating_sub(1).leading_zeros()) as usize
}

impl Bvh {
    /// Builds a tree over `ids[i]` bounded by `boxes[i]`. Empty input gives
    /// an empty tree (no nodes), which traversal treats as a miss.
    pub fn build(boxes: &[Aabb], ids: &[PrimId]) -> Bvh {
        Self::build_with_stack(boxes, ids, MAX_DEPTH)
    }

    /// As [`Bvh::build`], for a traversal stack of `stack` entries (at least
    /// 2 + ceil(log2(n)) for n primitives): no leaf deeper than `stack - 1`.
    pub fn build_with_stack(boxes: &[Aabb], ids: &[PrimId], stack: usize) -> Bvh {
        assert_eq!(boxes.len(), ids.len());
        assert!(stack >= 2 + ceil_log2(boxes.len()), "a stack of {stack} cannot hold a tree over {} primitives", boxes.len());
        let start = Instant::now();
        if boxes.is_empty() {
            return Bvh::default();
        }
        let mut work: Vec<Aabb> = boxes.to_vec();
        let mut order: Vec<u32> = (0..boxes.len() as u32).collect();
        let (bounds, cbounds) = bounds_of(&work);
        let prims = Prims { boxes: &mut work, order: &mut order };
        let root = build_node(stack, prims, 0, 0, bounds, cbounds);

        let mut nodes = Vec::with_capacity(2 * boxes.len());
        nodes.push(BvhNode::default());
        nodes.push(BvhNode::default()); // padding: sibling pairs start at even indices
        let mut stats = BvhStats { primitives: boxes.len(), ..Default::default() };
        flatten(&root, 0, 0, &mut nodes, &mut stats);
        let prims: Vec<PrimId> = order.iter().map(|&i| ids[i as usize]).collect();
        let pairs: Vec<NodePair> = nodes.chunks_exact(2).map(|c| NodePair([c[0], c[1]])).collect();
        stats.nodes = nodes.len() - 1;
        stats.bytes = pairs.len() * std::mem::size_of::<NodePair>() + prims.len() * std::mem::size_of::<PrimId>();
        stats.build_time = start.elapsed();
        debug_assert!(stats.depth < stack);
        Bvh { pairs, prims, stats, id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed) }
    }

    /// Node `i` of the flattened tree.
    #[inline(always)]
    pub fn node(&self, i: usize) -> &BvhNode {
        &self.pairs[i >> 1].0[i & 1]
    }

    /// The node array as bytes, for upload to a GPU (32 bytes per node).
    pub fn node_bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.pairs)
    }
}

fn bounds_of(boxes: &[Aabb]) -> (Aabb, Aabb) {
    let mut b = Aabb::EMPTY;
    let mut c = Aabb::EMPTY;
    for p in boxes {
        b.grow(p);
        c.grow_point(p.centroid());
    }
    (b, c)
}

/// Builds the subtree over `prims` (which start at `offset` in the final
/// order), at depth `depth`, partitioning them in place. `bounds` and
/// `cbounds` bound the primitives' boxes and centroids; `stack` is the
/// traversal stack size (leaves at most `stack - 1` deep).
fn build_node(stack: usize, prims: Prims, offset: usize, depth: usize, bounds: Aabb, cbounds: Aabb) -> BuildNode {
    let n = prims.len();
    if n == 1 {
        return BuildNode::Leaf { bounds, start: offset, count: 1 };
    }
    // Depth budget: median splits finish any subtree within ceil(log2 n)
    // more levels, so use them once the SAH could overrun the stack.
    let median = depth + ceil_log2(n) >= stack - 1;
    let split = if median { None } else { sah_split(prims.boxes, &bounds, &cbounds) };
    let mut prims = prims;
    let (mid, lb, rb) = match split {
        Some(Split::Leaf) => return BuildNode::Leaf { bounds, start: offset, count: n },
        Some(Split::Bin { axis, bin, lo, scale, left, right }) => {
            let (mid, lc, rc) = partition_bins(&mut prims, axis, bin, lo, scale);
            (mid, (left, lc), (right, rc))
        }
        None => {
            if !median && n <= MAX_LEAF {
                return BuildNode::Leaf { bounds, start: offset, count: n };
            }
            let mid = median_split(&mut prims, &cbounds);
            (mid, bounds_of(&prims.boxes[..mid]), bounds_of(&prims.boxes[mid..]))
        }
    };
    let (left, right) = prims.split_at(mid);
    let build_l = move || build_node(stack, left, offset, depth + 1, lb.0, lb.1);
    let build_r = move || build_node(stack, right, offset + mid, depth + 1, rb.0, rb.1);
    let (l, r) = if n >= PARALLEL_MIN { rayon::join(build_l, build_r) } else { (build_l(), build_r()) };
    BuildNode::Inner { bounds, children: Box::new([l, r]), median }
}

enum Split {
    Leaf,
    /// Primitives whose centroid bins below `bin` on `axis` go left; the
    /// binning (`lo`, `scale`) and both sides' box bounds.
    Bin { axis: usize, bin: usize, lo: Vec3A, scale: Vec3A, left: Aabb, right: Aabb },
}

/// Bins of a centroid on the three axes: `(c - lo) * scale` truncated and
/// clamped to [0, BINS - 1] (NaN lands in the last bin). The one function
/// both binning and partitioning use, so their counts agree.
#[inline(always)]
fn bins_of(c: Vec3A, lo: Vec3A, scale: Vec3A) -> [usize; 3] {
    // `min` first: SSE's min returns its second operand for a NaN.
    let f = ((c - lo) * scale).min(Vec3A::splat((BINS - 1) as f32)).max(Vec3A::ZERO);
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{__m128, __m128i, _mm_cvttps_epi32};
        // SAFETY: SSE2 is part of x86_64; both types are 16 plain bytes.
        let i: [i32; 4] = unsafe { std::mem::transmute::<__m128i, [i32; 4]>(_mm_cvttps_epi32(__m128::from(f))) };
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
fn sah_split(boxes: &[Aabb], bounds: &Aabb, cbounds: &Aabb) -> Option<Split> {
    let n = boxes.len();
    let lo = cbounds.min;
    let extent = cbounds.max - lo;
    // Axes with no spread (or one too small to bin) get scale 0: every
    // primitive lands in bin 0 there, so they offer no split.
    let scale = Vec3A::from_array([0, 1, 2].map(|a| {
        let s = BINS as f32 * (1.0 - 1e-6) / extent[a];
        if extent[a] > 0.0 && s.is_finite() { s } else { 0.0 }
    }));
    let empty = Bin { bounds: Aabb::EMPTY, count: 0 };
    let mut bins = [[empty; BINS]; 3];
    for b in boxes {
        let k = bins_of(b.centroid(), lo, scale);
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
        for b in (1..BINS).rev() {
            acc.grow(&bins[b].bounds);
            cnt += bins[b].count;
            right_area[b] = acc.half_area();
            right_count[b] = cnt;
        }
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        for b in 0..BINS - 1 {
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
    Some(Split::Bin { axis, bin, lo, scale, left: side(0..bin), right: side(bin..BINS) })
}

/// Moves primitives of bins < `bin` to the front; returns how many and the
/// centroid bounds of both sides (gathered here rather than per bin: one
/// box grow per primitive instead of three). Bins are computed exactly as
/// in [`sah_split`], so the counts match.
fn partition_bins(prims: &mut Prims, axis: usize, bin: usize, lo: Vec3A, scale: Vec3A) -> (usize, Aabb, Aabb) {
    let (mut lc, mut rc) = (Aabb::EMPTY, Aabb::EMPTY);
    // Classifies a box, growing its side's centroid bounds.
    let mut left = |b: &Aabb| {
        let c = b.centroid();
        let l = bins_of(c, lo, scale)[axis] < bin;
        if l { lc.grow_point(c) } else { rc.grow_point(c) }
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
    let axis = if ext.x >= ext.y && ext.x >= ext.z { 0 } else if ext.y >= ext.z { 1 } else { 2 };
    if ext[axis] > 0.0 {
        let mut pairs: Vec<(Aabb, u32)> = prims.boxes.iter().copied().zip(prims.order.iter().copied()).collect();
        pairs.select_nth_unstable_by(mid, |a, b| a.0.centroid()[axis].total_cmp(&b.0.centroid()[axis]));
        for (k, (b, o)) in pairs.into_iter().enumerate() {
            prims.boxes[k] = b;
            prims.order[k] = o;
        }
    }
    mid
}

/// Writes `node` at `nodes[at]` and its subtree after it.
fn flatten(node: &BuildNode, at: usize, depth: usize, nodes: &mut Vec<BvhNode>, stats: &mut BvhStats) {
    let b = node.bounds();
    let (min, max) = (Vec3A::to_array(&b.min), Vec3A::to_array(&b.max));
    match node {
        BuildNode::Leaf { start, count, .. } => {
            nodes[at] = BvhNode { min, first: *start as u32, max, count: *count as u32 };
            stats.leaves += 1;
            stats.depth = stats.depth.max(depth);
            stats.max_leaf_size = stats.max_leaf_size.max(*count);
        }
        BuildNode::Inner { children, median, .. } => {
            let first = nodes.len();
            nodes.push(BvhNode::default());
            nodes.push(BvhNode::default());
            nodes[at] = BvhNode { min, first: first as u32, max, count: 0 };
            stats.depth_limited |= *median;
            flatten(&children[0], first, depth + 1, nodes, stats);
            flatten(&children[1], first + 1, depth + 1, nodes, stats);
        }
    }
}

/// Per-ray state of a slab test: origin, reciprocal direction (zeros made
/// huge-but-finite, so `0 * inv` is 0, never NaN).
#[derive(Clone, Copy)]
struct BoxRay<R: Real> {
    origin: R::V3,
    inv: R::V3,
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
        BoxRay { origin: ray.origin, inv: R::V3::new(inv1(d.x()), inv1(d.y()), inv1(d.z())) }
    }

    /// Entry distance into `node`'s box if the ray meets it within [0, t_max].
    /// The exit distance is widened by a few ulps (Ize 2013, "Robust BVH ray
    /// traversal") so that rounding never culls a box the ray grazes.
    #[inline(always)]
    fn hit(&self, node: &BvhNode, t_max: R) -> Option<R> {
        let (min, max) = load_box::<R>(node);
        let lo = (min - self.origin) * self.inv;
        let hi = (max - self.origin) * self.inv;
        let t0 = lo.min(hi).max_element().max(R::ZERO);
        let t1 = lo.max(hi).min_element() * R::from_f64(1.000_000_4);
        (t0 <= t1 && t0 <= t_max).then_some(t0)
    }
}

/// A node's box in the ray's precision. In `f32` on x86_64: two 16-byte
/// loads with the fourth lane (`first`, `count`) zeroed, rather than six
/// scalar loads and shuffles (zeroed, not ignored: as floats those integers
/// are denormals, which slow arithmetic down even in an unused lane).
#[inline(always)]
fn load_box<R: Real>(node: &BvhNode) -> (R::V3, R::V3) {
    #[cfg(target_arch = "x86_64")]
    if std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>() {
        use std::arch::x86_64::{_mm_and_ps, _mm_castsi128_ps, _mm_loadu_ps, _mm_set_epi32};
        // SAFETY: a node is 8 plain 4-byte fields, min then first, max then
        // count (`#[repr(C)]`); SSE2 is part of x86_64; R is f32, whose V3
        // is Vec3A, so the copies below are Vec3A to Vec3A.
        unsafe {
            let p = node as *const BvhNode as *const f32;
            let xyz = _mm_castsi128_ps(_mm_set_epi32(0, -1, -1, -1));
            let min = Vec3A::from(_mm_and_ps(_mm_loadu_ps(p), xyz));
            let max = Vec3A::from(_mm_and_ps(_mm_loadu_ps(p.add(4)), xyz));
            return (std::mem::transmute_copy::<Vec3A, R::V3>(&min), std::mem::transmute_copy::<Vec3A, R::V3>(&max));
        }
    }
    (load::<R>(&node.min), load::<R>(&node.max))
}

#[inline(always)]
fn load<R: Real>(a: &[f32; 3]) -> R::V3 {
    R::V3::new(R::from_f64(a[0] as f64), R::from_f64(a[1] as f64), R::from_f64(a[2] as f64))
}

/// Tests the primitive `id` against the ray; `skip` is the primitive the ray starts on.
#[inline(always)]
fn hit_prim<R: Real>(world: &World<R>, id: PrimId, ray: &Ray<R>, tri: &TriangleRay<R>, t_max: R, skip: PrimId) -> Option<R> {
    if id.kind() == PrimId::TRIANGLE {
        // A ray leaving a triangle cannot hit that (flat) triangle again.
        if id == skip {
            return None;
        }
        world.triangles[id.index()].intersect(tri, t_max)
    } else {
        world.spheres[id.index()].intersect(ray, t_max, id == skip)
    }
}

/// Nearest hit in (0, t_max) of the tree's primitives.
#[inline]
pub fn closest_hit<R: Real>(world: &World<R>, bvh: &Bvh, ray: &Ray<R>, mut best: R, skip: PrimId) -> Option<(R, PrimId)> {
    if bvh.pairs.is_empty() {
        return None;
    }
    let br = BoxRay::new(ray);
    let tr = TriangleRay::new(ray);
    br.hit(bvh.node(0), best)?;
    let mut found = PrimId::NONE;
    // Uninitialised: zeroing 64 entries per ray costs more than a short traversal.
    let mut stack = [const { MaybeUninit::<(u32, R)>::uninit() }; MAX_DEPTH];
    let mut sp = 0usize;
    let mut node = 0usize;
    loop {
        let n = bvh.node(node);
        if n.count == 0 {
            let l = n.first as usize;
            let [cl, cr] = &bvh.pairs[l >> 1].0;
            let hl = br.hit(cl, best);
            let hr = br.hit(cr, best);
            match (hl, hr) {
                (Some(a), Some(b)) => {
                    let (near, far, t_far) = if a <= b { (l, l + 1, b) } else { (l + 1, l, a) };
                    stack[sp].write((far as u32, t_far));
                    sp += 1;
                    node = near;
                    continue;
                }
                (Some(_), None) => {
                    node = l;
                    continue;
                }
                (None, Some(_)) => {
                    node = l + 1;
                    continue;
                }
                (None, None) => {}
            }
        } else {
            let first = n.first as usize;
            for &id in &bvh.prims[first..first + n.count as usize] {
                if let Some(t) = hit_prim(world, id, ray, &tr, best, skip) {
                    best = t;
                    found = id;
                }
            }
        }
        // Pop the next subtree that may still hold something nearer.
        loop {
            if sp == 0 {
                return (found != PrimId::NONE).then_some((best, found));
            }
            sp -= 1;
            // SAFETY: entries below `sp` were written before `sp` was raised past them.
            let (next, t_enter) = unsafe { stack[sp].assume_init() };
            if t_enter <= best {
                node = next as usize;
                break;
            }
        }
    }
}

/// Whether any primitive of the tree lies on the ray before `t_max`.
#[inline]
pub fn occluded<R: Real>(world: &World<R>, bvh: &Bvh, ray: &Ray<R>, t_max: R, skip: PrimId) -> bool {
    if bvh.pairs.is_empty() {
        return false;
    }
    let br = BoxRay::new(ray);
    let tr = TriangleRay::new(ray);
    if br.hit(bvh.node(0), t_max).is_none() {
        return false;
    }
    let mut stack = [const { MaybeUninit::<u32>::uninit() }; MAX_DEPTH];
    let mut sp = 0usize;
    let mut node = 0usize;
    loop {
        let n = bvh.node(node);
        if n.count == 0 {
            let l = n.first as usize;
            let [cl, cr] = &bvh.pairs[l >> 1].0;
            let hl = br.hit(cl, t_max).is_some();
            let hr = br.hit(cr, t_max).is_some();
            if hl || hr {
                if hl && hr {
                    stack[sp].write((l + 1) as u32);
                    sp += 1;
                }
                node = if hl { l } else { l + 1 };
                continue;
            }
        } else {
            let first = n.first as usize;
            for &id in &bvh.prims[first..first + n.count as usize] {
                if hit_prim(world, id, ray, &tr, t_max, skip).is_some() {
                    return true;
                }
            }
        }
        if sp == 0 {
            return false;
        }
        sp -= 1;
        // SAFETY: entries below `sp` were written before `sp` was raised past them.
        node = unsafe { stack[sp].assume_init() } as usize;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box(c: [f32; 3], r: f32) -> Aabb {
        let c = Vec3A::from_array(c);
        Aabb { min: c - Vec3A::splat(r), max: c + Vec3A::splat(r) }
    }

    /// Checks the layout invariants: every primitive in exactly one leaf,
    /// children inside their parents, leaves within the depth bound.
    fn check(bvh: &Bvh, boxes: &[Aabb], limit: usize) {
        let mut seen = vec![0u32; boxes.len()];
        let mut stack = vec![(0usize, 0usize)];
        while let Some((i, depth)) = stack.pop() {
            assert!(depth < limit, "node {i} at depth {depth}");
            let n = *bvh.node(i);
            let nb = Aabb { min: Vec3A::from_array(n.min), max: Vec3A::from_array(n.max) };
            if n.count == 0 {
                for c in [n.first as usize, n.first as usize + 1] {
                    assert_eq!(n.first % 2, 0, "sibling pairs start at even indices");
                    let cn = *bvh.node(c);
                    assert!(Vec3A::from_array(cn.min).cmpge(nb.min).all() && Vec3A::from_array(cn.max).cmple(nb.max).all());
                    stack.push((c, depth + 1));
                }
            } else {
                for p in &bvh.prims[n.first as usize..(n.first + n.count) as usize] {
                    let b = boxes[p.index()];
                    assert!(b.min.cmpge(nb.min).all() && b.max.cmple(nb.max).all());
                    seen[p.index()] += 1;
                }
            }
        }
        assert!(seen.iter().all(|&s| s == 1));
    }

    #[test]
    fn builds_a_valid_tree_over_scattered_boxes() {
        let boxes: Vec<Aabb> = (0..5000u32)
            .map(|i| {
                let h = crate::sampling::hash_u32(i);
                unit_box([(h & 1023) as f32, ((h >> 10) & 1023) as f32, ((h >> 20) & 1023) as f32], 0.5)
            })
            .collect();
        let ids: Vec<PrimId> = (0..boxes.len() as u32).map(|i| PrimId::new(PrimId::SPHERE, i)).collect();
        let bvh = Bvh::build(&boxes, &ids);
        check(&bvh, &boxes, MAX_DEPTH);
        assert!(bvh.stats.depth < 40 && !bvh.stats.depth_limited, "{:?}", bvh.stats);
    }

    #[test]
    fn identical_boxes_and_a_degenerate_chain_stay_within_the_stack() {
        // All in one spot: no split separates them; median splits by index.
        let same = vec![unit_box([1.0, 2.0, 3.0], 0.0); 10_000];
        let ids: Vec<PrimId> = (0..same.len() as u32).map(|i| PrimId::new(PrimId::TRIANGLE, i)).collect();
        let bvh = Bvh::build(&same, &ids);
        check(&bvh, &same, MAX_DEPTH);
        assert!(bvh.stats.depth <= ceil_log2(10_000));
        // Boxes at x = 2^i: the SAH peels off a few of the farthest at each
        // level (the others share the first bin), a chain 34 deep. Built for
        // a stack of 12 entries, the depth budget must take over.
        let chain: Vec<Aabb> = (0..120).map(|i| unit_box([2f32.powi(i), 0.0, 0.0], 1e-3)).collect();
        let ids: Vec<PrimId> = (0..chain.len() as u32).map(|i| PrimId::new(PrimId::TRIANGLE, i)).collect();
        let free = Bvh::build(&chain, &ids);
        check(&free, &chain, MAX_DEPTH);
        assert!(free.stats.depth > 30 && !free.stats.depth_limited, "{:?}", free.stats);
        let bounded = Bvh::build_with_stack(&chain, &ids, 12);
        check(&bounded, &chain, 12);
        assert!(bounded.stats.depth_limited && bounded.stats.depth == 11, "{:?}", bounded.stats);
    }

    #[test]
    fn node_is_32_bytes_for_the_gpu() {
        assert_eq!(std::mem::size_of::<BvhNode>(), 32);
        assert_eq!(std::mem::align_of::<BvhNode>(), 4);
        assert_eq!((std::mem::size_of::<NodePair>(), std::mem::align_of::<NodePair>()), (64, 64));
    }
}
