//! Host mirrors of every structure the WGSL kernel reads or writes.
//!
//! Keep in sync with the struct declarations of `scene.wgsl`
//! (and, for meshes and the BVH, `bvh.wgsl`; for distributed effects the
//! `dist` words of `distributed.wgsl` and `moving_meshes.wgsl`; for the
//! resolve, `resolve.wgsl`):
//! same field order, same sizes, WGSL alignment rules (a `vec3<f32>` is
//! 16-byte aligned, so each one is followed by a scalar that fills its
//! fourth lane). The `const` asserts below pin the sizes WGSL expects.

use bytemuck::{Pod, Zeroable};

use crate::bsdf::Bsdf;
use crate::bvh::{Bvh, BvhNode4, STACK};
use crate::distributed::PathScene;
use crate::geometry::{Plane, PrimId, Sphere};
use crate::triangle::{Triangle, TriangleShading};
use crate::world::{InstancedMesh, Instances, Material, PointLight, World};

use super::GpuError;

/// Per-scene constants. WGSL: `struct Frame`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
pub struct FrameUniform {
    pub forward: [f32; 3],
    pub inv_width: f32,
    pub right: [f32; 3],
    pub inv_height: f32,
    pub up: [f32; 3],
    /// Samples per pixel of the whole frame (the sampler's `count`).
    pub samples: u32,
    pub ambient: [f32; 3],
    /// n if `samples` = n*n, else 0 (R2 points).
    pub grid_n: u32,
    pub background: [f32; 3],
    /// 0 = grid, 1 = jittered.
    pub sampler: u32,
}

/// Per-dispatch parameters, read at a dynamic offset. WGSL: `struct Dispatch`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq, Eq)]
pub struct DispatchParams {
    /// The film's rectangle in image pixels.
    pub rect_x: u32,
    pub rect_y: u32,
    pub rect_w: u32,
    pub rect_h: u32,
    /// Band of rows (relative to the rect) this dispatch covers.
    pub row0: u32,
    pub rows: u32,
    /// Sample indices this dispatch adds.
    pub sample_start: u32,
    pub sample_end: u32,
    pub frame: u32,
    /// The film's size. Equal to `rect_w` x `rect_h` in a uniform render;
    /// in an adaptive round the grid (`rect_w` x `rect_h`) is 8 columns by
    /// 8 rows per active block instead (sums.wgsl `grid_pixel`).
    pub film_w: u32,
    pub film_h: u32,
    /// 1: a listed dispatch, an adaptive render whose blocks each take
    /// their own range of samples (`block_ranges`, sums.wgsl
    /// `listed_work`): `sample_start..sample_end` are then the items it
    /// traces, each a block's chunk of `chunk` samples, 64 invocations
    /// an item.
    pub ranged: u32,
    pub chunk: u32,
}

/// WGSL: `struct Sphere`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuSphere {
    pub center: [f32; 3],
    pub radius: f32,
    pub material: u32,
    pub _pad: [u32; 3],
}

/// WGSL: `struct Plane`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuPlane {
    pub normal: [f32; 3],
    pub distance: f32,
    pub material: u32,
    pub _pad: [u32; 3],
}

/// WGSL: `struct Material`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuMaterial {
    pub ambient: [f32; 3],
    pub shininess: f32,
    pub diffuse: [f32; 3],
    pub reflectivity: f32,
    pub specular: [f32; 3],
    pub transparency: f32,
    pub ior: f32,
    /// N.H below which the specular term is skipped (`Material::specular_cos_min`).
    pub specular_cos_min: f32,
    /// Cosines of the gloss and translucency half-angles (1: none).
    pub gloss_cos: f32,
    pub translucency_cos: f32,
}

/// WGSL: `struct Light`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuLight {
    pub position: [f32; 3],
    pub _pad0: f32,
    pub diffuse: [f32; 3],
    pub _pad1: f32,
    pub specular: [f32; 3],
    pub _pad2: f32,
}

/// The vertices of a triangle. WGSL (bvh.wgsl): `struct Triangle`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuTriangle {
    pub v0: [f32; 3],
    pub _pad0: f32,
    pub v1: [f32; 3],
    pub _pad1: f32,
    pub v2: [f32; 3],
    pub _pad2: f32,
}

/// What shading needs of a triangle (`TriangleShading`). WGSL (bvh.wgsl): `struct TriangleShading`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuTriangleShading {
    /// Unit geometric normal, outward by the winding.
    pub normal: [f32; 3],
    pub material: u32,
    pub n0: [f32; 3],
    /// 1 when `n0..n2` are vertex normals to interpolate, 0 for flat shading.
    pub smooth_shaded: u32,
    pub n1: [f32; 3],
    /// `TriangleShading::attrs`: the triangle's vertex attributes in
    /// [`PbrData`] (`NO_ATTRS` for none, and for moving meshes' triangles).
    pub attrs: u32,
    pub n2: [f32; 3],
    pub _pad2: u32,
}

/// One placement of an instanced mesh (`world::Instance`). WGSL
/// (instances.wgsl): `struct Instance`. Its maps as columns, the
/// translation last (`Affine3`), with the mesh's tree and ids in the
/// fourth lanes: 128 bytes an instance.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuInstance {
    pub w0: [f32; 3],
    /// The mesh's root node in [`TreeData::nodes`].
    pub root: u32,
    pub w1: [f32; 3],
    /// The mesh's first triangle in [`TreeData::triangles`].
    pub tri0: u32,
    pub w2: [f32; 3],
    /// `Instance::first`: the id index of its first placed triangle.
    pub first: u32,
    pub w3: [f32; 3],
    /// The mesh's triangles.
    pub count: u32,
    /// `to_object`'s columns.
    pub o: [[f32; 4]; 4],
}

/// The BVH node is uploaded as is: `bvh::BvhNode4` (128 bytes) is already
/// the WGSL `struct BvhNode4` (six vec4<f32> rows of the four slots' boxes,
/// then vec4<u32> child and count).
pub type GpuBvhNode = BvhNode4;

/// Per-pixel output: fixed-point sums as (low, high) u32 words per channel,
/// i.e. the `u64` sums of [`crate::film::Film`]. WGSL: `sums: array<u32>`, 6 words a pixel.
pub const SUM_WORDS: usize = 6;
/// Per-pixel output of an adaptive round: the [`SUM_WORDS`] sums, then per
/// channel the sum of squares as four u32 words, least significant first
/// (the `u128` of [`crate::film::Film::squares`]). WGSL: `sum_stride()`.
pub const ADAPTIVE_SUM_WORDS: usize = 18;

/// Parameters of the convergence test after an adaptive round on the GPU.
/// WGSL (converge.wgsl): `struct ConvergeParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct ConvergeParams {
    pub film_w: u32,
    pub film_h: u32,
    /// Blocks per row of the film, and in all.
    pub cols: u32,
    pub blocks: u32,
    /// Samples each pixel of a block active in the round has after it.
    pub samples: u32,
    /// 1: the error-optimal mode's statistics, each block at the end of
    /// its own range (`count_ranges`), nothing retired; 0: the per-pixel
    /// test at `samples`.
    pub ranged: u32,
    /// The target: a pixel's limit is max(absolute, relative x its
    /// brightest channel mean) (`scene::adaptive::Target`).
    pub absolute: f32,
    pub relative: f32,
}

/// One block's statistics after its last round, written by converge.wgsl
/// (`block_stats`): f32 bits of its pixels' summed variances of the mean
/// (finite ones, over the three channels) and of its worst error ratio
/// (above 1: not converged; `f32::MAX`-like: infinite), then its samples,
/// then (ranged) f32 bits of its pixels' summed channel means.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq, Eq)]
pub struct GpuBlockStats {
    pub variance_sum: u32,
    pub worst: u32,
    pub samples: u32,
    pub mean_sum: u32,
}

/// Parameters of the error-optimal mode's decision between rounds on the
/// GPU. WGSL (allocate.wgsl): `struct AllocateParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct AllocateParams {
    pub film_w: u32,
    pub film_h: u32,
    /// Blocks per row of the film, and in all.
    pub cols: u32,
    pub blocks: u32,
    pub min_samples: u32,
    pub max_samples: u32,
    /// `RmseSettings::max_rounds`, and the round the dispatch ends
    /// (rewritten before each round).
    pub max_rounds: u32,
    pub round: u32,
    /// Samples a listed item ([`super::plan::LISTED_CHUNK`]).
    pub chunk: u32,
    /// The trace's slices a round, items a slice, and invocations a
    /// workgroup of the trace kernel.
    pub slices: u32,
    pub slice_items: u32,
    pub group_invocations: u32,
    pub target_rmse: f32,
    pub relative_rmse: f32,
}

