//! Building a tree: a binary tree by the binned surface area heuristic
//! (subtrees of many primitives on other rayon tasks), held within
//! [`MAX_DEPTH`] binary levels by median splits where the SAH would go
//! deeper, then collapsed into the 4-wide tree (a node's slots are its
//! binary grandchildren) and flattened into [`BvhNode4`]s depth first
//! (big subtrees as soon as they are built, [`FLATTEN_MIN`]).
//!
//! The build sees only boxes and ids ([`Bvh::build`]): what the boxes bound
//! is the caller's business (`accel.rs` boxes a world's spheres and
//! triangles), or triangles as corners into shared vertices
//! ([`Bvh::build_indexed`], a big mesh: the same tree, its boxes computed
//! where they are read). Both go through [`BuildPrims`], so they make the
//! same partitions of the same boxes.

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
/// Subtrees of at least this many primitives are flattened as soon as
/// they are built (when they head a 4-wide node and hold no such subtree
/// themselves), and their binary nodes freed: a big mesh's build then
/// never holds its whole binary tree beside its flattened one (24 and 20
/// bytes a triangle). 8 K: a 1 M-triangle mesh peaks at 75.8 MB on 2 or
/// 16 build threads (79.0 and 81.8 MB at 16 K, 83.4 and 91.3 at 64 K).
const FLATTEN_MIN: usize = 1 << 13;

/// Bytes from which glibc maps an allocation of its own (the threshold
/// `src/main.rs` fixes): reserved at least this big, a flattened subtree's
/// arrays are given back to the system when freed, not kept in the heap.
const MAPPED_MIN: usize = 1 << 20;

/// Source of [`Bvh::id`].
static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// Build-time tree before flattening. Kept small (40 bytes a node, a
/// box of 24): a subtree's build holds about one node a triangle until
/// it is flattened.
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
        /// Whether a subtree below it is flattened already.
        holds_flat: bool,
    },
    /// A subtree flattened already ([`FLATTEN_MIN`]), its leaves naming
    /// build places.
    Flat { bounds: BuildBox, chunk: Box<Flat> },
}

impl BuildNode {
    fn holds_flat(&self) -> bool {
        match self {
            BuildNode::Leaf { .. } => false,
            BuildNode::Inner { holds_flat, .. } => *holds_flat,
            BuildNode::Flat { .. } => true,
        }
    }

    fn bounds(&self) -> Aabb {
        match self {
            BuildNode::Leaf { bounds, .. }
            | BuildNode::Inner { bounds, .. }
            | BuildNode::Flat { bounds, .. } => bounds.aabb(),
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

/// The primitives of a subtree under construction, as the build sees
/// them: each one's box, permuted in place as the build partitions them.
/// The same partitions of the same boxes give the same tree whatever
/// holds them.
trait BuildPrims: Send + Sized {
    fn len(&self) -> usize;
    fn bbox(&self, i: usize) -> Aabb;
    fn swap(&mut self, i: usize, j: usize);
    fn split_at(self, mid: usize) -> (Self, Self);
    /// Puts the primitive at `from[k]` at place k, for every k.
    fn permute(&mut self, from: &[u32]);
}

/// Boxes and their indices into the caller's arrays, permuted together.
/// Boxes are moved rather than indexed so that binning and partitioning
/// stream through memory (an index array into 28 MB of boxes misses the
/// cache on every access for a large mesh).
struct Prims<'a> {
    boxes: &'a mut [BuildBox],
    order: &'a mut [u32],
}

impl BuildPrims for Prims<'_> {
    #[inline(always)]
    fn len(&self) -> usize {
        self.boxes.len()
    }
    #[inline(always)]
    fn bbox(&self, i: usize) -> Aabb {
        self.boxes[i].aabb()
    }
    #[inline(always)]
    fn swap(&mut self, i: usize, j: usize) {
        self.boxes.swap(i, j);
        self.order.swap(i, j);
    }
    fn split_at(self, mid: usize) -> (Self, Self) {
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
    fn permute(&mut self, from: &[u32]) {
        permute(self.boxes, from);
        permute(self.order, from);
    }
}

/// Triangles as their corners' indices into shared vertex positions, with
/// a record each (`payload`) that moves with them: the build permutes
/// both in place, into leaf order, and computes a triangle's box from its
/// vertices where it needs it. A big mesh's build then holds no array of
/// boxes (24 bytes a triangle) and no order (4).
struct IndexedPrims<'a, S> {
    positions: &'a [Vec3A],
    corners: &'a mut [[u32; 3]],
    payload: &'a mut [S],
}

impl<S: Copy + Send> BuildPrims for IndexedPrims<'_, S> {
    #[inline(always)]
    fn len(&self) -> usize {
        self.corners.len()
    }
    #[inline(always)]
    fn bbox(&self, i: usize) -> Aabb {
        triangle_box(self.corners[i].map(|v| self.positions[v as usize]))
    }
    #[inline(always)]
    fn swap(&mut self, i: usize, j: usize) {
        self.corners.swap(i, j);
        self.payload.swap(i, j);
    }
    fn split_at(self, mid: usize) -> (Self, Self) {
        let (cl, cr) = self.corners.split_at_mut(mid);
        let (pl, pr) = self.payload.split_at_mut(mid);
        let positions = self.positions;
        (
            IndexedPrims {
                positions,
                corners: cl,
                payload: pl,
            },
            IndexedPrims {
                positions,
                corners: cr,
                payload: pr,
            },
        )
    }
    fn permute(&mut self, from: &[u32]) {
        permute(self.corners, from);
        permute(self.payload, from);
    }
}

