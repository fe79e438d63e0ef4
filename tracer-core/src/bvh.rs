//! Bounding volume hierarchy over the bounded primitives of a world
//! (triangles and spheres; infinite planes stay outside), built with the
//! binned surface area heuristic as a binary tree, collapsed into a 4-wide
//! tree (BVH4) and flattened into one array of 128-byte nodes that the CPU
//! traverses here and the GPU (`render/gpu/bvh.wgsl`) traverses as is,
//! uploaded unchanged.
//!
//! Layout (mirrored by `bvh.wgsl`'s `struct BvhNode4`; `#[repr(C)]`, `Pod`):
//! - `nodes[0]` is the root. A node has four slots, each with a box and a
//!   reference. The boxes are stored by rows, structure of arrays:
//!   `b[0]` = min x of slots 0..4, `b[1]` = max x, `b[2..4]` = min/max y,
//!   `b[4..6]` = min/max z, so one SIMD pass tests all four. Slot k refers
//!   to a node (`count[k] == 0`, `child[k]` its index, never 0), to a leaf
//!   (`count[k] > 0`: `prims[child[k] .. child[k] + count[k]]`, packed
//!   [`PrimId`]s), or to nothing (`child[k] == count[k] == 0`; its box is
//!   inverted, min +inf and max -inf, so no ray meets it). Nodes are 64-byte
//!   aligned: two cache lines.
//! - Bounds are `f32`, rounded outward from the world's coordinates, so
//!   they are conservative for the `f64` reference as well.
//! - The binary tree has no leaf deeper than [`MAX_DEPTH`] - 1 (the builder
//!   switches from SAH to median splits where a subtree could get deeper);
//!   each 4-wide level is two binary levels (a node's slots are its binary
//!   grandchildren), so a traversal stack of [`STACK`] entries (a node
//!   pushes at most three) never overflows. `BvhStats::stack` is the exact
//!   need of the tree built.

mod packet;

use std::mem::MaybeUninit;
use std::time::{Duration, Instant};

use bytemuck::{Pod, Zeroable};
use glam::Vec3A;

use crate::geometry::PrimId;
use crate::math::{Ray, Real, Vector3};
use crate::triangle::{Triangle, Triangle4, TriangleRay, finish};
use crate::world::World;

pub use packet::{
    PACKET, closest_hits, closest_hits_at, occluded_hits, occluded_hits_at, render_level,
};

/// Binary levels of the tree as built: no leaf of the binary tree is this deep.
pub const MAX_DEPTH: usize = 64;
/// Entries of the traversal stack that a tree built within [`MAX_DEPTH`]
/// binary levels never exceeds: its 4-wide nodes lie at most
/// `MAX_DEPTH / 2 - 1` deep and each pushes at most three slots.
pub const STACK: usize = stack_for_depth(MAX_DEPTH);
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

/// Traversal stack entries needed by a tree whose binary leaves lie less
/// than `depth` levels deep: its 4-wide nodes lie at depths 0 to
/// `depth / 2 - 1`, each pushing at most three slots.
pub const fn stack_for_depth(depth: usize) -> usize {
    3 * (depth / 2)
}

/// One node of the flattened 4-wide tree (see the module docs for the layout).
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct BvhNode4 {
    /// Rows of the slots' boxes: min x, max x, min y, max y, min z, max z.
    pub b: [[f32; 4]; 6],
    /// Node: index of the child node. Leaf: first index into `prims`. Empty: 0.
    pub child: [u32; 4],
    /// 0 for a child node or an empty slot, else the number of primitives of the leaf.
    pub count: [u32; 4],
}

impl BvhNode4 {
    /// A node of four empty slots.
    pub const EMPTY: BvhNode4 = {
        let (i, ni) = (f32::INFINITY, f32::NEG_INFINITY);
        BvhNode4 {
            b: [[i; 4], [ni; 4], [i; 4], [ni; 4], [i; 4], [ni; 4]],
            child: [0; 4],
            count: [0; 4],
        }
    };