/// What a round of the error-optimal mode on the GPU ended with, written
/// by allocate.wgsl (`round_log`, one a round). WGSL: `struct RoundLog`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct RoundLog {
    /// Blocks the round sampled.
    pub active_blocks: u32,
    /// Pixel-samples of the image after the round, low and high words.
    pub samples: [u32; 2],
    /// Items of the next round: 0 once the render is done.
    pub next_items: u32,
    /// The image's estimated MSE after the round, and the target MSE.
    pub estimated_mse: f32,
    pub target_mse: f32,
    /// Pixel-samples the render is expected to take in all (f32: an
    /// estimate for progress; `RmseStep::expected_pixel_samples`).
    pub expected_samples: f32,
    pub _pad: u32,
}

/// Parameters of the GPU resolve of a film's sums. WGSL (resolve.wgsl):
/// `struct ResolveParams`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq, Eq)]
pub struct ResolveParams {
    pub pixels: u32,
    pub _pad: u32,
    /// `resolve_linear` only: the bits of the host's f64 scale for the
    /// film's sample count ([`crate::film::resolve_scale`]), low word
    /// first; 0 for no samples (every pixel black, as on the host).
    pub scale: [u32; 2],
}

impl ResolveParams {
    /// A film of `pixels`, each of `n` samples (the GPU's films count the
    /// same samples in every pixel).
    pub fn new(pixels: usize, n: u32) -> Self {
        let bits = if n == 0 {
            0
        } else {
            crate::film::resolve_scale(n).to_bits()
        };
        ResolveParams {
            pixels: pixels as u32,
            _pad: 0,
            scale: [bits as u32, (bits >> 32) as u32],
        }
    }
}

/// Global counters, each a (low, high) u32 pair. WGSL: `counters: array<atomic<u32>, 10>`.
pub const COUNTERS: usize = 5;
pub const COUNTER_PRIMARY: usize = 0;
pub const COUNTER_SHADOW: usize = 1;
pub const COUNTER_REFLECTION: usize = 2;
pub const COUNTER_REFRACTION: usize = 3;
pub const COUNTER_NONFINITE: usize = 4;

/// A ray task of the wavefront strategy. WGSL (wavefront.wgsl): `struct WaveTask`.
pub const WAVE_TASK_BYTES: u64 = 48;
/// A path of the path integrator's wavefront. WGSL (path_wave.wgsl):
/// `struct WaveTask` (path.wgsl `PathState`, then four words).
pub const PATH_WAVE_TASK_BYTES: u64 = 80;
/// WGSL: `struct WaveState` (count_in, count_out, overflow), padded.
pub const WAVE_STATE_BYTES: u64 = 16;
/// WGSL: `wave_args_out: array<u32, 3>`, an indirect dispatch's x, y, z.
pub const WAVE_ARGS_BYTES: u64 = 12;

const _: () = assert!(size_of::<FrameUniform>() == 80);
const _: () = assert!(size_of::<DispatchParams>() == 52);
const _: () = assert!(size_of::<GpuSphere>() == 32);
const _: () = assert!(size_of::<GpuPlane>() == 32);
const _: () = assert!(size_of::<GpuMaterial>() == 64);
const _: () = assert!(size_of::<GpuLight>() == 48);
const _: () = assert!(size_of::<GpuTriangle>() == 48);
const _: () = assert!(size_of::<GpuTriangleShading>() == 64);
const _: () = assert!(size_of::<GpuBvhNode>() == 128);
const _: () = assert!(size_of::<GpuInstance>() == 128);
const _: () = assert!(size_of::<ResolveParams>() == 16);
const _: () = assert!(size_of::<ConvergeParams>() == 32);
const _: () = assert!(size_of::<GpuBlockStats>() == 16);
const _: () = assert!(size_of::<AllocateParams>() == 56);
const _: () = assert!(size_of::<RoundLog>() == 32);

/// The arrays of packed trees that grow with their triangles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TreeArray {
    /// The flattened 4-wide nodes exactly as the CPU traverses them, child
    /// and leaf indices rebased by the trees packed before.
    Nodes,
    /// Leaf references: packed `PrimId`s (kind << 28 | index), triangle
    /// indices rebased like the nodes, so each names one triangle of one tree.
    Prims,
    Triangles,
    Shading,
}

impl TreeArray {
    pub const ALL: [TreeArray; 4] = [Self::Nodes, Self::Prims, Self::Triangles, Self::Shading];

    /// Bytes of one element.
    pub fn element_bytes(self) -> usize {
        match self {
            Self::Nodes => size_of::<GpuBvhNode>(),
            Self::Prims => size_of::<u32>(),
            Self::Triangles => size_of::<GpuTriangle>(),
            Self::Shading => size_of::<GpuTriangleShading>(),
        }
    }
}

/// The trees of a world and what their leaves refer to, for scenes that
/// have one: the static world's (meshes, or many spheres: the pipeline then
/// compiles `bvh.wgsl` and `accel.wgsl`) and each moving mesh's
/// (`distributed::MovingMesh`: then `bvh.wgsl` and `moving_meshes.wgsl`),
/// one after another in the same arrays ([`TreeArray`]), then the
/// instanced meshes'. This is what a renderer keeps of them: where each
/// lies and how long the arrays are. The arrays themselves are written
/// from the world's trees in pieces ([`TreePack::write`]) straight to the
/// device, so a big mesh's never exist whole on the host (a 10 M-triangle
/// mesh's are 1.3 GB).
#[derive(Clone, Debug, PartialEq)]
pub struct TreeLayout {
    pub n_nodes: u32,
    pub n_prims: u32,
    pub n_triangles: u32,
    /// Traversal stack entries the deepest tree needs, as measured at packing.
    pub stack: u32,
    /// Where each tree starts, in the order packed.
    pub places: Vec<TreePlace>,
    /// The world's instances (its tree's `PrimId::INSTANCE`s), their
    /// meshes' trees packed after the parts' (one unused element when
    /// there are none).
    pub instances: Vec<GpuInstance>,
    pub n_instances: u32,
}

impl TreeLayout {
    /// Elements of `array` as uploaded: never 0 (bindings must not be
    /// empty; one unused element when the trees hold only spheres).
    pub fn len(&self, array: TreeArray) -> usize {
        let n = match array {
            TreeArray::Nodes => self.n_nodes,
            TreeArray::Prims => self.n_prims,
            TreeArray::Triangles | TreeArray::Shading => self.n_triangles,
        };
        (n as usize).max(1)
    }

    /// Bytes of `array` as uploaded.
    pub fn bytes(&self, array: TreeArray) -> u64 {
        (self.len(array) * array.element_bytes()) as u64
    }
}

/// Where one tree lies in the packed arrays.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TreePlace {
    /// Its root node.
    pub root: u32,
    /// Its first triangle; its triangles run to the next tree's first.
    pub first_triangle: u32,
}

/// A tree's triangles as packing reads them: gathered, or a big world's
/// corners into its vertices, gathered one at a time as they are packed.
#[derive(Clone, Copy)]
pub enum TriangleSource<'a> {
    Gathered(&'a [Triangle<f32>]),
    Corners {
        positions: &'a [glam::Vec3A],
        corners: &'a [[u32; 3]],
    },
}

impl TriangleSource<'_> {
    pub fn len(&self) -> usize {
        match self {
            Self::Gathered(t) => t.len(),
            Self::Corners { corners, .. } => corners.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn get(&self, i: usize) -> Triangle<f32> {
        match self {
            Self::Gathered(t) => t[i],
            Self::Corners { positions, corners } => crate::triangle::gather(positions, corners[i]),
        }
    }
}

/// A tree to pack: its triangles and their shading, how many spheres and
/// instances its leaves may name (the world's own tree), and for a moving
/// mesh, whose world has its own materials, the index in the GPU's
/// materials of each of them.
pub struct TreePart<'a> {
    pub triangles: TriangleSource<'a>,
    /// Their corners, which name their vertex normals.
    pub corners: &'a [[u32; 3]],
    pub shading: &'a [TriangleShading],
    pub vertex_normals: &'a [glam::Vec3A],
    pub spheres: usize,
    pub instances: usize,
    pub tree: &'a Bvh,
    pub materials: Option<Vec<u32>>,
}

impl<'a> TreePart<'a> {
    /// A world's tree (the static world's, or a moving mesh's).
    pub fn world(w: &'a World<f32>, tree: &'a Bvh, materials: Option<Vec<u32>>) -> Self {
        TreePart {
            triangles: match w.gathered_triangles() {
                Some(t) => TriangleSource::Gathered(t),
                None => TriangleSource::Corners {
                    positions: &w.positions,
                    corners: &w.corners,
                },
            },
            corners: &w.corners,
            shading: &w.triangle_shading,
            vertex_normals: &w.vertex_normals,
            spheres: w.spheres.len(),
            instances: w.instances.list.len(),
            tree,
            materials,
        }
    }

    /// An instanced mesh's tree (its triangles in object space).
    pub fn mesh(m: &'a InstancedMesh<f32>) -> Self {
        TreePart {
            triangles: TriangleSource::Gathered(&m.triangles),
            corners: &m.corners,
            shading: &m.shading,
            vertex_normals: &m.vertex_normals,
            spheres: 0,
            instances: 0,
            tree: &m.tree,
            materials: None,
        }
    }

