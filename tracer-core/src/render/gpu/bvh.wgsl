// Scene queries for worlds with a BVH (accel.rs, bvh.rs): planes by loop,
// spheres and triangles through the tree. Mirrors `bvh::closest_hit` and
// `bvh::occluded` (same node layout, same slab test, same near-first order
// and culling), `Triangle::intersect` (the watertight test) and the
// triangle parts of world.rs / accel.rs (`triangle_surface`,
// `shading_normal`).
//
// The traversal stack has BVH_STACK (= bvh::MAX_DEPTH) entries. A push
// happens at most once per level on the way down, so a tree whose leaves
// are all shallower than BVH_STACK never overflows it; the builder
// guarantees that and the host checks it at upload (layout.rs check_tree),
// refusing deeper trees with an error.

// ---- Layouts: keep in sync with layout.rs (GpuBvhNode, GpuTriangle, GpuTriangleShading)
struct BvhNode {
    bmin: vec3<f32>,
    // Interior: index of the left child (the right one follows). Leaf: first index into `prims`.
    first: u32,
    bmax: vec3<f32>,
    // 0 for an interior node, else the leaf's primitive count.
    count: u32,
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
    n2: vec3<f32>,
}

@group(0) @binding(8) var<storage, read> nodes: array<BvhNode>;
@group(0) @binding(9) var<storage, read> prims: array<u32>;
@group(0) @binding(10) var<storage, read> triangles: array<Triangle>;
@group(0) @binding(11) var<storage, read> shading: array<TriangleShading>;

// f32::MAX, standing in for 1/0 in the reciprocal direction (bvh.rs BoxRay).
const INV_BIG: f32 = 3.4028235e38;
// Exit distances are widened by this (bvh.rs: Ize 2013) so rounding never
// culls a box the ray grazes.
const EXIT_WIDEN: f32 = 1.0000004;

fn reciprocal(d: vec3<f32>) -> vec3<f32> {
    // Zero (or denormal, which the GPU flushes) components: a huge finite
    // value of the component's sign, so 0 * inv is 0, never NaN.
    let big = select(vec3<f32>(INV_BIG), vec3<f32>(-INV_BIG), vec3<bool>(sign_bit(d.x), sign_bit(d.y), sign_bit(d.z)));
    return select(1.0 / d, big, abs(d) < vec3<f32>(1.1754944e-38));
}

// Entry distance into the node's box if the ray meets it within [0, t_max], else MISS.
fn box_entry(n: BvhNode, o: vec3<f32>, inv: vec3<f32>, t_max: f32) -> f32 {
    let lo = (n.bmin - o) * inv;
    let hi = (n.bmax - o) * inv;
    let near = min(lo, hi);
    let far = max(lo, hi);
    let t0 = max(max(max(near.x, near.y), near.z), 0.0);
    let t1 = min(min(far.x, far.y), far.z) * EXIT_WIDEN;
    return select(MISS, t0, t0 <= t1 && t0 <= t_max);
}

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

// bvh.rs hit_prim: a leaf's primitive against the ray.
fn hit_prim(id: u32, o: vec3<f32>, d: vec3<f32>, tr: TriRay, t_max: f32, skip: u32) -> f32 {
    let index = id & ((1u << KIND_SHIFT) - 1u);
    if ((id >> KIND_SHIFT) == KIND_TRIANGLE) {
        // A ray leaving a triangle cannot hit that (flat) triangle again.
        if (id == skip) {
            return MISS;
        }
        return hit_triangle(triangles[index], tr, t_max);
    }
    return hit_sphere(spheres[index], o, d, t_max, id == skip);
}