    /// Sets slot `k`'s box.
    pub fn set_box(&mut self, k: usize, b: &Aabb) {
        for a in 0..3 {
            self.b[2 * a][k] = b.min[a];
            self.b[2 * a + 1][k] = b.max[a];
        }
    }

    /// Slot `k`'s box.
    pub fn slot_box(&self, k: usize) -> Aabb {
        Aabb {
            min: Vec3A::new(self.b[0][k], self.b[2][k], self.b[4][k]),
            max: Vec3A::new(self.b[1][k], self.b[3][k], self.b[5][k]),
        }
    }

    /// Whether slot `k` refers to nothing.
    pub fn is_empty(&self, k: usize) -> bool {
        self.child[k] == 0 && self.count[k] == 0
    }
}

/// An axis-aligned box in `f32`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: Vec3A,
    pub max: Vec3A,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: Vec3A::splat(f32::INFINITY),
        max: Vec3A::splat(f32::NEG_INFINITY),
    };

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
        Aabb {
            min: Vec3A::from_array(lo.map(down)),
            max: Vec3A::from_array(hi.map(up)),
        }
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
    /// 4-wide nodes.
    pub nodes: usize,
    pub leaves: usize,
    pub primitives: usize,
    /// Depth of the deepest leaf of the 4-wide tree (the root is depth 0,
    /// its slots depth 1).
    pub depth: usize,
    /// Traversal stack entries the tree can need (at most [`STACK`]).
    pub stack: usize,
    pub max_leaf_size: usize,
    /// Bytes of `nodes` + `prims`.
    pub bytes: usize,
    /// Whether some subtree was built with median splits to respect [`MAX_DEPTH`].
    pub depth_limited: bool,
}

#[derive(Clone, Debug, Default)]
pub struct Bvh {
    /// The 4-wide nodes; `nodes[0]` is the root (empty for an empty tree).
    pub nodes: Vec<BvhNode4>,
    /// Leaf references: packed [`PrimId`]s, each leaf's starting at a
    /// multiple of 4 (`PrimId::NONE` between leaves).
    pub prims: Vec<PrimId>,
    /// For trees over `f32` triangles alone (else empty): the triangles of
    /// `prims[4 i .. 4 i + 4]` as packet i, for the 4-wide triangle test (CPU only).
    pub packets: Vec<Triangle4>,
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
    Leaf {
        bounds: Aabb,
        start: usize,
        count: usize,
    },
    Inner {
        bounds: Aabb,
        children: Box<[BuildNode; 2]>,
        median: bool,
    },
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
        let stack = depth;
        assert_eq!(boxes.len(), ids.len());
        assert!(
            stack >= 2 + ceil_log2(boxes.len()),
            "a depth of {stack} cannot hold a tree over {} primitives",
            boxes.len()
        );
        let start = Instant::now();
        if boxes.is_empty() {
            return Bvh::default();
        }
        let mut work: Vec<Aabb> = boxes.to_vec();
        let mut order: Vec<u32> = (0..boxes.len() as u32).collect();
        let (bounds, cbounds) = bounds_of(&work);
        let prims = Prims {
            boxes: &mut work,
            order: &mut order,
        };
        let root = build_node(stack, prims, 0, 0, bounds, cbounds);