    /// The packed records of triangles `range`.
    fn pack_triangles(
        &self,
        range: std::ops::Range<usize>,
        triangles: &mut Vec<GpuTriangle>,
        shading: &mut Vec<GpuTriangleShading>,
    ) {
        let normals = crate::triangle::VertexNormals::<f32>(self.vertex_normals);
        for i in range {
            let t = self.triangles.get(i);
            let [v0, v1, v2] = t.vertices().map(a3);
            triangles.push(GpuTriangle {
                v0,
                v1,
                v2,
                ..Default::default()
            });
            let (s, c) = (self.shading[i], self.corners[i]);
            let smooth = normals.smooth(c);
            let ns = if smooth {
                c.map(|i| a3(self.vertex_normals[i as usize]))
            } else {
                [[0.0; 3]; 3]
            };
            shading.push(GpuTriangleShading {
                normal: a3(t.normal()),
                material: self
                    .materials
                    .as_ref()
                    .map_or(s.material, |m| m[s.material as usize]),
                n0: ns[0],
                smooth_shaded: smooth as u32,
                n1: ns[1],
                attrs: if self.materials.is_none() {
                    s.attrs
                } else {
                    crate::triangle::NO_ATTRS
                },
                n2: ns[2],
                ..Default::default()
            });
        }
    }
}

/// Trees to pack, checked, and where each goes ([`TreeLayout`]).
pub struct TreePack<'a> {
    /// The world's parts, then the instanced meshes'.
    parts: Vec<TreePart<'a>>,
    /// Each part's first node, leaf reference and triangle.
    bases: Vec<(u32, u32, u32)>,
    pub layout: TreeLayout,
}

/// The arrays of a [`TreePack`] whole, as the device receives them
/// ([`TreePack::arrays`]: what tests check on the host).
#[derive(Clone, Debug, PartialEq)]
pub struct TreeData {
    pub layout: TreeLayout,
    pub nodes: Vec<GpuBvhNode>,
    pub prims: Vec<u32>,
    pub triangles: Vec<GpuTriangle>,
    pub shading: Vec<GpuTriangleShading>,
}

impl<'a> TreePack<'a> {
    /// Lays out the trees one after another after checking that the GPU
    /// can traverse each: every index in range and no path from the root
    /// that pushes more than `STACK` entries, since the kernel's traversal
    /// stack has `STACK` entries. The builder guarantees both; this refuses
    /// a tree from anywhere else rather than render a wrong image. The
    /// first tree is packed as is (its root is node 0). `instances`: the
    /// first part's (the world's), whose meshes' trees follow the parts'.
    pub fn new(
        mut parts: Vec<TreePart<'a>>,
        instances: &'a Instances<f32>,
    ) -> Result<Self, GpuError> {
        let n_parts = parts.len();
        parts.extend(instances.meshes.iter().map(TreePart::mesh));
        let (mut nodes, mut prims, mut triangles, mut stack) = (0usize, 0usize, 0usize, 0u32);
        let mut places = Vec::with_capacity(parts.len());
        let mut bases = Vec::with_capacity(parts.len());
        for part in &parts {
            let tree = part.tree;
            let need = check_tree(
                &tree.nodes,
                &tree.prims,
                [part.spheres, part.triangles.len(), part.instances],
            )?;
            stack = stack.max(need);
            // The kernel's stack refers to a leaf as node << 2 | slot in
            // 31 bits, and a PrimId holds a triangle's index in 28.
            if nodes + tree.nodes.len() >= 1 << 29 || triangles + part.triangles.len() >= 1 << 28 {
                return Err(GpuError::BadTree(format!(
                    "the trees have {} nodes and {} triangles in all, more than the kernel can refer to",
                    nodes + tree.nodes.len(),
                    triangles + part.triangles.len()
                )));
            }
            bases.push((nodes as u32, prims as u32, triangles as u32));
            places.push(TreePlace {
                root: nodes as u32,
                first_triangle: triangles as u32,
            });
            nodes += tree.nodes.len();
            prims += tree.prims.len();
            triangles += part.triangles.len();
        }
        let mesh_places = &places[n_parts..];
        let list: Vec<GpuInstance> = instances
            .list
            .iter()
            .map(|i| {
                let place = mesh_places[i.mesh as usize];
                let (w, o) = (i.to_world.0, i.to_object.0);
                let col = |m: [f32; 12], c: usize| [m[3 * c], m[3 * c + 1], m[3 * c + 2]];
                GpuInstance {
                    w0: col(w, 0),
                    root: place.root,
                    w1: col(w, 1),
                    tri0: place.first_triangle,
                    w2: col(w, 2),
                    first: i.first,
                    w3: col(w, 3),
                    count: instances.meshes[i.mesh as usize].triangles.len() as u32,
                    o: std::array::from_fn(|c| {
                        let [x, y, z] = col(o, c);
                        [x, y, z, 0.0]
                    }),
                }
            })
            .collect();
        let layout = TreeLayout {
            n_nodes: nodes as u32,
            n_prims: prims as u32,
            n_triangles: triangles as u32,
            stack,
            places,
            n_instances: list.len() as u32,
            instances: non_empty(list),
        };
        Ok(TreePack {
            parts,
            bases,
            layout,
        })
    }

