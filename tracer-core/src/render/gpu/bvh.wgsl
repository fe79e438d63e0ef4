//! import geometry.wgsl
//! import instances.wgsl
//! specialise tree_closest as mesh_closest: hit_prim -> mesh_prim
// Tree traversal on the GPU (bvh/, triangle.rs): the 4-wide node layout,
// the same slab test with planes chosen by the direction's sign, the same
// near-first order and culling, `Triangle::intersect` (the watertight test)
// and the triangle parts of world/query.rs (`triangle_surface`,
// `shading_normal`). Compiled in for worlds with a tree (then accel.wgsl
// holds the scene queries) and for moving meshes (distributed.wgsl,
// moving_meshes.wgsl): each tree lies in the same arrays, the static one
// from node 0, every moving mesh's after it, its node, leaf and triangle
// indices rebased by the host (layout.rs TreeData::pack), so a traversal
// takes the index of its root and a triangle's index is unique across trees.
// Instanced meshes' trees lie there too (instances.wgsl), walked by
// `mesh_closest`: `tree_closest` with `mesh_prim` for `hit_prim`, which the
// assembler generates (wgsl.rs, the `specialise` line above), as Rust
// instantiates bvh/traverse.rs's generic traversal for the world and for
// an instanced mesh.
//
// The traversal stack has BVH_STACK entries: one more than the most any of
// the trees can need on any path (a node pushes all its met slots but the
// one it continues with), as measured by the host at upload (layout.rs
// check_tree, which refuses trees needing more than bvh::STACK).

// ---- Layouts: keep in sync with layout.rs (GpuBvhNode, GpuTriangle, GpuTriangleShading)
struct BvhNode4 {
    // Rows of the four slots' boxes (bvh/node.rs BvhNode4::b).
    min_x: vec4<f32>,
    max_x: vec4<f32>,
    min_y: vec4<f32>,
    max_y: vec4<f32>,
    min_z: vec4<f32>,
    max_z: vec4<f32>,
    // Slot k: a child node (count 0, child its index, never 0), a leaf
    // (count > 0: prims[child .. child + count]) or nothing (both 0).
    child: vec4<u32>,
    count: vec4<u32>,
}

struct Triangle {
    v0: vec3<f32>,
    v1: vec3<f32>,
    v2: vec3<f32>,
}

struct TriangleShading {
    normal: vec3<f32>,
    material: u32,
    n0: vec3<f32>,
    smooth_shaded: u32,
    n1: vec3<f32>,
    // Its vertex attributes in pbr.wgsl's tri_attrs, or NONE.
    attrs: u32,
    n2: vec3<f32>,
}

// Bindings 8-11 (nodes, prims, triangles, shading): wgsl.rs SCENE.

// f32::MAX, standing in for 1/0 in the reciprocal direction (bvh/traverse.rs BoxRay).
const INV_BIG: f32 = 3.4028235e38;
// Exit distances are widened by this (bvh/traverse.rs: Ize 2013) so rounding never
// culls a box the ray grazes.
const EXIT_WIDEN: f32 = 1.0000004;

fn reciprocal(d: vec3<f32>) -> vec3<f32> {
    // Zero (or denormal, which the GPU flushes) components: a huge finite
    // value of the component's sign, so 0 * inv is 0, never NaN.
    let big = select(vec3<f32>(INV_BIG), vec3<f32>(-INV_BIG), vec3<bool>(sign_bit(d.x), sign_bit(d.y), sign_bit(d.z)));
    return select(1.0 / d, big, abs(d) < vec3<f32>(1.1754944e-38));
}