        let mut flat = Flat {
            nodes: Vec::with_capacity(boxes.len() / 2 + 1),
            prims: Vec::with_capacity(boxes.len() * 3 / 2),
            stats: BvhStats {
                primitives: boxes.len(),
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
        if self.prims.iter().any(|p| {
            *p != PrimId::NONE && (p.kind() != PrimId::TRIANGLE || p.index() >= triangles.len())
        }) {
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

    /// The node array as bytes, for upload to a GPU (128 bytes per node).
    pub fn node_bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.nodes)
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
            bounds,
            start: offset,
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
                bounds,
                start: offset,
                count: n,
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
                    bounds,
                    start: offset,
                    count: n,
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
        bounds,
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
fn sah_split(boxes: &[Aabb], bounds: &Aabb, cbounds: &Aabb) -> Option<Split> {
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
    let mut left = |b: &Aabb| {
        let c = b.centroid();
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
        let mut pairs: Vec<(Aabb, u32)> = prims
            .boxes
            .iter()
            .copied()
            .zip(prims.order.iter().copied())
            .collect();
        pairs.select_nth_unstable_by(mid, |a, b| {
            a.0.centroid()[axis].total_cmp(&b.0.centroid()[axis])
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
/// the depth bound of the binary build carries over (see [`STACK`]).
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
        node.set_box(k, c.bounds());
        match c {
            BuildNode::Leaf { start, count, .. } => {
                let stats = &mut out.stats;
                stats.leaves += 1;
                stats.depth = stats.depth.max(depth + 1);
                stats.max_leaf_size = stats.max_leaf_size.max(*count);
                let first = out.prims.len().next_multiple_of(4);
                out.prims.resize(first, PrimId::NONE);
                out.prims.extend(
                    out.order[*start..*start + *count]
                        .iter()
                        .map(|&i| out.ids[i as usize]),
                );
                node.child[k] = first as u32;
                node.count[k] = *count as u32;
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
    ids: &'a [PrimId],
}

/// Exit distances are widened by this factor (Ize 2013, "Robust BVH ray
/// traversal") so that rounding never culls a box the ray grazes.
const EXIT_WIDEN: f64 = 1.000_000_4;

/// A box is culled only when the ray enters it beyond the nearest hit so far
/// times this factor. The entry distance and a triangle's distance round
/// differently, so a triangle inside a box can be hit a few ulps before the
/// box's computed entry; without the slack a box could be culled or not
/// depending on which hit was found first, and the answer (the distance, or
/// the lower id of a tie) would depend on the visiting order, which differs
/// between single rays, packets and brute force. 2^-14 is far above those
/// ulps and costs only the rare visits of boxes entered just behind a hit.
const CULL_WIDEN: f64 = 1.0 + 1.0 / 16384.0;

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

/// Distance along the ray to the primitive `id`, if it may be at most
/// `t_max` (a farther one may be returned: callers compare); `skip` is the
/// primitive the ray starts on.
#[inline(always)]
fn hit_prim<R: Real>(
    world: &World<R>,
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
        world.triangles[id.index()].distance(tri, t_max)
    } else {
        world.spheres[id.index()].intersect(ray, R::INFINITY, id == skip)
    }
}

/// Tests the primitives `prims[first .. first + count]` of a leaf: `best`
/// and `found` are updated on each hit that is [`PrimId::nearer`]. With
/// `ANY`, stops at the first hit before `best` (and returns true). In `f32` over packed triangles the 4-wide test
/// does the bulk of the work; lanes it leaves open are finished in order
/// with the same arithmetic as the scalar test, so the result is the same.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn leaf<R: Real, const ANY: bool>(
    world: &World<R>,
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
        let (tr, tris, best) = unsafe {
            (
                &*(tr as *const TriangleRay<R> as *const TriangleRay<f32>),
                &*(world.triangles.as_slice() as *const [Triangle<R>] as *const [Triangle<f32>]),
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
                    tris[id.index()].distance(tr, *best)
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
        if let Some(t) = hit_prim(world, id, ray, tr, *best, skip) {
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
fn far_to_near<E, T: PartialOrd>(e: &mut [E], t: impl Fn(&E) -> T) {
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
pub fn closest_hit<R: Real>(
    world: &World<R>,
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
            leaf::<R, false>(
                world,
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
pub fn occluded<R: Real>(
    world: &World<R>,
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
                if leaf::<R, true>(
                    world,
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

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn node_is_two_cache_lines_for_the_gpu() {
        assert_eq!(
            (
                std::mem::size_of::<BvhNode4>(),
                std::mem::align_of::<BvhNode4>()
            ),
            (128, 64)
        );
    }
}