    /// Writes the arrays in order, each in pieces of at most `piece`
    /// elements: `sink(array, first element, bytes)`. A part's triangles
    /// and their shading are made together; nothing is made twice.
    pub fn write<E>(
        &self,
        piece: usize,
        mut sink: impl FnMut(TreeArray, usize, &[u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        let piece = piece.max(1);
        let (mut nodes, mut prims) = (Vec::new(), Vec::new());
        let (mut triangles, mut shading) = (Vec::new(), Vec::new());
        for (part, &(node0, prim0, tri0)) in self.parts.iter().zip(&self.bases) {
            let tree = part.tree;
            for (k, chunk) in tree.nodes.chunks(piece).enumerate() {
                nodes.clear();
                nodes.extend(chunk.iter().map(|n| {
                    let mut n = *n;
                    for k in 0..4 {
                        if !n.is_empty(k) {
                            n.child[k] += if n.count[k] == 0 { node0 } else { prim0 };
                        }
                    }
                    n
                }));
                let at = node0 as usize + k * piece;
                sink(TreeArray::Nodes, at, bytemuck::cast_slice(&nodes))?;
            }
            for (k, chunk) in tree.prims.chunks(piece).enumerate() {
                prims.clear();
                prims.extend(chunk.iter().map(|p| {
                    if *p != PrimId::NONE && p.kind() == PrimId::TRIANGLE {
                        p.0 + tri0
                    } else {
                        p.0
                    }
                }));
                let at = prim0 as usize + k * piece;
                sink(TreeArray::Prims, at, bytemuck::cast_slice(&prims))?;
            }
            let n = part.triangles.len();
            for start in (0..n).step_by(piece) {
                triangles.clear();
                shading.clear();
                part.pack_triangles(start..n.min(start + piece), &mut triangles, &mut shading);
                let at = tri0 as usize + start;
                sink(TreeArray::Triangles, at, bytemuck::cast_slice(&triangles))?;
                sink(TreeArray::Shading, at, bytemuck::cast_slice(&shading))?;
            }
        }
        Ok(())
    }

    /// The arrays whole, each at least one element long as uploaded.
    pub fn arrays(&self) -> TreeData {
        self.arrays_in(1 << 12)
    }

    /// The arrays whole, written in pieces of `piece` elements.
    fn arrays_in(&self, piece: usize) -> TreeData {
        let l = &self.layout;
        let mut d = TreeData {
            layout: l.clone(),
            nodes: vec![GpuBvhNode::zeroed(); l.len(TreeArray::Nodes)],
            prims: vec![0; l.len(TreeArray::Prims)],
            triangles: vec![GpuTriangle::default(); l.len(TreeArray::Triangles)],
            shading: vec![GpuTriangleShading::default(); l.len(TreeArray::Shading)],
        };
        self.write(piece, |array, at, bytes| {
            let out: &mut [u8] = match array {
                TreeArray::Nodes => bytemuck::cast_slice_mut(&mut d.nodes),
                TreeArray::Prims => bytemuck::cast_slice_mut(&mut d.prims),
                TreeArray::Triangles => bytemuck::cast_slice_mut(&mut d.triangles),
                TreeArray::Shading => bytemuck::cast_slice_mut(&mut d.shading),
            };
            let at = at * array.element_bytes();
            out[at..at + bytes.len()].copy_from_slice(bytes);
            Ok::<(), std::convert::Infallible>(())
        })
        .unwrap_or_else(|e| match e {});
        d
    }
}

/// Walks the tree from the root: child nodes and leaf ranges in bounds,
/// leaves referring to existing spheres or triangles, and at most `STACK`
/// entries on the traversal stack along any path (a node pushes all but one
/// of its used slots). Returns the most entries any path needs.
fn check_tree(
    nodes: &[BvhNode4],
    prims: &[PrimId],
    [spheres, triangles, instances]: [usize; 3],
) -> Result<u32, GpuError> {
    let bad = |why: String| Err(GpuError::BadTree(why));
    if nodes.is_empty() {
        return bad("the tree has no nodes".into());
    }
    // The kernel's stack refers to a leaf as node << 2 | slot in 31 bits.
    if nodes.len() >= 1 << 29 {
        return bad(format!(
            "the tree has {} nodes, more than the kernel can refer to",
            nodes.len()
        ));
    }
    let mut stack = vec![(0usize, 0usize, 0usize)];
    let mut most = 0;
    let mut visited = 0usize;
    while let Some((i, depth, need)) = stack.pop() {
        visited += 1;
        if visited > nodes.len() {
            return bad("nodes are shared or form a cycle".into());
        }
        let n = &nodes[i];
        let used = (0..4).filter(|&k| !n.is_empty(k)).count();
        if used == 0 {
            return bad(format!("node {i} has no children"));
        }
        let need = need + used - 1;
        if need > STACK {
            return Err(GpuError::TreeTooDeep {
                depth,
                stack: STACK,
            });
        }
        most = most.max(need);
        for k in (0..4).filter(|&k| !n.is_empty(k)) {
            let first = n.child[k] as usize;
            if n.count[k] == 0 {
                if first >= nodes.len() {
                    return bad(format!(
                        "node {i} has a child at {first}, outside the {} nodes",
                        nodes.len()
                    ));
                }
                stack.push((first, depth + 1, need));
                continue;
            }
            let Some(leaf) = prims.get(first..first + n.count[k] as usize) else {
                return bad(format!(
                    "node {i} has a leaf of primitives {first}..{} of {}",
                    first + n.count[k] as usize,
                    prims.len()
                ));
            };
            for p in leaf {
                let ok = match p.kind() {
                    PrimId::SPHERE => p.index() < spheres,
                    PrimId::TRIANGLE => p.index() < triangles,
                    PrimId::INSTANCE => p.index() < instances,
                    _ => false,
                };
                if !ok {
                    return bad(format!(
                        "node {i} has a leaf that refers to {p:?}, which is not a sphere, triangle or instance of the scene"
                    ));
                }
            }
        }
    }
    Ok(most as u32)
}

/// Everything the kernel needs of one frame of a scene, packed for upload.
/// Arrays are never empty (bindings must not be): an absent kind gets one
/// unused element, and its count (a pipeline constant) stays 0.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneData {
    pub frame: FrameUniform,
    pub spheres: Vec<GpuSphere>,
    pub planes: Vec<GpuPlane>,
    pub materials: Vec<GpuMaterial>,
    pub lights: Vec<GpuLight>,
    pub n_spheres: u32,
    pub n_planes: u32,
    pub n_lights: u32,
    pub max_depth: u32,
    pub has_reflection: bool,
    pub has_refraction: bool,
    /// The world's BVH over spheres and triangles (when it has one, first,
    /// with root 0), then the moving meshes' trees.
    pub tree: Option<SharedTree>,
    /// Whether `tree` starts with the world's own (the scene queries then
    /// traverse it: `accel.wgsl`, else `analytic.wgsl`).
    pub static_tree: bool,
    /// Distributed effects (`World::dist`), packed as distributed.wgsl reads them.
    pub dist: Option<DistData>,
    /// The path integrator's words, appended to `dist` (path scenes only).
    pub path: Option<PathData>,
    /// Model files' materials whose textures, vertex colours, emission or
    /// cut-outs the kernel looks up per hit (pbr.wgsl), or `None`.
    pub pbr: Option<std::sync::Arc<PbrData>>,
}

/// `World::dist` for distributed.wgsl: its `dist` array of vec4 (keep in
/// sync with the layout described there and in moving_meshes.wgsl) and the
/// pipeline constants.
#[derive(Clone, Debug, PartialEq)]
pub struct DistData {
    pub words: Vec<[f32; 4]>,
    pub n_lights: u32,
    pub n_moving: u32,
    /// Moving meshes with triangles (one with none can never be hit).
    pub n_moving_meshes: u32,
    pub has_lens: bool,
    pub has_blur: bool,
    pub has_camera_motion: bool,
}

impl DistData {
    /// Packs `d`; `meshes` are the moving meshes the kernel traces, each as
    /// its index in `d.moving_meshes` and the place of its packed tree.
    pub fn from_dist(
        d: &crate::distributed::Distributed<f32>,
        meshes: &[(usize, TreePlace)],
    ) -> Self {
        use crate::distributed::LightGeom;
        let v4 = |v: glam::Vec3A, w: f32| [v.x, v.y, v.z, w];
        let u = |x: u32| f32::from_bits(x);
        let zero = glam::Vec3A::ZERO;
        let (focus, cam) = (
            d.lens
                .as_ref()
                .and_then(|l| l.focus_distance)
                .unwrap_or(0.0),
            d.camera_motion.as_ref(),
        );
        let mut words = vec![
            v4(d.unit_right, d.lens.as_ref().map_or(0.0, |l| l.aperture)),
            v4(d.unit_up, focus),
            v4(cam.map_or(zero, |c| c.delta_position), d.look_distance),
            v4(
                cam.map_or(zero, |c| c.look_at),
                cam.map_or(0.0, |c| c.fov_y as f32),
            ),
            v4(
                cam.map_or(zero, |c| c.delta_look_at),
                cam.map_or(0.0, |c| c.delta_fov_y as f32),
            ),
            v4(cam.map_or(zero, |c| c.up), cam.map_or(1.0, |c| c.aspect)),
        ];
        for l in &d.lights {
            let (kind, a, b, c, radius) = match l.geom {
                LightGeom::Point(p) => (0, p, zero, zero, 0.0),
                LightGeom::Quad {
                    corner,
                    edge_u,
                    edge_v,
                } => (1, corner, edge_u, edge_v, 0.0),
                LightGeom::Sphere { center, radius } => (2, center, zero, zero, radius),
                LightGeom::Spot {
                    position,
                    direction,
                    scale,
                    offset,
                } => (
                    3,
                    position,
                    direction,
                    glam::Vec3A::new(scale, offset, 0.0),
                    0.0,
                ),
                LightGeom::Directional { direction, radius } => (4, zero, direction, zero, radius),
            };
            words.push(v4(a, u(kind)));
            words.push(v4(b, radius));
            words.push(v4(c, u(l.samples)));
            words.push(v4(l.diffuse, u(l.first_sample)));
            words.push(v4(l.specular, 0.0));
        }
        for m in &d.moving_spheres {
            words.push(v4(m.sphere.center, m.sphere.radius));
            words.push(v4(m.delta, u(m.sphere.material)));
        }
        for &(i, place) in meshes {
            let m = &d.moving_meshes[i];
            words.push(v4(m.lo, u(place.root)));
            words.push(v4(m.hi, u(place.first_triangle)));
            words.push(v4(m.delta, 0.0));
        }
        DistData {
            words,
            n_lights: d.lights.len() as u32,
            n_moving: d.moving_spheres.len() as u32,
            n_moving_meshes: meshes.len() as u32,
            has_lens: d.lens.is_some(),
            has_blur: d.blur,
            has_camera_motion: d.camera_motion.is_some(),
        }
    }
}

// ---- The path integrator (path.wgsl, bsdf.wgsl) ---------------------------

/// Where the path integrator's words start in `DistData::words` and
/// whether any light emits (path.wgsl's `PATH_BASE`, `PATH_NEE`). The
/// words: the environment; per light (its selection probability, the
/// first 24-bit uniform number that picks past it); per GPU material
/// [`PathData::MATERIAL_WORDS`] words of its [`Bsdf`] (path.wgsl
/// `path_bsdf`), the fourth one's w its emissive triangles' selection
/// density (`PathScene::emit_density`), the fifth its absorption;
/// then per emissive triangle 4 words (path.wgsl `emitter_sample`) from
/// `emit_base` (`PATH_EMIT_BASE`, `PATH_EMITTERS`); then, where there is
/// an environment image (`crate::environment`), from `env_base`
/// (`PATH_ENV_BASE`, 0 without one): a header (the first 24-bit number
/// that picks past it, W and H as bits, the rotation in turns), W x H
/// texels (linear RGB, and in w the density of the cell whose top-left
/// corner the texel is: 0 on the last row), the cells' row CDFs and the
/// rows' marginal CDF, 4 to a word. The first word's w is the image's
/// selection probability.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathData {
    pub base: u32,
    pub nee: bool,
    pub emitters: u32,
    pub emit_base: u32,
    pub env_base: u32,
}

impl PathData {
    /// Words per material (path.wgsl `PATH_MATERIAL_WORDS`).
    pub const MATERIAL_WORDS: u32 = 5;