// bvh.rs closest_hit: nearest hit of the tree's primitives nearer than h.t.
fn tree_closest(o: vec3<f32>, d: vec3<f32>, skip: u32, h: Hit) -> Hit {
    var best = h.t;
    var found = NONE;
    let inv = reciprocal(d);
    let tr = tri_ray(o, d);
    if (box_entry(nodes[0], o, inv, best) < 0.0) {
        return h;
    }
    var stack_node: array<u32, BVH_STACK>;
    var stack_t: array<f32, BVH_STACK>;
    var sp = 0u;
    var node = 0u;
    loop {
        let n = nodes[node];
        if (n.count == 0u) {
            let l = n.first;
            let hl = box_entry(nodes[l], o, inv, best);
            let hr = box_entry(nodes[l + 1u], o, inv, best);
            if (hl >= 0.0 && hr >= 0.0) {
                // Both: visit the nearer first, keep the farther with its entry distance.
                let left_first = hl <= hr;
                stack_node[sp] = select(l, l + 1u, left_first);
                stack_t[sp] = select(hl, hr, left_first);
                sp = min(sp + 1u, BVH_STACK - 1u); // never clamps: depth checked at upload
                node = select(l + 1u, l, left_first);
                continue;
            }
            if (hl >= 0.0) {
                node = l;
                continue;
            }
            if (hr >= 0.0) {
                node = l + 1u;
                continue;
            }
        } else {
            for (var k = n.first; k < n.first + n.count; k++) {
                let id = prims[k];
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
                node = stack_node[sp];
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

// bvh.rs occluded: any primitive of the tree before t_max.
fn tree_occluded(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    let inv = reciprocal(d);
    let tr = tri_ray(o, d);
    if (box_entry(nodes[0], o, inv, t_max) < 0.0) {
        return false;
    }
    var stack_node: array<u32, BVH_STACK>;
    var sp = 0u;
    var node = 0u;
    loop {
        let n = nodes[node];
        if (n.count == 0u) {
            let l = n.first;
            let hl = box_entry(nodes[l], o, inv, t_max) >= 0.0;
            let hr = box_entry(nodes[l + 1u], o, inv, t_max) >= 0.0;
            if (hl || hr) {
                if (hl && hr) {
                    stack_node[sp] = l + 1u;
                    sp = min(sp + 1u, BVH_STACK - 1u); // never clamps: depth checked at upload
                }
                node = select(l + 1u, l, hl);
                continue;
            }
        } else {
            for (var k = n.first; k < n.first + n.count; k++) {
                if (hit_prim(prims[k], o, d, tr, t_max, skip) > 0.0) {
                    return true;
                }
            }
        }
        if (sp == 0u) {
            return false;
        }
        sp -= 1u;
        node = stack_node[sp];
    }
    return false;
}

// accel.rs closest_hit_accel: planes by loop, then the tree.
fn closest_hit(o: vec3<f32>, d: vec3<f32>, skip: u32) -> Hit {
    return tree_closest(o, d, skip, planes_closest(o, d, skip, Hit(BIG, NONE)));
}

fn occluded(o: vec3<f32>, d: vec3<f32>, t_max: f32, skip: u32) -> bool {
    return planes_occlude(o, d, t_max, skip) || tree_occluded(o, d, t_max, skip);
}

// world.rs surface; for triangles (accel.rs triangle_surface) the point
// snapped onto the triangle's plane and its outward geometric normal.
fn surface(id: u32, p: vec3<f32>) -> Surface {
    if ((id >> KIND_SHIFT) != KIND_TRIANGLE) {
        return analytic_surface(id, p);
    }
    let index = id & ((1u << KIND_SHIFT) - 1u);
    let s = shading[index];
    let v0 = triangles[index].v0;
    return Surface(p - s.normal * dot(s.normal, p - v0), s.normal, s.material);
}

// accel.rs shading_normal: on smooth triangles the interpolated vertex
// normal, turned to the side of n (the geometric normal facing the viewer),
// and n itself wherever that would face away from the viewer v.
fn shading_normal(id: u32, p: vec3<f32>, n: vec3<f32>, v: vec3<f32>) -> vec3<f32> {
    if ((id >> KIND_SHIFT) != KIND_TRIANGLE) {
        return n;
    }
    let index = id & ((1u << KIND_SHIFT) - 1u);
    let s = shading[index];
    if (s.smooth_shaded == 0u) {
        return n;
    }
    // triangle.rs TriangleShading::normal_at: barycentric weights, clamped.
    let tri = triangles[index];
    let e1 = tri.v1 - tri.v0;
    let e2 = tri.v2 - tri.v0;
    let dp = p - tri.v0;
    let c = cross(e1, e2);
    let cc = dot(c, c);
    let b1 = clamp(dot(cross(dp, e2), c) / cc, 0.0, 1.0);
    let b2 = clamp(dot(cross(e1, dp), c) / cc, 0.0, 1.0 - b1);
    let b0 = 1.0 - b1 - b2;
    let sum = s.n0 * b0 + s.n1 * b1 + s.n2 * b2;
    let len = length(sum);
    var ns = s.normal;
    if (len > 0.0 && len <= BIG) {
        ns = sum * (1.0 / len);
    }
    if (dot(ns, n) < 0.0) {
        ns = -ns;
    }
    return select(n, ns, dot(ns, v) > 0.0);
}