/// The box of a triangle's vertices, as `accel.rs` boxes an `f32`
/// triangle (its vertices are `f32`, so the outward rounding is exact):
/// both builds see the same boxes.
#[inline(always)]
pub fn triangle_box([a, b, c]: [Vec3A; 3]) -> Aabb {
    Aabb {
        min: a.min(b).min(c),
        max: a.max(b).max(c),
    }
}

/// `items[k] = items[from[k]]` for every k, through a copy.
fn permute<T: Copy>(items: &mut [T], from: &[u32]) {
    let moved: Vec<T> = from.iter().map(|&i| items[i as usize]).collect();
    items.copy_from_slice(&moved);
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
        Self::build_flattening(&mut work, ids, depth, FLATTEN_MIN)
    }

    /// [`Bvh::build_inner`] flattening subtrees of `flatten_min`
    /// primitives or more as they are built (`usize::MAX`: none).
    fn build_flattening(
        work: &mut Vec<BuildBox>,
        ids: &dyn Fn(u32) -> PrimId,
        depth: usize,
        flatten_min: usize,
    ) -> Bvh {
        let start = Instant::now();
        let n = work.len();
        let mut order: Vec<u32> = (0..n as u32).collect();
        let root = binary_tree(
            Prims {
                boxes: work,
                order: &mut order,
            },
            depth,
            flatten_min,
        );
        *work = Vec::new();
        flatten(root, n, depth, &|k| ids(order[k as usize]), start)
    }

    /// A tree over triangles given as `corners` into `positions` (`f32`
    /// vertices), built as [`Bvh::build`] builds it over their boxes (the
    /// same tree), without holding their boxes: `corners` and `payload`
    /// (a record a triangle) are permuted into leaf order in place, and the
    /// leaves name triangle k as `PrimId::TRIANGLE` k of that order. A big
    /// mesh's build holds its corners and the binary tree alone.
    pub fn build_indexed<S: Copy + Send>(
        positions: &[Vec3A],
        corners: &mut [[u32; 3]],
        payload: &mut [S],
    ) -> Bvh {
        assert_eq!(corners.len(), payload.len());
        let start = Instant::now();
        let n = corners.len();
        let root = binary_tree(
            IndexedPrims {
                positions,
                corners,
                payload,
            },
            MAX_DEPTH,
            FLATTEN_MIN,
        );
        flatten(
            root,
            n,
            MAX_DEPTH,
            &|k| PrimId::new(PrimId::TRIANGLE, k),
            start,
        )
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

    /// Whether `prims` names triangles below `n` alone (or nothing).
    fn packable(&self, n: usize) -> bool {
        self.prims
            .iter()
            .all(|p| *p == PrimId::NONE || (p.kind() == PrimId::TRIANGLE && p.index() < n))
    }
}