    /// Appends `scene`'s words and `bsdfs` (one per GPU material) to `d`.
    pub fn append(d: &mut DistData, scene: &PathScene<f32>, bsdfs: &[Bsdf<f32>]) -> Self {
        let base = d.words.len() as u32;
        let v4 = |v: glam::Vec3A, w: f32| [v.x, v.y, v.z, w];
        d.words.push(v4(scene.environment, scene.env_prob));
        // PathScene::pick takes the first light whose running sum c
        // exceeds u = k / 2^24: c <= u exactly when ceil(c 2^24) <= k.
        let first = |i: usize| {
            let b = scene.light_cdf.get(i).map_or(u32::MAX, |c| {
                (c * 16_777_216.0).ceil().min(u32::MAX as f64) as u32
            });
            f32::from_bits(b)
        };
        for (i, &p) in scene.light_prob.iter().enumerate() {
            d.words.push([p, first(i), 0.0, 0.0]);
        }
        let materials = d.words.len();
        for (i, b) in bsdfs.iter().enumerate() {
            let density = scene.emit_density.get(i).copied().unwrap_or(0.0);
            d.words.push(v4(b.base_colour, b.metallic));
            d.words.push(v4(b.specular_colour, b.roughness));
            d.words.push(v4(b.emission, b.ior));
            d.words
                .push([b.transmission, b.specular, b.mirror, density]);
            d.words.push(v4(b.absorption, 0.0));
        }
        debug_assert_eq!(
            d.words.len() - materials,
            Self::MATERIAL_WORDS as usize * bsdfs.len()
        );
        let emit_base = d.words.len() as u32;
        let first_emitter = scene.first_emitter();
        for (k, e) in scene.emitters.iter().enumerate() {
            d.words.push(v4(e.a, first(first_emitter + k)));
            d.words.push(v4(e.e1, f32::from_bits(e.material)));
            // The triangle's id: where a textured emission is read.
            d.words.push(v4(e.e2, f32::from_bits(e.id.0)));
            d.words.push(v4(e.n, 0.0));
        }
        let mut env_base = 0;
        if let (Some(env), Some(i)) = (&scene.environment_map, scene.env_index()) {
            env_base = d.words.len() as u32;
            d.words.push([
                first(i),
                f32::from_bits(env.width),
                f32::from_bits(env.height),
                env.u_offset as f32,
            ]);
            let w = env.width as usize;
            d.words.extend(
                env.texels
                    .iter()
                    .enumerate()
                    .map(|(i, t)| [t[0], t[1], t[2], env.density.get(i).copied().unwrap_or(0.0)]),
            );
            for floats in [&env.row_cdf, &env.marginal_cdf] {
                d.words.extend(
                    floats
                        .chunks(4)
                        .map(|c| std::array::from_fn(|k| c.get(k).copied().unwrap_or(1.0))),
                );
            }
            debug_assert_eq!(env.density.len(), w * (env.height as usize - 1));
        }
        PathData {
            base,
            nee: !scene.light_cdf.is_empty(),
            emitters: scene.emitters.len() as u32,
            emit_base,
            env_base,
        }
    }
}

/// The path integrator's BSDF of material `i` of `w` (worlds made without
/// BSDFs get Blinn-Phong's mapping, as `World` does).
fn bsdf_of(w: &World<f32>, i: usize) -> Bsdf<f32> {
    w.bsdfs
        .get(i)
        .copied()
        .unwrap_or_else(|| Bsdf::from_material(&w.materials[i]))
}

/// Packed trees as a renderer keeps them, shared between renders of the
/// same world (every tile of a frame): equal when it is the same
/// allocation, or was packed from the same trees (`Bvh::id`s, none
/// unknown) into the same layout.
#[derive(Clone, Debug)]
pub struct SharedTree {
    /// `Bvh::id` of each tree it was packed from, in order (0: unknown,
    /// never reused).
    pub ids: Vec<u64>,
    pub layout: std::sync::Arc<TreeLayout>,
}

impl PartialEq for SharedTree {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.layout, &other.layout)
            || (self.ids.iter().all(|&id| id != 0)
                && self.ids == other.ids
                && self.layout == other.layout)
    }
}

fn a3(v: glam::Vec3A) -> [f32; 3] {
    v.to_array()
}

fn non_empty<T: Default>(mut v: Vec<T>) -> Vec<T> {
    if v.is_empty() {
        v.push(T::default());
    }
    v
}

/// The GPU's record of a material.
fn gpu_material(m: &Material<f32>) -> GpuMaterial {
    GpuMaterial {
        ambient: a3(m.ambient),
        shininess: m.shininess,
        diffuse: a3(m.diffuse),
        reflectivity: m.reflectivity,
        specular: a3(m.specular),
        transparency: m.transparency,
        ior: m.ior,
        specular_cos_min: m.specular_cos_min,
        gloss_cos: m.gloss_cos,
        translucency_cos: m.translucency_cos,
    }
}

/// The trees of `w` to pack: the world's own, then each moving mesh's,
/// whose materials are the world's so far and then its file's
/// (world/mod.rs): those that differ from the world's get places of their
/// own in `materials` and `bsdfs` (the world's, on entry). Also the index
/// in `moving_meshes` of each moving part.
fn tree_parts<'w>(
    w: &'w World<f32>,
    materials: &mut Vec<GpuMaterial>,
    bsdfs: &mut Vec<Bsdf<f32>>,
) -> Result<(Vec<TreePart<'w>>, Vec<usize>), GpuError> {
    // The path integrator's BSDFs are compared too when a moving mesh's
    // material is matched to the world's.
    let is_path = w.dist.as_ref().is_some_and(|d| d.path.is_some());
    let mut parts: Vec<TreePart<'w>> = w
        .accel
        .as_ref()
        .filter(|t| !t.nodes.is_empty())
        .map(|t| TreePart::world(w, t, None))
        .into_iter()
        .collect();
    let mut moving = Vec::new();
    for (i, m) in w
        .dist
        .iter()
        .flat_map(|d| d.moving_meshes.iter().enumerate())
    {
        let Some(t) = m.world.accel.as_ref().filter(|t| !t.nodes.is_empty()) else {
            if m.world.triangle_count() == 0 {
                continue; // nothing to hit
            }
            return Err(GpuError::BadTree(format!(
                "a moving mesh has {} triangles but no BVH over them",
                m.world.triangle_count()
            )));
        };
        let map: Vec<u32> = m
            .world
            .materials
            .iter()
            .enumerate()
            .map(|(j, own)| {
                let g = gpu_material(own);
                let b = bsdf_of(&m.world, j);
                if j < w.materials.len() && materials[j] == g && (!is_path || bsdfs[j] == b) {
                    j as u32
                } else {
                    materials.push(g);
                    bsdfs.push(b);
                    materials.len() as u32 - 1
                }
            })
            .collect();
        parts.push(TreePart::world(&m.world, t, Some(map)));
        moving.push(i);
    }
    Ok((parts, moving))
}