// Entry distances into the node's four boxes where the ray meets them
// within [0, t_max], else MISS. The near plane on each axis is the min one
// where the direction is positive (bvh/traverse.rs BoxRay).
fn box_entry4(n: BvhNode4, o: vec3<f32>, inv: vec3<f32>, t_max: f32) -> vec4<f32> {
    let pos = inv >= vec3<f32>(0.0);
    let t0x = (select(n.max_x, n.min_x, pos.x) - o.x) * inv.x;
    let t1x = (select(n.min_x, n.max_x, pos.x) - o.x) * inv.x;
    let t0y = (select(n.max_y, n.min_y, pos.y) - o.y) * inv.y;
    let t1y = (select(n.min_y, n.max_y, pos.y) - o.y) * inv.y;
    let t0z = (select(n.max_z, n.min_z, pos.z) - o.z) * inv.z;
    let t1z = (select(n.min_z, n.max_z, pos.z) - o.z) * inv.z;
    let t0 = max(max(t0x, t0y), max(t0z, vec4<f32>(0.0)));
    let t1 = min(min(t1x, t1y), t1z) * EXIT_WIDEN;
    let used = (n.count != vec4<u32>(0u)) | (n.child != vec4<u32>(0u));
    return select(vec4<f32>(MISS), t0, used & (t0 <= t1) & (t0 <= vec4<f32>(t_max)));
}

// A stack entry for a leaf: LEAF_REF | node << 2 | slot (host-checked: fewer than 2^29 nodes).
const LEAF_REF: u32 = 0x80000000u;

// triangle.rs TriangleRay: the origin and the ray-aligned shear as three rows.
struct TriRay {
    o: vec3<f32>,
    rx: vec3<f32>,
    ry: vec3<f32>,
    rz: vec3<f32>,
}

fn tri_ray(o: vec3<f32>, d: vec3<f32>) -> TriRay {
    let a = abs(d);
    var kz = 2u;
    if (a.x >= a.y && a.x >= a.z) {
        kz = 0u;
    } else if (a.y >= a.z) {
        kz = 1u;
    }
    var kx = (kz + 1u) % 3u;
    var ky = (kz + 2u) % 3u;
    // Keep the winding (and so the sign of det) consistent.
    if (d[kz] < 0.0) {
        let t = kx;
        kx = ky;
        ky = t;
    }
    let sz = 1.0 / d[kz];
    var rx = vec3<f32>(0.0);
    var ry = vec3<f32>(0.0);
    var rz = vec3<f32>(0.0);
    rx[kx] = 1.0;
    rx[kz] = -d[kx] * sz;
    ry[ky] = 1.0;
    ry[kz] = -d[ky] * sz;
    rz[kz] = sz;
    return TriRay(o, rx, ry, rz);
}

// p q - s t with the sign of the exact value. Called where the rounded
// difference is 0: then p q and s t rounded to the same float, and the
// sign is that of the difference of their rounding errors, which fma
// computes exactly (the CPU redoes this case in f64 instead).
fn edge_exact(p: f32, q: f32, s: f32, t: f32) -> f32 {
    let a = p * q;
    let b = s * t;
    if (a != b) {
        return a - b;
    }
    return fma(p, q, -a) - fma(s, t, -b);
}

// triangle.rs Triangle::intersect: distance in (0, t_max), or MISS.
// Degenerate triangles are never hit and give no NaN.
fn hit_triangle(tri: Triangle, r: TriRay, t_max: f32) -> f32 {
    let dx = vec3<f32>(tri.v0.x, tri.v1.x, tri.v2.x) - r.o.x;
    let dy = vec3<f32>(tri.v0.y, tri.v1.y, tri.v2.y) - r.o.y;
    let dz = vec3<f32>(tri.v0.z, tri.v1.z, tri.v2.z) - r.o.z;
    let x = dx * r.rx.x + dy * r.rx.y + dz * r.rx.z; // (ax, bx, cx)
    let y = dx * r.ry.x + dy * r.ry.y + dz * r.ry.z; // (ay, by, cy)
    // Edge functions (u, v, w) = (cx by - cy bx, ax cy - ay cx, bx ay - by ax).
    var uvw = vec3<f32>(x.z, x.x, x.y) * vec3<f32>(y.y, y.z, y.x) - vec3<f32>(y.z, y.x, y.y) * vec3<f32>(x.y, x.z, x.x);
    let au = abs(uvw);
    if (min(min(au.x, au.y), au.z) == 0.0) {
        // On (or within rounding of) an edge: the sign decides which of the
        // two neighbours owns the ray.
        uvw = vec3<f32>(edge_exact(x.z, y.y, y.z, x.y), edge_exact(x.x, y.z, y.x, x.z), edge_exact(x.y, y.x, y.y, x.x));
    }
    let lo = min(min(uvw.x, uvw.y), uvw.z);
    let hi = max(max(uvw.x, uvw.y), uvw.z);
    if (lo < 0.0 && hi > 0.0) {
        return MISS;
    }
    let det = uvw.x + uvw.y + uvw.z;
    if (det == 0.0) {
        return MISS;
    }
    let z = dx * r.rz.x + dy * r.rz.y + dz * r.rz.z; // (az, bz, cz)
    let t_scaled = dot(uvw, z);
    // t = t_scaled / det must lie in (0, t_max); test before dividing.
    var inside: bool;
    if (det > 0.0) {
        inside = t_scaled > 0.0 && t_scaled < t_max * det;
    } else {
        inside = t_scaled < 0.0 && t_scaled > t_max * det;
    }
    if (!inside) {
        return MISS;
    }
    let t = t_scaled / det;
    return select(MISS, t, t > 0.0 && t < t_max);
}