/// The binary tree over `prims` within `depth` binary levels (`None` for
/// no primitives).
fn binary_tree<P: BuildPrims>(prims: P, depth: usize, flatten_min: usize) -> Option<BuildNode> {
    let n = prims.len();
    assert!(n <= u32::MAX as usize, "{n} primitives: ids are 32-bit");
    assert!(
        depth >= 2 + ceil_log2(n),
        "a depth of {depth} cannot hold a tree over {n} primitives"
    );
    if n == 0 {
        return None;
    }
    let (bounds, cbounds) = bounds_of(&prims, 0..n);
    let limits = Limits {
        stack: depth,
        flatten_min,
    };
    Some(build_node(limits, prims, 0, 0, bounds, cbounds))
}

/// The 4-wide tree of the binary tree `root` (an empty tree for `None`),
/// whose leaf places k name `id_at(k)`; `start`: when its build began.
fn flatten(
    root: Option<BuildNode>,
    n: usize,
    depth: usize,
    id_at: &dyn Fn(u32) -> PrimId,
    start: Instant,
) -> Bvh {
    let Some(root) = root else {
        return Bvh::default();
    };
    let mut flat = Flat::for_primitives(n);
    flatten4(root, 0, 0, &mut flat);
    let Flat {
        nodes,
        mut prims,
        mut stats,
    } = flat;
    // The leaves name build places until here.
    for p in prims.iter_mut().filter(|p| **p != PrimId::NONE) {
        *p = id_at(p.0);
    }
    stats.primitives = n;

    stats.nodes = nodes.len();
    stats.bytes =
        nodes.len() * std::mem::size_of::<BvhNode4>() + prims.len() * std::mem::size_of::<PrimId>();
    stats.build_time = start.elapsed();
    debug_assert!(stats.stack <= stack_for_depth(depth));
    Bvh {
        nodes,
        prims,
        packets: Vec::new(),
        stats,
        id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
    }
}

/// The bounds of the boxes and of the centroids of `prims[range]`.
fn bounds_of<P: BuildPrims>(prims: &P, range: std::ops::Range<usize>) -> (Aabb, Aabb) {
    let mut b = Aabb::EMPTY;
    let mut c = Aabb::EMPTY;
    for i in range {
        let p = &prims.bbox(i);
        b.grow(p);
        c.grow_point(p.centroid());
    }
    (b, c)
}

/// What bounds a build: the traversal stack (leaves at most `stack - 1`
/// deep) and the size from which subtrees are flattened as built.
#[derive(Clone, Copy)]
struct Limits {
    stack: usize,
    flatten_min: usize,
}

