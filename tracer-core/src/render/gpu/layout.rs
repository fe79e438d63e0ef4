//! Host mirrors of every structure the WGSL kernel reads or writes.
//!
//! Keep in sync with the struct declarations at the top of `whitted.wgsl`
//! (and, for meshes and the BVH, `bvh.wgsl`):
//! same field order, same sizes, WGSL alignment rules (a `vec3<f32>` is
//! 16-byte aligned, so each one is followed by a scalar that fills its
//! fourth lane). The `const` asserts below pin the sizes WGSL expects.

use bytemuck::{Pod, Zeroable};

use crate::bvh::{Bvh, BvhNode4, STACK};
use crate::geometry::{Plane, PrimId, Sphere};
use crate::triangle::{Triangle, TriangleShading};
use crate::world::{Material, PointLight, World};

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
    pub _pad: [u32; 3],
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
    pub _pad1: u32,
    pub n2: [f32; 3],
    pub _pad2: u32,
}

/// The BVH node is uploaded as is: `bvh::BvhNode4` (128 bytes) is already
/// the WGSL `struct BvhNode4` (six vec4<f32> rows of the four slots' boxes,
/// then vec4<u32> child and count).
pub type GpuBvhNode = BvhNode4;

/// Per-pixel output: fixed-point sums as (low, high) u32 words per channel,
/// i.e. the `u64` sums of [`crate::film::Film`]. WGSL: `sums: array<u32>`, 6 words a pixel.
pub const SUM_WORDS: usize = 6;

/// Global counters, each a (low, high) u32 pair. WGSL: `counters: array<atomic<u32>, 10>`.
pub const COUNTERS: usize = 5;
pub const COUNTER_PRIMARY: usize = 0;
pub const COUNTER_SHADOW: usize = 1;
pub const COUNTER_REFLECTION: usize = 2;
pub const COUNTER_REFRACTION: usize = 3;
pub const COUNTER_NONFINITE: usize = 4;

/// A ray task of the wavefront strategy. WGSL (wavefront.wgsl): `struct WaveTask`.
pub const WAVE_TASK_BYTES: u64 = 48;
/// WGSL: `struct WaveState` (count_in, count_out, overflow), padded.
pub const WAVE_STATE_BYTES: u64 = 16;
/// WGSL: `wave_args_out: array<u32, 3>`, an indirect dispatch's x, y, z.
pub const WAVE_ARGS_BYTES: u64 = 12;

const _: () = assert!(size_of::<FrameUniform>() == 80);
const _: () = assert!(size_of::<DispatchParams>() == 48);
const _: () = assert!(size_of::<GpuSphere>() == 32);
const _: () = assert!(size_of::<GpuPlane>() == 32);
const _: () = assert!(size_of::<GpuMaterial>() == 64);
const _: () = assert!(size_of::<GpuLight>() == 48);
const _: () = assert!(size_of::<GpuTriangle>() == 48);
const _: () = assert!(size_of::<GpuTriangleShading>() == 64);
const _: () = assert!(size_of::<GpuBvhNode>() == 128);

/// A world's tree and what its leaves refer to, for scenes that have one
/// (meshes, or many spheres): the pipeline then compiles `bvh.wgsl`.
#[derive(Clone, Debug, PartialEq)]
pub struct TreeData {
    /// The flattened 4-wide nodes exactly as the CPU traverses them.
    pub nodes: Vec<GpuBvhNode>,
    /// Leaf references: packed `PrimId`s (kind << 28 | index).
    pub prims: Vec<u32>,
    /// Never empty (one unused element when the tree holds only spheres).
    pub triangles: Vec<GpuTriangle>,
    pub shading: Vec<GpuTriangleShading>,
    pub n_triangles: u32,
    /// Traversal stack entries the tree needs, as measured at upload.
    pub stack: u32,
}

impl TreeData {
    /// Packs `tree` after checking that the GPU can traverse it: every index
    /// in range and no path from the root that pushes more than `STACK`
    /// entries, since the kernel's traversal stack has `STACK` entries. The
    /// builder guarantees both; this refuses a tree from anywhere else
    /// rather than render a wrong image.
    pub fn from_tree(w: &World<f32>, tree: &Bvh) -> Result<Self, GpuError> {
        let stack = check_tree(&tree.nodes, &tree.prims, w.spheres.len(), w.triangles.len())?;
        let triangle = |t: &Triangle<f32>| {
            let [v0, v1, v2] = t.vertices().map(a3);
            GpuTriangle {
                v0,
                v1,
                v2,
                ..Default::default()
            }
        };
        let shading = |s: &TriangleShading<f32>| {
            let ns = s.vertex_normals.map(|n| n.map(a3)).unwrap_or([[0.0; 3]; 3]);
            GpuTriangleShading {
                normal: a3(s.normal),
                material: s.material,
                n0: ns[0],
                smooth_shaded: s.vertex_normals.is_some() as u32,
                n1: ns[1],
                n2: ns[2],
                ..Default::default()
            }
        };
        Ok(TreeData {
            nodes: tree.nodes.clone(),
            prims: non_empty(tree.prims.iter().map(|p| p.0).collect()),
            triangles: non_empty(w.triangles.iter().map(triangle).collect()),
            shading: non_empty(w.triangle_shading.iter().map(shading).collect()),
            n_triangles: w.triangles.len() as u32,
            stack,
        })
    }
}

