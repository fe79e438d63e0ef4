//! The tree's memory layout, shared with the GPU: the 4-wide node that
//! `render/gpu/bvh.wgsl`'s `struct BvhNode4` mirrors (keep in sync), the
//! `f32` box it is built from, and the depth and stack bounds that both
//! traversals rely on.
//!
//! Layout (`#[repr(C)]`, `Pod`, uploaded as is):
//! - `nodes[0]` is the root. A node has four slots, each with a box and a
//!   reference. The boxes are stored by rows, structure of arrays:
//!   `b[0]` = min x of slots 0..4, `b[1]` = max x, `b[2..4]` = min/max y,
//!   `b[4..6]` = min/max z, so one SIMD pass tests all four. Slot k refers
//!   to a node (`count[k] == 0`, `child[k]` its index, never 0), to a leaf
//!   (`count[k] > 0`: `prims[child[k] .. child[k] + count[k]]`, packed
//!   [`PrimId`](crate::geometry::PrimId)s), or to nothing
//!   (`child[k] == count[k] == 0`; its box is inverted, min +inf and max
//!   -inf, so no ray meets it). Nodes are 64-byte aligned: two cache lines.
//! - Bounds are `f32`, rounded outward from the world's coordinates, so
//!   they are conservative for the `f64` reference as well.
//! - The binary tree has no leaf deeper than [`MAX_DEPTH`] - 1 (the builder
//!   switches from SAH to median splits where a subtree could get deeper);
//!   each 4-wide level is two binary levels (a node's slots are its binary
//!   grandchildren), so a traversal stack of [`STACK`] entries (a node
//!   pushes at most three) never overflows. `BvhStats::stack` is the exact
//!   need of the tree built.

use bytemuck::{Pod, Zeroable};
use glam::Vec3A;

/// Binary levels of the tree as built: no leaf of the binary tree is this deep.
pub const MAX_DEPTH: usize = 64;
/// Entries of the traversal stack that a tree built within [`MAX_DEPTH`]
/// binary levels never exceeds: its 4-wide nodes lie at most
/// `MAX_DEPTH / 2 - 1` deep and each pushes at most three slots.
pub const STACK: usize = stack_for_depth(MAX_DEPTH);

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
    pub(super) fn grow_point(&mut self, p: Vec3A) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }
    /// Half the surface area (the SAH only compares ratios); 0 for empty boxes.
    #[inline]
    pub(super) fn half_area(&self) -> f32 {
        let d = (self.max - self.min).max(Vec3A::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    }
    #[inline]
    pub(super) fn centroid(&self) -> Vec3A {
        (self.min + self.max) * 0.5
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