impl SceneData {
    /// The trees of `w` to write to the device, laid out as
    /// [`SceneData::from_world`] lays them out (`None`: `w` has none).
    pub fn tree_pack(w: &World<f32>) -> Result<Option<TreePack<'_>>, GpuError> {
        let mut materials: Vec<GpuMaterial> = w.materials.iter().map(gpu_material).collect();
        let mut bsdfs: Vec<Bsdf<f32>> = (0..w.materials.len()).map(|i| bsdf_of(w, i)).collect();
        let (parts, _) = tree_parts(w, &mut materials, &mut bsdfs)?;
        if parts.is_empty() {
            return Ok(None);
        }
        TreePack::new(parts, &w.instances).map(Some)
    }

    /// Packs `w`. `packed` is a tree packed earlier, reused (not repacked)
    /// when it was packed from this world's trees (same non-zero `Bvh::id`s
    /// and primitive counts); `texels`, texels packed earlier, reused when
    /// packed from this world's images.
    pub fn from_world(
        w: &World<f32>,
        packed: Option<&SharedTree>,
        texels: Option<&std::sync::Arc<TexelPack>>,
    ) -> Result<Self, GpuError> {
        let s = &w.settings;
        // 0: the low-discrepancy points (non-square counts, and the
        // progressive sampler whatever the count), as `sample_offset`,
        // and no strata for the path integrator's pairs.
        let grid_n = crate::sampling::strata_side(s.sampler, s.samples);
        let frame = FrameUniform {
            forward: a3(w.camera.forward),
            inv_width: w.camera.inv_width,
            right: a3(w.camera.right),
            inv_height: w.camera.inv_height,
            up: a3(w.camera.up),
            samples: s.samples,
            ambient: a3(w.ambient),
            grid_n,
            background: a3(w.background),
            sampler: match s.sampler {
                crate::sampling::Sampler::Grid => 0,
                crate::sampling::Sampler::Jittered => 1,
                crate::sampling::Sampler::Progressive => 2,
            },
        };
        let sphere = |s: &Sphere<f32>| GpuSphere {
            center: a3(s.center),
            radius: s.radius,
            material: s.material,
            _pad: [0; 3],
        };
        let plane = |p: &Plane<f32>| GpuPlane {
            normal: a3(p.normal),
            distance: p.distance,
            material: p.material,
            _pad: [0; 3],
        };
        let light = |l: &PointLight<f32>| GpuLight {
            position: a3(l.position),
            diffuse: a3(l.diffuse),
            specular: a3(l.specular),
            ..Default::default()
        };
        let mut materials: Vec<GpuMaterial> = w.materials.iter().map(gpu_material).collect();
        let mut bsdfs: Vec<Bsdf<f32>> = (0..w.materials.len()).map(|i| bsdf_of(w, i)).collect();
        let (parts, moving) = tree_parts(w, &mut materials, &mut bsdfs)?;
        let static_tree = w.accel.as_ref().filter(|t| !t.nodes.is_empty());
        let instances = &w.instances;
        let ids: Vec<u64> = parts
            .iter()
            .map(|p| p.tree.id)
            .chain(instances.meshes.iter().map(|m| m.tree.id))
            .collect();
        let tree = if parts.is_empty() {
            None
        } else {
            match packed {
                Some(p)
                    if ids.iter().all(|&id| id != 0)
                        && p.ids == ids
                        && p.layout.n_triangles as usize
                            == parts.iter().map(|p| p.triangles.len()).sum::<usize>()
                                + instances
                                    .meshes
                                    .iter()
                                    .map(|m| m.triangles.len())
                                    .sum::<usize>()
                        && p.layout.n_prims as usize
                            == parts.iter().map(|p| p.tree.prims.len()).sum::<usize>()
                                + instances
                                    .meshes
                                    .iter()
                                    .map(|m| m.tree.prims.len())
                                    .sum::<usize>()
                        && p.layout.n_instances as usize == instances.list.len() =>
                {
                    Some(p.clone())
                }
                _ => Some(SharedTree {
                    ids,
                    layout: std::sync::Arc::new(TreePack::new(parts, instances)?.layout),
                }),
            }
        };
        let meshes: Vec<(usize, TreePlace)> = match &tree {
            Some(t) => moving
                .iter()
                .zip(&t.layout.places[static_tree.is_some() as usize..])
                .map(|(i, place)| (*i, *place))
                .collect(),
            None => Vec::new(),
        };
        if static_tree.is_none() && w.triangle_count() > 0 {
            // Worlds always get a tree with their triangles (accel.rs); the
            // kernel has no loop over triangles.
            return Err(GpuError::BadTree(format!(
                "the scene has {} triangles but no BVH over them",
                w.triangle_count()
            )));
        }
        let mut dist = w.dist.as_deref().map(|d| DistData::from_dist(d, &meshes));
        let path = match (&mut dist, w.dist.as_ref().and_then(|d| d.path.as_ref())) {
            (Some(d), Some(scene)) => Some(PathData::append(d, scene, &bsdfs)),
            _ => None,
        };
        let pbr = PbrData::from_world(w, materials.len(), texels).map(std::sync::Arc::new);
        Ok(SceneData {
            frame,
            spheres: non_empty(w.spheres.iter().map(sphere).collect()),
            planes: non_empty(w.planes.iter().map(plane).collect()),
            materials: non_empty(materials),
            lights: non_empty(w.lights.iter().map(light).collect()),
            n_spheres: w.spheres.len() as u32,
            n_planes: w.planes.len() as u32,
            n_lights: w.lights.len() as u32,
            max_depth: s.max_depth,
            has_reflection: w.features.reflection,
            has_refraction: w.features.refraction,
            tree,
            static_tree: static_tree.is_some(),
            dist,
            path,
            pbr,
        })
    }

    /// Bytes of the scene's buffers on the device (placeholders for absent
    /// kinds included): its geometry, trees, instances, distributed and
    /// path words, model materials and texels.
    pub fn device_bytes(&self) -> u64 {
        use std::mem::size_of_val as bytes;
        let mut n = bytes(self.spheres.as_slice())
            + bytes(self.planes.as_slice())
            + bytes(self.materials.as_slice())
            + bytes(self.lights.as_slice());
        if let Some(t) = &self.tree {
            n += TreeArray::ALL
                .iter()
                .map(|&a| t.layout.bytes(a) as usize)
                .sum::<usize>()
                + bytes(t.layout.instances.as_slice());
        }
        if let Some(d) = &self.dist {
            n += bytes(d.words.as_slice());
        }
        if let Some(p) = &self.pbr {
            n += bytes(p.mat_pbr.as_slice())
                + bytes(p.pbrs.as_slice())
                + bytes(p.tri_attrs.as_slice())
                + bytes(p.vertices.as_slice())
                + bytes(p.texels.words.as_slice());
        }
        n as u64
    }

    /// Entries of the per-thread task stack the kernel needs: the kernel
    /// continues with one child and pushes the other, so only a node with
    /// both a refracted and a reflected child pushes, at most one entry per
    /// generation.
    pub fn stack_capacity(&self) -> u32 {
        if self.has_refraction {
            self.max_depth.max(1)
        } else {
            1
        }
    }
}

// ---- Model files' materials (pbr.wgsl) -----------------------------------

/// A texture as a material uses it (`texture::TextureRef`). WGSL (pbr.wgsl): `struct TexRef`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuTexRef {
    /// Its image's first texel in `PbrData::texels` (after the decode tables).
    pub offset: u32,
    pub width: u32,
    pub height: u32,
    /// `TEX_*` bits: present, nearest, sRGB, UV set 1, wrap modes.
    pub flags: u32,
    /// The `KHR_texture_transform` rows (a, b, c) ...
    pub row0: [f32; 3],
    /// ... the first texel of its mip level 1 (`Image::levels` for its
    /// decoding, one level after another) ...
    pub mips: u32,
    /// ... (d, e, f) ...
    pub row1: [f32; 3],
    /// ... and how many levels lie below the image.
    pub levels: u32,
}

pub const TEX_PRESENT: u32 = 1;
pub const TEX_NEAREST: u32 = 2;
pub const TEX_SRGB: u32 = 4;
pub const TEX_UV1: u32 = 8;
/// Wrap modes (0 repeat, 1 clamp, 2 mirrored repeat) of u at bits 4-5, v at 6-7.
pub const TEX_WRAP_SHIFT: u32 = 4;

/// A model file's material (`material::Pbr`) as pbr.wgsl reads it. WGSL: `struct Pbr`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuPbr {
    pub base_color: [f32; 4],
    /// emissiveFactor x emissiveStrength (`Material::emission` where no texture).
    pub emissive: [f32; 3],
    /// `PBR_*` bits.
    pub flags: u32,
    pub metallic: f32,
    pub roughness: f32,
    pub transmission: f32,
    pub ior: f32,
    /// The dielectric's specular colour, 0.04 specularFactor specularColor
    /// (`Pbr::whitted`'s f0, made in f64 as there).
    pub f0: [f32; 3],
    /// The smallest f32 not below alphaCutoff: alpha < it exactly when
    /// alpha < the f64 cutoff the CPU compares with.
    pub alpha_cutoff: f32,
    pub occlusion_strength: f32,
    /// normalTexture.scale.
    pub normal_scale: f32,
    /// An MTL bump map's `-bm` (`Pbr::bump_scale`).
    pub bump_scale: f32,
    pub _pad: f32,
    /// Base colour, metallic-roughness, emissive, occlusion, MTL alpha,
    /// normal or bump (`PBR_BUMP`) (`PBR_TEX_*`).
    pub tex: [GpuTexRef; 6],
}

pub const PBR_MASK: u32 = 1;
pub const PBR_BLEND: u32 = 2;
pub const PBR_MTL: u32 = 4;
/// `Pbr::varies`: hits look the material up (else the material and emission as they are).
pub const PBR_VARIES: u32 = 8;
/// `Pbr::culls_back_faces`: a back face is cut away for every ray.
pub const PBR_CULL: u32 = 16;
/// The normal slot holds an MTL bump map (`Pbr::bump_texture`).
pub const PBR_BUMP: u32 = 32;

/// One vertex's attributes (`VertexAttrs`). WGSL: `struct VertexAttr`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuVertexAttr {
    pub uv0: [f32; 2],
    pub uv1: [f32; 2],
    pub colour: [f32; 4],
    /// `VertexAttrs::tangent` (w 0: unknown).
    pub tangent: [f32; 4],
}

const _: () = assert!(size_of::<GpuTexRef>() == 48);
const _: () = assert!(size_of::<GpuPbr>() == 80 + 6 * 48);
const _: () = assert!(size_of::<GpuVertexAttr>() == 48);

/// Texels of the decode tables that lead `PbrData::texels`: 256 sRGB
/// bytes to linear, then 256 bytes / 255 (`texture.rs`'s exact values).
pub const TEXEL_TABLES: u32 = 512;