/// Builds the subtree over `prims` (which start at `offset` in the final
/// order), at depth `depth`, partitioning them in place. `bounds` and
/// `cbounds` bound the primitives' boxes and centroids.
fn build_node<P: BuildPrims>(
    limits: Limits,
    prims: P,
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
    let median = depth + ceil_log2(n) >= limits.stack - 1;
    let split = if median {
        None
    } else {
        sah_split(&prims, &bounds, &cbounds)
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
            (mid, bounds_of(&prims, 0..mid), bounds_of(&prims, mid..n))
        }
    };
    let (left, right) = prims.split_at(mid);
    let build_l = move || build_node(limits, left, offset, depth + 1, lb.0, lb.1);
    let build_r = move || build_node(limits, right, offset + mid, depth + 1, rb.0, rb.1);
    let (l, r) = if n >= PARALLEL_MIN {
        rayon::join(build_l, build_r)
    } else {
        (build_l(), build_r())
    };
    let holds_flat = l.holds_flat() || r.holds_flat();
    let node = BuildNode::Inner {
        bounds: BuildBox::of(&bounds),
        children: Box::new([l, r]),
        median,
        holds_flat,
    };
    // A big subtree that heads a 4-wide node (every 4-wide node is a
    // binary node at an even depth: its slots are its grandchildren) is
    // flattened now, its binary nodes freed; the wide tree that contains
    // it copies it in ([`Flat::append`]). Only the lowest such subtrees:
    // flattened again above them, their nodes would be copied once a
    // level, and on many threads those copies coexist (a 1 M-triangle
    // mesh's render peaked at 98.6 MB with 16 build threads, 75.7 with 2).
    if n >= limits.flatten_min && depth > 0 && depth.is_multiple_of(2) && !holds_flat {
        let mut chunk = Flat::for_subtree(n);
        flatten4(node, 0, 0, &mut chunk);
        return BuildNode::Flat {
            bounds: BuildBox::of(&bounds),
            chunk: Box::new(chunk),
        };
    }
    node
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
fn sah_split<P: BuildPrims>(prims: &P, bounds: &Aabb, cbounds: &Aabb) -> Option<Split> {
    let n = prims.len();
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
    for i in 0..n {
        let b = &prims.bbox(i);
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
fn partition_bins<P: BuildPrims>(
    prims: &mut P,
    axis: usize,
    bin: usize,
    lo: Vec3A,
    scale: Vec3A,
    top: f32,
) -> (usize, Aabb, Aabb) {
    let (mut lc, mut rc) = (Aabb::EMPTY, Aabb::EMPTY);
    // Classifies a box, growing its side's centroid bounds.
    let mut left = |b: Aabb| {
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
        while i < j && left(prims.bbox(i)) {
            i += 1;
        }
        if i == j {
            break;
        }
        // boxes[i] goes right (and is counted so); find a left one from the end.
        j -= 1;
        while i < j && !left(prims.bbox(j)) {
            j -= 1;
        }
        if i == j {
            break;
        }
        prims.swap(i, j);
        i += 1;
    }
    debug_assert!(i > 0 && i < prims.len());
    (i, lc, rc)
}

/// Halves the primitives by count along the widest centroid axis (in their
/// current order when all centroids coincide): always makes progress,
/// whatever the geometry. Rare (degenerate or depth-limited subtrees), so it
/// sorts pairs in a scratch vector.
fn median_split<P: BuildPrims>(prims: &mut P, cbounds: &Aabb) -> usize {
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
        let mut keys: Vec<(f32, u32)> = (0..prims.len())
            .map(|i| (prims.bbox(i).centroid()[axis], i as u32))
            .collect();
        keys.select_nth_unstable_by(mid, |a, b| a.0.total_cmp(&b.0));
        let from: Vec<u32> = keys.into_iter().map(|(_, i)| i).collect();
        prims.permute(&from);
    }
    mid
}

/// Writes the wide node of the binary subtree `node` (an interior node, or
/// the root leaf of a one-leaf tree) and, after it, its subtrees; returns
/// its index. Its slots are the binary node's grandchildren, or a child
/// itself where that is a leaf: each wide level is two binary levels, so
/// the depth bound of the binary build carries over (see [`super::STACK`]).
/// `need` is the traversal stack occupancy on arrival at this node. Leaves
/// get their primitives' build places (`PrimId(k)`, made ids by
/// [`flatten`]) written to `out.prims` in this depth-first order, each
/// leaf starting at a multiple of 4 (padded with `PrimId::NONE`), so
/// that a leaf's triangles fill whole [`Triangle4`] packets. A subtree
/// flattened already is copied in as it is ([`Flat::append`]): the same
/// nodes and places as flattening it here.
fn flatten4(node: BuildNode, depth: usize, need: usize, out: &mut Flat) -> u32 {
    let at = out.nodes.len();
    out.nodes.push(BvhNode4::EMPTY);
    let stats = &mut out.stats;
    // The tree is consumed as it is written: each subtree's binary nodes
    // (or flattened copy) are freed once it is in `out`.
    let mut slots: [Option<BuildNode>; 4] = [None, None, None, None];
    let mut n = 0;
    match node {
        BuildNode::Leaf { .. } => {
            slots[0] = Some(node);
            n = 1;
        }
        // Only a slot (a grandchild) is flattened before its parent.
        BuildNode::Flat { .. } => unreachable!("a flattened subtree is copied, not flattened"),
        BuildNode::Inner {
            children, median, ..
        } => {
            stats.depth_limited |= median;
            let [a, b] = *children;
            for c in [a, b] {
                match c {
                    BuildNode::Inner {
                        children: grand,
                        median,
                        ..
                    } => {
                        stats.depth_limited |= median;
                        let [g0, g1] = *grand;
                        slots[n] = Some(g0);
                        slots[n + 1] = Some(g1);
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
    for (k, c) in slots.into_iter().flatten().enumerate() {
        node.set_box(k, &c.bounds());
        match c {
            BuildNode::Leaf { start, count, .. } => {
                let stats = &mut out.stats;
                stats.leaves += 1;
                stats.depth = stats.depth.max(depth + 1);
                let (start, count) = (start as usize, count as usize);
                stats.max_leaf_size = stats.max_leaf_size.max(count);
                let first = out.prims.len().next_multiple_of(4);
                out.prims.resize(first, PrimId::NONE);
                out.prims
                    .extend((start..start + count).map(|k| PrimId(k as u32)));
                node.child[k] = first as u32;
                node.count[k] = count as u32;
            }
            BuildNode::Inner { .. } => node.child[k] = flatten4(c, depth + 1, need, out),
            BuildNode::Flat { chunk, .. } => node.child[k] = out.append(&chunk, depth + 1, need),
        }
    }
    out.nodes[at] = node;
    at as u32
}

/// A flattened tree (or subtree) as it is written: its nodes from its
/// root (index 0) on, its leaves' places from 0 on, and its figures.
#[derive(Default)]
struct Flat {
    nodes: Vec<BvhNode4>,
    prims: Vec<PrimId>,
    stats: BvhStats,
}

impl Flat {
    /// Room for a tree over `n` primitives, reserved rather than grown
    /// (pages never written are never resident).
    fn for_primitives(n: usize) -> Flat {
        Flat {
            nodes: Vec::with_capacity(n / 2 + 1),
            prims: Vec::with_capacity(n * 3 / 2),
            stats: BvhStats::default(),
        }
    }

    /// The same for a subtree flattened early, at least [`MAPPED_MIN`]
    /// bytes an array: each then has a mapping of its own, given back to
    /// the system when the tree that contains it has copied it, instead of
    /// staying in the heap beside the arrays it is copied into.
    fn for_subtree(n: usize) -> Flat {
        Flat {
            nodes: Vec::with_capacity((n / 2 + 1).max(MAPPED_MIN / size_of::<BvhNode4>())),
            prims: Vec::with_capacity((n * 3 / 2).max(MAPPED_MIN / size_of::<PrimId>())),
            stats: BvhStats::default(),
        }
    }

    /// Copies the flattened subtree `sub` in, as [`flatten4`] would have
    /// written it at 4-wide depth `depth` with `need` stack entries on
    /// arrival; returns the index of its root. Its nodes' references move
    /// by where its nodes and places land; its places start at a multiple
    /// of 4, as its first leaf's would, so every leaf keeps its padding.
    fn append(&mut self, sub: &Flat, depth: usize, need: usize) -> u32 {
        let (node0, prim0) = (
            self.nodes.len() as u32,
            self.prims.len().next_multiple_of(4),
        );
        self.prims.resize(prim0, PrimId::NONE);
        self.prims.extend_from_slice(&sub.prims);
        self.nodes.extend(sub.nodes.iter().map(|n| {
            let mut n = *n;
            for k in 0..4 {
                if n.count[k] > 0 {
                    n.child[k] += prim0 as u32;
                } else if n.child[k] != 0 {
                    n.child[k] += node0;
                }
            }
            n
        }));
        let (s, t) = (&mut self.stats, &sub.stats);
        s.leaves += t.leaves;
        s.depth = s.depth.max(depth + t.depth);
        s.max_leaf_size = s.max_leaf_size.max(t.max_leaf_size);
        s.stack = s.stack.max(need + t.stack);
        s.depth_limited |= t.depth_limited;
        node0
    }
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

    /// `n` unit boxes at hashed points of a 1024-cube.
    fn scattered_boxes(n: u32) -> Vec<Aabb> {
        (0..n)
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
            .collect()
    }

    /// The build tree's node stays at 40 bytes (a big mesh's build holds
    /// about one a triangle: docs/meshes.md, "Big scenes").
    #[test]
    fn a_build_node_takes_40_bytes() {
        assert_eq!(std::mem::size_of::<BuildNode>(), 40);
    }

    #[test]
    fn builds_a_valid_tree_over_scattered_boxes() {
        let boxes = scattered_boxes(5000);
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

    /// Subtrees flattened as they are built and copied in give the tree
    /// flattened in one pass: the same nodes, places and figures, for
    /// scattered boxes, boxes in one spot (median splits) and a chain
    /// under a depth limit (the lowest subtrees of 16 primitives and more
    /// flattened early: many).
    #[test]
    fn subtrees_flattened_early_give_the_same_tree() {
        let scattered = scattered_boxes(5000);
        let same = vec![unit_box([1.0, 2.0, 3.0], 0.0); 3000];
        let chain: Vec<Aabb> = (0..120)
            .map(|i| unit_box([2f32.powi(i), 0.0, 0.0], 1e-3))
            .collect();
        for (boxes, depth) in [(&scattered, MAX_DEPTH), (&same, MAX_DEPTH), (&chain, 12)] {
            let ids: Vec<PrimId> = (0..boxes.len() as u32)
                .map(|i| PrimId::new(PrimId::TRIANGLE, i))
                .collect();
            let build = |flatten_min| {
                let mut work: Vec<BuildBox> = boxes.iter().map(BuildBox::of).collect();
                Bvh::build_flattening(&mut work, &|i| ids[i as usize], depth, flatten_min)
            };
            let (once, early) = (build(usize::MAX), build(16));
            check(&early, boxes, stack_for_depth(depth));
            assert!(once.nodes == early.nodes, "the same nodes");
            assert_eq!(once.prims, early.prims);
            let figures = |b: &Bvh| {
                let s = b.stats;
                (
                    s.nodes,
                    s.leaves,
                    s.primitives,
                    s.depth,
                    s.stack,
                    s.max_leaf_size,
                    s.bytes,
                    s.depth_limited,
                )
            };
            assert_eq!(figures(&once), figures(&early));
        }
    }

    /// Built over corners into shared vertices, a mesh gets the tree its
    /// triangles' boxes get: the same nodes, its leaves naming the same
    /// triangles, which (with their records) are permuted into that leaf
    /// order. The mesh: a wavy grid, and a pile of copies of one triangle
    /// (one centroid: the median splits).
    #[test]
    fn an_indexed_build_is_the_box_build() {
        let side = 48u32;
        let mut positions = Vec::new();
        for y in 0..=side {
            for x in 0..=side {
                let h = crate::sampling::hash_u32(y * 1000 + x) as f32 / u32::MAX as f32;
                positions.push(Vec3A::new(x as f32, y as f32, (x as f32 * 0.3).sin() + h));
            }
        }
        let at = |x: u32, y: u32| y * (side + 1) + x;
        let mut corners = Vec::new();
        for y in 0..side {
            for x in 0..side {
                corners.push([at(x, y), at(x + 1, y), at(x, y + 1)]);
                corners.push([at(x + 1, y), at(x + 1, y + 1), at(x, y + 1)]);
            }
        }
        corners.extend(std::iter::repeat_n([0, 1, at(0, 1)], 300));
        let n = corners.len();
        let boxes: Vec<Aabb> = corners
            .iter()
            .map(|c| triangle_box(c.map(|i| positions[i as usize])))
            .collect();
        let ids: Vec<PrimId> = (0..n as u32)
            .map(|i| PrimId::new(PrimId::TRIANGLE, i))
            .collect();
        let by_boxes = Bvh::build(&boxes, &ids);
        check(&by_boxes, &boxes, STACK);
        assert!(by_boxes.stats.leaves > 100, "{:?}", by_boxes.stats);
        let mut leaf_order = corners.clone();
        let mut original: Vec<u32> = (0..n as u32).collect();
        let by_corners = Bvh::build_indexed(&positions, &mut leaf_order, &mut original);
        assert!(by_corners.nodes == by_boxes.nodes, "the same nodes");
        assert_eq!(by_corners.prims.len(), by_boxes.prims.len());
        let mut named = 0;
        for (a, b) in by_corners.prims.iter().zip(&by_boxes.prims) {
            if *b == PrimId::NONE {
                assert_eq!(*a, PrimId::NONE);
                continue;
            }
            // Leaf place k names triangle k of the permuted arrays.
            assert_eq!(a.index(), named);
            named += 1;
            assert_eq!(original[a.index()] as usize, b.index());
            assert_eq!(leaf_order[a.index()], corners[b.index()]);
        }
        assert_eq!(named, n);
    }
}
