//! Bounding volume hierarchy over bounded primitives (triangles and
//! spheres; infinite planes stay outside), built with the binned surface
//! area heuristic as a binary tree, collapsed into a 4-wide tree (BVH4) and
//! flattened into one array of 128-byte nodes that the CPU traverses here
//! and the GPU (`render/gpu/bvh.wgsl`) traverses as is, uploaded unchanged.
//!
//! One file a job:
//! - `node.rs`: the layout the GPU shares ([`BvhNode4`], [`Aabb`]) and the
//!   depth and stack bounds ([`MAX_DEPTH`], [`STACK`]);
//! - `build.rs`: [`Bvh::build`] (binned SAH, the depth limit, the collapse
//!   to 4-wide nodes, flattening), [`Bvh::build_indexed`] (the same over
//!   indexed triangles, without their boxes) and [`Bvh::pack_triangles`];
//! - `traverse.rs`: one ray at a time ([`closest_hit`], [`occluded`]);
//! - `packet.rs`: up to [`PACKET`] coherent rays at once.
//!
//! The tree knows its primitives only by [`PrimId`] and reaches them
//! through a [`Primitives`] view, which traversal is generic over; the
//! build takes their boxes. So this module depends on geometry, math,
//! triangles and SIMD detection only, never on `world`: the world
//! implements the view and `accel.rs` decides what a world's tree holds,
//! one way down (`world` -> `accel` -> `bvh`).

mod build;
mod node;
mod packet;
mod traverse;

use std::time::Duration;

use crate::geometry::PrimId;
use crate::triangle::Triangle4;

pub use build::{BuildBox, triangle_box};
pub use node::{Aabb, BvhNode4, MAX_DEPTH, STACK, stack_for_depth};
pub use packet::{
    PACKET, closest_hits, closest_hits_at, occluded_hits, occluded_hits_at, render_level,
};
pub use traverse::{Primitives, closest_hit, occluded};

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

/// A built tree: the flattened 4-wide nodes and the primitives its leaves
/// refer to, by [`PrimId`].
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    /// The 4-wide nodes; `nodes[0]` is the root (empty for an empty tree).
    pub nodes: Vec<BvhNode4>,
    /// Leaf references: packed [`PrimId`]s, each leaf's starting at a
    /// multiple of 4 (`PrimId::NONE` between leaves).
    pub prims: Vec<PrimId>,
    /// For trees over `f32` triangles alone (else empty): the triangles of
    /// `prims[4 i .. 4 i + 4]` as packet i, for the 4-wide triangle test
    /// (CPU only). A big mesh's tree has none (`Bvh::build_indexed`): its
    /// leaves are tested through the [`Primitives`] view, which reads
    /// each triangle from its corners.
    pub packets: Vec<Triangle4>,
    pub stats: BvhStats,
    /// Unique per build (never 0 for a built tree; 0 for a tree made any
    /// other way): lets a GPU renderer keep an uploaded tree while the
    /// same world renders tile after tile, without comparing its contents.
    pub id: u64,
}

impl Bvh {
    /// The node array as bytes, for upload to a GPU (128 bytes per node).
    pub fn node_bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.nodes)
    }
}