/// The world's model materials for pbr.wgsl: per GPU material its
/// `GpuPbr` (or `NO_PBR`), the materials, the triangles' vertex
/// attributes and every image once per decoding with its mip levels, as
/// the RGBA bytes the CPU filters (four to a word, little-endian), after
/// the decode tables.
#[derive(Clone, Debug, PartialEq)]
pub struct PbrData {
    pub mat_pbr: Vec<u32>,
    pub pbrs: Vec<GpuPbr>,
    /// Three vertex indices per attribute triangle (`VertexAttrs::tri`).
    pub tri_attrs: Vec<u32>,
    pub vertices: Vec<GpuVertexAttr>,
    pub texels: std::sync::Arc<TexelPack>,
    /// Some material is alphaMode MASK: every query passes cut-outs.
    pub cutouts: bool,
}

/// The texels binding: the decode tables, then every image of a world's
/// model materials once per decoding (sRGB colour or data), in first-use
/// order, each followed by its mip levels for that decoding
/// (`Image::levels`), with the images it was packed from. Kept with the scene between renders, so that another tile
/// or frame of the same world packs, compares and uploads no texel
/// (DamagedHelmet's 84 MB cost ~100 ms a call): equal when it is the same
/// allocation or was packed from the same images (the same `Arc`s, held
/// here, so no address is reused while it is compared); a world of other
/// images is packed and uploaded afresh, even if their texels are equal.
pub struct TexelPack {
    /// Each image with its decoding (sRGB colour channels or not).
    pub images: Vec<(std::sync::Arc<crate::texture::Image>, bool)>,
    pub words: Vec<u32>,
}

impl TexelPack {
    /// Packs `images` after the decode tables.
    fn pack(images: Vec<(std::sync::Arc<crate::texture::Image>, bool)>) -> Self {
        let mut words: Vec<u32> = crate::texture::decode_tables()
            .iter()
            .map(|v| v.to_bits())
            .collect();
        let le = |c: &[u8; 4]| u32::from_le_bytes(*c);
        for (i, srgb) in &images {
            words.extend(i.texels.iter().map(le));
            for l in i.levels(*srgb) {
                words.extend(l.texels.iter().map(le));
            }
        }
        TexelPack { images, words }
    }

    /// Whether it was packed from exactly `images` (by identity).
    fn holds(&self, images: &[(std::sync::Arc<crate::texture::Image>, bool)]) -> bool {
        self.images.len() == images.len()
            && self
                .images
                .iter()
                .zip(images)
                .all(|((a, sa), (b, sb))| std::sync::Arc::ptr_eq(a, b) && sa == sb)
    }
}

impl PartialEq for TexelPack {
    fn eq(&self, other: &Self) -> bool {
        std::ptr::eq(self, other) || self.holds(&other.images)
    }
}

impl std::fmt::Debug for TexelPack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "TexelPack {{ {} images, {} words }}",
            self.images.len(),
            self.words.len()
        )
    }
}

impl PbrData {
    /// The texture bytes on the GPU (images only, the tables left out).
    pub fn texture_bytes(&self) -> u64 {
        (self.texels.words.len() as u64 - TEXEL_TABLES as u64) * 4
    }