/// Walks the tree from the root: child nodes and leaf ranges in bounds,
/// leaves referring to existing spheres or triangles, and at most `STACK`
/// entries on the traversal stack along any path (a node pushes all but one
/// of its used slots). Returns the most entries any path needs.
fn check_tree(
    nodes: &[BvhNode4],
    prims: &[PrimId],
    spheres: usize,
    triangles: usize,
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
                    _ => false,
                };
                if !ok {
                    return bad(format!(
                        "node {i} has a leaf that refers to {p:?}, which is not a sphere or triangle of the scene"
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
    /// The world's BVH over spheres and triangles, when it has one.
    pub tree: Option<SharedTree>,
    /// Distributed effects (`World::dist`), packed as distributed.wgsl reads them.
    pub dist: Option<DistData>,
}

/// `World::dist` for distributed.wgsl: its `dist` array of vec4 (keep in
/// sync with the layout described there) and the pipeline constants.
#[derive(Clone, Debug, PartialEq)]
pub struct DistData {
    pub words: Vec<[f32; 4]>,
    pub n_lights: u32,
    pub n_moving: u32,
    pub has_lens: bool,
    pub has_blur: bool,
    pub has_camera_motion: bool,
}

impl DistData {
    pub fn from_dist(d: &crate::distributed::Distributed<f32>) -> Result<Self, GpuError> {
        use crate::distributed::LightGeom;
        if !d.moving_meshes.is_empty() {
            return Err(GpuError::DistributedUnsupported);
        }
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
        Ok(DistData {
            words,
            n_lights: d.lights.len() as u32,
            n_moving: d.moving_spheres.len() as u32,
            has_lens: d.lens.is_some(),
            has_blur: d.blur,
            has_camera_motion: d.camera_motion.is_some(),
        })
    }
}

/// Packed tree data, shared between renders of the same world: equal when
/// it is the same allocation (no O(n) comparison) or has equal contents.
#[derive(Clone, Debug)]
pub struct SharedTree {
    /// `Bvh::id` of the tree it was packed from (0: unknown, never reused).
    pub id: u64,
    pub data: std::sync::Arc<TreeData>,
}

impl PartialEq for SharedTree {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.data, &other.data)
            || (self.id == other.id && self.data == other.data)
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

impl SceneData {
    /// Packs `w`. `packed` is a tree packed earlier, reused (not repacked)
    /// when it was packed from this world's tree (same non-zero `Bvh::id`
    /// and primitive counts).
    pub fn from_world(w: &World<f32>, packed: Option<&SharedTree>) -> Result<Self, GpuError> {
        let s = &w.settings;
        // 0: the low-discrepancy points (non-square counts, and the
        // progressive sampler whatever the count), as `sample_offset`.
        let grid_n = match s.sampler {
            crate::sampling::Sampler::Progressive => 0,
            _ => crate::sampling::exact_sqrt(s.samples).unwrap_or(0),
        };
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
        let material = |m: &Material<f32>| GpuMaterial {
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
        };
        let light = |l: &PointLight<f32>| GpuLight {
            position: a3(l.position),
            diffuse: a3(l.diffuse),
            specular: a3(l.specular),
            ..Default::default()
        };
        let tree = match w.accel.as_ref().filter(|t| !t.nodes.is_empty()) {
            None => None,
            Some(t) => match packed {
                Some(p)
                    if t.id != 0
                        && p.id == t.id
                        && p.data.n_triangles as usize == w.triangles.len()
                        && p.data.prims.len() == t.prims.len() =>
                {
                    Some(p.clone())
                }
                _ => Some(SharedTree {
                    id: t.id,
                    data: std::sync::Arc::new(TreeData::from_tree(w, t)?),
                }),
            },
        };
        if tree.is_none() && !w.triangles.is_empty() {
            // Worlds always get a tree with their triangles (accel.rs); the
            // kernel has no loop over triangles.
            return Err(GpuError::BadTree(format!(
                "the scene has {} triangles but no BVH over them",
                w.triangles.len()
            )));
        }
        Ok(SceneData {
            frame,
            spheres: non_empty(w.spheres.iter().map(sphere).collect()),
            planes: non_empty(w.planes.iter().map(plane).collect()),
            materials: non_empty(w.materials.iter().map(material).collect()),
            lights: non_empty(w.lights.iter().map(light).collect()),
            n_spheres: w.spheres.len() as u32,
            n_planes: w.planes.len() as u32,
            n_lights: w.lights.len() as u32,
            max_depth: s.max_depth,
            has_reflection: w.features.reflection,
            has_refraction: w.features.refraction,
            tree,
            dist: w.dist.as_deref().map(DistData::from_dist).transpose()?,
        })
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