// world/query.rs Primitives::intersect: a leaf's primitive against the ray.
fn hit_prim(id: u32, o: vec3<f32>, d: vec3<f32>, tr: TriRay, t_max: f32, skip: u32) -> f32 {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    if ((id >> KIND_SHIFT) == KIND_TRIANGLE) {
        return mesh_prim(id, o, d, tr, t_max, skip);
    }
    if (HAS_INSTANCES && (id >> KIND_SHIFT) == KIND_INSTANCE) {
        let h = instance_closest(index, o, d, t_max, skip);
        return select(MISS, h.t, h.id != NONE);
    }
    return hit_sphere(spheres[index], o, d, t_max, id == skip);
}

// world/instances.rs InstancedMesh's Primitives::intersect: a mesh's tree
// holds triangles only.
fn mesh_prim(id: u32, o: vec3<f32>, d: vec3<f32>, tr: TriRay, t_max: f32, skip: u32) -> f32 {
    // A ray leaving a triangle cannot hit that (flat) triangle again.
    if (id == skip) {
        return MISS;
    }
    return hit_triangle(triangles[id & ((1u << KIND_SHIFT) - 1u)], tr, t_max);
}

// bvh/traverse.rs closest_hit: nearest hit of the primitives of the tree rooted at
// node `root` nearer than h.t.
fn tree_closest(root: u32, o: vec3<f32>, d: vec3<f32>, skip: u32, h: Hit) -> Hit {
    var best = h.t;
    var found = NONE;
    let inv = reciprocal(d);
    let tr = tri_ray(o, d);
    var stack_ref: array<u32, BVH_STACK>;
    var stack_t: array<f32, BVH_STACK>;
    var sp = 0u;
    // The subtree being visited: a node index, or a LEAF_REF; first the root.
    var cur = root;
    loop {
        if ((cur & LEAF_REF) == 0u) {
            let n = nodes[cur];
            let t = box_entry4(n, o, inv, best);
            // The met slots sorted nearest first (insertion).
            var r: array<u32, 4>;
            var rt: array<f32, 4>;
            var c = 0u;
            for (var k = 0u; k < 4u; k++) {
                let tk = t[k];
                if (tk >= 0.0) {
                    var j = c;
                    while (j > 0u && rt[j - 1u] > tk) {
                        rt[j] = rt[j - 1u];
                        r[j] = r[j - 1u];
                        j -= 1u;
                    }
                    rt[j] = tk;
                    r[j] = select(n.child[k], LEAF_REF | (cur << 2u) | k, n.count[k] != 0u);
                    c += 1u;
                }
            }
            if (c > 0u) {
                // Push all but the nearest, farthest first; continue with the nearest.
                for (var j = c - 1u; j > 0u; j--) {
                    stack_ref[sp] = r[j];
                    stack_t[sp] = rt[j];
                    sp = min(sp + 1u, BVH_STACK - 1u); // never clamps: stack need checked at upload
                }
                cur = r[0];
                continue;
            }
        } else {
            let node = (cur & ~LEAF_REF) >> 2u;
            let k = cur & 3u;
            let first = nodes[node].child[k];
            let count = nodes[node].count[k];
            for (var i = first; i < first + count; i++) {
                let id = prims[i];
                let t = hit_prim(id, o, d, tr, best, skip);
                if (t > 0.0) {
                    best = t;
                    found = id;
                }
            }
        }
        // Pop the next subtree that may still hold something nearer.
        var done = true;
        loop {
            if (sp == 0u) {
                break;
            }
            sp -= 1u;
            if (stack_t[sp] <= best) {
                cur = stack_ref[sp];
                done = false;
                break;
            }
        }
        if (done) {
            break;
        }
    }
    if (found == NONE) {
        return h;
    }
    return Hit(best, found);
}