    /// `None` when nothing of `w`'s model materials varies over a surface,
    /// emits or is cut out (alpha MASK, or single-sided:
    /// `Pbr::culls_back_faces`): the kernel then renders its materials as
    /// before model materials existed. `n_materials`: the GPU's materials.
    /// `packed`: texels packed for an earlier render, reused when they
    /// were packed from this world's images ([`TexelPack`]).
    pub fn from_world(
        w: &World<f32>,
        n_materials: usize,
        packed: Option<&std::sync::Arc<TexelPack>>,
    ) -> Option<Self> {
        use crate::material::{AlphaMode, NO_PBR};
        use crate::texture::{TextureRef, Wrap};
        let used = w.pbr.iter().any(|p| {
            p.varies()
                || p.emissive.iter().any(|&e| e != 0.0)
                || p.alpha_mode == AlphaMode::Mask
                || p.culls_back_faces()
        });
        if !used {
            return None;
        }
        // Every image once per decoding, in first-use order, and its first word.
        let images: Vec<(std::sync::Arc<crate::texture::Image>, bool)> = w
            .texture_decodings()
            .into_iter()
            .map(|(i, srgb)| (i.clone(), srgb))
            .collect();
        let mut offsets: Vec<u32> = Vec::with_capacity(images.len());
        let mut next = TEXEL_TABLES;
        for (i, srgb) in &images {
            offsets.push(next);
            next += i.texels.len() as u32;
            next += i
                .levels(*srgb)
                .iter()
                .map(|l| l.texels.len() as u32)
                .sum::<u32>();
        }
        let tex = |t: &Option<TextureRef>| -> GpuTexRef {
            let Some(t) = t else {
                return GpuTexRef::default();
            };
            let at = images
                .iter()
                .position(|(i, srgb)| std::sync::Arc::ptr_eq(i, &t.image) && *srgb == t.srgb)
                .expect("every image was listed");
            let offset = offsets[at];
            let wrap = |w: Wrap| match w {
                Wrap::Repeat => 0,
                Wrap::ClampToEdge => 1,
                Wrap::MirroredRepeat => 2,
            };
            let [a, b] = t.transform;
            GpuTexRef {
                offset,
                width: t.image.width,
                height: t.image.height,
                flags: TEX_PRESENT
                    | if t.nearest { TEX_NEAREST } else { 0 }
                    | if t.srgb { TEX_SRGB } else { 0 }
                    | if t.uv_set == 1 { TEX_UV1 } else { 0 }
                    | wrap(t.wrap[0]) << TEX_WRAP_SHIFT
                    | wrap(t.wrap[1]) << (TEX_WRAP_SHIFT + 2),
                row0: a,
                mips: offset + t.image.texels.len() as u32,
                row1: b,
                levels: t.image.levels(t.srgb).len() as u32,
            }
        };
        let pbrs: Vec<GpuPbr> = w
            .pbr
            .iter()
            .map(|p| {
                let mut cutoff = p.alpha_cutoff as f32;
                if (cutoff as f64) < p.alpha_cutoff {
                    cutoff = cutoff.next_up();
                }
                GpuPbr {
                    base_color: p.base_color.map(|c| c as f32),
                    emissive: p.emissive.map(|c| c as f32),
                    flags: match p.alpha_mode {
                        AlphaMode::Opaque => 0,
                        AlphaMode::Mask => PBR_MASK,
                        AlphaMode::Blend => PBR_BLEND,
                    } | if p.mtl { PBR_MTL } else { 0 }
                        | if p.varies() { PBR_VARIES } else { 0 }
                        | if p.culls_back_faces() { PBR_CULL } else { 0 }
                        | if p.bump_texture.is_some() {
                            PBR_BUMP
                        } else {
                            0
                        },
                    metallic: p.metallic as f32,
                    roughness: p.roughness as f32,
                    transmission: p.transmission as f32,
                    ior: p.ior as f32,
                    f0: p
                        .specular_color
                        .map(|c| (0.04 * p.specular_factor * c) as f32),
                    alpha_cutoff: cutoff,
                    occlusion_strength: p.occlusion_strength as f32,
                    normal_scale: p.normal_scale as f32,
                    bump_scale: p.bump_scale as f32,
                    _pad: 0.0,
                    tex: [
                        tex(&p.base_color_texture),
                        tex(&p.metallic_roughness_texture),
                        tex(&p.emissive_texture),
                        tex(&p.occlusion_texture),
                        tex(&p.alpha_texture),
                        tex(if p.normal_texture.is_some() {
                            &p.normal_texture
                        } else {
                            &p.bump_texture
                        }),
                    ],
                }
            })
            .collect();
        let mut mat_pbr: Vec<u32> = w
            .materials
            .iter()
            .map(|m| if m.pbr == NO_PBR { NO_PBR } else { m.pbr })
            .collect();
        // Materials only moving meshes use have none here (their triangles
        // keep no attributes on the GPU).
        mat_pbr.resize(n_materials.max(1), NO_PBR);
        let a = &w.attrs;
        let vertices = (0..a.color.len())
            .map(|i| GpuVertexAttr {
                uv0: a.uv[0].get(i).copied().unwrap_or_default(),
                uv1: a.uv[1].get(i).copied().unwrap_or_default(),
                colour: a.color[i],
                tangent: a.tangent.get(i).copied().unwrap_or_default(),
            })
            .collect();
        Some(PbrData {
            mat_pbr,
            pbrs: non_empty(pbrs),
            tri_attrs: non_empty(a.tri.iter().flatten().copied().collect()),
            vertices: non_empty(vertices),
            texels: match packed {
                Some(t) if t.holds(&images) => t.clone(),
                _ => std::sync::Arc::new(TexelPack::pack(images)),
            },
            cutouts: a.cutouts,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::SceneDesc;

    /// OBJ text of an n x n grid of unit quads at z = 0, two triangles each
    /// (enough for a tree of several nodes), with `head` first.
    fn grid(n: u32, head: &str) -> String {
        grid_with(n, head, |_, _| (0.0, None))
    }

    /// The same grid, vertex (x, y) at the height `vertex` gives, with the
    /// vertex normal it gives (every vertex or none).
    fn grid_with(
        n: u32,
        head: &str,
        vertex: impl Fn(u32, u32) -> (f32, Option<[f32; 3]>),
    ) -> String {
        let mut s = head.to_string();
        let mut normals = false;
        for y in 0..=n {
            for x in 0..=n {
                let (z, normal) = vertex(x, y);
                s += &format!("v {x} {y} {z}\n");
                if let Some([nx, ny, nz]) = normal {
                    s += &format!("vn {nx} {ny} {nz}\n");
                    normals = true;
                }
            }
        }
        let at = |x: u32, y: u32| y * (n + 1) + x + 1;
        let c = |i: u32| {
            if normals {
                format!("{i}//{i}")
            } else {
                i.to_string()
            }
        };
        for y in 0..n {
            for x in 0..n {
                let [a, b, cc, d] = [at(x, y), at(x + 1, y), at(x + 1, y + 1), at(x, y + 1)].map(c);
                s += &format!("f {a} {b} {cc}\nf {a} {cc} {d}\n");
            }
        }
        s
    }

    /// Moving meshes' trees are packed after the static one, which stays as
    /// it was: walked from its root, each reaches exactly its own mesh's
    /// triangles, each once (rebased node, leaf and triangle indices), and
    /// its file's materials, which differ from those of a static mesh
    /// listed after it, are mapped to their own places.
    #[test]
    fn moving_mesh_trees_are_packed_after_the_static_one() {
        let dir = std::env::temp_dir().join(format!("tessera-pack-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("plain.obj"), grid(6, "")).unwrap();
        std::fs::write(dir.join("red.mtl"), "newmtl red\nKd 1 0 0\n").unwrap();
        std::fs::write(dir.join("blue.mtl"), "newmtl blue\nKd 0 0 1\n").unwrap();
        std::fs::write(dir.join("red.obj"), grid(5, "mtllib red.mtl\nusemtl red\n")).unwrap();
        std::fs::write(
            dir.join("blue.obj"),
            grid(4, "mtllib blue.mtl\nusemtl blue\n"),
        )
        .unwrap();
        let src = r#"
[camera]
position = [0, 0, -10]
look_at = [0, 0, 0]
shutter = [0, 1]
[materials.grey]
diffuse = [0.5, 0.5, 0.5]
[[objects]]
type = "mesh"
path = "plain.obj"
material = "grey"
[[objects]]
type = "mesh"
path = "red.obj"
[[objects.keyframes]]
frame = 0
translate = [-3, 0, 0]
[[objects.keyframes]]
frame = 1
translate = [3, 0, 0]
[[objects]]
type = "mesh"
path = "plain.obj"
material = "grey"
[[objects.keyframes]]
frame = 0
translate = [0, -3, 0]
[[objects.keyframes]]
frame = 1
translate = [0, 3, 1]
[[objects]]
type = "mesh"
path = "blue.obj"
translate = [0, 0, 2]
"#;
        let desc = SceneDesc::parse(src, dir.join("s.toml")).unwrap();
        let w = World::<f32>::build(&desc, &desc.render, 0);
        let data = SceneData::from_world(&w, None, None).unwrap();
        let tree = SceneData::tree_pack(&w).unwrap().unwrap().arrays();
        assert_eq!(&tree.layout, &*data.tree.as_ref().unwrap().layout);
        let meshes = &w.dist.as_ref().unwrap().moving_meshes;
        assert!(data.static_tree);
        assert_eq!(tree.layout.places.len(), 3);
        let own = w.accel.as_ref().unwrap();
        assert_eq!(tree.layout.places[0], TreePlace::default());
        assert_eq!(&tree.nodes[..own.nodes.len()], &own.nodes[..]);
        let dist = data.dist.as_ref().unwrap();
        assert_eq!(dist.n_moving_meshes, 2);
        for (k, m) in meshes.iter().enumerate() {
            let place = tree.layout.places[k + 1];
            let first = place.first_triangle as usize;
            let end = first + m.world.triangle_count();
            assert_eq!(
                tree.layout
                    .places
                    .get(k + 2)
                    .map_or(tree.layout.n_triangles as usize, |p| p.first_triangle
                        as usize),
                end
            );
            // The mesh's words in `dist`: after 6 camera words, 5 a light
            // and 2 a moving sphere, 3 a mesh.
            let at = 6 + 5 * dist.n_lights as usize + 2 * dist.n_moving as usize + 3 * k;
            let words = &dist.words[at..at + 3];
            assert_eq!(words[0][3].to_bits(), place.root);
            assert_eq!(words[1][3].to_bits(), place.first_triangle);
            assert_eq!(words[2][..3], a3(m.delta));
            // Walk from the root: every triangle of the mesh, once.
            let mut seen = vec![0; m.world.triangle_count()];
            let mut todo = vec![place.root as usize];
            while let Some(i) = todo.pop() {
                let n = &tree.nodes[i];
                for s in (0..4).filter(|&s| !n.is_empty(s)) {
                    if n.count[s] == 0 {
                        todo.push(n.child[s] as usize);
                        continue;
                    }
                    let leaf = n.child[s] as usize..(n.child[s] + n.count[s]) as usize;
                    for &p in &tree.prims[leaf] {
                        let id = PrimId(p);
                        assert_eq!(id.kind(), PrimId::TRIANGLE);
                        assert!((first..end).contains(&id.index()), "mesh {k}: {id:?}");
                        seen[id.index() - first] += 1;
                    }
                }
            }
            assert!(seen.iter().all(|&c| c == 1), "mesh {k}: {seen:?}");
            for (j, t) in m.world.triangles().enumerate() {
                let g = tree.triangles[first + j];
                assert_eq!([g.v0, g.v1, g.v2], t.vertices().map(a3));
                let mat = &m.world.materials[m.world.triangle_shading[j].material as usize];
                let gm = data.materials[tree.shading[first + j].material as usize];
                assert_eq!(gm.diffuse, a3(mat.diffuse), "mesh {k}, triangle {j}");
            }
        }
        // The red file material has a place of its own: the world's
        // material at that index is the static blue mesh's.
        let red = tree.shading[tree.layout.places[1].first_triangle as usize].material as usize;
        assert_eq!(data.materials[red].diffuse, [1.0, 0.0, 0.0]);
        assert!(red >= w.materials.len());
        let _ = std::fs::remove_dir_all(&dir);
    }
    /// A big world keeps only its triangles' corners into its vertices:
    /// packing gathers each triangle from them, with its vertex normals by
    /// corner, and the pieces the arrays are written in change nothing.
    #[test]
    fn a_big_world_is_packed_from_its_corners() {
        let dir = std::env::temp_dir().join(format!("tessera-pack-big-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // 2 n^2 triangles: a big world.
        let obj = grid_with(363, "", |x, y| {
            let z = ((x * 7 + y * 3) % 5) as f32 * 0.1;
            (z, Some([(x % 3) as f32 * 0.2, (y % 4) as f32 * 0.1, 1.0]))
        });
        std::fs::write(dir.join("big.obj"), obj).unwrap();
        let src = r#"
[camera]
position = [180, 180, -400]
look_at = [180, 180, 0]
[materials.grey]
diffuse = [0.5, 0.5, 0.5]
[[objects]]
type = "mesh"
path = "big.obj"
material = "grey"
"#;
        let desc = SceneDesc::parse(src, dir.join("s.toml")).unwrap();
        let w = World::<f32>::build(&desc, &desc.render, 0);
        assert!(w.triangle_count() >= crate::world::GIVE_UP_TRIANGLES_FROM);
        assert!(w.gathered_triangles().is_none(), "a big world");
        let pack = SceneData::tree_pack(&w).unwrap().unwrap();
        let whole = pack.arrays();
        assert_eq!(whole.layout.n_triangles as usize, w.triangle_count());
        assert_eq!(&whole.nodes[..], &w.accel.as_ref().unwrap().nodes[..]);
        for (i, t) in w.triangles().enumerate() {
            let (g, s) = (whole.triangles[i], whole.shading[i]);
            assert_eq!([g.v0, g.v1, g.v2], t.vertices().map(a3), "triangle {i}");
            assert_eq!(s.normal, a3(t.normal()), "triangle {i}");
            assert_eq!(s.smooth_shaded, 1, "triangle {i}");
            let ns = w.corners[i].map(|k| a3(w.vertex_normals[k as usize]));
            assert_eq!([s.n0, s.n1, s.n2], ns, "triangle {i}");
        }
        assert!(pack.arrays_in(7_777) == whole, "pieces of 7,777 elements");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
