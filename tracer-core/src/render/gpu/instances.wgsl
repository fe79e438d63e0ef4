//! import geometry.wgsl
// Instanced meshes on the GPU (world/instances.rs): a mesh placed many
// times is stored once, in its own (object) space, with its own tree in
// bvh.wgsl's arrays; the world's tree holds each placement as one
// primitive (KIND_INSTANCE, its index here). A ray that reaches one is
// moved into object space (its direction not renormalised, so distances
// along it are the world's) and walks the mesh's tree with bvh.wgsl's
// `mesh_closest` (`tree_closest` specialised to triangles: WGSL has no
// recursion, and the world's tree reaches this file through `hit_prim`).
//
// A hit on triangle k of instance i is KIND_INSTANCE_TRIANGLE with index
// first(i) + k: one id per placed triangle, so that a ray leaving one copy
// skips that triangle of that copy only. bvh.wgsl imports this file.

// ---- Layout: keep in sync with layout.rs (GpuInstance)
struct Instance {
    // to_world (Affine3: object space to the world's camera-relative
    // space) as its columns, the translation last; in their w, the mesh's
    // root node, its first triangle in bvh.wgsl's arrays, this placement's
    // first id index and the mesh's triangle count.
    w0: vec3<f32>,
    root: u32,
    w1: vec3<f32>,
    tri0: u32,
    w2: vec3<f32>,
    first: u32,
    w3: vec3<f32>,
    count: u32,
    // to_object, its inverse, the same way.
    o0: vec3<f32>,
    _p0: u32,
    o1: vec3<f32>,
    _p1: u32,
    o2: vec3<f32>,
    _p2: u32,
    o3: vec3<f32>,
    _p3: u32,
}

// Whether the world's tree holds instances: off, the branches below are
// compiled out of the traversal.
override HAS_INSTANCES: bool = false;

// Binding `instances`: wgsl.rs SCENE.

// Affine3::point and ::vector of to_object, and to_world's point.
fn to_object_point(m: Instance, p: vec3<f32>) -> vec3<f32> {
    return m.o0 * p.x + m.o1 * p.y + m.o2 * p.z + m.o3;
}

fn to_object_vector(m: Instance, v: vec3<f32>) -> vec3<f32> {
    return m.o0 * v.x + m.o1 * v.y + m.o2 * v.z;
}

fn to_world_point(m: Instance, p: vec3<f32>) -> vec3<f32> {
    return m.w0 * p.x + m.w1 * p.y + m.w2 * p.z + m.w3;
}

// Affine3::transposed of to_object: an object-space normal in the world
// (not unit).
fn normal_to_world(m: Instance, n: vec3<f32>) -> vec3<f32> {
    return vec3<f32>(dot(m.o0, n), dot(m.o1, n), dot(m.o2, n));
}

// Instances::closest: the nearest hit on instance i nearer than t_max, as
// the placed triangle's KIND_INSTANCE_TRIANGLE id. `skip`: the id the ray
// starts on, of any kind.
fn instance_closest(i: u32, o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> Hit {
    let m = instances[i];
    var local_skip = NONE;
    let k = (skip & ((1u << KIND_SHIFT) - 1u)) - m.first; // wraps below first
    if ((skip >> KIND_SHIFT) == KIND_INSTANCE_TRIANGLE && skip != NONE && k < m.count) {
        local_skip = (KIND_TRIANGLE << KIND_SHIFT) | (m.tri0 + k);
    }
    let h = mesh_closest(m.root, to_object_point(m, o), to_object_vector(m, d), local_skip, Hit(t_max, NONE));
    if (h.id == NONE) {
        return h;
    }
    let local = (h.id & ((1u << KIND_SHIFT) - 1u)) - m.tri0;
    return Hit(h.t, (KIND_INSTANCE_TRIANGLE << KIND_SHIFT) | (m.first + local));
}

// world/query.rs resolve: a hit as the world's tree gives it, with an
// instance's id (the tree knows only which instance) made the id of the
// triangle hit, found again the same way.
fn resolve_instance(h: Hit, o: vec3<f32>, d: vec3<f32>, skip: u32) -> Hit {
    if (!HAS_INSTANCES || h.id == NONE || (h.id >> KIND_SHIFT) != KIND_INSTANCE) {
        return h;
    }
    return instance_closest(h.id & ((1u << KIND_SHIFT) - 1u), o, d, BIG, skip);
}

// Instances::locate: the instance whose ids hold `index` (the last whose
// first is at most it).
fn instance_of(index: u32) -> u32 {
    var lo = 0u;
    var hi = arrayLength(&instances);
    while (hi - lo > 1u) {
        let mid = (lo + hi) / 2u;
        if (instances[mid].first <= index) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// Instances::surface: the point snapped onto placed triangle `index`, its
// outward unit normal and material, in the world's space.
fn instance_surface(index: u32, p: vec3<f32>) -> SurfacePoint {
    let m = instances[instance_of(index)];
    let tri = m.tri0 + index - m.first;
    let s = shading[tri];
    var q = to_object_point(m, p);
    q = q - s.normal * dot(s.normal, q - triangles[tri].v0);
    return SurfacePoint(to_world_point(m, q), normalize(normal_to_world(m, s.normal)), s.material);
}

// world/query.rs PlacedTriangle: a hit triangle as shading sees it, a
// world triangle or an instance's: its index in bvh.wgsl's arrays (NONE
// for other primitives), the hit point in its own space (barycentric
// weights are the same there: the map is affine) and the instance that
// places it (NONE for a world triangle).
struct Placed {
    tri: u32,
    q: vec3<f32>,
    inst: u32,
}

fn placed_triangle(id: u32, p: vec3<f32>) -> Placed {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    if ((id >> KIND_SHIFT) == KIND_TRIANGLE) {
        return Placed(index, p, NONE);
    }
    if (HAS_INSTANCES && (id >> KIND_SHIFT) == KIND_INSTANCE_TRIANGLE) {
        let i = instance_of(index);
        let m = instances[i];
        return Placed(m.tri0 + index - m.first, to_object_point(m, p), i);
    }
    return Placed(NONE, p, NONE);
}

// PlacedTriangle::corners: its corners in the world's space.
fn placed_corners(t: Placed) -> Triangle {
    let tri = triangles[t.tri];
    if (t.inst == NONE) {
        return tri;
    }
    let m = instances[t.inst];
    return Triangle(to_world_point(m, tri.v0), to_world_point(m, tri.v1), to_world_point(m, tri.v2));
}

// PlacedTriangle::normal_at: the interpolated vertex normal (or the
// geometric one, when flat), unit, in the world's space.
fn placed_normal_at(t: Placed) -> vec3<f32> {
    let n = triangle_normal_at(t.tri, t.q);
    if (t.inst == NONE) {
        return n;
    }
    return normalize(normal_to_world(instances[t.inst], n));
}

// World::tangent_at's map of an interpolated tangent (xyz) and its sign
// (w) to the world: by the instance's linear part, the sign flipped by a
// mirror.
fn placed_tangent(t: Placed, tangent: vec4<f32>) -> vec4<f32> {
    if (t.inst == NONE) {
        return tangent;
    }
    let m = instances[t.inst];
    let v = m.w0 * tangent.x + m.w1 * tangent.y + m.w2 * tangent.z;
    return vec4<f32>(v, select(tangent.w, -tangent.w, dot(cross(m.w0, m.w1), m.w2) < 0.0));
}