// bvh/traverse.rs occluded: any primitive of the tree rooted at node `root` before
// t_max; leaves are tested as soon as their box is met.
fn tree_occluded(root: u32, o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    let inv = reciprocal(d);
    let tr = tri_ray(o, d);
    var stack_node: array<u32, BVH_STACK>;
    var sp = 0u;
    var node = root;
    loop {
        let n = nodes[node];
        let t = box_entry4(n, o, inv, t_max);
        var next = NONE;
        for (var k = 0u; k < 4u; k++) {
            if (t[k] >= 0.0) {
                if (n.count[k] != 0u) {
                    let first = n.child[k];
                    for (var i = first; i < first + n.count[k]; i++) {
                        if (hit_prim(prims[i], o, d, tr, t_max, skip) > 0.0) {
                            return true;
                        }
                    }
                } else if (next == NONE) {
                    next = n.child[k];
                } else {
                    stack_node[sp] = n.child[k];
                    sp = min(sp + 1u, BVH_STACK - 1u); // never clamps: stack need checked at upload
                }
            }
        }
        if (next != NONE) {
            node = next;
            continue;
        }
        if (sp == 0u) {
            return false;
        }
        sp -= 1u;
        node = stack_node[sp];
    }
    return false;
}

// world/query.rs triangle_surface: the point snapped onto the plane of triangle
// `index` and its outward geometric normal.
fn triangle_surface(index: u32, p: vec3<f32>) -> SurfacePoint {
    let s = shading[index];
    let v0 = triangles[index].v0;
    return SurfacePoint(p - s.normal * dot(s.normal, p - v0), s.normal, s.material);
}

// triangle.rs Triangle::barycentric: the weights of p on triangle
// `index`, clamped into the triangle.
fn triangle_barycentric(index: u32, p: vec3<f32>) -> vec3<f32> {
    let tri = triangles[index];
    let e1 = tri.v1 - tri.v0;
    let e2 = tri.v2 - tri.v0;
    let dp = p - tri.v0;
    let c = cross(e1, e2);
    let cc = dot(c, c);
    let b1 = clamp(dot(cross(dp, e2), c) / cc, 0.0, 1.0);
    let b2 = clamp(dot(cross(e1, dp), c) / cc, 0.0, 1.0 - b1);
    return vec3<f32>(1.0 - b1 - b2, b1, b2);
}

// triangle.rs TriangleShading::normal_at: the vertex normals interpolated
// at p, or the geometric normal (outward, as the vertex normals are).
fn triangle_normal_at(index: u32, p: vec3<f32>) -> vec3<f32> {
    let s = shading[index];
    if (s.smooth_shaded == 0u) {
        return s.normal;
    }
    let b = triangle_barycentric(index, p);
    let sum = s.n0 * b.x + s.n1 * b.y + s.n2 * b.z;
    let len = length(sum);
    if (len > 0.0 && len <= BIG) {
        return sum * (1.0 / len);
    }
    return s.normal;
}

// world/query.rs shading_normal for triangle `index`: on smooth triangles the
// interpolated vertex normal, turned to the side of n (the geometric normal
// facing the viewer), and n itself wherever that would face away from the
// viewer v.
fn triangle_shading_normal(index: u32, p: vec3<f32>, n: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    if (shading[index].smooth_shaded == 0u) {
        return n;
    }
    return facing_normal(triangle_normal_at(index, p), n, v);
}

// The interpolated normal ns turned to the side of n, or n itself where
// it would face away from the viewer v (world/query.rs shading_normal).
fn facing_normal(ns: vec3<f32>, n: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    let turned = select(ns, -ns, dot(ns, n) < 0.0);
    return select(n, turned, dot(turned, v) > 0.0);
}
